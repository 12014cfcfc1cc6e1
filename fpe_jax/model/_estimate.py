"""The leading car's state at each prediction time, from its recent observation history.

Two parts: `history_windows` (NumPy) gathers, for every observation, the last few *distinct*
observations (a log repeats the last pose when no new detection came; repeats carry no
information and would fake a stop); `estimate_state` (JAX, one window, vmap it) turns a window into
a `State` with robust Theil-Sen slopes (the median of pairwise slopes ignores a single outlier).

A repeated row is predicted from as if it were fresh (its position is the last detection's, not
advanced over the time since): rows repeat mostly while the car is slow or the tag is lost, and
advancing them by their age at the estimated speed predicted the real Levine lap worse.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from fpe_jax.geometry._track import wrap_angle
from fpe_jax.model._constants import TRACK_FRAME_ITERS
from fpe_jax.model._history import MIN_PAIR_DT_S, OUTLIER_M
from fpe_jax.model._state import State


def _masked_median(x, mask):
    """Median of x over mask (any shape, reduces everything; NaN values count as masked out); 0
    where the mask is empty. Bitwise the value of `jnp.nanmedian` over the masked values.

    By ranks, not by a sort: each value's rank among the masked ones is a count of comparisons
    (ties broken by position), and the median is the value of the middle rank, or the mean of
    the two middle ones. The windows hold at most 45 pairs, so the n^2 comparisons are few, and
    XLA's CPU sort is slow on such short rows: ranks estimate a long drive's states in about
    half the time, for a somewhat larger stored executable.
    """
    x = jnp.ravel(x)
    mask = jnp.ravel(mask) & ~jnp.isnan(x)
    n = x.shape[0]
    earlier = np.tril(np.ones((n, n), dtype=bool), -1)  # [i, j]: j comes before i
    below = (x[None, :] < x[:, None]) | ((x[None, :] == x[:, None]) & earlier)
    rank = jnp.sum(mask[None, :] & below, axis=1, dtype=jnp.int32)
    count = jnp.sum(mask, dtype=jnp.int32)
    lo, hi = jnp.maximum(count - 1, 0) // 2, count // 2

    def at(k):  # the one masked value of rank k
        return jnp.sum(jnp.where(mask & (rank == k), x, 0.0))

    w_hi = jnp.where(lo == hi, 0.0, 0.5).astype(x.dtype)  # as nanmedian weighs them
    return jnp.where(count > 0, at(lo) * (1.0 - w_hi) + at(hi) * w_hi, 0.0)


def estimate_state(
    t_s: Float[Array, " W"],
    xy_m: Float[Array, "W 2"],
    yaw_rad: Float[Array, " W"],
    valid: Bool[Array, " W"],
    t_now_s: Float[Array, ""] | None = None,
) -> State:
    """State at t_now from one right-aligned history window (index W-1 is the newest).

    Args:
        t_s: (W,) stamps [s]; xy_m: (W, 2) positions [m]; yaw_rad: (W,) observed yaw [rad] or NaN;
        valid: (W,) which slots hold an observation (the newest must); t_now_s: prediction time
        [s], unused (kept so windows from `history_windows` can be passed as they are).

    Velocity is the Theil-Sen slope of x(t), y(t); yaw is the observed one at the newest
    observation (smoothed along the same robust line) or, without orientation, the direction of
    motion; yaw rate is the Theil-Sen slope of the yaw (or of the segment courses).
    """
    w = t_s.shape[0]
    i, j = np.triu_indices(w, 1)
    dt = t_s[j] - t_s[i]
    pair_ok = valid[i] & valid[j] & (dt >= MIN_PAIR_DT_S)
    safe_dt = jnp.where(pair_ok, dt, 1.0)
    vx = _masked_median((xy_m[j, 0] - xy_m[i, 0]) / safe_dt, pair_ok)
    vy = _masked_median((xy_m[j, 1] - xy_m[i, 1]) / safe_dt, pair_ok)
    t_new = t_s[-1]

    # robust line through the window, evaluated at the newest stamp: replaces an outlier newest
    ahead = t_new - t_s
    fit_x = _masked_median(xy_m[:, 0] + vx * ahead, valid)
    fit_y = _masked_median(xy_m[:, 1] + vy * ahead, valid)
    off = jnp.hypot(xy_m[-1, 0] - fit_x, xy_m[-1, 1] - fit_y)
    use_fit = (off > OUTLIER_M) & (jnp.sum(valid) >= 3)
    x = jnp.where(use_fit, fit_x, xy_m[-1, 0])
    y = jnp.where(use_fit, fit_y, xy_m[-1, 1])

    speed = jnp.hypot(vx, vy)
    course = jnp.arctan2(vy, vx)

    has_yaw = valid & jnp.isfinite(yaw_rad)
    yaw0 = jnp.where(has_yaw, yaw_rad, 0.0)
    yaw_ok = pair_ok & has_yaw[i] & has_yaw[j]
    rate_obs = _masked_median(wrap_angle(yaw0[j] - yaw0[i]) / safe_dt, yaw_ok)
    yaw_ref = jnp.where(has_yaw[-1], yaw0[-1], course)
    yaw_fit = yaw_ref + _masked_median(wrap_angle(yaw0 + rate_obs * ahead - yaw_ref), has_yaw)

    # without orientation: the course of each segment between consecutive observations
    seg_ok = valid[:-1] & valid[1:] & ((t_s[1:] - t_s[:-1]) >= MIN_PAIR_DT_S)
    seg_course = jnp.arctan2(xy_m[1:, 1] - xy_m[:-1, 1], xy_m[1:, 0] - xy_m[:-1, 0])
    seg_t = 0.5 * (t_s[1:] + t_s[:-1])
    a, b = np.triu_indices(w - 1, 1)
    seg_pair_ok = seg_ok[a] & seg_ok[b] & ((seg_t[b] - seg_t[a]) >= MIN_PAIR_DT_S)
    seg_dt = jnp.where(seg_pair_ok, seg_t[b] - seg_t[a], 1.0)
    rate_course = _masked_median(wrap_angle(seg_course[b] - seg_course[a]) / seg_dt, seg_pair_ok)

    n_yaw = jnp.sum(has_yaw)
    yaw = jnp.where(n_yaw >= 2, wrap_angle(yaw_fit), yaw_ref)
    yaw_rate = jnp.where(n_yaw >= 2, rate_obs, rate_course)
    return State(
        x_m=x,
        y_m=y,
        yaw_rad=yaw,
        v_mps=speed,
        yaw_rate_rps=yaw_rate,
        course_rad=course,
        s_m=None,
    )


def track_frame_window(
    xy_m: Float[Array, "W 2"],
    valid: Bool[Array, " W"],
    s_hint_m: Float[Array, ""],
    track,
) -> tuple[Float[Array, " W"], Float[Array, " W"]]:
    """Arc length s [m] and lateral offset d [m] (left positive) of each observation of one
    window (invalid slots: their newer neighbour's arc length, any d).

    Each observation is projected onto the path, newest first, each from its newer neighbour's
    arc length (`Track.project_local`: consecutive observations are close), so s is continuous
    over the window (across the seam of a loop too). Both track-frame estimators read these.
    """
    w = xy_m.shape[0]

    def back(s_next, k):
        s = track.project_local(xy_m[k], s_next, iters=TRACK_FRAME_ITERS)
        s = jnp.where(valid[k], s, s_next)
        return s, s

    _, s_rev = jax.lax.scan(back, s_hint_m, jnp.arange(w - 1, -1, -1))
    s = s_rev[::-1]
    centre = jax.vmap(track.point_at)(s)
    heading = jax.vmap(track.heading_at)(s)
    d = (xy_m[:, 1] - centre[:, 1]) * jnp.cos(heading) - (xy_m[:, 0] - centre[:, 0]) * jnp.sin(
        heading
    )
    return s, d


def track_frame_lines(
    t_s: Float[Array, " W"],
    s_m: Float[Array, " W"],
    d_m: Float[Array, " W"],
    valid: Bool[Array, " W"],
) -> tuple[Float[Array, ""], ...]:
    """Theil-Sen lines through a window in the track frame (`track_frame_window`): s [m],
    ds/dt [m/s], d [m], dd/dt [m/s] at the newest stamp, and the speed's age [s] (the median
    observation's age: a slope describes the window's middle).

    s and d at the newest stamp are the medians of the observations moved along their Theil-Sen
    slopes: noise along the line of sight averages out over the window, and unlike a straight
    line in the map frame the path's curvature adds no bias. The frenet and line rollouts start
    from these with the "theil-sen" estimator; the Kalman filter starts from them.
    """
    w = t_s.shape[0]
    s, d = s_m, d_m
    i, j = np.triu_indices(w, 1)
    dt = t_s[j] - t_s[i]
    pair_ok = valid[i] & valid[j] & (dt >= MIN_PAIR_DT_S)
    safe_dt = jnp.where(pair_ok, dt, 1.0)
    sdot = _masked_median((s[j] - s[i]) / safe_dt, pair_ok)
    ddot = _masked_median((d[j] - d[i]) / safe_dt, pair_ok)
    ahead = t_s[-1] - t_s
    s_now = s[-1] + _masked_median(s + sdot * ahead - s[-1], valid)
    d_now = _masked_median(d + ddot * ahead, valid)
    age = _masked_median(ahead, valid)
    return s_now, sdot, d_now, ddot, age
