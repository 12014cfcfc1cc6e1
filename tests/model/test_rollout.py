"""Rollouts: exact kinematics where they are exact, wrap-free near +-pi, jit/vmap/grad, and
finite-difference gradient checks of every fitted value in both blend modes."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import fd_gradient

from fpe_jax import Params, Settings, State, Track
from fpe_jax.geometry._path import wrap_angle
from fpe_jax.model._rollout import (
    FALLBACK_TAU_S,
    _sincos,
    pure_pursuit_steer,
    rollout,
    rollout_blend,
    rollout_ctrv,
    rollout_cv,
    rollout_frenet,
    rollout_linear,
    rollout_pure_pursuit,
    rollout_seed,
)

H, DT = 10, 0.1
STEPS = DT * np.arange(1, H + 1)


def line_track(angle_rad, length_m=30.0, start=(0.0, 0.0)):
    """Open straight path from `start` in direction `angle_rad`."""
    u = np.linspace(0.0, length_m, 61)
    x0, y0 = start
    return Track.from_waypoints(
        np.column_stack([x0 + u * np.cos(angle_rad), y0 + u * np.sin(angle_rad)])
    )


def state(x, y, yaw, v, **kw):
    kw = {k: jnp.asarray(val, dtype=float) for k, val in kw.items()}
    return State(
        x_m=jnp.asarray(x, dtype=float),
        y_m=jnp.asarray(y, dtype=float),
        yaw_rad=jnp.asarray(yaw, dtype=float),
        v_mps=jnp.asarray(v, dtype=float),
        **kw,
    )


def params(blend="position", model="blend", **kw):
    return Params.create(Settings(blend=blend, model=model), **kw)


def packed(rollout_fn):
    """rollout_fn giving its Poses as the (H, 3) array x, y, yaw that the checks index."""
    return lambda *args: rollout_fn(*args).packed()


# jitted once per (settings, track shape): the scan-based rollouts would recompile their loop
# body on every eager call; jit-vs-eager equality is tested separately below
PP = eqx.filter_jit(packed(rollout_pure_pursuit))
BLEND = eqx.filter_jit(packed(rollout_blend))
CTRV = eqx.filter_jit(packed(rollout_ctrv))


@pytest.fixture(scope="module")
def circle():
    """Closed circle of radius 4 m centred at the origin, counter-clockwise."""
    a = np.linspace(0.0, 2 * np.pi, 180, endpoint=False)
    return Track.from_waypoints(4.0 * np.column_stack([np.cos(a), np.sin(a)]))


@pytest.fixture(scope="module")
def diagonal():
    return line_track(0.5)


@pytest.fixture(scope="module")
def westward():
    """Straight path heading due west (yaw pi) along y = 0, from x = 30 to x = 0."""
    return line_track(np.pi, start=(30.0, 0.0))


@pytest.fixture(scope="module")
def levine(shared_data):
    wps = np.loadtxt(shared_data / "levine" / "levine-waypoints.csv", delimiter=",")[:, :2]
    return Track.from_waypoints(wps)


# ---- linear, constant velocity, CTRV -----------------------------------------------------------


def test_linear_positions_are_exact():
    st = state(1.5, -2.0, 0.7, 3.2)
    out = np.asarray(rollout_linear(params(delay_s=0.0), st).packed())
    assert out.shape == (H, 3)
    np.testing.assert_allclose(out[:, 0], 1.5 + 3.2 * STEPS * np.cos(0.7), rtol=0, atol=1e-12)
    np.testing.assert_allclose(out[:, 1], -2.0 + 3.2 * STEPS * np.sin(0.7), rtol=0, atol=1e-12)
    np.testing.assert_array_equal(out[:, 2], 0.7)
    # the delay lengthens the first step
    out = np.asarray(rollout_linear(params(delay_s=0.08), st).packed())
    np.testing.assert_allclose(out[:, 0], 1.5 + 3.2 * (STEPS + 0.08) * np.cos(0.7), atol=1e-12)
    # speed_weight 0 ignores the measured speed (the original's hard-coded one); in between the
    # measured speed is shrunk toward speed_mps
    fixed = Params.create(Settings(), speed_weight=0.0, speed_mps=0.5, delay_s=0.0)
    out = np.asarray(rollout_linear(fixed, st).packed())
    np.testing.assert_allclose(out[:, 1], -2.0 + 0.5 * STEPS * np.sin(0.7), atol=1e-12)
    shrunk = Params.create(Settings(), speed_weight=0.25, speed_mps=0.5, delay_s=0.0)
    out = np.asarray(rollout_linear(shrunk, st).packed())
    v = 0.25 * 3.2 + 0.75 * 0.5
    np.testing.assert_allclose(out[:, 1], -2.0 + v * STEPS * np.sin(0.7), atol=1e-12)


@pytest.mark.parametrize("delay_s", [0.0, 0.037, 0.25])
def test_delay_equals_starting_further_along(delay_s):
    """A rollout with delay d equals one without delay started d * v further along."""
    x, y, yaw, v = 3.0, 1.0, -2.1, 4.5
    delayed = rollout_linear(params(delay_s=delay_s), state(x, y, yaw, v)).packed()
    d = delay_s * v
    moved = state(x + d * np.cos(yaw), y + d * np.sin(yaw), yaw, v)
    np.testing.assert_allclose(
        np.asarray(delayed),
        np.asarray(rollout_linear(params(delay_s=0.0), moved).packed()),
        atol=1e-12,
    )


def test_constant_velocity_follows_the_course():
    st = state(0.0, 0.0, 0.3, 2.0, course_rad=-0.4)
    out = np.asarray(rollout_cv(params(model="cv", delay_s=0.0), st).packed())
    np.testing.assert_allclose(out[:, 0], 2.0 * STEPS * np.cos(-0.4), atol=1e-12)
    np.testing.assert_allclose(out[:, 1], 2.0 * STEPS * np.sin(-0.4), atol=1e-12)


def test_ctrv_with_zero_yaw_rate_is_linear():
    st = state(1.0, 2.0, 2.9, 3.0, yaw_rate_rps=0.0)
    p = params(model="ctrv", delay_s=0.05)
    np.testing.assert_allclose(
        np.asarray(CTRV(p, st)), np.asarray(rollout_linear(p, st).packed()), rtol=0, atol=1e-12
    )


@pytest.mark.parametrize("yaw_rate_rps", [0.8, -2.5])
def test_ctrv_lands_on_its_circle(yaw_rate_rps):
    x, y, yaw, v = 1.0, -1.0, 2.8, 3.0
    st = state(x, y, yaw, v, yaw_rate_rps=yaw_rate_rps)
    out = np.asarray(CTRV(params(model="ctrv", delay_s=0.03), st))
    r = v / yaw_rate_rps
    cx, cy = x - r * np.sin(yaw), y + r * np.cos(yaw)
    np.testing.assert_allclose(np.hypot(out[:, 0] - cx, out[:, 1] - cy), abs(r), atol=1e-12)
    t = STEPS + 0.03
    np.testing.assert_allclose(out[:, 2], wrap_angle(yaw + yaw_rate_rps * t), atol=1e-12)
    # and on the circle at the right place: the tangent there is the predicted yaw
    expected = np.column_stack([cx + r * np.sin(out[:, 2]), cy - r * np.cos(out[:, 2])])
    np.testing.assert_allclose(out[:, :2], expected, atol=1e-12)


# ---- pure pursuit ------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype, tol", [("float32", 1e-7), ("float64", 3e-14)])
def test_shared_sincos_matches_numpy(dtype, tol):
    """The rollout's one-reduction sin/cos (its docstring quotes these bounds)."""
    x = np.concatenate([np.linspace(-1e4, 1e4, 200_001), np.arange(-8, 9) * np.pi / 4])
    with jax.enable_x64(dtype == "float64"):
        s, c = jax.jit(_sincos)(jnp.asarray(x.astype(dtype)))
        assert s.dtype == c.dtype == dtype
        slope = jax.grad(lambda a: _sincos(a)[0])(jnp.asarray(1.3, dtype=dtype))
    xd = x.astype(dtype).astype(np.float64)  # the argument as the function saw it
    assert np.max(np.abs(np.asarray(s, np.float64) - np.sin(xd))) < tol
    assert np.max(np.abs(np.asarray(c, np.float64) - np.cos(xd))) < tol
    assert float(slope) == pytest.approx(np.cos(1.3), abs=10 * tol)


def test_pure_pursuit_steering_law():
    track = line_track(0.0)
    p = params(lookahead_m=1.5, lookahead_gain_s=0.25)
    x, y, v = 5.0, 0.5, 2.0
    steer, s = pure_pursuit_steer(
        p, jnp.asarray(x), jnp.asarray(y), jnp.asarray(0.0), jnp.asarray(v), jnp.asarray(4.0), track
    )
    assert float(s) == pytest.approx(5.0, abs=1e-12)
    lookahead = 1.5 + 0.25 * v
    d = np.hypot(lookahead, y)
    assert float(steer) == pytest.approx(np.arctan(2 * 0.325 * (-y / d) / d), abs=1e-12)
    # with a near goal well to the side the law asks for more than the limit: clipped
    short = params(lookahead_m=0.3, lookahead_gain_s=0.0)
    steer, _ = pure_pursuit_steer(short, *(jnp.asarray(a) for a in (x, 0.5, 0.0, v, 5.0)), track)
    d = np.hypot(0.3, 0.5)
    assert np.arctan(2 * 0.325 * (0.5 / d) / d) > short.settings.max_steer_rad
    assert float(steer) == -short.settings.max_steer_rad


def test_pure_pursuit_on_a_straight_equals_linear(diagonal):
    x, y = 4.0 * np.cos(0.5), 4.0 * np.sin(0.5)
    st = state(x, y, 0.5, 3.0)
    p = params(lookahead_m=1.2, lookahead_gain_s=0.1, delay_s=0.06)
    np.testing.assert_allclose(
        np.asarray(PP(p, st, diagonal)),
        np.asarray(rollout_linear(p, st).packed()),
        rtol=0,
        atol=1e-12,
    )
    st_hint = dataclasses.replace(st, s_m=jnp.asarray(3.9))  # with a hint: the same
    np.testing.assert_allclose(
        np.asarray(PP(p, st_hint, diagonal)),
        np.asarray(rollout_linear(p, st).packed()),
        rtol=0,
        atol=1e-12,
    )


def test_pure_pursuit_steers_back_to_the_path(diagonal):
    n = np.array([-np.sin(0.5), np.cos(0.5)])
    x, y = 4.0 * np.cos(0.5) + 0.4 * n[0], 4.0 * np.sin(0.5) + 0.4 * n[1]
    out = np.asarray(PP(params(lookahead_m=1.0), state(x, y, 0.5, 2.0), diagonal))
    offset = out[:, 0] * n[0] + out[:, 1] * n[1]
    assert np.all(np.diff(offset) < 0) and offset[-1] < 0.25 * 0.4  # converges to the line
    assert offset.min() > -0.02  # without overshooting
    assert out[0, 2] < 0.5 - 0.05  # by turning right first


def test_pure_pursuit_heading_west_has_no_wrap_jump(westward):
    p = params(lookahead_m=1.0, delay_s=0.05)
    # on the line: both sides of +-pi give the straight line west
    a = PP(p, state(20.0, 0.0, np.pi - 1e-9, 2.0), westward)
    b = PP(p, state(20.0, 0.0, -np.pi + 1e-9, 2.0), westward)
    np.testing.assert_allclose(np.asarray(a[:, :2]), np.asarray(b[:, :2]), rtol=0, atol=1e-8)
    np.testing.assert_allclose(np.asarray(a[:, 0]), 20.0 - 2.0 * (STEPS + 0.05), atol=1e-8)
    np.testing.assert_allclose(np.asarray(a[:, 1]), 0.0, atol=1e-8)
    # beside the line the car steers (north of a westward line: turn left, yaw grows past pi)
    a = PP(p, state(20.0, 0.3, np.pi - 1e-9, 2.0), westward)
    b = PP(p, state(20.0, 0.3, -np.pi + 1e-9, 2.0), westward)
    np.testing.assert_allclose(np.asarray(a[:, :2]), np.asarray(b[:, :2]), rtol=0, atol=1e-8)
    assert np.all(np.asarray(a[:, 1]) < 0.3) and float(a[-1, 1]) < 0.15
    for yaw in (np.pi - 1e-9, -np.pi + 1e-9):
        steer, _ = pure_pursuit_steer(
            p, *(jnp.asarray(v) for v in (20.0, 0.3, yaw, 2.0, 10.0)), westward
        )
        assert 0.05 < float(steer) < p.settings.max_steer_rad


# ---- blends ------------------------------------------------------------------------------------


def test_position_blend_limits(circle):
    st = state(4.0, 0.0, 0.5 * np.pi + 0.1, 2.5)
    kw = dict(lookahead_m=1.0, lookahead_gain_s=0.1, delay_s=0.05)
    lin = np.asarray(rollout_linear(params(**kw), st).packed())
    pp = np.asarray(PP(params(**kw), st, circle))
    assert np.abs(pp[:, :2] - lin[:, :2]).max() > 0.3  # the two differ: the test can fail
    one = np.asarray(BLEND(params(weights=1.0, **kw), st, circle))
    zero = np.asarray(BLEND(params(weights=0.0, **kw), st, circle))
    np.testing.assert_allclose(one, lin, rtol=0, atol=1e-12)
    np.testing.assert_allclose(zero, pp, rtol=0, atol=1e-12)
    w = np.linspace(0.95, 0.05, H)
    mix = np.asarray(BLEND(params(weights=w, **kw), st, circle))
    np.testing.assert_allclose(mix[:, :2], w[:, None] * lin[:, :2] + (1 - w[:, None]) * pp[:, :2])


def test_heading_blend_limits(circle):
    st = state(4.0, 0.0, 0.5 * np.pi + 0.1, 2.5)
    kw = dict(lookahead_m=1.0, delay_s=0.05)
    lin = np.asarray(rollout_linear(params(**kw), st).packed())
    pp = np.asarray(PP(params(**kw), st, circle))
    one = np.asarray(BLEND(params("heading", weights=1.0, **kw), st, circle))
    zero = np.asarray(BLEND(params("heading", weights=0.0, **kw), st, circle))
    np.testing.assert_allclose(one, lin, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(zero, pp)
    # in between, the turn is scaled: the final heading lies strictly between the two
    half = np.asarray(BLEND(params("heading", weights=0.5, **kw), st, circle))
    assert lin[-1, 2] < half[-1, 2] < pp[-1, 2]


def test_position_blend_of_headings_across_pi(westward):
    """The linear rollout keeps yaw pi - 0.01; pure pursuit turns left past pi to about -pi +
    0.01: their blend must stay near pi, not average to 0."""
    st = state(20.0, 0.05, np.pi - 0.01, 2.0)
    kw = dict(lookahead_m=0.8, delay_s=0.0)
    lin = np.asarray(rollout_linear(params(**kw), st).packed())
    pp = np.asarray(PP(params(**kw), st, westward))
    assert np.all(lin[:, 2] > 3.13) and np.any(pp[:, 2] < -3.13)  # on both sides of the cut
    out = np.asarray(BLEND(params(weights=0.5, **kw), st, westward))
    assert np.all(np.abs(wrap_angle(out[:, 2] - np.pi)) < 0.02)
    expected = lin[:, 2] + 0.5 * wrap_angle(pp[:, 2] - lin[:, 2])
    np.testing.assert_allclose(wrap_angle(out[:, 2] - expected), 0.0, atol=1e-12)
    # the heading blend scales each turn; its yaw crosses the cut without a jump either
    heading = np.asarray(BLEND(params("heading", weights=0.5, **kw), st, westward))
    assert np.all(np.abs(wrap_angle(heading[:, 2] - np.pi)) < 0.05)
    assert np.all(np.abs(wrap_angle(np.diff(heading[:, 2]))) < 0.03)
    assert np.any(heading[:, 2] < -3.1)  # it did cross
    assert np.all(np.abs(np.diff(heading[:, 1])) < 0.25 * DT * 2.0)


# ---- the seed rules ----------------------------------------------------------------------------


def test_seed_rollout_first_step_is_linear_and_it_turns_to_the_goal(circle):
    p = Params.create(
        Settings(max_steer_rad=0.5236, blend="heading", model="seed"),
        lookahead_m=2.0,
        weights=0.7 ** np.arange(H),
        speed_weight=0.0,
        speed_mps=1.0,
    )
    st = state(4.0, 0.0, 0.5 * np.pi, 5.0)  # on the circle, tangent: the goal is to the left
    out = np.asarray(rollout_seed(p, st, circle).packed())
    np.testing.assert_allclose(out[0, :2], [4.0, 0.1], atol=1e-12)  # speed 1 m/s, not 5
    assert np.all(np.diff(out[:, 2]) > 0)
    np.testing.assert_array_equal(out, np.asarray(rollout(p, st, circle).packed()))


# ---- jit / vmap / grad -------------------------------------------------------------------------


def _steer(p, s, t):
    """pure_pursuit_steer as a function of a State: (steering [rad], arc length [m])."""
    hint = t.project(jnp.stack([s.x_m, s.y_m]))
    return jnp.stack(pure_pursuit_steer(p, s.x_m, s.y_m, s.yaw_rad, s.v_mps, hint, t))


ROLLOUTS = {
    "linear": (lambda p, s, t: rollout_linear(p, s).packed(), "position"),
    "cv": (lambda p, s, t: rollout_cv(p, s).packed(), "position"),
    "ctrv": (lambda p, s, t: rollout_ctrv(p, s).packed(), "position"),
    "pure_pursuit_steer": (_steer, "position"),
    "pure_pursuit": (packed(rollout_pure_pursuit), "position"),
    "blend_position": (packed(rollout_blend), "position"),
    "blend_heading": (packed(rollout_blend), "heading"),
    "dispatch_seed": (packed(rollout), "seed"),
}


@pytest.mark.parametrize("name", list(ROLLOUTS))
def test_rollouts_under_jit_and_vmap_equal_eager(circle, name):
    """jit(vmap(f)) over two cars equals f called eagerly car by car; grad (in the same
    compiled call, to compile once) is finite and moves with the fitted values. The gradients of
    the pure-pursuit and position-blend rollouts are checked against finite differences below
    and through `predict` (test_predict.py), so they are not compiled a third time here."""
    f, mode = ROLLOUTS[name]
    if mode == "seed":
        p = Params.create(Settings(blend="heading", model="seed"), weights=0.7 ** np.arange(H))
    else:
        p = params(mode, lookahead_m=1.1, lookahead_gain_s=0.1, weights=0.6, delay_s=0.04)
    angles = np.array([0.1, -2.9])
    states = State(
        x_m=jnp.asarray(4.1 * np.cos(angles)),
        y_m=jnp.asarray(4.1 * np.sin(angles)),
        yaw_rad=jnp.asarray(angles + 0.5 * np.pi + 0.05),
        v_mps=jnp.array([1.5, 4.0]),
        yaw_rate_rps=jnp.array([0.3, -0.9]),
        course_rad=jnp.asarray(angles + 0.5 * np.pi),
    )
    one = lambda i: jax.tree.map(lambda a: a[i], states)
    eager = np.stack([np.asarray(f(p, one(i), circle)) for i in range(2)])
    assert np.all(np.isfinite(eager))
    differentiable = name not in ("dispatch_seed", "pure_pursuit", "blend_position")

    def batched_and_grad(p_, states_, st_):
        out = jax.vmap(f, in_axes=(None, 0, None))(p_, states_, circle)
        if not differentiable:
            return out, None
        return out, jax.grad(lambda a, b: jnp.sum(f(a, b, circle)), argnums=(0, 1))(p_, st_)

    batched, grads = eqx.filter_jit(batched_and_grad)(p, states, one(1))
    np.testing.assert_allclose(np.asarray(batched), eager, rtol=0, atol=1e-12)
    if differentiable:
        gp, gs = grads
        assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree.leaves((gp, gs)))
        if name != "pure_pursuit_steer":
            assert float(jnp.abs(gp.delay_s)) > 0.1  # the delay moves every prediction
        else:
            assert float(jnp.abs(gp.lookahead_m)) > 0.0
        if name in ("linear", "cv", "ctrv"):  # each output's x moves 1:1 with the state's
            assert float(gs.x_m) == pytest.approx(H, rel=1e-12)


# ---- finite-difference gradient checks ---------------------------------------------------------

FITTED = ("lookahead_m", "lookahead_gain_s", "weights", "delay_s", "speed_weight", "speed_mps")


@pytest.mark.parametrize("blend", ["position", "heading"])
def test_gradients_match_central_differences(levine, blend):
    """In a Levine corner (pure pursuit steers, unclipped), the gradient of a squared-distance
    loss w.r.t. lookahead, gain, every weight, the delay and the speed shrinkage equals central
    differences (step 1e-6, float64) to rtol 1e-5 / atol 1e-8, and none of them vanishes."""
    k = 160  # ~1.2 m before Levine's sharpest corner
    ds = float(levine.ds_m)
    xy, h = np.asarray(levine.xy_m[k]), float(levine.heading_rad[k])
    v = 2.0
    st = state(xy[0] - 0.1 * np.sin(h), xy[1] + 0.1 * np.cos(h), h + 0.05, v, s_m=k * ds)
    p0 = params(
        blend,
        lookahead_m=1.0,
        lookahead_gain_s=0.2,
        weights=np.linspace(0.9, 0.1, H),
        delay_s=0.08,
        speed_weight=0.8,
        speed_mps=1.5,
    )
    target = jax.vmap(levine.point_at)(k * ds + v * (0.1 + jnp.asarray(STEPS)))

    # pure pursuit really steers here, below the limit at every step
    pp = np.asarray(PP(p0, st, levine))
    yaws = np.concatenate([[float(st.yaw_rad)], pp[:, 2]])
    turn = np.abs(wrap_angle(np.diff(yaws)))[1:]  # regular steps
    max_turn = (0.8 * v + 0.2 * 1.5) / 0.325 * np.tan(p0.settings.max_steer_rad) * DT
    assert np.all(turn > 0.05 * max_turn) and np.all(turn < 0.9 * max_turn)

    def loss(p):
        return jnp.sum((rollout_blend(p, st, levine).xy_m - target) ** 2)

    grad = eqx.filter_jit(jax.grad(loss))(p0)
    loss_jit = eqx.filter_jit(loss)
    for name in FITTED:
        value = np.asarray(getattr(p0, name), dtype=float)
        at = lambda v, n=name: loss_jit(eqx.tree_at(lambda p: getattr(p, n), p0, jnp.asarray(v)))
        fd = np.ravel(fd_gradient(at, value, eps=1e-6))
        g = np.ravel(np.asarray(getattr(grad, name)))
        np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-8, err_msg=f"{blend} {name}")
        assert np.all(np.abs(g) > 1e-6) and np.abs(g).max() > 1e-2, (blend, name, g)
    # L = lookahead + gain * v: the two gradients are exactly proportional (v the rollout speed)
    v_roll = 0.8 * v + 0.2 * 1.5
    assert float(grad.lookahead_gain_s) == pytest.approx(v_roll * float(grad.lookahead_m), rel=1e-9)


# ---- the line model's fallback and lateral rate ----------------------------------------------


def line_model(coverage: float, offset_m: float = 0.0, **kw) -> Params:
    """A line-model Params on the 30 m straight: the line at offset_m, covered by `coverage`."""
    p = 60
    return params(
        model="line",
        line_offset_m=np.full(p, offset_m),
        line_speed_mps=np.full(p, 2.0),
        line_coverage=np.full(p, coverage),
        **kw,
    )


def lateral_offsets(p: Params, st: State, track: Track) -> np.ndarray:
    """(H,) the rollout's left offset [m] from the straight along +x."""
    return np.asarray(eqx.filter_jit(rollout_frenet)(p, st, track).y_m)


def test_uncovered_line_holds_the_cars_offset_decaying_slowly():
    """Where the fit drives never went the car keeps its own offset (the centerline is rarely
    where it drives), decaying with FALLBACK_TAU_S, not with the fitted time constant."""
    track, st = line_track(0.0), state(5.0, 0.8, 0.0, 2.0)
    p = line_model(0.0, offset_tau_s=0.2)
    expected = 0.8 * np.exp(-STEPS / FALLBACK_TAU_S)
    np.testing.assert_allclose(lateral_offsets(p, st, track), expected, atol=1e-9)
    # covered: the offset returns to the line with the fitted time constant
    covered = lateral_offsets(line_model(1.0, offset_tau_s=0.2), st, track)
    e0, t = 0.8, STEPS
    np.testing.assert_allclose(covered, (e0 + e0 / 0.2 * t) * np.exp(-t / 0.2), atol=1e-9)


def test_the_return_to_the_line_starts_at_the_cars_lateral_rate():
    """A car on its line but heading away from it keeps moving away at first (its course), then
    returns: the offset's first step follows v sin(course - heading)."""
    track = line_track(0.0)
    st = state(5.0, 0.0, 0.0, 2.0, course_rad=0.1)
    d = lateral_offsets(line_model(1.0, offset_tau_s=0.5), st, track)
    rate = 2.0 * np.sin(0.1)
    np.testing.assert_allclose(d, rate * STEPS * np.exp(-STEPS / 0.5), atol=1e-9)
    assert d[0] == pytest.approx(rate * DT, rel=0.2) and abs(d[-1]) < d[2]


def test_uncovered_line_follows_the_priors_change_from_the_cars_own_offset():
    """Where coverage is 0 the profile is `fpe_jax.model`'s prior: the car keeps its own offset
    from it (decaying with FALLBACK_TAU_S) and follows its change, and its speed follows the
    prior's ratio."""
    track, p_pts = line_track(0.0), 60
    s_pts = np.linspace(0.0, 30.0, p_pts)
    slope = 0.02
    p = line_model(0.0, offset_tau_s=0.2)
    p = dataclasses.replace(p, line_offset_m=jnp.asarray(0.1 + slope * s_pts))
    # heading along the prior's slope: no lateral rate relative to it
    st = state(5.0, 0.8, 0.0, 2.0, course_rad=np.arctan(slope))
    v0 = 2.0 * np.cos(np.arctan(slope))
    s = 5.0 + v0 * STEPS
    expected = 0.1 + slope * s + (0.8 - 0.1 - slope * 5.0) * np.exp(-STEPS / FALLBACK_TAU_S)
    np.testing.assert_allclose(lateral_offsets(p, st, track), expected, atol=1e-9)
    # a prior that speeds up ahead carries the car further than its current speed would
    faster = dataclasses.replace(p, line_speed_mps=jnp.asarray(2.0 + 0.2 * s_pts))
    x_end = float(eqx.filter_jit(rollout_frenet)(faster, st, track).x_m[-1])
    assert x_end > s[-1] + 0.05, x_end


def _pace_positions(v0, vp, delay_s, speed_tau_s, rate_1ps):
    """(H,) the along-track positions [m] the line model's speed law gives from x = 5 m on a
    profile of constant speed vp: v = v0 + (1 - exp(-t r)) (1 - exp(-t / tau)) (vp - v0) over
    each step, t its start (the delay step first)."""
    dts = np.concatenate([[delay_s], np.full(H, DT)])
    t0 = np.cumsum(dts) - dts
    v = v0 + -np.expm1(-t0 * rate_1ps) * -np.expm1(-t0 / speed_tau_s) * (vp - v0)
    return (5.0 + np.cumsum(v * dts))[1:]


@pytest.mark.parametrize("rate_1ps", [0.0, 0.7, 50.0])
def test_the_cars_pace_returns_to_the_profiles(rate_1ps):
    """A car faster than its profile (3 against 2 m/s) keeps its pace with pace_return_1ps 0
    (the profile's shape only: a constant profile, a constant speed) and slows to the
    profile's speed at that rate otherwise; exact on the straight."""
    track, st = line_track(0.0), state(5.0, 0.0, 0.0, 3.0)
    p = line_model(1.0, delay_s=0.05, speed_tau_s=0.3, pace_return_1ps=rate_1ps)
    x = np.asarray(eqx.filter_jit(rollout_frenet)(p, st, track).x_m)
    np.testing.assert_allclose(x, _pace_positions(3.0, 2.0, 0.05, 0.3, rate_1ps), atol=1e-9)
    if rate_1ps == 0.0:
        np.testing.assert_allclose(x, 5.0 + 3.0 * (0.05 + STEPS), atol=1e-9)


def test_no_pace_return_where_the_profile_is_no_speed_reference():
    """Where the profile is slower than MIN_PROFILE_SPEED_MPS (no reference) the car keeps its
    own speed, whatever the rate."""
    track, st = line_track(0.0), state(5.0, 0.0, 0.0, 3.0)
    p = line_model(1.0, speed_tau_s=0.3, pace_return_1ps=5.0)
    p = dataclasses.replace(p, line_speed_mps=jnp.full(60, 0.1))
    x = np.asarray(eqx.filter_jit(rollout_frenet)(p, st, track).x_m)
    np.testing.assert_allclose(x, 5.0 + 3.0 * STEPS, atol=1e-9)


def test_pace_return_under_vmap_and_its_gradient():
    """vmapped over cars equals one at a time; d(last x)/d(rate) matches central differences."""
    track = line_track(0.0)
    states = jax.tree.map(
        lambda *xs: jnp.stack(xs), state(5.0, 0.0, 0.0, 3.0), state(6.0, 0.1, 0.0, 1.0)
    )
    p = line_model(1.0, speed_tau_s=0.3, pace_return_1ps=0.7)
    # compiled: run eagerly, the vmapped scan goes op by op
    vmapped = eqx.filter_jit(jax.vmap(rollout_frenet, in_axes=(None, 0, None)))
    batch = vmapped(p, states, track).x_m
    for i in range(2):
        one = eqx.filter_jit(rollout_frenet)(p, jax.tree.map(lambda x, i=i: x[i], states), track)
        np.testing.assert_allclose(batch[i], one.x_m, atol=1e-12)

    @jax.jit
    def last_x(rate):
        q = dataclasses.replace(p, pace_return_1ps=jnp.asarray(rate).reshape(()))
        return rollout_frenet(q, state(5.0, 0.0, 0.0, 3.0), track).x_m[-1]

    grad = float(jax.jit(jax.grad(last_x))(jnp.asarray(0.7)))
    np.testing.assert_allclose(grad, fd_gradient(last_x, np.asarray(0.7), 1e-5), rtol=1e-6)
    assert grad < 0.0  # a faster return to the slower profile: less far
