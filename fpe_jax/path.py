"""Path geometry in NumPy only (no JAX): waypoint cleaning, loop detection, uniform resampling.

`fpe_jax.track.Track` and the JAX-free on-car runner both build their tracks with `build_path`,
so the two see exactly the same resampled points.
"""

from __future__ import annotations

import bisect
import hashlib

import numpy as np

from fpe_jax.errors import InputError


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


def nearest_index(points_m: np.ndarray, path_xy_m: np.ndarray, chunk: int = 256) -> np.ndarray:
    """(P,) index of the nearest path point (K, 2) to each point (P, 2), in bounded chunks
    (memory O(chunk x K))."""
    out = np.empty(len(points_m), dtype=np.int64)
    for i in range(0, len(points_m), chunk):
        d = points_m[i : i + chunk, None, :] - path_xy_m[None, :, :]
        out[i : i + chunk] = np.argmin(np.einsum("pkd,pkd->pk", d, d), axis=1)
    return out


def left_normals(loop_xy_m: np.ndarray) -> np.ndarray:
    """(K, 2) unit normals pointing left of the direction of travel of a closed loop (K, 2)."""
    d = np.roll(loop_xy_m, -1, axis=0) - np.roll(loop_xy_m, 1, axis=0)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
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
