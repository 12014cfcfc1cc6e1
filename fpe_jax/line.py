"""The opponent's own line and speed profile, learned from drives on one track.

Where the car was (ground truth when a drive has it, else its distinct observations) is projected
onto the centerline: arc length s, signed lateral offset d (left positive) and along-track speed
ds/dt. These samples are spread onto P points evenly spaced in arc length (linear weights) and
smoothed with a Gaussian kernel in arc length (circular on loops): a smooth periodic function
whose smoothness is the kernel width. A point's coverage is the kernel-weighted sample count,
capped at 1: where the fit drives never went it is 0 and the rollout holds the car's own offset
(slowly decaying) and its current speed (`fpe_jax.rollout.rollout_frenet`).

The profile is tied to the waypoints it was learned on by `waypoints_sha256`.
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import numpy as np

from fpe_jax import aot
from fpe_jax.drive import Drive
from fpe_jax.history import distinct_mask
from fpe_jax.predict import no_arclength, pad_rows, row_blocks
from fpe_jax.track import Track, arclength_along

PROFILE_DS_M = 0.5  # spacing of the profile's points [m]
PROFILE_SMOOTH_M = 1.0  # standard deviation of the smoothing kernel [m]
MAX_GAP_S = 0.5  # samples further apart than this give no speed
MIN_SAMPLES = 1.0  # kernel-weighted samples for full coverage


@aot.jit
def _project(track: Track, xy_m, s_before_m):
    """Arc length s (N,) [m] of points (N, 2) [m] (continuing from s_before_m, NaN: none), the
    centerline point (N, 2) [m] and heading (N,) [rad] there."""
    s = arclength_along(track, xy_m, s_before_m)
    return s, jax.vmap(track.point_at)(s), jax.vmap(track.heading_at)(s)


def _samples(drive: Drive, track: Track) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Arc length s [m] (unwrapped), offset d [m] and along-track speed [m/s] (NaN at gaps)."""
    if drive.has_truth:
        t, xy = drive.truth_t_s, drive.truth_xy_m
    else:
        keep = distinct_mask(drive.xy_m)
        t, xy = drive.t_s[keep], drive.xy_m[keep]
    # in the padded blocks of `row_blocks`: a drive and every fold of it (the cross-fitted
    # uncertainty) reuse one stored executable
    s, centre, heading = np.zeros(0), np.zeros((0, 2)), np.zeros(0)
    parts, s_before = [], no_arclength()
    for rows, size in row_blocks(len(xy)):
        part = _project(track, pad_rows(xy[rows], size), s_before)
        part = [np.asarray(a)[: rows.stop - rows.start] for a in part]
        s_before = part[0][-1]
        parts.append(part)
    if parts:
        s, centre, heading = (np.concatenate(a) for a in zip(*parts))
    d = (xy[:, 1] - centre[:, 1]) * np.cos(heading) - (xy[:, 0] - centre[:, 0]) * np.sin(heading)
    v = np.full_like(s, np.nan)
    if len(t) >= 3:
        dt = np.diff(t)
        ok = (dt[1:] <= MAX_GAP_S) & (dt[:-1] <= MAX_GAP_S)
        central = (s[2:] - s[:-2]) / np.maximum(t[2:] - t[:-2], 1e-9)
        v[1:-1] = np.where(ok, central, np.nan)
    return s, d, v


def _smooth(values: np.ndarray, closed: bool, sigma_pts: float) -> np.ndarray:
    """Gaussian smoothing over points (circular on loops, zero beyond the ends otherwise)."""
    p = len(values)
    half = min(int(np.ceil(4 * sigma_pts)), p // 2 if closed else (p - 1) // 2)
    k = np.exp(-0.5 * (np.arange(-half, half + 1) / max(sigma_pts, 1e-9)) ** 2)
    k /= k.sum()
    if closed:
        padded = np.concatenate([values[-half:], values, values[:half]]) if half else values
        return np.convolve(padded, k, mode="valid")
    return np.convolve(values, k, mode="same")


def learn_line(
    drives: Sequence[Drive],
    track: Track,
    *,
    ds_m: float = PROFILE_DS_M,
    smooth_m: float = PROFILE_SMOOTH_M,
) -> dict[str, np.ndarray]:
    """Line offset, speed profile and coverage, each (P,), from drives on `track`.

    Args:
        ds_m: profile resolution [m] (P = length / ds_m points, at least 8).
        smooth_m: smoothing kernel's standard deviation [m].

    Returns dict with line_offset_m, line_speed_mps, line_coverage (see `fpe_jax.params.Params`).
    """
    length = float(track.length_m)
    n = max(int(round(length / ds_m)), 8)
    spacing = length / (n if track.closed else n - 1)
    sums = {k: np.zeros(n) for k in ("w", "d", "vw", "v")}
    for drive in drives:
        s, d, v = _samples(drive, track)
        u = (np.mod(s, length) if track.closed else np.clip(s, 0.0, length)) / spacing
        i = np.floor(u).astype(np.int64)
        f = u - i
        for idx, w in ((i, 1.0 - f), (i + 1, f)):
            idx = idx % n if track.closed else np.clip(idx, 0, n - 1)
            np.add.at(sums["w"], idx, w)
            np.add.at(sums["d"], idx, w * d)
            has_v = np.isfinite(v)
            np.add.at(sums["vw"], idx[has_v], w[has_v])
            np.add.at(sums["v"], idx[has_v], w[has_v] * v[has_v])
    sm = {k: _smooth(a, track.closed, smooth_m / spacing) for k, a in sums.items()}
    # the kernel sums to 1 over points: sm["w"] is samples per point, locally averaged
    coverage = np.clip(np.minimum(sm["w"], sm["vw"]) / MIN_SAMPLES, 0.0, 1.0)
    offset = np.where(sm["w"] > 1e-9, sm["d"] / np.maximum(sm["w"], 1e-9), 0.0)
    speed = np.where(sm["vw"] > 1e-9, sm["v"] / np.maximum(sm["vw"], 1e-9), 0.0)
    return {
        "line_offset_m": np.where(coverage > 0, offset, 0.0),
        "line_speed_mps": np.where(coverage > 0, speed, 0.0),
        "line_coverage": coverage,
    }
