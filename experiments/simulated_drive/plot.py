"""Look at simulated drives: a built-in track and an F1TENTH track, truth vs delayed detections.

Writes experiments/simulated_drive/drive.png. Run from anywhere:
    .venv/bin/python experiments/simulated_drive/plot.py
The F1TENTH panel needs ../shared/data/tracks beside the project (it is left out otherwise).
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from fpe_jax.plots import closed, track_edges  # noqa: E402
from fpe_jax.sim._sim import SimResult, simulate  # noqa: E402

HERE = Path(__file__).resolve().parent
TRACKS = HERE.parents[1].parent / "shared" / "data" / "tracks"
DURATION_S, LATENCY_S, SEED = 60.0, 0.3, 0


def _track_panel(ax, res: SimResult, title: str, zoom: tuple[float, float, float] | None = None):
    d = res.drive
    for edge in track_edges(res.centerline_xy_m, res.half_width_m):
        ax.plot(*closed(edge).T, color="0.3", lw=0.8)
    center = closed(res.centerline_xy_m)
    ax.plot(*center.T, color="0.6", lw=0.8, ls="--", label="centerline (given to predictors)")
    if res.scenario["raceline"]:
        ax.plot(*res.reference_xy_m.T, color="tab:green", lw=0.8, label="raceline (driver's path)")
    ax.plot(*d.truth_xy_m.T, color="tab:blue", lw=1.0, label="true path (50 Hz)")
    ok = ~res.outlier
    ax.plot(*d.xy_m[ok].T, ".", color="tab:red", ms=3, label="detections (~11 Hz)")
    ax.plot(*d.xy_m[res.outlier].T, "x", color="black", ms=6, label="outliers")
    if zoom is not None:
        # One pass through the zoom window: tie each detection to where the car really was at
        # its stamp; the lines show how far the car moved during the latency.
        x0, y0, r = zoom
        inside = np.hypot(d.truth_xy_m[:, 0] - x0, d.truth_xy_m[:, 1] - y0) < r
        first = int(np.argmax(inside))
        last = first + int(np.argmin(inside[first:])) if not inside[first:].all() else len(inside)
        t0, t1 = d.truth_t_s[first], d.truth_t_s[last - 1]
        sel = (d.t_s >= t0) & (d.t_s <= t1)
        x_true = np.interp(d.t_s[sel], d.truth_t_s, d.truth_xy_m[:, 0])
        y_true = np.interp(d.t_s[sel], d.truth_t_s, d.truth_xy_m[:, 1])
        label = f"true position at the detection's stamp ({t0:.0f}-{t1:.0f} s)"
        ax.plot(x_true, y_true, "o", mfc="none", color="tab:blue", ms=6, label=label)
        for a, b, p, q in zip(d.xy_m[sel, 0], d.xy_m[sel, 1], x_true, y_true):
            ax.plot([a, p], [b, q], color="tab:purple", lw=0.8)
        ax.plot(*d.xy_m[sel & ok].T, "o", color="tab:red", ms=4)
        ax.set(xlim=(x0 - r, x0 + r), ylim=(y0 - r, y0 + r))
    ax.set(aspect="equal", xlabel="x [m]", ylabel="y [m]")
    ax.set_title(title, fontsize=10)


def main() -> None:
    kw = dict(duration_s=DURATION_S, latency_s=LATENCY_S, seed=SEED)
    runs = [("hairpin", simulate("hairpin", **kw))]
    if TRACKS.is_dir():
        center, race = TRACKS / "Spielberg_centerline.csv", TRACKS / "Spielberg_raceline.csv"
        runs.append(("Spielberg (F1TENTH)", simulate(center, raceline=race, **kw)))
    else:
        print(f"note: {TRACKS} not found; plotting the built-in track only")

    fig = plt.figure(figsize=(17, 9))
    grid = fig.add_gridspec(2, 3, height_ratios=[1.9, 1], width_ratios=[1.4, 1, 1.2])
    hp = runs[0][1]
    _track_panel(fig.add_subplot(grid[0, 0]), hp, "built-in 'hairpin' track")
    title = f"hairpin, zoom: detections lag the car by {LATENCY_S} s (+ noise)"
    _track_panel(fig.add_subplot(grid[0, 1]), hp, title, zoom=(11.5, 5.5, 3.0))
    if len(runs) > 1:
        ax = fig.add_subplot(grid[0, 2])
        _track_panel(ax, runs[1][1], "F1TENTH Spielberg, driver on the raceline")
        ax.legend(loc="lower left", fontsize=7)
    # The zoom panel has every legend entry; show them in the blank space under the first map.
    handles, labels = fig.axes[1].get_legend_handles_labels()
    fig.axes[0].legend(handles, labels, loc="upper center", bbox_to_anchor=(0.5, -0.3), ncol=2)

    ax = fig.add_subplot(grid[1, :])
    for (name, res), color in zip(runs, ("tab:blue", "tab:orange")):
        d = res.drive
        ax.plot(d.truth_t_s, d.truth_v_mps, color=color, label=f"{name}: true speed")
    ax.axhspan(2.0, 8.0, color="0.9", zorder=0, label="target range 2-8 m/s")
    ax.set(xlabel="time [s]", ylabel="speed [m/s]", ylim=(0, 9))
    ax.legend(loc="lower right", fontsize=8)
    ax.set_title("speed of the leading car", fontsize=10)
    fig.suptitle(
        f"Simulated leading-car drives (dynamic single-track car, pure-pursuit driver; "
        f"AprilTag-like detector, latency {LATENCY_S} s; seed {SEED})"
    )
    fig.tight_layout()
    out = HERE / "drive.png"
    fig.savefig(out, dpi=110)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
