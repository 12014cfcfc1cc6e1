"""Errors and ellipse coverage of valid predictions by the age of their history window.

A prediction is valid (`fpe_jax.model.history_valid`) once its window holds 3 observations
spanning 0.2 s; a window fills to `MAX_SPAN_S` (1 s) after the car is first seen and again after
every detection gap longer than that. The ellipses a config carries (`uncertainty.cov_m2`) were
fitted on every prediction of the fit drive, nearly all from full windows. This study asks how
the young windows' predictions compare: simulated drives on the oval with the AprilTag sensor
(field-of-view dropouts restart the window) and one stop a minute, predicted by `fpe predict`'s
pipeline with the committed config `fit/sim-oval.json`, scored against the simulator's truth at
steps 1-10 and binned by the window's span at prediction time.

Run:  .venv/bin/python experiments/uncertainty/young_history.py   (about 3 minutes)
Writes experiments/results/young_history.md; drives are simulated into a temporary folder.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from fpe_jax import pipeline
from fpe_jax.model._history import history_windows

REPO = Path(__file__).resolve().parents[2]
OUT = REPO / "experiments" / "results" / "young_history.md"
CONFIG = REPO / "fit" / "sim-oval.json"
WAYPOINTS = REPO / "data" / "tracks" / "oval.csv"
SEEDS = range(5, 13)
DURATION_S = 300.0
BINS_S = [0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0 + 1e-9]


def scored(drive_mcap: Path) -> np.ndarray:
    """(M, 3) per valid (prediction, step) with truth: the window's span [s], the squared
    Mahalanobis distance of the error under the config's ellipse, and the error [m]."""
    p = pipeline.predict_log(drive_mcap, WAYPOINTS, config=CONFIG)
    d = p.drive
    w = history_windows(d, p.predictor.params.settings.history)
    oldest_s = np.where(w["valid"], w["t_s"], np.inf).min(axis=1)
    span_s = w["t_now_s"] - oldest_s
    out = []
    for k in range(p.poses_m.shape[1]):
        t_s = p.stamps_s + (k + 1) * p.dt_s
        known = (t_s >= d.truth_t_s[0]) & (t_s <= d.truth_t_s[-1]) & p.valid
        truth = np.column_stack([np.interp(t_s, d.truth_t_s, d.truth_xy_m[:, i]) for i in range(2)])
        r = truth - p.poses_m[:, k, :2]
        d2 = np.einsum("ni,nij,nj->n", r, np.linalg.inv(p.cov_m2[:, k]), r)
        out.append(np.column_stack([span_s, d2, np.hypot(r[:, 0], r[:, 1])])[known])
    return np.concatenate(out)


def main() -> None:
    start = time.perf_counter()
    parts = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in SEEDS:
            folder = Path(tmp) / f"oval{seed}"
            pipeline.simulate_to(
                folder,
                track="oval",
                duration_s=DURATION_S,
                seed=seed,
                sensor="apriltag",
                stops_per_min=1.0,
            )
            parts.append(scored(folder / "drive.mcap"))
    a = np.concatenate(parts)
    lines = [
        "# Valid predictions by the age of their history window",
        "",
        f"Regenerate: `.venv/bin/python experiments/uncertainty/young_history.py` (this run: "
        f"{(time.perf_counter() - start) / 60:.1f} min wall on the shared 2-core machine).",
        "",
        f"{len(SEEDS)} simulated {DURATION_S:.0f} s drives on the oval (seeds {SEEDS.start}-"
        f"{SEEDS.stop - 1}, AprilTag sensor, one stop a minute), predicted with "
        "`fit/sim-oval.json`; every valid prediction's steps 1-10 against the truth, binned by "
        "the span of its history window. Coverage: the share inside the config's 1- and "
        "2-sigma ellipses (ideal 39.3 % / 86.5 %). Targets: (prediction, step) pairs.",
        "",
        "| window span [s] | targets | 1 sigma | 2 sigma | median error [m] |",
        "|---|---:|---:|---:|---:|",
    ]
    for lo, hi in zip(BINS_S[:-1], BINS_S[1:], strict=True):
        m = (a[:, 0] >= lo - 1e-9) & (a[:, 0] < hi - 1e-9)
        if not m.any():
            continue
        lines.append(
            f"| {lo:.1f}-{min(hi, 1.0):.1f} | {m.sum()} | {np.mean(a[m, 1] <= 1):.1%} | "
            f"{np.mean(a[m, 1] <= 4):.1%} | {np.median(a[m, 2]):.3f} |"
        )
    young = a[:, 0] < 0.7 - 1e-9
    lines += [
        "",
        f"Windows younger than 0.7 s hold {young.mean():.2%} of the targets here: a window "
        "starts again only after a detection gap over 1 s, and these drives have few. Too few "
        "to fit a span-dependent ellipse on; the youngest windows' errors are larger than "
        "the ellipses fitted on full ones describe.",
        "",
    ]
    OUT.write_text("\n".join(lines))
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
