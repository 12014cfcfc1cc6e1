"""Cost of the online calibration of the ellipses: `AdaptiveRunner.update` with and without
`calibrate=True`, on the same stream.

A simulated drive of the oval (`fpe_jax.sim.simulate`, 60 s, the detector's ~11.5 Hz, 0.3 s
latency) through the adapting runner started from the waypoints alone with a 3 s (30-step) and
a 5 s (50-step) horizon, the ellipses to calibrate growing with the step. Every update is timed;
the median and 99th percentile per run, and the median of those over REPEATS runs (each run in
the same order: off, then on).

Run:  .venv/bin/python experiments/benchmarks/adapt_calibration.py
Writes experiments/benchmarks/adapt_calibration.md.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from fpe_jax.runner._adapt import AdaptiveRunner, start_config
from fpe_jax.sim._sim import simulate

OUT = Path(__file__).resolve().parent / "adapt_calibration.md"
REPEATS = 3
HORIZONS = (30, 50)


def config(waypoints_xy_m, horizon: int) -> dict:
    """The waypoints-only start, with made-up ellipses growing with the step."""
    cfg = start_config(None, waypoints_xy_m, settings={"horizon": horizon}, delay_s=0.3)
    cov = [[[0.01 * k, 0.0], [0.0, 0.004 * k]] for k in range(1, horizon + 1)]
    return cfg | {"uncertainty": {"frame": "track", "cov_m2": cov}}


def time_updates(cfg, waypoints_xy_m, drive, calibrate: bool) -> tuple[float, float, int]:
    """(median, p99) [ms] per update over the drive, and the errors realised."""
    runner = AdaptiveRunner(cfg, waypoints_xy_m, calibrate=calibrate)
    rows = zip(drive.t_s.tolist(), drive.xy_m.tolist(), drive.yaw_rad.tolist())
    took = []
    for t, (x, y), yaw in rows:
        t0 = time.perf_counter_ns()
        runner.update(t, x, y, yaw)
        took.append(time.perf_counter_ns() - t0)
    took_ms = np.array(took) * 1e-6
    errors = runner.calibration.errors if calibrate else 0
    return float(np.median(took_ms)), float(np.percentile(took_ms, 99)), errors


def main() -> int:
    res = simulate("oval", duration_s=60.0, seed=3)
    wp, drive = res.centerline_xy_m, res.drive
    lines = [
        "# Cost of the online calibration of the ellipses",
        "",
        "Regenerate: `.venv/bin/python experiments/benchmarks/adapt_calibration.py` (the shared "
        f"2-core machine, load {os.getloadavg()[0]:.1f} at the start).",
        "",
        f"`AdaptiveRunner.update` over a simulated 60 s drive of the oval ({len(drive.t_s)} "
        "detections), from the waypoints alone; per update [ms], median over "
        f"{REPEATS} runs of each run's median and 99th percentile.",
        "",
        "| horizon | calibrate | median ms | p99 ms | errors realised |",
        "|---|---|---|---|---|",
    ]
    for horizon in HORIZONS:
        cfg = config(wp, horizon)
        runs = {False: [], True: []}
        for _ in range(REPEATS):
            for calibrate in (False, True):
                runs[calibrate].append(time_updates(cfg, wp, drive, calibrate))
        for calibrate, got in runs.items():
            med, p99, errors = (float(np.median(v)) for v in zip(*got))
            lines.append(
                f"| {horizon} | {'on' if calibrate else 'off'} | {med:.3f} | {p99:.3f} | "
                f"{errors:.0f} |"
            )
    OUT.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
