"""The opponent's own line and speed profile, learned from drives on one track.

Where the car was (ground truth when a drive has it, else its distinct observations) is projected
onto the centerline: arc length s, signed lateral offset d (left positive) and along-track speed
ds/dt. These samples are spread onto P points evenly spaced in arc length (linear weights) and
smoothed with a Gaussian kernel in arc length (circular on loops): a smooth periodic function
whose smoothness is the kernel width. A point's coverage is the kernel-weighted sample count,
capped at 1. Where the fit drives never went (coverage 0) the profile is a prior from the
track's shape, fitted on the covered points: on loops the offset is a ridge regression on the
smoothest (least-curvature) line within the room the car used (`min_curvature_offset`: a racing
car's line on a stretch it has not been seen on); on open paths, and for the log speed, ridge
regressions on the centerline's curvature (its magnitude for the speed), smoothed at a few
widths and read a few metres behind and ahead (braking comes before a corner, the apex on its
inside); on loops the speed's also on the fastest speed along the car's line within grip,
acceleration and braking limits (`limit_speed`, the limits' shape fitted on the covered
speeds: the corners ahead of the car say where it will brake). There the
rollout keeps the car's own offset, following only the prior's change, and the prior's speed
ratio (`fpe_jax.model.rollout_frenet`). With less than PRIOR_MIN_COVERED_M covered the prior
is the covered mean (no change: the car's offset and speed held).

The profile is tied to the waypoints it was learned on by `waypoints_sha256`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import jax
import numpy as np

from fpe_jax.compile import _aot as aot
from fpe_jax.compile._rows import no_arclength, pad_rows, row_blocks
from fpe_jax.drive import Drive
from fpe_jax.geometry._track import Track, arclength_along
from fpe_jax.model._history import distinct_mask

PROFILE_DS_M = 0.5  # spacing of the profile's points [m]
PROFILE_SMOOTH_M = 1.0  # standard deviation of the smoothing kernel [m]
MAX_GAP_S = 0.5  # samples further apart than this give no speed
MIN_SAMPLES = 1.0  # kernel-weighted samples for full coverage
# the uncovered prior: curvature smoothed at these widths [m], read at these distances [m]
# ahead (positive) and behind, ridge penalty per unit weight on standardised features; fitted
# only on at least PRIOR_MIN_COVERED_M of covered track
PRIOR_SMOOTH_M = (1.0, 3.0, 8.0)
PRIOR_SHIFTS_M = (-8.0, -4.0, -2.0, 0.0, 2.0, 4.0, 8.0)
PRIOR_RIDGE = 0.1
PRIOR_MIN_COVERED_M = 20.0
PRIOR_FOLDS = 5  # held-out runs that set how far the prior's variation is trusted
PRIOR_LAG_M = 4.0  # ... judged on changes over this distance [m] (about 1 s of driving)
# the smoothest line within the car's room (loops): ridge on the offset [1/m^4] (fixes the mean
# offset, which curvature alone leaves free), ADMM penalty [1/m^4] (the curvature weight of a
# ~20 m wavelength: converges within 1000 steps to ~2 cm of the exact QP) and steps
MIN_CURV_RIDGE = 1e-4
MIN_CURV_RHO = 0.01
MIN_CURV_ITERS = 1000
# the speed a racing car can hold along its line (loops): grip limits it in corners
# (v^2 |kappa| <= a_lat), acceleration and braking between them. Only the profile's shape enters
# the prior, set by the ratios below (acceleration and braking to a_lat; top speed^2 / a_lat,
# the radius from which on the car is at top speed [m]): the combination that fits the covered
# speeds best (log speed, least squares with a free scale and exponent)
LIMIT_ACCEL_RATIOS = (0.03, 0.1, 0.3, 1.0)
LIMIT_BRAKE_RATIOS = (0.05, 0.15, 0.4, 1.0)
LIMIT_TOP_RADII_M = (1.0, 3.0, 10.0, 30.0, 100.0)
LIMIT_SMOOTH_M = 1.0  # the line's curvature is smoothed with this kernel [m]


@aot.jit
def _centerline_at(track: Track, s_m):
    """The centerline's points (N, 2) [m] and headings (N,) [rad] at arc lengths s_m (N,) [m]."""
    return jax.vmap(track.point_at)(s_m), jax.vmap(track.heading_at)(s_m)


@aot.jit
def _project(track: Track, xy_m, s_before_m):
    """Arc length s (N,) [m] of points (N, 2) [m] (continuing from s_before_m, NaN: none), the
    centerline point (N, 2) [m] and heading (N,) [rad] there."""
    s = arclength_along(track, xy_m, s_before_m)
    return (s, *_centerline_at(track, s))


class LineSamples(NamedTuple):
    """Where a car was, in the track frame (`line_samples`): each field (M,)."""

    t_s: np.ndarray  # stamps [s]
    s_m: np.ndarray  # arc length [m], unwrapped
    d_m: np.ndarray  # signed lateral offset [m], left positive
    v_mps: np.ndarray  # along-track speed [m/s], NaN at gaps

    def outside(self, t0_s: float, t1_s: float) -> LineSamples:
        """The samples before t0_s or from t1_s on, as `line_samples` gives them for the parts
        of the drive before and after (`Drive.slice_time`): a speed whose central difference
        reaches into [t0_s, t1_s) is NaN."""
        keep = (self.t_s < t0_s) | (self.t_s >= t1_s)
        inner = keep.copy()  # both neighbours kept too
        inner[1:] &= keep[:-1]
        inner[:-1] &= keep[1:]
        v = np.where(inner, self.v_mps, np.nan)
        return LineSamples(self.t_s[keep], self.s_m[keep], self.d_m[keep], v[keep])


def line_samples(drive: Drive, track: Track) -> LineSamples:
    """A drive's positions in the track frame: its ground truth when it has one, else its
    distinct observations."""
    if drive.has_truth:
        t, xy = drive.truth_t_s, drive.truth_xy_m
    else:
        keep = distinct_mask(drive.xy_m)
        t, xy = drive.t_s[keep], drive.xy_m[keep]
    # in the padded blocks of `row_blocks`: drives of every length reuse one stored executable
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
    return LineSamples(np.asarray(t, dtype=np.float64), s, d, v)


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

    Returns dict with line_offset_m, line_speed_mps, line_coverage (see `fpe_jax.model.Params`).
    """
    return line_from_samples([line_samples(d, track) for d in drives], track, ds_m, smooth_m)


def line_from_samples(
    samples: Sequence[LineSamples],
    track: Track,
    ds_m: float = PROFILE_DS_M,
    smooth_m: float = PROFILE_SMOOTH_M,
) -> dict[str, np.ndarray]:
    """`learn_line` from the drives' `line_samples`."""
    length = float(track.length_m)
    n = max(int(round(length / ds_m)), 8)
    spacing = length / (n if track.closed else n - 1)
    sums = {k: np.zeros(n) for k in ("w", "d", "vw", "v")}
    for _, s, d, v in samples:
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
    offset, speed = np.where(coverage > 0, offset, 0.0), np.where(coverage > 0, speed, 0.0)
    # the prior fills the share (1 - coverage) the samples leave: nothing on a covered track
    if coverage.any() and not (coverage == 1.0).all():
        prior_offset, prior_speed = _prior(track, offset, speed, coverage, spacing)
        offset = coverage * offset + (1.0 - coverage) * prior_offset
        speed = coverage * speed + (1.0 - coverage) * prior_speed
    return {"line_offset_m": offset, "line_speed_mps": speed, "line_coverage": coverage}


def _curvature(track: Track, n: int, spacing: float) -> np.ndarray:
    """The centerline's curvature (n,) [1/m] at the profile's n points."""
    heading = np.asarray(track.heading_rad)
    turn = np.angle(
        np.exp(1j * np.diff(heading, append=heading[:1] if track.closed else heading[-1:]))
    )
    ds = float(track.ds_m)
    return np.interp(
        np.arange(n) * spacing,
        (np.arange(len(heading)) + 0.5) * ds,
        turn / ds,
        period=float(track.length_m) if track.closed else None,
    )


def _curvature_features(track: Track, n: int, spacing: float, magnitude: bool) -> np.ndarray:
    """(n, F) standardised features of the centerline's curvature at the profile's n points: a
    constant, then the (signed or absolute) curvature smoothed at each PRIOR_SMOOTH_M and read
    at each PRIOR_SHIFTS_M."""
    kappa = _curvature(track, n, spacing)
    cols = [np.ones(n)]
    for width in PRIOR_SMOOTH_M:
        k = _smooth(kappa, track.closed, width / spacing)
        k = np.abs(k) if magnitude else k
        for shift in PRIOR_SHIFTS_M:
            i = np.arange(n) + int(round(shift / spacing))
            cols.append(k[i % n] if track.closed else k[np.clip(i, 0, n - 1)])
    return _standardised(np.stack(cols, axis=1))


def _standardised(feats: np.ndarray) -> np.ndarray:
    """feats (n, F) with every column but the constant (column 0) scaled to unit deviation."""
    scale = feats.std(axis=0)
    scale[0] = 1.0
    return feats / np.where(scale > 1e-12, scale, 1.0)


def min_curvature_offset(kappa_pm: np.ndarray, spacing_m: float, limit_m: float) -> np.ndarray:
    """Offset d (P,) [m] from a closed centerline of the smoothest line within |d| <= limit_m.

    The line's curvature is, to first order in d, kappa + d'' (second difference over spacing_m);
    d minimises sum (kappa + d'')^2 + MIN_CURV_RIDGE sum d^2 within the bound, by ADMM. The
    second difference on a loop is circulant, so each ADMM step solves its linear system with one
    real FFT pair: O(P log P) per step on any track length.

    Args:
        kappa_pm: (P,) centerline curvature [1/m] at P points spacing_m [m] apart on a loop.
        limit_m: bound on |d| [m] (the room the car uses).
    """
    n = len(kappa_pm)
    # eigenvalues of the circulant second difference (symmetric: its own transpose), at the
    # frequencies of a real FFT
    lam = (2.0 * np.cos(2.0 * np.pi * np.arange(n // 2 + 1) / n) - 2.0) / spacing_m**2
    gain = 1.0 / (lam**2 + MIN_CURV_RIDGE + MIN_CURV_RHO)
    rhs = -np.fft.irfft(np.fft.rfft(kappa_pm) * lam, n)
    z, u = np.zeros(n), np.zeros(n)
    for _ in range(MIN_CURV_ITERS):
        d = np.fft.irfft(np.fft.rfft(rhs + MIN_CURV_RHO * (z - u)) * gain, n)
        z = np.clip(d + u, -limit_m, limit_m)
        u += d - z
    return z


def limit_speed(
    kappa_pm: np.ndarray,
    step_m: np.ndarray,
    lat_mps2: float,
    accel_mps2: float,
    brake_mps2: float,
    top_mps: float,
) -> np.ndarray:
    """The fastest speed profile (P,) [m/s] around a loop of P points within the limits.

    Point i has curvature kappa_pm[i] [1/m] and lies step_m[i] [m] before point i + 1 (the
    last before point 0). v_i^2 <= lat_mps2 / |kappa_i| and v_i <= top_mps; speeding up from
    one point to the next adds at most 2 accel_mps2 step to v^2, slowing down removes at most
    2 brake_mps2 step. Each pass is a running minimum (v_i^2 - 2 a x_i is non-increasing along
    the pass), taken over two laps so the loop closes.
    """
    n = len(kappa_pm)
    cap = np.minimum(top_mps**2, lat_mps2 / np.maximum(np.abs(kappa_pm), 1e-12))
    cap2 = np.concatenate([cap, cap])
    x = np.concatenate([[0.0], np.cumsum(np.concatenate([step_m, step_m])[:-1])])
    fwd = np.minimum.accumulate(cap2 - 2.0 * accel_mps2 * x) + 2.0 * accel_mps2 * x
    fwd2 = np.concatenate([fwd[n:], fwd[n:]])
    back = (x[-1] - x)[::-1]  # distance to the end, along the reversed pass
    v2 = np.minimum.accumulate(fwd2[::-1] - 2.0 * brake_mps2 * back) + 2.0 * brake_mps2 * back
    return np.sqrt(v2[::-1][:n])


def _limit_feature(
    track: Track, offset: np.ndarray, log_v: np.ndarray, w: np.ndarray, spacing: float
) -> np.ndarray:
    """(P,) log of the along-track speed of `limit_speed` on the line at `offset` (P,) [m] from
    a closed centerline, for the limits' shape that fits log_v (weights w) best."""
    n = len(offset)
    s = np.arange(n) * spacing
    centre, heading = (np.asarray(a) for a in _centerline_at(track, s))
    xy = centre + offset[:, None] * np.stack([-np.sin(heading), np.cos(heading)], axis=1)
    chord = np.roll(xy, -1, axis=0) - xy
    step = np.hypot(chord[:, 0], chord[:, 1])
    direction = np.arctan2(chord[:, 1], chord[:, 0])
    turn = np.angle(np.exp(1j * (direction - np.roll(direction, 1))))
    kappa = _smooth(turn / (0.5 * (step + np.roll(step, 1))), True, LIMIT_SMOOTH_M / spacing)
    # the limits act along the line; the profile is the speed along the centerline
    to_track = np.log(spacing / np.maximum(step, 1e-9))
    sw = np.sqrt(w)
    best, best_sse = to_track, np.inf
    for accel in LIMIT_ACCEL_RATIOS:
        for brake in LIMIT_BRAKE_RATIOS:
            for radius in LIMIT_TOP_RADII_M:
                x = np.log(limit_speed(kappa, step, 1.0, accel, brake, np.sqrt(radius)))
                x += to_track
                design = np.stack([np.ones(n), x], axis=1)
                coef = np.linalg.lstsq(design * sw[:, None], log_v * sw, rcond=None)[0]
                sse = np.sum(w * (log_v - design @ coef) ** 2)
                if sse < best_sse:
                    best, best_sse = x, sse
    return best


def _ridge(feats: np.ndarray, y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted ridge regression of y on feats (the constant, column 0, unpenalised): the
    coefficients."""
    penalty = PRIOR_RIDGE * w.sum() * np.eye(feats.shape[1])
    penalty[0, 0] = 0.0
    return np.linalg.solve((feats.T * w) @ feats + penalty, (feats.T * w) @ y)


def _shrunk_fit(feats: np.ndarray, y: np.ndarray, w: np.ndarray, lag: int) -> np.ndarray:
    """The ridge fit of y on feats with its variation about the weighted mean shrunk by how well
    it predicts, held out, y's change over `lag` points: the covered points (w > 0) fall into
    PRIOR_FOLDS runs in arc length, each predicted from the others; the factor is the
    least-squares slope of the held-out changes on the predicted ones, within [0, 1] (the
    rollout follows only the prior's change where uncovered)."""
    mean = np.sum(w * y) / np.sum(w)
    fitted = feats @ _ridge(feats, y, w) - mean
    idx = np.flatnonzero(w > 0)
    fold = np.zeros(len(y), dtype=np.int64) - 1
    fold[idx] = np.arange(len(idx)) * PRIOR_FOLDS // len(idx)
    num = den = 0.0
    for k in range(PRIOR_FOLDS):
        held = fold == k
        pred = feats @ _ridge(feats, y, np.where(held, 0.0, w))
        i = np.flatnonzero(held)
        j = (i + lag) % len(y)
        i, j = i[held[j]], j[held[j]]
        dp, dy = pred[j] - pred[i], y[j] - y[i]
        num, den = num + np.sum(dp * dy), den + np.sum(dp * dp)
    return mean + float(np.clip(num / den, 0.0, 1.0) if den > 0 else 0.0) * fitted


def _prior(track: Track, offset, speed, coverage, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """The uncovered prior (P,) offset [m] and speed [m/s] from the track's curvature, fitted on
    the covered points (weights: coverage), within the covered values' range."""
    has_v = coverage * (speed > 0)
    seen = coverage >= 0.5
    if not seen.any() or coverage.sum() * spacing < PRIOR_MIN_COVERED_M:
        mean = lambda y, w: np.full_like(y, np.sum(w * y) / max(np.sum(w), 1e-12))  # noqa: E731
        return mean(offset, coverage), mean(speed, has_v)
    n = len(offset)
    lim = np.abs(offset[seen]).max()
    lag = max(int(round(PRIOR_LAG_M / spacing)), 1)
    if track.closed:
        # the smoothest line within the car's room: its weight (a plain ridge fit, whose scale
        # the data set; no further shrinking) carries the car's line onto unseen stretches
        smooth = min_curvature_offset(_curvature(track, n, spacing), spacing, lim)
        feats = _standardised(np.stack([np.ones(n), smooth], axis=1))
        prior_offset = feats @ _ridge(feats, offset, coverage)
    else:
        feats = _curvature_features(track, n, spacing, False)
        prior_offset = _shrunk_fit(feats, offset, coverage, lag)
    prior_offset = np.clip(prior_offset, -lim, lim)
    feats = _curvature_features(track, n, spacing, True)
    log_v = np.log(np.maximum(speed, 1e-3))
    if track.closed:  # where the car can go fast on its line, the prior's with the covered one
        line = coverage * offset + (1.0 - coverage) * prior_offset
        limit = _limit_feature(track, line, log_v, has_v, spacing)
        feats = np.concatenate([feats, _standardised(np.stack([np.ones(n), limit], 1))[:, 1:]], 1)
    log_v = _shrunk_fit(feats, log_v, has_v, lag)
    v_seen = speed[seen & (speed > 0)]
    prior_speed = (
        np.clip(np.exp(log_v), v_seen.min(), v_seen.max()) if len(v_seen) else np.exp(log_v)
    )
    return prior_offset, prior_speed
