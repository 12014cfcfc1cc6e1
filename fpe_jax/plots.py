"""Figures for `fpe demo`, `fpe plot` and the experiments (matplotlib, Agg backend).

Imported only by the CLI, the demo and experiments, never by core modules. Every figure has axis
labels with units, a legend and a title. Inputs are plain NumPy arrays; positions in metres in the
map frame, errors in metres, times in seconds.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only: no display on CI machines or cars (and the experiments' pyplot)
import numpy as np  # noqa: E402
from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.layout_engine import TightLayoutEngine  # noqa: E402

# One colour per predictor, the same in every figure.
COLORS = {
    "fitted": "tab:green",
    "seed": "tab:red",
    "seed-measured-speed": "tab:orange",
    "linear": "tab:purple",
    "pure-pursuit": "tab:blue",
    "constant-velocity": "tab:brown",
    "ctrv": "tab:gray",
    "frenet": "tab:olive",
}
# The thesis's names for the presets it describes.
APPROACH = {
    "constant-velocity": "approach 1: displacement (constant velocity)",
    "linear": "approach 2: linear",
    "pure-pursuit": "approach 3: pure pursuit",
    "seed": "approach 4: 0.7 blend as written (seed)",
    "seed-measured-speed": "approach 4 with measured speed",
    "ctrv": "constant turn rate and velocity",
    "frenet": "frenet (track speed held, offset decays)",
    "fitted": "fitted",
}


def color(name: str) -> str:
    return COLORS.get(name, "tab:green")  # a config: drawn like the fitted one


def subplots(nrows: int = 1, ncols: int = 1, *, figsize: tuple[float, float], **kwargs):
    """`pyplot.subplots` without pyplot: a Figure drawn by Agg and its axes. pyplot's figure
    manager and state, and the time its import adds to `fpe plot`, serve no purpose when every
    figure goes to a file."""
    fig = Figure(figsize=figsize)
    FigureCanvasAgg(fig)
    return fig, fig.subplots(nrows, ncols, **kwargs)


def tight_layout(fig, rect: tuple[float, float, float, float] | None = None) -> None:
    """`Figure.tight_layout` once, leaving the figure without a layout engine: the method leaves
    a placeholder engine behind, for which `savefig` lays the whole figure out again (a full
    draw without pixels) only to do nothing with it."""
    TightLayoutEngine(rect=rect).execute(fig)


def save(fig, path: str | Path, dpi: int = 110, *, force: bool = True) -> Path:
    """Write a figure (format from the suffix) atomically and free it; returns the path.

    `force=False` refuses to replace an existing file."""
    from fpe_jax.io.writers import atomic_output

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        with atomic_output(path, force) as tmp, open(tmp, "xb") as f:
            fig.savefig(f, dpi=dpi, format=path.suffix.lstrip(".").lower() or "png")
    finally:
        if fig.canvas.manager is not None:  # made by pyplot (the experiments'): let it go
            import matplotlib.pyplot as plt

            plt.close(fig)
    return path


# ---- geometry ------------------------------------------------------------------------------------


def closed(xy_m: np.ndarray) -> np.ndarray:
    """(K+1, 2) the loop (K, 2) with its first point repeated, for drawing."""
    return np.vstack([xy_m, xy_m[:1]])


def track_edges(center_xy_m: np.ndarray, half_width_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Left and right edges (K, 2) [m] of a closed centerline (K, 2) at `half_width_m`."""
    from fpe_jax.geometry._path import left_normals

    n = left_normals(np.asarray(center_xy_m, dtype=np.float64))
    return center_xy_m + half_width_m * n, center_xy_m - half_width_m * n


def bends(xy_m: np.ndarray, baseline_m: float = 1.0, reach_m: float = 3.0):
    """Where a path (K, 2) bends, on the cleaned path the predictors use (`path.build_path`:
    duplicate points dropped, resampled every 0.1 m, hand-driven jitter smoothed).

    Returns:
        xy_m: (M, 2) the path's points [m].
        tangent: (M, 2) unit tangents (in waypoint order).
        curvature_1pm: (M,) signed curvature [1/m] (left > 0): the heading change between
            baseline_m behind and ahead, over 2 * baseline_m.
        bend_1pm: (M,) the curvature of largest magnitude within +-reach_m: a point counts as
            "at a bend" when one is near, so an early turn on the approach is seen too.
    """
    from fpe_jax.geometry._path import build_path, wrap_angle

    path = build_path(xy_m)
    p, heading, ds = path["xy_m"], path["heading_rad"], path["ds_m"]
    b = max(int(round(baseline_m / ds)), 1)
    if path["closed"]:
        k = wrap_angle(np.roll(heading, -b) - np.roll(heading, b)) / (2 * b * ds)
    else:  # open path: one-sided at the ends
        i = np.arange(len(p))
        hi, lo = np.minimum(i + b, len(p) - 1), np.maximum(i - b, 0)
        k = wrap_angle(heading[hi] - heading[lo]) / np.maximum((hi - lo) * ds, ds)
    tangent = np.stack([np.cos(heading), np.sin(heading)], axis=1)
    r = int(round(reach_m / ds))
    pad = np.concatenate([k[-r:], k, k[:r]]) if path["closed"] else np.pad(k, r, mode="edge")
    win = np.lib.stride_tricks.sliding_window_view(pad, 2 * r + 1)
    bend = win[np.arange(len(k)), np.argmax(np.abs(win), axis=1)]
    return p, tangent, k, bend


def ellipse_xy(center_m: np.ndarray, cov_m2: np.ndarray, n_sigma: float, n: int = 64):
    """(n, 2) points [m] of the n_sigma ellipse {x : x^T cov^-1 x = n_sigma^2} around center."""
    vals, vecs = np.linalg.eigh(cov_m2)
    a = np.linspace(0.0, 2 * np.pi, n)
    circle = np.stack([np.cos(a), np.sin(a)], 1) * np.sqrt(np.maximum(vals, 0.0))
    return center_m + n_sigma * circle @ vecs.T


# ---- building blocks -----------------------------------------------------------------------------


def draw_track(ax, waypoints_xy_m: np.ndarray, half_width_m: float | None = None) -> None:
    """The predictors' path (dashed) and, when the half-width is known, the track edges."""
    if half_width_m is not None:
        left, right = track_edges(waypoints_xy_m, half_width_m)
        ax.plot(*closed(left).T, color="0.35", lw=0.8, label="track edges")
        ax.plot(*closed(right).T, color="0.35", lw=0.8)
    path = closed(waypoints_xy_m)
    ax.plot(*path.T, color="gold", lw=1.0, ls="--", label="waypoints (centerline)")


def draw_actual(ax, drive, label: str = "actual path") -> None:
    """The car's actual path: the truth when the drive has it, else its distinct observations."""
    if drive.has_truth:
        ax.plot(*drive.truth_xy_m.T, color="black", lw=1.0, label=f"{label} (truth)")
    else:
        from fpe_jax.model._history import distinct_mask

        xy = drive.xy_m[distinct_mask(drive.xy_m)]
        ax.plot(*xy.T, ".-", color="black", lw=0.6, ms=2.5, label=f"{label} (observed)")


def draw_predictions(
    ax, held, name: str, idx: np.ndarray, label: str | None = None, show_truth: bool = False
) -> None:
    """The 1 s predictions idx of predictor `name`, each drawn from the observation it started
    from; with show_truth, also where the car really was 1 s later (x) and the miss (dotted)."""
    c = color(name)
    org, pred = held.origin_xy_m, held.pred_xy_m[name]
    truth_label = "actual position 1 s later (dotted: the miss)"
    for j, i in enumerate(idx):
        path = np.vstack([org[i], pred[i]])
        ax.plot(*path.T, "-", color=c, lw=1.1, alpha=0.9, label=(label or name) if j == 0 else None)
        ax.plot(*pred[i, -1], "o", color=c, ms=3.5)
        if show_truth and held.mask[i, -1]:
            tgt = held.target_xy_m[i, -1]
            ax.plot(*np.vstack([pred[i, -1], tgt]).T, ":", color=c, lw=0.9)
            ax.plot(*tgt, "x", color="black", ms=5, mew=1.2, label=truth_label)
            truth_label = None  # one legend entry
    ax.plot(*org[idx].T, "s", mfc="none", color="0.2", ms=4, label="observation predicted from")


def every_index(n: int, step: int, start: int = 0) -> np.ndarray:
    return np.arange(start, n, max(step, 1))


def finish_map(ax, title: str, legend: bool = True, loc: str = "best", fontsize: int = 7) -> None:
    ax.set_aspect("equal", adjustable="datalim")
    ax.set(xlabel="x [m]", ylabel="y [m]")
    ax.set_title(title, fontsize=10)
    if legend:
        ax.legend(loc=loc, fontsize=fontsize)


def zoom_to(ax, center_m: np.ndarray, radius_m: float) -> None:
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlim(center_m[0] - radius_m, center_m[0] + radius_m)
    ax.set_ylim(center_m[1] - radius_m, center_m[1] + radius_m)


# ---- corner finding ------------------------------------------------------------------------------


BEND_MIN_1PM = 0.1  # radius < 10 m: a bend; below it the score is 0 (straights)
BEND_FULL_1PM = 0.3  # radius < 3.3 m: full weight


def _bend_geometry(held, name: str, waypoints_xy_m: np.ndarray):
    """(lateral offset [m] of the 1 s point toward the bend's inside, bend curvature [1/m])."""
    from fpe_jax.geometry._path import nearest_index

    p, tangent, _, bend = bends(waypoints_xy_m)
    tgt = held.target_xy_m[:, -1]
    j = nearest_index(tgt, p)
    left = np.stack([-tangent[j, 1], tangent[j, 0]], 1)
    lateral = np.sum((held.pred_xy_m[name][:, -1] - tgt) * left, axis=1)  # > 0: left of truth
    # (travel against the waypoint order flips both the normal and the bend's sign: no effect)
    return lateral * np.sign(bend[j]), bend[j]


def inside_offset(held, name: str, waypoints_xy_m: np.ndarray) -> np.ndarray:
    """(N,) how far [m] each prediction's 1 s point lies on the inside of the nearby bend
    relative to where the car really was 1 s later (> 0: the predictor turned earlier / tighter
    than the car did); NaN away from bends (|curvature| < BEND_MIN_1PM within 3 m) and where the
    target is missing."""
    offset, k = _bend_geometry(held, name, waypoints_xy_m)
    return np.where(held.mask[:, -1] & (np.abs(k) >= BEND_MIN_1PM), offset, np.nan)


def early_turn_score(held, name: str, waypoints_xy_m: np.ndarray) -> np.ndarray:
    """(N,) `inside_offset` weighted by the bend's sharpness (full weight from BEND_FULL_1PM),
    0 away from bends, NaN without target: what `pick_corner` maximises."""
    offset, k = _bend_geometry(held, name, waypoints_xy_m)
    weight = np.where(np.abs(k) < BEND_MIN_1PM, 0.0, np.minimum(np.abs(k) / BEND_FULL_1PM, 1.0))
    return np.where(held.mask[:, -1], offset * weight, np.nan)


def _window_argmax(score: np.ndarray, window: int) -> int:
    s = np.nan_to_num(score, nan=0.0)
    return int(np.argmax(np.convolve(s, np.ones(window) / window, mode="same")))


def pick_corner(held, name: str, waypoints_xy_m: np.ndarray, window: int = 9) -> int:
    """Index of the prediction at the centre of the window where `name` turns earliest."""
    return _window_argmax(early_turn_score(held, name, waypoints_xy_m), window)


def pick_worst(held, name: str, window: int = 9) -> int:
    """Index of the prediction at the centre of the window where `name` misses most at 1 s."""
    err = np.linalg.norm(held.pred_xy_m[name][:, -1] - held.target_xy_m[:, -1], axis=1)
    return _window_argmax(np.where(held.mask[:, -1], err, np.nan), window)


# ---- figures -------------------------------------------------------------------------------------


def trajectory_figure(
    waypoints_xy_m: np.ndarray,
    drive,
    held,
    *,
    names: Sequence[str],
    title: str,
    half_width_m: float | None = None,
    corner: int | None = None,
    corner_by: str | None = None,
    n_whole: int = 40,
    n_zoom: int = 12,
    zoom_radius_m: float | None = None,
):
    """Figure-13-style overlay, one column per predictor: the whole drive (top) and a zoom on
    one corner (bottom).

    Args:
        waypoints_xy_m: (K, 2) the predictors' path [m]; drive: the drive predicted from (its
            truth or observations are drawn as the actual path).
        held: an `evaluate.Heldout` with predictions for every name.
        names: predictors to draw (keys of held.pred_xy_m).
        corner: index into held of the zoom's centre; default: where `corner_by` turns earliest
            relative to the car (see `early_turn_score`), or, without corner_by, where names[0]
            misses most at 1 s.
        n_whole, n_zoom: about how many predictions to draw on the whole drive / in the zoom.
        zoom_radius_m: half-size of the zoom window [m] (default: ~1.3 s of travel).
    """
    n = len(held.rows)
    step_s = np.median(np.diff(drive.t_s[held.rows])) if n > 1 else 0.1
    travel = np.linalg.norm(held.target_xy_m[:, -1] - held.target_xy_m[:, 0], axis=1)
    speed = float(np.nanmedian(np.where(held.mask[:, 0] & held.mask[:, -1], travel, np.nan)))
    speed = speed / 0.9 if np.isfinite(speed) else 1.0  # the 0.1 s ... 1.0 s targets span 0.9 s
    radius = zoom_radius_m or float(np.clip(1.3 * speed + 1.0, 2.0, 10.0))
    if corner is None and corner_by:
        corner = pick_corner(held, corner_by, waypoints_xy_m)
    elif corner is None:
        corner = pick_worst(held, names[0])
    center = held.target_xy_m[corner, held.target_xy_m.shape[1] // 2]
    every = max(n // n_whole, 1)
    # the zoom shows the predictions whose start lies in the window: space n_zoom of them
    inside = np.flatnonzero(np.linalg.norm(held.origin_xy_m - center, axis=1) < radius)
    seg = inside[np.abs(inside - corner) < max(2 * radius / max(speed * step_s, 1e-3), 10)]
    zoom_every = max(len(seg) // n_zoom, 1)
    zoom_idx = seg[(seg - corner) % zoom_every == 0]
    if len(names) == 1:  # one predictor: whole drive and zoom side by side
        fig, axes = subplots(1, 2, figsize=(14, 7.6), squeeze=False)
        axes = axes.T  # axes[0, 0] whole, axes[1, 0] zoom
    else:
        fig, axes = subplots(2, len(names), figsize=(6.2 * len(names), 12.4), squeeze=False)
    panels = (
        (every_index(n, every), False, f"whole drive: one prediction per {every}"),
        (zoom_idx, True, f"zoom: one prediction per {zoom_every}"),
    )
    for col, name in enumerate(names):
        shown = APPROACH.get(name, name)
        for ax, (idx, zoom, what) in zip(axes[:, col], panels):
            draw_track(ax, waypoints_xy_m, half_width_m)
            draw_actual(ax, drive)
            draw_predictions(ax, held, name, idx, label=f"{shown}: 1 s prediction", show_truth=zoom)
            if not zoom:
                ax.plot(*center, "*", color="magenta", ms=15, ls="none", label="zoom centre")
            finish_map(ax, f"{shown}\n{what} observations", legend=False)
        zoom_to(axes[1, col], center, radius)
    handles = {}
    for ax in axes.flat:
        for hnd, lab in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(lab, hnd)
    ncol = 3 if len(names) == 1 else 4
    fig.legend(handles.values(), handles.keys(), loc="lower center", ncol=ncol, fontsize=9)
    fig.suptitle(title)
    legend_in = 0.3 * -(-len(handles) // ncol) + 0.25  # rows of ~0.3 inch, plus margins
    tight_layout(fig, rect=(0, legend_in / fig.get_figheight(), 1, 1))
    return fig


def error_vs_horizon_figure(
    reports: Mapping[str, dict],
    *,
    dt_s: float,
    title: str,
    names: Sequence[str] | None = None,
    ncols: int = 4,
):
    """Mean error [m] against the prediction horizon [s], one panel per case, one line per
    predictor (from `FitResult.report` dicts: name -> metrics with per_step_m)."""
    k = len(reports)
    ncols = min(ncols, k)
    nrows = int(np.ceil(k / ncols))
    fig, axes = subplots(nrows, ncols, figsize=(4.6 * ncols, 3.8 * nrows + 0.8), squeeze=False)
    for ax, (case, rep) in zip(axes.flat, reports.items()):
        for name in names or list(rep):
            per = np.asarray(rep[name]["per_step_m"])
            h = dt_s * np.arange(1, len(per) + 1)
            style, lw = ("o-", 2.2) if name == "fitted" else (".-", 1.2)
            ax.plot(h, per, style, color=color(name), lw=lw, ms=4, label=APPROACH.get(name, name))
        ax.set(xlabel="horizon [s]", ylabel="mean position error [m]")
        ax.set_title(case, fontsize=10)
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
        if k == 1:
            ax.legend(fontsize=7, loc="upper left")
    for ax in list(axes.flat)[k:]:
        ax.set_visible(False)
    fig.suptitle(title)
    if k > 1:  # one legend for all panels (same predictors, same colours)
        handles, labels = axes.flat[0].get_legend_handles_labels()
        fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 4), fontsize=9)
        tight_layout(fig, rect=(0, 0.05 + 0.03 / nrows, 1, 1))
    else:
        tight_layout(fig)
    return fig


def weights_figure(params_by_label: Mapping[str, object], *, title: str, latency_s=None):
    """Fitted per-step blend weights (1 = linear, 0 = pure pursuit) against the seed's 0.7^i,
    with each fit's lookahead, delay and speed model in its legend entry."""
    fig, ax = subplots(figsize=(8, 5))
    first = next(iter(params_by_label.values()))
    h = first.settings.horizon
    t = first.settings.dt_s * np.arange(1, h + 1)
    ax.plot(t, 0.7 ** np.arange(h), "s--", color=color("seed"), label="seed: 0.7^i (i = 0..9)")
    markers = "o^vD<>ph*"
    for j, (label, p) in enumerate(params_by_label.items()):
        v = p.physical()
        text = (
            f"{label}: L = {v['lookahead_m']:.2f} m + {v['lookahead_gain_s']:.2f} s*v, "
            f"delay {v['delay_s']:.3f} s"
        )
        if latency_s is not None and len(params_by_label) == 1:
            text += f" (true {latency_s:.2f} s)"
        ax.plot(t, v["weights"], markers[j % len(markers)] + "-", label=text)
    ax.set(ylim=(-0.03, 1.03), xlabel="horizon [s]")
    ax.set_ylabel("weight on the linear rollout [-] (1 - weight on pure pursuit)")
    ax.set_title(title, fontsize=11)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7.5, loc="upper right")
    tight_layout(fig)
    return fig


# ---- `fpe plot` ----------------------------------------------------------------------------------

FIGURE_SUFFIXES = (".png", ".pdf", ".svg")


def plot_drive(
    drive, waypoints_xy_m: np.ndarray, held, name: str, metrics: dict, out, *, source: str
) -> Path:
    """`fpe plot`'s figure: a user's drive with one predictor's 1 s predictions, whole and zoomed
    on the stretch where it misses most; writes `out`.

    Args:
        drive: the drive (`Drive`) in the map frame.
        waypoints_xy_m: (K, 2) the path the predictor follows [m].
        held: `evaluate.Heldout` of the predictor `name`, in the same frame.
        metrics: `metrics.summarize` of those predictions (for the title).
        out: figure path (.png, .pdf or .svg).
        source: what the drive is (for the title).
    """
    m = metrics
    fig = trajectory_figure(
        waypoints_xy_m,
        drive,
        held,
        names=(name,),
        title=f"{Path(source).name}: {name}\nADE {m['ade_m']:.3f} m, FDE {m['fde_m']:.3f} m "
        f"over {m['n_predictions']} predictions; zoom where it misses most",
    )
    return save(fig, out)


def line_figure(params, length_m: float, closed: bool, *, title: str):
    """The line model's learned profile against arc length: the line's offset from the
    centerline [m] and the speed profile [m/s], uncovered stretches shaded."""
    v = params.physical()
    off, speed, cov = (
        np.asarray(v[k]) for k in ("line_offset_m", "line_speed_mps", "line_coverage")
    )
    s = np.arange(len(off)) * (length_m / (len(off) if closed else len(off) - 1))
    fig, axes = subplots(2, 1, figsize=(9, 6), sharex=True)
    for ax, y, label in ((axes[0], off, "line offset m (left +)"), (axes[1], speed, "speed m/s")):
        ax.plot(s, y, color=color("fitted"))
        uncovered = dict(where=cov <= 0, color="0.85", transform=ax.get_xaxis_transform())
        ax.fill_between(s, 0, 1, **uncovered, label="not covered by the fit drives")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8)
    axes[1].set_xlabel("arc length along the centerline [m]")
    fig.suptitle(title)
    tight_layout(fig)
    return fig
