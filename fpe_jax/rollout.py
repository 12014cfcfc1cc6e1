"""Single-car rollouts: linear, constant velocity, CTRV, pure pursuit, their blend, and the seed.

All are pure functions of (params, state, track) returning (H, 3) poses x [m], y [m], yaw [rad]
at t + h * dt_s for h = 1..H; vmap them at the edge. Every rollout except the seed's is
differentiable in every fitted value. The observation delay is a fractional first step: the state
is advanced by `delay_s` before the H regular steps.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from fpe_jax.params import Params
from fpe_jax.track import Track, wrap_angle


class State(eqx.Module):
    """The leading car's state at prediction time (scalars; add a leading axis for batches).

    Attributes:
        x_m, y_m: position [m] (the newest observation).
        yaw_rad: heading of the car body [rad].
        v_mps: speed [m/s].
        yaw_rate_rps: yaw rate [rad/s].
        course_rad: direction of motion [rad] (differs from yaw when sliding or noisy).
        s_m: arc length hint [m]: where on the track the car is (from a windowed projection).
    """

    x_m: Float[Array, ""]
    y_m: Float[Array, ""]
    yaw_rad: Float[Array, ""]
    v_mps: Float[Array, ""]
    yaw_rate_rps: Float[Array, ""] | None = None
    course_rad: Float[Array, ""] | None = None
    s_m: Float[Array, ""] | None = None

    def __post_init__(self):
        # omitted fields: no turn, moving along the body heading
        if self.yaw_rate_rps is None:
            self.yaw_rate_rps = jnp.zeros_like(self.x_m)
        if self.course_rad is None:
            self.course_rad = self.yaw_rad


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


def _emit(xs, ys, yaws):
    """Drop the delay step's output: (H+1,) arrays -> (H, 3)."""
    return jnp.stack([xs, ys, yaws], axis=-1)[1:]


def rollout_linear(params: Params, state: State, heading_rad=None) -> Float[Array, "H 3"]:
    """Constant speed along a fixed heading (default: the car's yaw): thesis approach 2."""
    yaw = state.yaw_rad if heading_rad is None else heading_rad
    t = jnp.cumsum(_step_times(params))
    v = _speed(params, state)
    xs, ys = state.x_m + v * t * jnp.cos(yaw), state.y_m + v * t * jnp.sin(yaw)
    return _emit(xs, ys, jnp.broadcast_to(yaw, t.shape))


def rollout_cv(params: Params, state: State) -> Float[Array, "H 3"]:
    """Constant velocity vector (speed along the direction of motion): thesis approach 1."""
    return rollout_linear(params, state, heading_rad=state.course_rad)


def rollout_ctrv(params: Params, state: State) -> Float[Array, "H 3"]:
    """Constant turn rate and velocity, integrated exactly step by step (midpoint heading)."""
    v, w = _speed(params, state), state.yaw_rate_rps

    def step(c, dt):
        x, y, yaw = c
        # exact arc: chord 2 v/w sin(w dt / 2) along the mid heading; sinc stays smooth at w = 0
        chord = v * dt * jnp.sinc(w * dt / (2 * jnp.pi))
        mid = yaw + 0.5 * w * dt
        c = (x + chord * jnp.cos(mid), y + chord * jnp.sin(mid), yaw + w * dt)
        return c, c

    _, (xs, ys, yaws) = jax.lax.scan(
        step, (state.x_m, state.y_m, state.yaw_rad), _step_times(params)
    )
    return _emit(xs, ys, wrap_angle(yaws))


def pure_pursuit_steer(params: Params, x_m, y_m, yaw_rad, v_mps, s_m, track: Track):
    """Pure-pursuit steering angle [rad] and the car's arc length [m].

    The goal is the path point at s + L, L = lookahead_m + lookahead_gain_s * v, with s the
    car's own projection: it is always ahead along the path, never behind the car (the original
    picked the last waypoint within reach, which could lie behind). Law: delta =
    atan(2 * wheelbase * sin(alpha) / d), alpha the goal's bearing in the car frame, d its distance.
    """
    st = params.settings
    p = jnp.stack([x_m, y_m])
    s = track.project_local(p, s_m)
    goal = track.point_at(s + params.lookahead_m + params.lookahead_gain_s * v_mps)
    dx, dy = goal[0] - x_m, goal[1] - y_m
    d = jnp.sqrt(dx * dx + dy * dy + 1e-12)
    # sin(bearing - yaw) from a cross product: no angle difference, so no wrap at +-pi
    sin_alpha = (jnp.cos(yaw_rad) * dy - jnp.sin(yaw_rad) * dx) / d
    steer = jnp.arctan(2.0 * st.wheelbase_m * sin_alpha / d)
    return jnp.clip(steer, -st.max_steer_rad, st.max_steer_rad), s


def _rollout_bicycle(params: Params, state: State, track: Track, turn_scale) -> Float[Array, "H 3"]:
    """Kinematic bicycle steered by pure pursuit; the yaw change of step k is scaled by
    turn_scale[k] ((H+1,), 1 = pure pursuit, 0 = straight)."""
    v = _speed(params, state)
    wb = params.settings.wheelbase_m
    p0 = jnp.stack([state.x_m, state.y_m])
    s0 = track.project(p0) if state.s_m is None else track.project_local(p0, state.s_m)

    def step(c, inp):
        x, y, yaw, s = c
        dt, k = inp
        steer, s = pure_pursuit_steer(params, x, y, yaw, v, s, track)
        dyaw = k * v / wb * jnp.tan(steer) * dt
        mid = yaw + 0.5 * dyaw
        c = (x + v * dt * jnp.cos(mid), y + v * dt * jnp.sin(mid), yaw + dyaw, s)
        return c, c[:3]

    init = (state.x_m, state.y_m, state.yaw_rad, s0)
    _, (xs, ys, yaws) = jax.lax.scan(step, init, (_step_times(params), turn_scale))
    return _emit(xs, ys, wrap_angle(yaws))


def rollout_pure_pursuit(params: Params, state: State, track: Track) -> Float[Array, "H 3"]:
    """Kinematic bicycle following the path by pure pursuit: thesis approach 3, done properly."""
    return _rollout_bicycle(
        params, state, track, jnp.ones(params.settings.horizon + 1, dtype=params.weights.dtype)
    )


def rollout_blend(params: Params, state: State, track: Track) -> Float[Array, "H 3"]:
    """Linear and pure-pursuit rollouts blended with per-step weights w (1 = linear).

    "position": p_h = w_h * p_lin_h + (1 - w_h) * p_pp_h (the thesis's formula), yaw blended on
    the circle. "heading": one bicycle rollout whose yaw change at step h is scaled by 1 - w_h
    (what the original code did); the delay step uses w_1.
    """
    w = params.weights
    if params.settings.blend == "heading":
        scale = 1.0 - jnp.concatenate([w[:1], w])
        return _rollout_bicycle(params, state, track, scale)
    lin = rollout_linear(params, state)
    pp = rollout_pure_pursuit(params, state, track)
    xy = w[:, None] * lin[:, :2] + (1.0 - w[:, None]) * pp[:, :2]
    yaw = wrap_angle(lin[:, 2] + (1.0 - w) * wrap_angle(pp[:, 2] - lin[:, 2]))
    return jnp.concatenate([xy, yaw[:, None]], axis=1)


def rollout_seed(params: Params, state: State, track: Track) -> Float[Array, "H 3"]:
    """The original 2019 node's exact discrete rules (for conformance, not for fitting).

    Each step: goal = the waypoint found by scanning the raw list from its last row backwards
    for the first one within the lookahead (row 0 if none); "steering" = 2 sin(phi - yaw) / d (a
    curvature used as an angle), clipped; yaw_pp = yaw + dt v / wheelbase tan(steer);
    yaw' = w_i yaw + (1 - w_i) yaw_pp; x += v dt cos(yaw'), y += v dt sin(yaw'). No delay step.
    """
    st = params.settings
    v = _speed(params, state)
    wps = track.raw_xy_m

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

    _, (xs, ys, yaws) = jax.lax.scan(step, (state.x_m, state.y_m, state.yaw_rad), params.weights)
    return jnp.stack([xs, ys, yaws], axis=-1)


def rollout(params: Params, state: State, track: Track) -> Float[Array, "H 3"]:
    """Dispatch on the static `params.settings.model`."""
    model = params.settings.model
    if model == "seed":
        return rollout_seed(params, state, track)
    if model == "cv":
        return rollout_cv(params, state)
    if model == "ctrv":
        return rollout_ctrv(params, state)
    return rollout_blend(params, state, track)
