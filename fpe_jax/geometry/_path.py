"""Path geometry in NumPy only (no JAX): waypoint cleaning, loop detection, uniform resampling.

`fpe_jax.geometry.Track` and the JAX-free on-car runner both build their tracks with `build_path`,
so the two see exactly the same resampled points.
"""

from __future__ import annotations

import bisect
import hashlib
import math

import numpy as np

from fpe_jax.errors import InputError
from fpe_jax.spec import check_track_size


def map_origin(xy_m) -> np.ndarray:
    """(2,) origin [m] of a local frame for (K, 2) points [m]: the whole metres at or below their
    lower-left corner. Subtracting it (in float64) makes map coordinates small before they enter
    float32; being whole metres, equal shapes at different offsets get equal local coordinates."""
    xy = np.asarray(xy_m, dtype=np.float64)
    return np.floor(xy.min(axis=0)) if xy.size else np.zeros(2)


def waypoints_sha256(waypoints_xy_m) -> str:
    """Content hash of waypoints (K, 2) [m]: sha256 of their float64 bytes, row-major, in their
    local frame (`map_origin` subtracted), so the same file hashes alike before and after the
    commands move it to its local frame (a whole-metre shift changes nothing the line means)."""
    xy = np.asarray(waypoints_xy_m, dtype=np.float64)
    xy = np.ascontiguousarray(xy - map_origin(xy))
    return hashlib.sha256(xy.tobytes()).hexdigest()


def wrap_angle(a):
    """Wrap angles [rad] to [-pi, pi); works on NumPy and JAX arrays alike."""
    return (a + np.pi) % (2 * np.pi) - np.pi


def covariance_map(cov_track_m2, heading_rad: np.ndarray) -> np.ndarray:
    """(N, H, 2, 2) map-frame covariance [m^2] from the track-frame one, per step (H, 2, 2) or
    per prediction (N, H, 2, 2), turned by the path heading (N, H) [rad]."""
    c, s = np.cos(heading_rad), np.sin(heading_rad)
    rot = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)  # (N, H, 2, 2)
    return rot @ np.asarray(cov_track_m2) @ np.swapaxes(rot, -1, -2)


def nearest_index(points_m: np.ndarray, path_xy_m: np.ndarray) -> np.ndarray:
    """(P,) index of the nearest path point (K, 2) to each point (P, 2) (ties: the lowest).

    O(P + K) by the hash grid of `nearest_vertex`; only points farther than its radius from every
    vertex (none on a drive's own track) are searched exhaustively, in bounded chunks.
    """
    steps = np.hypot(*np.diff(path_xy_m, axis=0).T)
    spacing = float(np.median(steps)) if len(steps) else 1.0
    out, _ = nearest_vertex(points_m, path_xy_m, max(2.0, 4.0 * spacing))
    far = np.flatnonzero(out < 0)
    for i in range(0, len(far), 256):
        rows = far[i : i + 256]
        d = points_m[rows, None, :] - path_xy_m[None, :, :]
        out[rows] = np.argmin(np.einsum("pkd,pkd->pk", d, d), axis=1)
    return out


def left_normals(loop_xy_m: np.ndarray) -> np.ndarray:
    """(K, 2) unit normals pointing left of the direction of travel of a closed loop (K, 2)."""
    d = np.roll(loop_xy_m, -1, axis=0) - np.roll(loop_xy_m, 1, axis=0)
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)  # a point with no direction: 0
    return np.stack([-d[:, 1], d[:, 0]], axis=1)


# How far back along the kept path a reversing point is compared with: backing up further than
# this is not recording noise but a path that really turns back.
_BACKTRACK_WINDOW_M = 10.0


def _distance_to_polyline(p: np.ndarray, pts: np.ndarray) -> float:
    """Distance [m] from point p (2,) to the polyline through pts (J, 2), J >= 2."""
    a, ab = pts[:-1], np.diff(pts, axis=0)
    t = np.clip(
        np.einsum("jd,jd->j", p - a, ab) / np.maximum(np.einsum("jd,jd->j", ab, ab), 1e-300),
        0.0,
        1.0,
    )
    return float(np.min(np.hypot(*(a + t[:, None] * ab - p).T)))


def _clean_polyline(
    xy: np.ndarray, min_step_m: float, backtrack_tol_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Drop jitter and back-tracking from hand-driven waypoints, keep every real corner.

    A point is dropped when it is closer than `min_step_m` to the last kept one, or when its step
    turns by 90 degrees or more *and* it lies within `backtrack_tol_m` of the last
    `_BACKTRACK_WINDOW_M` of kept path: the recording went back over covered ground. A sharp
    turn onto new ground (a square's corner, a hairpin drawn with few points) is kept.

    Returns the kept points (J, 2) and the input indices dropped as too close (R1,) and as
    back-tracking (R2,), both int64.
    """
    kept = [0]
    s_m = [0.0]  # arc length at each kept point
    close, back = [], []
    for i in range(1, len(xy)):
        p, last = xy[i], xy[kept[-1]]
        step = p - last
        step_m = float(np.hypot(*step))
        if step_m < min_step_m:
            close.append(i)
            continue
        if len(kept) >= 2 and np.dot(step, last - xy[kept[-2]]) <= 0.0:
            first = bisect.bisect_left(s_m, s_m[-1] - _BACKTRACK_WINDOW_M)
            recent = xy[kept[max(first - 1, 0) :]]
            if _distance_to_polyline(p, recent) <= backtrack_tol_m:
                back.append(i)
                continue
        kept.append(i)
        s_m.append(s_m[-1] + step_m)
    return xy[kept], np.array(close, dtype=np.int64), np.array(back, dtype=np.int64)


def _resample(xy: np.ndarray, closed: bool, ds_m: float) -> np.ndarray:
    """Points at uniform arc-length spacing ~ds_m along the polyline (closing segment included)."""
    pts = np.vstack([xy, xy[:1]]) if closed else xy
    seg = np.hypot(*np.diff(pts, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    n = max(int(round(s[-1] / ds_m)), 3)
    s_new = np.arange(n) * (s[-1] / n) if closed else np.linspace(0.0, s[-1], n + 1)
    return np.stack([np.interp(s_new, s, pts[:, 0]), np.interp(s_new, s, pts[:, 1])], axis=1)


def _smooth(xy: np.ndarray, closed: bool, half_window: int) -> np.ndarray:
    """Moving average over 2 * half_window + 1 points (circular on loops, edge-padded otherwise)."""
    if half_window < 1:
        return xy
    mode = "wrap" if closed else "edge"
    padded = np.pad(xy, ((half_window, half_window), (0, 0)), mode=mode)
    kernel = np.ones(2 * half_window + 1) / (2 * half_window + 1)
    out = np.stack([np.convolve(padded[:, i], kernel, mode="valid") for i in range(2)], axis=1)
    if not closed:  # keep the end points where the user put them
        out[0], out[-1] = xy[0], xy[-1]
    return out


def build_path(
    waypoints_xy_m,
    *,
    ds_m: float = 0.1,
    closed: bool | None = None,
    smooth_m: float = 0.3,
    min_step_m: float = 0.15,
    backtrack_tol_m: float = 0.1,
    source: str = "waypoints",
) -> dict:
    """Resample waypoints (K, 2) [m] into a uniform path.

    Args:
        ds_m: resampling spacing [m].
        closed: force a loop or an open path; None detects a loop when the end comes back to
            within max(3 steps, 5 % of the length) of the start.
        smooth_m: half-width of the moving-average smoothing [m] (removes hand-driven jitter).
        min_step_m: waypoints closer than this to the previous kept one are dropped.
        backtrack_tol_m: a waypoint whose step turns by 90 degrees or more is dropped as
            back-tracking (a recording that backs up) when it lies within this distance [m] of
            the path already kept; farther away it is a corner and stays.
        source: name used in error messages.

    Returns:
        dict with xy_m (M, 2), heading_rad (M,), ds_m, length_m (floats), raw_xy_m (K, 2), closed,
        and what cleaning removed: removed_close_idx (R1,) (closer than min_step_m, the step used,
        to the previous kept waypoint) and removed_backtrack_idx (R2,), int64 indices into the
        waypoints as given.
    """
    xy = np.asarray(waypoints_xy_m, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] != 2:
        raise InputError(source, f"waypoints have shape {xy.shape}", "(K, 2) x, y in metres")
    if not np.all(np.isfinite(xy)):
        raise InputError(source, "waypoints contain NaN or inf", "finite x, y")
    raw_length_m = float(np.hypot(*np.diff(xy, axis=0).T).sum())
    if raw_length_m > 0.0:  # all points equal: "only 1 distinct waypoints" below says it better
        check_track_size(len(xy), raw_length_m, source)
    step = min(min_step_m, ds_m * 1.5)
    clean, removed_close, removed_back = _clean_polyline(xy, step, backtrack_tol_m)
    if len(clean) < 3:
        raise InputError(source, f"only {len(clean)} distinct waypoints", "at least 3")
    seg = np.hypot(*np.diff(clean, axis=0).T)
    length = seg.sum()
    gap = np.hypot(*(clean[-1] - clean[0]))
    if closed is None:
        closed = bool(gap <= max(3 * np.median(seg), 0.05 * length))
    pts = _resample(clean, closed, ds_m)
    pts = _smooth(pts, closed, int(round(smooth_m / ds_m)))
    pts = _resample(pts, closed, ds_m)  # smoothing shifts spacing a little; make it uniform
    ring = np.vstack([pts, pts[:1]]) if closed else pts
    seg = np.hypot(*np.diff(ring, axis=0).T)
    length = seg.sum()
    spacing = length / (len(pts) if closed else len(pts) - 1)
    if closed:
        d = np.roll(pts, -1, axis=0) - np.roll(pts, 1, axis=0)
    else:
        d = np.gradient(pts, axis=0)
    heading = np.arctan2(d[:, 1], d[:, 0])
    return {
        "xy_m": pts,
        "heading_rad": heading,
        "ds_m": float(spacing),
        "length_m": float(length),
        "raw_xy_m": xy,
        "closed": bool(closed),
        "min_step_m": float(step),
        "removed_close_idx": removed_close,
        "removed_backtrack_idx": removed_back,
    }


def nearest_vertex(points_m, vertices_m, radius_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Nearest vertex (K, 2) [m] to each point (P, 2) [m] among those within `radius_m` [m].

    A hash grid of cells `radius_m` wide holds the vertices; each point looks only at the 3 x 3
    cells around its own, so the work is O(P + K) times the vertices per cell, never (P, K).
    Ties go to the lowest vertex index (as np.argmin).

    Returns:
        idx (P,) int64, -1 where no vertex lies within radius_m; dist (P,) [m], inf there.
    """
    pts = np.asarray(points_m, dtype=np.float64).reshape(-1, 2)
    ver = np.asarray(vertices_m, dtype=np.float64).reshape(-1, 2)
    best_d2 = np.full(len(pts), np.inf)
    best_i = np.full(len(pts), -1, dtype=np.int64)
    if not len(pts) or not len(ver):
        return best_i, np.sqrt(best_d2)
    lo = np.floor(ver.min(axis=0) / radius_m) - 1
    vc = (np.floor(ver / radius_m) - lo).astype(np.int64)
    span = int(vc[:, 1].max()) + 2
    order = np.argsort(vc[:, 0] * span + vc[:, 1], kind="stable")
    keys = (vc[:, 0] * span + vc[:, 1])[order]
    hi_x = int(vc[:, 0].max()) + 1
    for start in range(0, len(pts), 1 << 16):  # bounded memory for any number of points
        p = pts[start : start + (1 << 16)]
        pc = np.floor(p / radius_m) - lo
        ok = np.all((pc >= 0) & (pc <= [hi_x, span - 1]), axis=1)
        pc = np.where(ok[:, None], pc, -10).astype(np.int64)
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                cx, cy = pc[:, 0] + dx, pc[:, 1] + dy
                key = np.where(ok & (cy >= 0) & (cy < span), cx * span + cy, -1)
                a, b = np.searchsorted(keys, key, "left"), np.searchsorted(keys, key, "right")
                n = b - a
                if not n.any():
                    continue
                has = np.flatnonzero(n)
                first = np.cumsum(n)[has] - n[has]  # each point's run in the candidates
                cand = order[np.repeat(a[has] - first, n[has]) + np.arange(first[-1] + n[has][-1])]
                d2 = np.sum((ver[cand] - np.repeat(p[has], n[has], axis=0)) ** 2, axis=1)
                # per point: the nearest, and among equally near the lowest index (O(T))
                d_min = np.minimum.reduceat(d2, first)
                tie = d2 == np.repeat(d_min, n[has])
                i_min = np.minimum.reduceat(np.where(tie, cand, len(ver)), first)
                o = has + start
                better = (d_min < best_d2[o]) | ((d_min == best_d2[o]) & (i_min < best_i[o]))
                best_d2[o[better]], best_i[o[better]] = d_min[better], i_min[better]
    far = best_d2 > radius_m * radius_m
    best_i[far], best_d2[far] = -1, np.inf
    return best_i, np.sqrt(best_d2)


# A drive on its own track: its observations lie near the waypoints' line, and where it moves it
# goes the way the waypoints run. "Near" scales with the track: 1:10 tracks are 1-2 m wide each
# side (a raceline, detection noise and the odd outlier add to that: ON_TRACK_M), full-size ones
# 6-8 m, where a racing line runs 3-6 m from the centre line. A track's width grows with its size
# (about 1 % of its extent on full-size circuits and speedways), so the bound is the larger of
# ON_TRACK_M and ON_TRACK_EXTENT times the path's extent (its bounding box's diagonal): 3 m on
# every 1:10 track, 10-20 m on a circuit or speedway 1-2 km across, still far below the offset of
# another map frame or another track.
ON_TRACK_M = 3.0
ON_TRACK_EXTENT = 0.01
MIN_ON_TRACK_SHARE = 0.8  # of the observations, within ON_TRACK_M
MIN_ALONG_SHARE = 0.5  # of the moves, starting near the waypoints and going their way
_MOVE_M = 2.0  # direction of motion judged over about this distance driven
_MAX_CHECKED = 200_000  # observations sampled for the share (its error is then < 0.3 %)


def on_track_m(path_xy_m) -> float:
    """The distance [m] within which an observation counts as on the path (M, 2) [m]: the larger
    of ON_TRACK_M and ON_TRACK_EXTENT times the path's extent (its bounding box's diagonal)."""
    xy = np.asarray(path_xy_m, dtype=np.float64).reshape(-1, 2)
    xy = xy[np.all(np.isfinite(xy), axis=1)]
    extent = float(np.hypot(*np.ptp(xy, axis=0))) if len(xy) else 0.0
    return max(ON_TRACK_M, ON_TRACK_EXTENT * extent)


# Where a track crosses itself (a figure-eight) two branches are equally near the car: a global
# projection with a known heading takes the nearest segment whose direction lies within
# BRANCH_MAX_ANGLE of it, if that lies within BRANCH_M of the car; else the nearest of all (a
# car far off the track, or driving against it). Where the nearest agrees (everywhere but at
# crossings and hairpin mix-ups) the result is the nearest, exactly. The heading counts as
# known when the car's yaw is observed, or its measured speed is at least MIN_HEADING_SPEED_MPS.
BRANCH_MAX_ANGLE_RAD = math.pi / 4
BRANCH_COS = math.cos(BRANCH_MAX_ANGLE_RAD)
BRANCH_M = 2.0

# Local projection onto the track (`Track.project_window`, `Track.project_local`, and the
# runner's mirror of them): the window searched around a hint [m] and the Newton-like
# refinement steps.
WINDOW_BEHIND_M = 2.0
WINDOW_AHEAD_M = 4.0
LOCAL_PROJECTION_ITERS = 2
MIN_HEADING_SPEED_MPS = 0.5

ALLOW_HINT = "pass --allow-off-track to use them anyway"


def window_points(ds_m: float) -> tuple[int, int]:
    """How many points (behind, ahead) of the hint a local projection searches on a path of
    spacing ds [m]: the window covers at least WINDOW_BEHIND_M and WINDOW_AHEAD_M."""
    return math.ceil(WINDOW_BEHIND_M / ds_m), math.ceil(WINDOW_AHEAD_M / ds_m)


def _vertex_stride(xy_m: np.ndarray) -> int:
    """Every how many points of a resampled path (M, 2) [m] a vertex is kept so that the
    nearest-vertex distance is within 0.15 m of the distance to the path's line."""
    spacing = float(np.median(np.hypot(*np.diff(xy_m, axis=0).T))) if len(xy_m) > 1 else 1.0
    return max(1, int(0.3 / max(spacing, 1e-9)))


def near_path(
    points_xy_m, path_xy_m, near_m: float | None = None, max_cells: int = 1 << 21
) -> np.ndarray:
    """(P,) bool: whether each point (P, 2) [m] lies within `near_m` [m] of a resampled path
    (M, 2) [m] (judged to 0.15 m: a vertex every ~0.3 m). The rule of the on-track checks.

    Many points are judged on a raster of at most `max_cells` cells over the path: a cell whose
    centre lies within near_m minus its half-diagonal of a vertex is near for every point in it,
    one beyond near_m plus that is far; only the points of the cells between are searched
    (the same answers as searching every point, at O(1) per point). `NearPath` keeps the
    raster for points given in many calls.
    """
    return NearPath(path_xy_m, near_m, max_cells)(points_xy_m)


class NearPath:
    """`near_path` for one path, asked many times (a batch judged block by block): the raster
    is built on the first call that pays for it and kept.

    Args:
        path_xy_m: (M, 2) resampled path [m].
        near_m: the distance [m] (default `on_track_m` of the path).
        max_cells: the raster's cells at most.
    """

    def __init__(self, path_xy_m, near_m: float | None = None, max_cells: int = 1 << 21):
        xy = np.asarray(path_xy_m, dtype=np.float64)
        self.near_m = on_track_m(xy) if near_m is None else float(near_m)
        self.fine = xy[:: _vertex_stride(xy)]
        self.lo = self.fine.min(axis=0) - self.near_m - 1.0
        span = self.fine.max(axis=0) + self.near_m + 1.0 - self.lo
        self.cell = max(self.near_m / 8, float(np.sqrt(span[0] * span[1] / max_cells)))
        self.shape = tuple(np.ceil(span / self.cell).astype(np.int64).tolist())
        self._padded: np.ndarray | None = None

    def __call__(self, points_xy_m, n_points: int | None = None) -> np.ndarray:
        """(P,) bool for points (P, 2) [m]; n_points: how many points all calls together judge
        (default P), which decides whether the raster pays (the answers are the same)."""
        pts = np.asarray(points_xy_m, dtype=np.float64).reshape(-1, 2)
        n = len(pts) if n_points is None else n_points
        if n <= self.shape[0] * self.shape[1] or self.cell >= self.near_m:  # few: search each
            idx, _ = nearest_vertex(pts, self.fine, self.near_m)
            return idx >= 0
        padded = self._raster()
        # each point's cell; points outside the raster land in its border of far cells
        ix, iy = (
            np.clip(np.floor((pts[:, k] - self.lo[k]) / self.cell), -1, self.shape[k]) + 1
            for k in (0, 1)
        )
        judged = padded[ix.astype(np.intp), iy.astype(np.intp)]
        near = judged == 1
        unsure = np.flatnonzero(judged == 2)
        if len(unsure):
            idx, _ = nearest_vertex(pts[unsure], self.fine, self.near_m)
            near[unsure] = idx >= 0
        return near

    def _raster(self) -> np.ndarray:
        """(nx + 2, ny + 2) int8 per cell: 1 near for all its points, 0 far for all (and the
        border), 2 unsure. Two threads building it at once build the same array."""
        if self._padded is None:
            shape, cell = self.shape, self.cell
            half_diag = cell * math.sqrt(0.5)
            ij = np.stack(np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij"), -1)
            centres = self.lo + (ij.reshape(-1, 2) + 0.5) * cell
            _, d = nearest_vertex(centres, self.fine, self.near_m + half_diag)
            state = np.where(d <= self.near_m - half_diag, 1, np.where(np.isfinite(d), 2, 0))
            padded = np.zeros((shape[0] + 2, shape[1] + 2), dtype=np.int8)
            padded[1:-1, 1:-1] = state.reshape(shape)
            self._padded = padded
        return self._padded


def profile_values(values, s_m, length_m: float, closed: bool) -> np.ndarray:
    """A line profile (P,) at arc lengths s (N,) [m], linear between its P evenly spread points
    (NumPy twin of `fpe_jax.model.profile_at`: on a loop point i sits at s = i L / P and the
    profile wraps; on an open path at s = i L / (P - 1), held beyond the ends)."""
    v = np.asarray(values, dtype=np.float64)
    p, s = len(v), np.asarray(s_m, dtype=np.float64)
    if closed:
        u = s * (p / length_m)
        u_floor = np.floor(u)
        i = u_floor.astype(np.int64) % p
        j, f = (i + 1) % p, u - u_floor
    else:
        u = np.clip(s / length_m, 0.0, 1.0) * (p - 1)
        i = np.clip(np.floor(u).astype(np.int64), 0, p - 2)
        j, f = i + 1, u - i
    return v[i] + f * (v[j] - v[i])


def off_track(
    points_xy_m, path: dict, line_offset_m=None, near_m: float | None = None
) -> np.ndarray:
    """(P,) bool: points (P, 2) [m] farther than `near_m` [m] from the path (`build_path`'s dict,
    or any with xy_m, heading_rad, ds_m, length_m, closed) and, given a learned line's offset
    profile (P_line,) [m, left positive], from that line too (`near_path`'s rule; near_m
    defaults to `on_track_m` of the path). `off_track_judge` asks it of many blocks of points."""
    return off_track_judge(path, line_offset_m, near_m)(points_xy_m)


def off_track_judge(path: dict, line_offset_m=None, near_m: float | None = None):
    """`off_track` for one path (and line), made once: judge(points (P, 2) [m], n_points=None)
    -> (P,) bool, n_points as for `NearPath` (all the points of the blocks judged together)."""
    if near_m is None:
        near_m = on_track_m(path["xy_m"])
    on_path = NearPath(path["xy_m"], near_m)
    on_line = None
    if line_offset_m is not None:
        xy, h = np.asarray(path["xy_m"]), np.asarray(path["heading_rad"])
        d = profile_values(
            line_offset_m,
            np.arange(len(xy)) * float(path["ds_m"]),
            float(path["length_m"]),
            bool(path["closed"]),
        )
        on_line = NearPath(xy + d[:, None] * np.stack([-np.sin(h), np.cos(h)], axis=1), near_m)

    def judge(points_xy_m, n_points: int | None = None) -> np.ndarray:
        pts = np.asarray(points_xy_m).reshape(-1, 2)
        off = ~on_path(pts, n_points)
        if on_line is not None and off.any():
            rows = np.flatnonzero(off)
            off[rows] = ~on_line(pts[rows])
        return off

    return judge


def check_share_near(
    share_near: float,
    drive_to_path_m: float,
    *,
    source: str,
    drive: str,
    near_m: float,
    hint: str = ALLOW_HINT,
) -> None:
    """InputError (naming the waypoints `source` and the `drive`) when less than
    MIN_ON_TRACK_SHARE of a drive's observations lie within near_m [m] of the waypoints."""
    if share_near < MIN_ON_TRACK_SHARE:
        raise InputError(
            source,
            f"only {share_near:.0%} of the observations of {drive} lie within "
            f"{near_m:.3g} m of these waypoints (the drive's centre is "
            f"{drive_to_path_m:.0f} m from theirs): likely the wrong waypoints file or a "
            f"different map frame; {hint}",
            f"at least {MIN_ON_TRACK_SHARE:.0%}",
        )


def track_agreement(obs_xy_m, path_xy_m, path_heading_rad, *, near_m: float | None = None) -> dict:
    """How well a drive's observations (N, 2) [m] sit on a resampled path (M, 2) [m] with its
    headings (M,) [rad] (`build_path`'s, or a Track's, in the same frame).

    near_m: the distance [m] that counts as near (default `on_track_m` of the path).

    Returns dict: share_near (share of observations within `near_m` of the path), share_along
    (of the drive's moves of about 2 m, the share that start near the path and go its way; NaN
    when the car never moved), share_backward (those that start near it and go against it),
    n_moves, and drive_to_path_m (distance between the centres of the
    drive and of the path, for the message). O(N + M): a hash grid, no (N, M) distances.
    """
    obs = np.asarray(obs_xy_m, dtype=np.float64).reshape(-1, 2)
    obs = obs[np.all(np.isfinite(obs), axis=1)]
    xy = np.asarray(path_xy_m, dtype=np.float64)
    heading = np.asarray(path_heading_rad, dtype=np.float64)
    near_m = on_track_m(xy) if near_m is None else float(near_m)
    stride = max(1, len(obs) // _MAX_CHECKED)
    near = near_path(obs[::stride], xy, near_m)
    share_near = float(np.mean(near)) if len(near) else 1.0
    # every few points of the path: a nearest-vertex distance within 0.15 m of the true one
    k = _vertex_stride(xy)
    xy, heading = xy[::k], heading[::k]
    # moves: the drive cut where its travelled distance passes each whole metre (repeated
    # detections and jitter add nothing), each judged against the path at its start
    travelled = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(obs, axis=0).T))])
    cut = np.flatnonzero(np.diff(np.floor(travelled / _MOVE_M), prepend=-1.0) > 0)
    cut = cut[:: max(1, len(cut) // _MAX_CHECKED)]
    step = np.diff(obs[cut], axis=0)
    moved = np.hypot(*step.T) >= 0.5 * _MOVE_M
    start, step = obs[cut[:-1]][moved], step[moved]
    j, _ = nearest_vertex(start, xy, near_m)
    near = j >= 0
    forward = step[near, 0] * np.cos(heading[j[near]]) + step[near, 1] * np.sin(heading[j[near]])
    n = max(len(step), 1)
    share_along = float(np.sum(forward > 0) / n) if len(step) else float("nan")
    gap = float(np.hypot(*(obs.mean(axis=0) - xy.mean(axis=0)))) if len(obs) else 0.0
    return dict(
        share_near=share_near,
        share_along=share_along,
        share_backward=float(np.sum(forward < 0) / n),
        n_moves=len(step),
        drive_to_path_m=gap,
        near_m=near_m,
    )


def check_on_track(
    obs_xy_m, path_xy_m, path_heading_rad, *, source: str, drive: str, allow: bool = False
) -> dict:
    """`track_agreement`, raising InputError (naming the waypoints `source` and the `drive`)
    when the drive is not on these waypoints or runs against them; `allow` only reports."""
    a = track_agreement(obs_xy_m, path_xy_m, path_heading_rad)
    if allow:
        return a
    hint = ALLOW_HINT
    check_share_near(
        a["share_near"], a["drive_to_path_m"], source=source, drive=drive, near_m=a["near_m"]
    )
    if a["share_along"] < MIN_ALONG_SHARE:  # NaN (a car that never moved) passes
        cause = (
            "likely waypoints in the reverse direction"
            if a["share_backward"] > a["share_along"]
            else "it crosses them rather than following them: likely the wrong waypoints file"
            " or a different map frame"
        )
        raise InputError(
            source,
            f"{drive} moves along these waypoints in only {a['share_along']:.0%} of its "
            f"{a['n_moves']} moves of ~{_MOVE_M:g} m: {cause}; {hint}",
            f"at least {MIN_ALONG_SHARE:.0%}",
        )
    return a
