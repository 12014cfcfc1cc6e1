"""Single-car rollouts: linear, constant velocity, CTRV, pure pursuit, their blend, and the seed.

All are pure functions of (params, state, track) returning `Poses` (fields (H,)) at
t + h * dt_s for h = 1..H; vmap them at the edge. Every rollout except the seed's is
differentiable in every fitted value. The observation delay is a fractional first step: the state
is advanced by `delay_s` before the H regular steps.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from fpe_jax.geometry._track import Track, wrap_angle
from fpe_jax.model._constants import (
    FALLBACK_TAU_S,
    MAX_SPEED_RATIO,
    MIN_PROFILE_SPEED_MPS,
    SLOPE_DS_M,
)
from fpe_jax.model._params import Params
from fpe_jax.model._state import Poses, State  # State re-exported: rollouts take a State


def _step_times(params: Params) -> Float[Array, " H1"]:
    """Durations [s] of the fractional delay step followed by the H regular steps."""
    h = params.settings.horizon
    # the params' dtype, not the global default: float32 batches must stay float32 under x64
    dt = jnp.full((h,), params.settings.dt_s, dtype=params.delay_s.dtype)
    return jnp.concatenate([params.delay_s[None], dt])


def _speed(params: Params, state: State):
    """Speed of the rollout [m/s]: the measured one shrunk toward the typical one."""
    w = params.speed_weight
    return w * state.v_mps + (1.0 - w) * params.speed_mps


def _emit(xs, ys, yaws) -> Poses:
    """Drop the delay step's output: (H+1,) arrays -> Poses (H,)."""
    return Poses(xs[1:], ys[1:], yaws[1:])


def rollout_linear(params: Params, state: State, heading_rad=None) -> Poses:
    """Constant speed along a fixed heading (default: the car's yaw): thesis approach 2."""
    yaw = state.yaw_rad if heading_rad is None else heading_rad
    t, v = jnp.cumsum(_step_times(params)), _speed(params, state)
    xs, ys = state.x_m + v * t * jnp.cos(yaw), state.y_m + v * t * jnp.sin(yaw)
    return _emit(xs, ys, jnp.broadcast_to(yaw, t.shape))


def rollout_cv(params: Params, state: State) -> Poses:
    """Constant velocity vector (speed along the direction of motion): thesis approach 1."""
    return rollout_linear(params, state, heading_rad=state.course_rad)


def rollout_ctrv(params: Params, state: State) -> Poses:
    """Constant turn rate and velocity, integrated exactly step by step (midpoint heading)."""
    v, w = _speed(params, state), state.yaw_rate_rps

    def step(c, dt):
        x, y, yaw = c
        # exact arc: chord 2 v/w sin(w dt / 2) along the mid heading; sinc stays smooth at w = 0
        chord = v * dt * jnp.sinc(w * dt / (2 * jnp.pi))
        mid = yaw + 0.5 * w * dt
        c = (x + chord * jnp.cos(mid), y + chord * jnp.sin(mid), yaw + w * dt)
        return c, c

    init = (state.x_m, state.y_m, state.yaw_rad)
    _, (xs, ys, yaws) = jax.lax.scan(step, init, _step_times(params))
    return _emit(xs, ys, wrap_angle(yaws))


# Taylor coefficients of sin (r, r^3, ..., r^13) and cos (1, r^2, ..., r^14) for |r| <= pi/4
_SIN_COEFFS = tuple((-1) ** k / math.factorial(2 * k + 1) for k in range(7))
_COS_COEFFS = tuple((-1) ** k / math.factorial(2 * k) for k in range(8))


def _poly(coeffs, r2):
    """sum_k coeffs[k] * r2**k by Horner's rule."""
    acc = coeffs[-1]
    for c in reversed(coeffs[:-1]):
        acc = c + r2 * acc
    return acc


def _sincos(x):
    """(sin x, cos x) from one shared range reduction and two short polynomials.

    XLA's CPU sin and cos each reduce the argument on their own; sharing it made a rollout step
    about 20 % faster. Measured error (tests/model/test_rollout.py): < 1e-7 in float32 and
    < 3e-14 in float64 for |x| < 1e4 rad, far more than any step turns.
    """
    n = jnp.round(x * (2.0 / math.pi))
    # x - n pi/2 with pi/2 split in two parts (Cody-Waite), so the reduction loses little
    r = (x - n * 1.5707963705062866) + n * 4.371139000186241e-08
    r2 = r * r
    sin_r, cos_r = r * _poly(_SIN_COEFFS, r2), _poly(_COS_COEFFS, r2)
    quadrant = n.astype(jnp.int32) & 3  # x = r + quadrant * pi/2 (mod 2 pi)
    odd = (quadrant & 1) == 1
    sin_x = jnp.where(odd, cos_r, sin_r) * jnp.where(quadrant >= 2, -1.0, 1.0)
    cos_x = jnp.where(odd, sin_r, cos_r) * jnp.where((quadrant == 1) | (quadrant == 2), -1.0, 1.0)
    return sin_x, cos_x


def _pursuit(params: Params, x_m, y_m, cos_yaw, sin_yaw, v_mps, s_m, track: Track):
    """tan(steering angle) of pure pursuit, clipped, and the car's arc length [m].

    Works on the heading as a unit vector and returns tan(steer) directly: the rollout needs
    only tan(steer), and clipping it at tan(max_steer) is clipping the angle (tan is monotone),
    so no atan/tan pair per step.
    """
    st = params.settings
    s = track.project_local(jnp.stack([x_m, y_m]), s_m)
    goal = track.point_at(s + params.lookahead_m + params.lookahead_gain_s * v_mps)
    dx, dy = goal[0] - x_m, goal[1] - y_m
    # tan(steer) = 2 wheelbase sin(alpha) / d, sin(alpha) = (heading x goal direction) / d
    tan_steer = 2.0 * st.wheelbase_m * (cos_yaw * dy - sin_yaw * dx) / (dx * dx + dy * dy + 1e-12)
    lim = math.tan(st.max_steer_rad)  # a Python float: keeps float32 batches float32
    return jnp.clip(tan_steer, -lim, lim), s


def pure_pursuit_steer(params: Params, x_m, y_m, yaw_rad, v_mps, s_m, track: Track):
    """Pure-pursuit steering angle [rad] and the car's arc length [m].

    The goal is the path point at s + L, L = lookahead_m + lookahead_gain_s * v, with s the
    car's own projection: it is always ahead along the path, never behind the car (the original
    picked the last waypoint within reach, which could lie behind). Law: delta =
    atan(2 * wheelbase * sin(alpha) / d), alpha the goal's bearing in the car frame, d its
    distance, clipped to +-max_steer_rad.
    """
    tan_steer, s = _pursuit(params, x_m, y_m, jnp.cos(yaw_rad), jnp.sin(yaw_rad), v_mps, s_m, track)
    return jnp.arctan(tan_steer), s


def _rollout_bicycle(params: Params, state: State, track: Track, turn_scale) -> Poses:
    """Kinematic bicycle steered by pure pursuit; the yaw change of step k is scaled by
    turn_scale[k] ((H+1,), 1 = pure pursuit, 0 = straight)."""
    v, wb = _speed(params, state), params.settings.wheelbase_m
    p0 = jnp.stack([state.x_m, state.y_m])
    s0 = (
        track.project(p0, state.yaw_rad)
        if state.s_m is None
        else track.project_local(p0, state.s_m)
    )

    def step(c, inp):
        x, y, yaw, cos_yaw, sin_yaw, s = c
        dt, k = inp
        tan_steer, s = _pursuit(params, x, y, cos_yaw, sin_yaw, v, s, track)
        dyaw = k * v / wb * tan_steer * dt
        # the heading vector turns by dyaw / 2 to the midpoint heading (the move's direction)
        # and by dyaw / 2 again: one sin/cos pair per step
        sh, ch = _sincos(0.5 * dyaw)
        cm, sm = cos_yaw * ch - sin_yaw * sh, sin_yaw * ch + cos_yaw * sh
        c = (x + v * dt * cm, y + v * dt * sm, yaw + dyaw, cm * ch - sm * sh, sm * ch + cm * sh, s)
        return c, c[:3]

    init = (state.x_m, state.y_m, state.yaw_rad, jnp.cos(state.yaw_rad), jnp.sin(state.yaw_rad), s0)
    # a rolled loop: scan(unroll=True) measured 2-4x slower here on CPU (larger fusions).
    # checkpoint: under reverse-mode (the fit) each step is recomputed from its carry rather
    # than ~60 intermediates per step being stored; a 10-minute fit traced, compiled and ran
    # 1.5x faster (medians of 5). Forward-only calls run the same code as without it.
    step = jax.checkpoint(step, prevent_cse=False)  # scan already keeps steps apart
    _, (xs, ys, yaws) = jax.lax.scan(step, init, (_step_times(params), turn_scale))
    return _emit(xs, ys, wrap_angle(yaws))


def rollout_pure_pursuit(params: Params, state: State, track: Track) -> Poses:
    """Kinematic bicycle following the path by pure pursuit: thesis approach 3, done properly."""
    ones = jnp.ones(params.settings.horizon + 1, dtype=params.weights.dtype)
    return _rollout_bicycle(params, state, track, ones)


def rollout_blend(params: Params, state: State, track: Track) -> Poses:
    """Linear and pure-pursuit rollouts blended with per-step weights w (1 = linear).

    "position": p_h = w_h * p_lin_h + (1 - w_h) * p_pp_h (the thesis's formula), yaw blended on
    the circle. "heading": one bicycle rollout whose yaw change at step h is scaled by 1 - w_h
    (what the original code did); the delay step uses w_1.
    """
    w = params.weights
    if params.settings.blend == "heading":
        return _rollout_bicycle(params, state, track, 1.0 - jnp.concatenate([w[:1], w]))
    lin, pp = rollout_linear(params, state), rollout_pure_pursuit(params, state, track)
    mix = lambda a, b: w * a + (1.0 - w) * b
    yaw = lin.yaw_rad + (1.0 - w) * wrap_angle(pp.yaw_rad - lin.yaw_rad)  # on the circle
    return Poses(mix(lin.x_m, pp.x_m), mix(lin.y_m, pp.y_m), wrap_angle(yaw))


def rollout_seed(params: Params, state: State, track: Track) -> Poses:
    """The original 2019 node's exact discrete rules (for conformance, not for fitting).

    Each step: goal = the waypoint found by scanning the raw list from its last row backwards
    for the first one within the lookahead (row 0 if none); "steering" = 2 sin(phi - yaw) / d (a
    curvature used as an angle), clipped; yaw_pp = yaw + dt v / wheelbase tan(steer);
    yaw' = w_i yaw + (1 - w_i) yaw_pp; x += v dt cos(yaw'), y += v dt sin(yaw'). No delay step.
    """
    st, v, wps = params.settings, _speed(params, state), track.raw_xy_m

    def step(c, w):
        x, y, yaw = c
        d_all = jnp.hypot(wps[:, 0] - x, wps[:, 1] - y)
        within = d_all <= params.lookahead_m
        last = wps.shape[0] - 1 - jnp.argmax(within[::-1])
        g = wps[jnp.where(jnp.any(within), last, 0)]
        d = jnp.hypot(g[0] - x, g[1] - y)
        phi = jnp.arctan2(g[1] - y, g[0] - x)
        steer = jnp.where(d > 0, 2.0 * jnp.sin(phi - yaw) / jnp.where(d > 0, d, 1.0), 0.0)
        steer = jnp.clip(steer, -st.max_steer_rad, st.max_steer_rad)
        yaw_pp = yaw + st.dt_s * v / st.wheelbase_m * jnp.tan(steer)
        yaw = w * yaw + (1.0 - w) * yaw_pp
        c = (x + v * st.dt_s * jnp.cos(yaw), y + v * st.dt_s * jnp.sin(yaw), yaw)
        return c, c

    return Poses(*jax.lax.scan(step, (state.x_m, state.y_m, state.yaw_rad), params.weights)[1])


def profile_at(values: Float[Array, " P"], s_m, track: Track):
    """A line profile (P,) at arc length s [m], linear between its P evenly spread points.

    On a loop point i sits at s = i * L / P and the profile wraps; on an open path point i sits
    at s = i * L / (P - 1) and the profile is held beyond the ends.
    """
    p = values.shape[0]
    if track.closed:
        u = s_m * (p / track.length_m)
        u_floor = jnp.floor(u)
        i = u_floor.astype(jnp.int32) % p
        j, f = (i + 1) % p, u - u_floor
    else:
        u = jnp.clip(s_m / track.length_m, 0.0, 1.0) * (p - 1)
        i = jnp.clip(jnp.floor(u).astype(jnp.int32), 0, p - 2)
        j, f = i + 1, u - i.astype(u.dtype)
    return values[i] + f * (values[j] - values[i])


def rollout_frenet(params: Params, state: State, track: Track) -> Poses:
    """Frenet rollout: along-track speed and a lateral offset that decays toward the line.

    s0, d0 = the car's arc length and signed offset from the path (left positive): between the
    newest observation's projection and the track-frame estimate (the Kalman filter's or the
    Theil-Sen lines', by `position_smoothing`); its along-track speed v0 is the track-frame
    estimate's (without one: v cos(course - heading)).
    Without a line profile ("frenet") the speed is held and the offset decays to 0:
    d(t) = d0 exp(-t / offset_tau_s). With one ("line") the offset decays toward the learned
    line l(s): d(t) = l(s(t)) + (d0 - l(s0)) exp(-t / offset_tau_s), and the speed follows the
    profile's shape scaled to the car's own: v(t) = v0 (1 + (v_p(s(t)) / v_p(s_ref) - 1)
    (1 - exp(-t / speed_tau_s))), s_ref where the speed was measured, so the car keeps its pace
    and brakes where the profile brakes (a profile speed below MIN_PROFILE_SPEED_MPS: ratio 1).
    Over longer leads the car's own pace returns to the profile's: the speed blended in is
    q(t) v0 v_p(s(t)) / v_p(s_ref) + (1 - q(t)) v_p(s(t)), q(t) = exp(-t pace_return_1ps)
    (where v_p(s(t)) is a speed reference; 0: the car's pace is kept): a car whose speed
    wanders about its typical one, or that stops and goes, is best predicted far ahead at its
    typical speed there.
    Where the profile's coverage c(s) is 0 (the profile there is `fpe_jax.model`'s prior from the
    track's curvature) the car keeps its own offset and follows only the profile's change:
    target l(s) + (d0 - l(s0)) exp(-t / FALLBACK_TAU_S), held and slowly decaying; in general
    l(s) + (1 - c(s)) (d0 - l(s0)) exp(-t / FALLBACK_TAU_S), which at s0 is c l + (1 - c) d0.
    The line model's return to its target L starts at the car's lateral rate relative
    to the target's, r0 = v sin(course - heading) - L'(s0) v0 (critically damped): d(t) = L(t) +
    (e0 + (r0 + e0 / tau) t) exp(-t / tau), e0 = d0 - L(s0). The yaw is the path heading turned
    by the offset's slope.
    """
    p0 = jnp.stack([state.x_m, state.y_m])
    s0 = (
        track.project(p0, state.yaw_rad)
        if state.s_m is None
        else track.project_local(p0, state.s_m)
    )
    h0 = track.heading_at(s0)
    c0 = track.point_at(s0)
    d0 = (p0[1] - c0[1]) * jnp.cos(h0) - (p0[0] - c0[0]) * jnp.sin(h0)
    v0 = state.v_mps * jnp.cos(state.course_rad - h0)
    age = jnp.zeros_like(v0)
    if state.s_fit_m is not None:  # the track-frame estimate; NaN (an export's input): absent
        ok = jnp.isfinite(state.s_fit_m)
        w = jnp.where(ok, params.position_smoothing, 0.0)
        fit_s = jnp.where(ok, state.s_fit_m, s0)
        fit_d = jnp.where(ok, state.offset_m, d0)
        s0, d0 = s0 + w * (fit_s - s0), d0 + w * (fit_d - d0)
        v0, age = jnp.where(ok, state.sdot_mps, v0), jnp.where(ok, state.sdot_age_s, age)
    dts = _step_times(params)
    t_end = jnp.cumsum(dts)
    has_line = params.line_offset_m.shape[0] > 0  # static: the line model
    tau = params.offset_tau_s

    def line(s):  # the line's offset [m], its coverage and the speed profile [m/s] at s
        profiles = (params.line_offset_m, params.line_coverage, params.line_speed_mps)
        return tuple(profile_at(values, s, track) for values in profiles)

    if has_line:
        own = d0 - line(s0)[0]  # the car's offset from the profile, kept where uncovered

        def target(x):  # the offset the car returns to: its line, where uncovered its own
            lx, cx, _ = line(x)
            return lx + (1.0 - cx) * own

        l0 = target(s0)
        hold = own * jnp.exp(-t_end / FALLBACK_TAU_S)  # uncovered: held, slowly decaying
        # the measured speed is the window's average: the profile's shape from where the car
        # was then (s0 - v0 age) carries it to now and over the horizon
        _, _, vp0 = line(s0 - v0 * age)
        ok0 = (vp0 > MIN_PROFILE_SPEED_MPS).astype(vp0.dtype)
        vp0 = jnp.maximum(vp0, MIN_PROFILE_SPEED_MPS)

        def step(s, inp):
            dt, t0 = inp
            _, _, vp = line(s)
            ratio = jnp.where(
                vp > MIN_PROFILE_SPEED_MPS, jnp.clip(vp / vp0, 0.0, MAX_SPEED_RATIO), 1.0
            )
            ratio = 1.0 + ok0 * (ratio - 1.0)
            # the car's own pace (v0 along the profile's shape) hands over to the profile's
            # where the profile is a speed reference
            own = v0 * ratio
            back = -jnp.expm1(-(t0 + age) * params.pace_return_1ps)
            goal = own + jnp.where(vp > MIN_PROFILE_SPEED_MPS, back * (vp - own), 0.0)
            v = v0 + (goal - v0) * -jnp.expm1(-(t0 + age) / params.speed_tau_s)
            s = s + v * dt
            return s, s

        _, s = jax.lax.scan(step, s0, (dts, t_end - dts))
        l_s, c_s, _ = jax.vmap(line)(s)
        l_s = l_s + (1.0 - c_s) * hold
        # the return to the target starts at the car's own lateral rate relative to the
        # target's (critically damped): the course says where the car is heading now
        slope = (target(s0 + SLOPE_DS_M) - target(s0 - SLOPE_DS_M)) / (2.0 * SLOPE_DS_M)
        rate = state.v_mps * jnp.sin(state.course_rad - h0) - slope * v0
        e0 = d0 - l0
        d = l_s + (e0 + (rate + e0 / tau) * t_end) * jnp.exp(-t_end / tau)
    else:
        s, l0, l_s = s0 + v0 * t_end, 0.0, 0.0
        d = l_s + (d0 - l0) * jnp.exp(-t_end / tau)
    heading, xy = jax.vmap(track.heading_at)(s), jax.vmap(track.point_at)(s)
    xs, ys = xy[:, 0] - d * jnp.sin(heading), xy[:, 1] + d * jnp.cos(heading)
    dd_ds = jnp.diff(d, prepend=d0) / jnp.maximum(jnp.diff(s, prepend=s0), 1e-3)
    return _emit(xs, ys, wrap_angle(heading + jnp.arctan(dd_ds)))


def estimate_variance(params: Params, state: State) -> Float[Array, "H 2"]:
    """Variance [m^2] (H, 2) along and across the track of each predicted point that the state
    estimate's own uncertainty causes: the Kalman filter's covariance `state.filter_cov`
    carried through `rollout_frenet`, linearised. Zeros without the filter.

    The rollout starts at s0 = z + w (s_hat - z) between the newest observation z (noise
    r = filter_obs_m) and the filter's estimate s_hat (w = position_smoothing). z was the
    filter's last update, so the estimate's error covaries with z's by exactly the estimate's
    own variance (a Kalman gain times r^2 is the posterior variance): var(s0) = u r^2 +
    (1 - u) P_ss with u = (1 - w)^2, and cov(s0, speed) = P_sv. Along the track at the step's
    time t (the delay included): var(s0) + 2 g P_sv + g^2 P_vv, g = t, or (1 - exp(-r t)) / r
    where the car's pace returns to the profile's at rate r = pace_return_1ps; across: var(d0)
    times the squared sensitivity of the offset's return to its start, (1 + t / tau)^2
    exp(-2 t / tau) for the line model's critically damped return, exp(-2 t / tau) for
    frenet's decay.
    """
    h = params.settings.horizon
    if state.filter_cov is None:
        return jnp.zeros((h, 2), params.delay_s.dtype)
    p = state.filter_cov
    t = jnp.cumsum(_step_times(params))[1:]
    w = params.position_smoothing
    u = (1.0 - w) * (1.0 - w)
    r2 = params.filter_obs_m * params.filter_obs_m
    var_s0 = u * r2 + (1.0 - u) * p[0, 0]
    var_d0 = u * r2 + (1.0 - u) * p[2, 2]
    # how far an error in the speed carries: t, or with the pace's return to the profile
    # (line model) its integral, (1 - exp(-r t)) / r
    r = params.pace_return_1ps
    reach = jnp.where(r > 0.0, -jnp.expm1(-r * t) / jnp.where(r > 0.0, r, 1.0), t)
    along = var_s0 + 2.0 * reach * p[0, 1] + reach * reach * p[1, 1]
    decay = jnp.exp(-t / params.offset_tau_s)
    if params.line_offset_m.shape[0] > 0:  # static: the line model
        decay = (1.0 + t / params.offset_tau_s) * decay
    return jnp.stack([along, var_d0 * decay * decay], axis=-1)


def rollout(params: Params, state: State, track: Track) -> Poses:
    """Dispatch on the static `params.settings.model`."""
    model = params.settings.model
    if model in ("cv", "ctrv"):
        return (rollout_cv if model == "cv" else rollout_ctrv)(params, state)
    by_model = {"frenet": rollout_frenet, "line": rollout_frenet, "seed": rollout_seed}
    return by_model.get(model, rollout_blend)(params, state, track)
