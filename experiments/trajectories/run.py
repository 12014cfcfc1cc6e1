"""A picture like the thesis's Figure 13: track, actual path and predicted 1 s trajectories every
few observations, hand-set (seed) vs fitted, with a zoom on the corner where the seed turns
earliest relative to the car.

- Levine (real): fit on the first 60 % of the lap, draw the last 40 % (held out): seed vs fitted.
- hairpin (simulated, latency 0.3 s): fit drive 60 s, test drive 40 s (other seed): seed,
  seed-measured-speed and fitted; the zoom is where seed-measured-speed turns earliest (the seed
  drives at a hard-coded 1 m/s and so hardly moves on a 4-8 m/s track).

"Turns early" is measured: for every prediction, how far its 1 s point lies on the inside of the
bend relative to where the car really was 1 s later (> 0: turned earlier / tighter than the car);
the table gives its mean over the zoomed passage and over all bends.

Run:  .venv/bin/python experiments/trajectories/run.py   (about 2 minutes on the 2-core machine)
Writes experiments/results/trajectories.md, trajectories_levine.png, trajectories_hairpin.png.
"""

from __future__ import annotations

import time
from pathlib import Path

import jax
import numpy as np

from fpe_jax import plots
from fpe_jax.evaluate._evaluate import heldout_predictions
from fpe_jax.fit._cases import LATENCY_S, fit_case, real_cases, simulated_case
from fpe_jax.fit._report import md_table
from fpe_jax.model._params import presets
from fpe_jax.progress import Progress

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT.parent / "shared" / "data"
RESULTS = ROOT / "experiments" / "results"
WINDOW = 9  # predictions averaged when choosing the corner (plots.pick_corner)


def early_turn_rows(held, names, waypoints_xy_m, corner: int) -> list[list[str]]:
    """Table rows: per predictor, mean inside offset [m] at the zoomed passage and on bends, and
    the mean 1 s error [m] at the zoomed passage."""
    rows = []
    lo, hi = max(corner - WINDOW // 2, 0), corner + WINDOW // 2 + 1
    for name in names:
        score = plots.inside_offset(held, name, waypoints_xy_m)
        err = np.linalg.norm(held.pred_xy_m[name][:, -1] - held.target_xy_m[:, -1], axis=1)
        err = np.where(held.mask[:, -1], err, np.nan)
        means = np.nanmean(score[lo:hi]), np.nanmean(score), np.nanmean(err[lo:hi])
        rows.append([plots.APPROACH[name], *(f"{x:+.3f}" for x in means[:2]), f"{means[2]:.3f}"])
    return rows


def figure(case, result, names, corner_by, title, png):
    """Draw one case; returns the markdown section describing it."""
    track = case.track()
    by_name = {n: presets[n] for n in names if n != "fitted"} | {"fitted": result.params}
    held = heldout_predictions(case.test_drive, track, by_name)
    corner = plots.pick_corner(held, corner_by, case.waypoints_xy_m, window=WINDOW)
    kw = dict(names=names, half_width_m=case.half_width_m, corner=corner, title=title)
    fig = plots.trajectory_figure(case.waypoints_xy_m, case.test_drive, held, **kw)
    plots.save(fig, RESULTS / png)
    t_corner = case.test_drive.t_s[held.rows[corner]] - case.test_drive.t_s[0]
    center = held.target_xy_m[corner, held.target_xy_m.shape[1] // 2]
    p = result.params.physical()
    return [
        f"## {case.name}",
        "",
        f"{case.description}. Fitted ({result.info['blend']} blend): lookahead "
        f"{p['lookahead_m']:.3f} m + {p['lookahead_gain_s']:.3f} s * v, delay "
        f"{p['delay_s']:.3f} s.",
        "",
        f"![{case.name}]({png})",
        "",
        f"Zoomed corner: around ({center[0]:.1f}, {center[1]:.1f}) m, {t_corner:.1f} s into the "
        f"test part; chosen where `{corner_by}` turns earliest (largest mean inside offset over "
        f"{WINDOW} consecutive predictions).",
        "",
        *md_table(
            "predictor | inside offset at 1 s, zoomed passage m | inside offset at 1 s, all "
            "bends m | 1 s error, zoomed passage m",
            early_turn_rows(held, names, case.waypoints_xy_m, corner),
        ),
        "",
    ]


def main() -> None:
    jax.config.update("jax_enable_x64", True)  # fitting and evaluation in float64
    t0 = time.perf_counter()
    sections = []
    with Progress() as say:
        title = "Levine (real AprilTag trace), held-out last 40 % of the lap: the 2019 seed vs "
        title += "the fitted predictor"
        drawn = ("seed", "fitted"), "seed", title, "trajectories_levine.png"
        runs = [(c, "auto", *drawn) for c in real_cases(DATA, say)]  # (case, blend, names, ...)
        hairpin = simulated_case("hairpin", fit_s=60.0, test_s=40.0, latency_s=LATENCY_S)
        title = f"hairpin (simulated, latency {LATENCY_S} s), separate test drive: hand-set blends "
        title += "vs the fitted predictor"
        names = ("seed", "seed-measured-speed", "fitted")
        runs.append((hairpin, "position", names, names[1], title, "trajectories_hairpin.png"))
        for case, blend, names, corner_by, title, png in runs:
            say(f"{case.name}: fitting ({blend} blend)")
            progress = lambda m, n=case.name: say(f"{n}: {m}")  # noqa: E731
            res = fit_case(case, model="blend", blend=blend, progress=progress)
            say(f"{case.name}: drawing")
            sections += figure(case, res, names, corner_by, title, png)
    head = [
        "# Predicted 1 s trajectories: hand-set vs fitted (cf. the thesis's Figure 13)",
        "",
        "Regenerate: `.venv/bin/python experiments/trajectories/run.py` (this run: "
        f"{(time.perf_counter() - t0) / 60:.1f} min).",
        "",
        "Top row: the whole held-out drive with one 1 s prediction every few "
        "observations (each drawn from the observation it started from; the dot is its "
        "1.0 s point). Bottom row: the zoomed corner, with the car's actual position 1 s "
        "later (x) joined to each prediction's 1 s point (dotted). 'Inside offset': how "
        "far the 1 s point lies toward the inside of the bend relative to the actual "
        "position (> 0: the predictor turned earlier / tighter than the car did).",
        "",
    ]
    md = RESULTS / "trajectories.md"
    md.write_text("\n".join(head + sections))
    print(f"wrote {md}")


if __name__ == "__main__":
    main()
