"""In-race learning (`fpe_jax.adapt.AdaptiveRunner`) against configs fitted offline.

(a) No fit drive at all: the adapting runner starts from the waypoints alone (the line model's
    defaults, the ego sensor's known detection delay) and drives the opponent's race; its FDE at
    1 s on laps 1, 2, 3 and 5 against a config fitted offline on a separate drive of the same
    opponent (the static runner with that config, on the same race).
(b) The opponent changes mid-race: after three laps on its normal line it drives a defensive line
    (0.6 m further inside), takes corners slower (lateral acceleration 5 -> 3 m/s^2, as on worn
    tyres) and keeps a lower pace (top speed 8 -> 6 m/s). FDE at 1 s per lap after the change for
    the static config (fitted on the old behaviour), the adapting runner (started from that same
    config), and a config fitted offline on a separate drive of the new behaviour.

Simulated on the built-in oval and hairpin (`fpe_jax.sim`), detection latency 0.3 s, targets the
true positions 1 s after each detection's stamp. Every prediction comes from the NumPy runners
(`fpe_jax.runner`), whose parity with the JAX predictor is tested.

Run:  .venv/bin/python experiments/inrace/run.py   (a few minutes: two offline fits per track)
Writes experiments/results/inrace.md.
"""

from __future__ import annotations

import dataclasses
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

from fpe_jax.adapt import AdaptiveRunner
from fpe_jax.cases import LATENCY_S
from fpe_jax.config import params_to_config
from fpe_jax.path import waypoints_sha256
from fpe_jax.progress import Progress
from fpe_jax.runner import Runner, RunnerPath
from fpe_jax.sim import Driver, simulate

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "experiments" / "results"
TRACKS = ("oval", "hairpin")
AHEAD_S = 1.0  # the FDE's lead time [s] (step 10 of 0.1 s)
FIT_S = 60.0  # each offline fit drive [s]
RACE_LAPS = 6  # (a): laps of the race scored
OLD_LAPS, NEW_LAPS = 3, 5  # (b): laps before and after the change
INSIDE_M = 0.6  # (b): the defensive line's shift toward the inside [m]
NEW_DRIVER = dict(lat_accel_mps2=3.0, v_max_mps=6.0)  # (b): slower corners, lower pace
SEEDS = dict(fit_old=1, race=3, fit_new=11, race_new=12)


def defensive_line(center_xy_m: np.ndarray, inside_m: float) -> np.ndarray:
    """The centerline (K, 2) [m] moved `inside_m` toward the loop's inside (left on a
    counter-clockwise loop)."""
    xy = np.asarray(center_xy_m, dtype=float)
    nxt = np.roll(xy, -1, axis=0)
    area = 0.5 * np.sum(xy[:, 0] * nxt[:, 1] - nxt[:, 0] * xy[:, 1])
    tangent = np.roll(xy, -1, axis=0) - np.roll(xy, 1, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    left = np.column_stack([-tangent[:, 1], tangent[:, 0]])
    return xy + np.sign(area) * inside_m * left


def lap_of(path: RunnerPath, t_s: np.ndarray, drive) -> np.ndarray:
    """The lap (0 = the first) the car is on at each stamp t_s (N,), from its true arc length."""
    s, out = None, []
    for x, y in drive.truth_xy_m:
        s = path.project(x, y) if s is None else path.project_window(x, y, s)
        out.append(s)
    s = np.unwrap(np.asarray(out), period=path.length_m)
    lap = np.floor((s - s[0]) / path.length_m)
    return np.interp(t_s, drive.truth_t_s, lap).astype(int)


def errors_at(runner, drive, lead_s: float = AHEAD_S) -> np.ndarray:
    """(N,) distance [m] between each observation's prediction lead_s ahead and the truth then
    (NaN past the truth's end)."""
    k = int(round(lead_s / runner.dt_s)) - 1
    rows = zip(drive.t_s.tolist(), drive.xy_m.tolist(), drive.yaw_rad.tolist())
    pred = np.array([runner.update(t, x, y, a)[k, :2] for t, (x, y), a in rows])
    t = drive.t_s + lead_s
    tx = np.interp(t, drive.truth_t_s, drive.truth_xy_m[:, 0], right=np.nan)
    ty = np.interp(t, drive.truth_t_s, drive.truth_xy_m[:, 1], right=np.nan)
    return np.hypot(pred[:, 0] - tx, pred[:, 1] - ty)


def fitted_config(drive, wp: np.ndarray, say) -> dict:
    """A line-model config fitted offline (`fpe fit`'s default) on one whole drive."""
    from fpe_jax.fit import fit
    from fpe_jax.track import Track

    track = Track.from_waypoints(wp)
    res = fit([drive], [track], test_drives=[drive], test_tracks=[track], progress=say)
    return params_to_config(res.params, line={"waypoints_sha256": waypoints_sha256(wp)})


def per_lap(err: np.ndarray, lap: np.ndarray, laps) -> list[float]:
    """Median error [m] on each lap in `laps` (1-based)."""
    return [
        float(np.nanmedian(err[lap == n - 1])) if np.any(lap == n - 1) else np.nan for n in laps
    ]


def run_track(name: str, say) -> dict:
    old = simulate(name, duration_s=1.0)
    wp, hw = old.centerline_xy_m, old.half_width_m
    path = RunnerPath(wp)
    lap_s = path.length_m / 5.0  # a generous lap time at the default pace
    # (a) the opponent's race and a separate fit drive of it
    race = simulate(name, duration_s=(RACE_LAPS + 0.5) * lap_s, seed=SEEDS["race"])
    fit_old = simulate(name, duration_s=FIT_S, seed=SEEDS["fit_old"]).drive
    say(f"{name}: fitting the old behaviour offline")
    cfg_old = fitted_config(fit_old, wp, say)
    lap = lap_of(path, race.drive.t_s, race.drive)
    laps = (1, 2, 3, 5)
    a = {
        "offline fit (separate drive)": per_lap(
            errors_at(Runner(cfg_old, wp), race.drive), lap, laps
        ),
        "adapting, from the waypoints alone": per_lap(
            errors_at(AdaptiveRunner(None, wp, delay_s=LATENCY_S), race.drive), lap, laps
        ),
        "adapting, from the offline fit": per_lap(
            errors_at(AdaptiveRunner(cfg_old, wp), race.drive), lap, laps
        ),
    }
    # (b) the change: a defensive line, slower corners, lower pace
    with tempfile.TemporaryDirectory() as tmp:
        line = Path(tmp) / "defensive.csv"
        np.savetxt(line, defensive_line(wp, INSIDE_M), delimiter=",", header="x,y", comments="")
        driver = dataclasses.replace(Driver(), **NEW_DRIVER)
        kw = dict(raceline=str(line), half_width_m=hw, driver=driver)
        fit_new = simulate(name, duration_s=FIT_S, seed=SEEDS["fit_new"], **kw).drive
        new_lap_s = path.length_m / 3.5
        after = simulate(
            name, duration_s=(NEW_LAPS + 0.5) * new_lap_s, seed=SEEDS["race_new"], **kw
        )
    say(f"{name}: fitting the new behaviour offline")
    cfg_new = fitted_config(fit_new, wp, say)
    before = simulate(name, duration_s=OLD_LAPS * lap_s, seed=SEEDS["race"]).drive
    new_laps = tuple(range(1, NEW_LAPS + 1))
    lap_new = lap_of(path, after.drive.t_s, after.drive)
    runners = {
        "static (fitted on the old behaviour)": Runner(cfg_old, wp),
        "adapting (from the same config)": AdaptiveRunner(cfg_old, wp),
        "offline fit on the new behaviour": Runner(cfg_new, wp),
    }
    b = {}
    for label, r in runners.items():
        errors_at(r, before)  # the race before the change: the adapting runner learns the old line
        r.reset()  # the car out of sight for a moment as it changes (the history restarts)
        b[label] = per_lap(errors_at(r, after.drive), lap_new, new_laps)
    adapt = runners["adapting (from the same config)"]
    return dict(
        a=a,
        b=b,
        laps=laps,
        new_laps=new_laps,
        length_m=path.length_m,
        adapt_laps=adapt.laps,
        samples=adapt.samples,
    )


def main() -> None:
    jax.config.update("jax_enable_x64", True)
    t0 = time.perf_counter()
    out = {}
    with Progress() as say:
        for name in TRACKS:
            out[name] = run_track(name, say)
    RESULTS.mkdir(parents=True, exist_ok=True)
    md = RESULTS / "inrace.md"
    md.write_text(markdown(out, time.perf_counter() - t0))
    print(f"wrote {md}")


def _cells(values, ref=None) -> str:
    if ref is None:
        return " | ".join(f"{v:.3f}" for v in values)
    return " | ".join(f"{v:.3f} ({v / r:.2f}x)" for v, r in zip(values, ref))


def markdown(out: dict, wall_s: float) -> str:
    lines = [
        "# In-race learning: the adapting runner against configs fitted offline",
        "",
        f"Regenerate: `.venv/bin/python experiments/inrace/run.py` (this run: {wall_s / 60:.1f} "
        "min wall on the shared 2-core machine, mostly the four offline fits).",
        "",
        "Median distance [m] between the prediction 1 s ahead and the true position then, per "
        "lap of the opponent. Simulated drives on the built-in tracks, detection latency "
        f"{LATENCY_S} s, every prediction from the NumPy runners (`fpe_jax.runner.Runner`, "
        "`fpe_jax.adapt.AdaptiveRunner`, lap decay 0.25). Offline fits: `fpe fit`'s default "
        f"(line model) on a separate {FIT_S:g} s drive.",
        "",
        "## (a) No fit drive: learning from the first lap",
        "",
        "The adapting runner starts from the waypoints alone: the line model's defaults, an "
        "empty profile (where the car has not been seen it keeps its own offset and speed), "
        f"and the ego sensor's detection delay ({LATENCY_S} s, a property of one's own car, "
        "known without any drive of the opponent). Ratio: to the offline fit on the same lap "
        "(target: lap 2 within 1.2x).",
        "",
    ]
    for name, r in out.items():
        ref = r["a"]["offline fit (separate drive)"]
        lines += [
            f"### {name} ({r['length_m']:.0f} m loop)",
            "",
            "| runner | " + " | ".join(f"lap {n}" for n in r["laps"]) + " |",
            "|---" * (len(r["laps"]) + 1) + "|",
        ]
        for label, v in r["a"].items():
            lines.append(f"| {label} | {_cells(v, None if v is ref else ref)} |")
        lines.append("")
    lines += [
        "## (b) The opponent changes its line, cornering and pace",
        "",
        f"Three laps on its normal line, then a defensive line {INSIDE_M} m further inside, "
        "corners at 3 instead of 5 m/s^2 of lateral acceleration and a top speed of 6 instead "
        "of 8 m/s. Laps counted from the change; ratio: to the offline fit on the new "
        "behaviour (target: by lap 2 within 1.2x, and at least 30 % better than static).",
        "",
    ]
    for name, r in out.items():
        ref = r["b"]["offline fit on the new behaviour"]
        static = r["b"]["static (fitted on the old behaviour)"]
        adapt = r["b"]["adapting (from the same config)"]
        lines += [
            f"### {name}",
            "",
            "| runner | " + " | ".join(f"lap {n}" for n in r["new_laps"]) + " |",
            "|---" * (len(r["new_laps"]) + 1) + "|",
        ]
        for label, v in r["b"].items():
            lines.append(f"| {label} | {_cells(v, None if v is ref else ref)} |")
        gain = 1.0 - adapt[1] / static[1]
        lines += [
            "",
            f"Lap 2 after the change: adapting {adapt[1]:.3f} m = {adapt[1] / ref[1]:.2f}x the "
            f"new-behaviour fit, {gain:.0%} better than static.",
            "",
        ]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
