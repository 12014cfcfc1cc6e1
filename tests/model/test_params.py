"""Params, Settings and presets: validation, reparametrisation round trips, jit/vmap/grad."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import assert_trees_close

from fpe_jax import Params, Settings, constrain, presets, stack_params, unconstrain
from fpe_jax.spec import FILTER_DEFAULTS

PRESET_NAMES = (
    "seed",
    "seed-measured-speed",
    "linear",
    "pure-pursuit",
    "constant-velocity",
    "ctrv",
    "frenet",
    "default",
)
FITTED = ("lookahead_m", "lookahead_gain_s", "weights", "delay_s", "speed_weight", "speed_mps")


def interior(settings=None, **kw):
    """Params strictly inside every bound (the round trip is exact only there)."""
    values = dict(
        lookahead_m=1.37,
        lookahead_gain_s=0.21,
        weights=np.linspace(0.93, 0.04, (settings or Settings()).horizon),
        delay_s=0.083,
        speed_weight=0.62,
        speed_mps=1.7,
    )
    values.update(kw)
    return Params.create(settings, **values)


def assert_params_close(a, b, atol):
    fitted = lambda p: {name: getattr(p, name) for name in FITTED}
    assert_trees_close(fitted(a), fitted(b), atol=atol)
    assert a.settings == b.settings


# ---- Settings ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "bad",
    [
        {"blend": "angle"},
        {"model": "kalman"},
        {"dt_s": 0.0},
        {"dt_s": -0.1},
        {"dt_s": float("nan")},
        {"horizon": 0},
        {"horizon": 2.5},
        {"wheelbase_m": 0.0},
        {"max_steer_rad": -0.1},
        {"max_steer_rad": 2.0},
        {"min_lookahead_m": -0.5},
        {"history": 1},
        {"history": 4.0},
    ],
)
def test_settings_reject_bad_values(bad):
    with pytest.raises(ValueError, match="Settings"):
        Settings(**bad)


def test_settings_defaults_and_immutability():
    s = Settings()
    assert (s.dt_s, s.horizon, s.wheelbase_m, s.blend, s.model) == (
        0.1,
        10,
        0.325,
        "position",
        "blend",
    )
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.horizon = 5
    assert hash(Settings()) == hash(Settings())  # usable as a static jit argument


# ---- Params ------------------------------------------------------------------------------------


def test_create_broadcasts_weights_and_reports_physical_values():
    p = Params.create(Settings(horizon=4), lookahead_m=2.5, weights=0.25, delay_s=0.05)
    assert p.weights.shape == (4,)
    assert p.weights.dtype == jnp.float64
    assert p.physical() == {
        "lookahead_m": 2.5,
        "lookahead_gain_s": 0.0,
        "weights": [0.25] * 4,
        "delay_s": 0.05,
        "speed_weight": 1.0,
        "speed_mps": 1.0,
        "offset_tau_s": 1.0,
        "speed_tau_s": 0.5,
        "pace_return_1ps": 0.0,
        "position_smoothing": 0.0,
        **FILTER_DEFAULTS,
    }
    with pytest.raises(ValueError):
        Params.create(Settings(horizon=4), weights=np.ones(3))


def test_presets_are_exactly_the_documented_ones():
    assert tuple(presets) == PRESET_NAMES
    assert len(presets) == len(PRESET_NAMES)
    with pytest.raises(KeyError, match="unknown preset"):
        presets["fast"]
    with pytest.raises(TypeError):
        presets["mine"] = presets["default"]


def test_preset_values():
    seed = presets["seed"]
    assert seed.settings == Settings(max_steer_rad=0.5236, blend="heading", model="seed")
    np.testing.assert_allclose(np.asarray(seed.weights), 0.7 ** np.arange(10), rtol=1e-15)
    assert float(seed.lookahead_m) == 2.0
    # the original's hard-coded 1 m/s: no trust in the measured speed
    assert float(seed.speed_weight) == 0.0 and float(seed.speed_mps) == 1.0
    assert float(seed.delay_s) == 0.0
    measured = presets["seed-measured-speed"]
    assert measured.settings == seed.settings and float(measured.speed_weight) == 1.0
    np.testing.assert_array_equal(np.asarray(measured.weights), np.asarray(seed.weights))
    np.testing.assert_array_equal(np.asarray(presets["linear"].weights), 1.0)
    assert presets["linear"].settings.model == "blend"
    pp = presets["pure-pursuit"]
    np.testing.assert_array_equal(np.asarray(pp.weights), 0.0)
    assert float(pp.lookahead_m) == 2.0
    assert presets["constant-velocity"].settings.model == "cv"
    assert presets["ctrv"].settings.model == "ctrv"
    default = presets["default"]
    assert default.settings.blend == "position" and default.settings.model == "blend"
    assert 0.0 < float(default.weights[0]) < 1.0 and float(default.delay_s) > 0.0
    # every preset is a fresh object (mutating one cannot leak into another)
    assert presets["default"] is not presets["default"]


# ---- reparametrisation -------------------------------------------------------------------------


def test_round_trip_is_exact_inside_the_bounds():
    p = interior(Settings(min_lookahead_m=0.5))
    back = constrain(unconstrain(p))
    assert_params_close(back, p, atol=1e-12)
    back_jit = eqx.filter_jit(lambda q: constrain(unconstrain(q)))(p)
    assert_params_close(back_jit, p, atol=1e-12)
    # and from the raw side, over a wide range of raw values
    for r in (-4.0, -0.3, 0.0, 0.7, 4.0):
        raw = Params.create(
            p.settings,
            lookahead_m=r,
            lookahead_gain_s=-r,
            weights=r,
            delay_s=0.5 * r,
            speed_weight=-r,
            speed_mps=0.3 * r,
        )
        assert_params_close(unconstrain(constrain(raw)), raw, atol=1e-12)


def test_constrained_values_stay_in_range():
    for r in (-60.0, -5.0, 0.0, 5.0, 60.0):
        raw = Params.create(Settings(), **{name: r for name in FITTED})
        p = constrain(raw)
        assert float(p.lookahead_m) >= 0.3
        assert float(p.lookahead_gain_s) >= 0.0 and float(p.delay_s) >= 0.0
        w = np.asarray(p.weights)
        assert np.all((w >= 0.0) & (w <= 1.0))
        assert float(p.speed_mps) >= 0.0 and 0.0 <= float(p.speed_weight) <= 1.0
        assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree.leaves(p))


def test_round_trip_at_the_bounds_is_finite_and_close():
    """At w = 0 or 1, zero delay/gain and the minimum lookahead the inverse is clipped 1e-6
    inside the bound (finite raw values); the round trip lands within 1e-6."""
    for name in PRESET_NAMES:
        p = presets[name]
        raw = unconstrain(p)
        assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree.leaves(raw)), name
        assert_params_close(constrain(raw), p, atol=1.01e-6)
    at_min = Params.create(Settings(), lookahead_m=0.3)
    assert float(constrain(unconstrain(at_min)).lookahead_m) == pytest.approx(0.3, abs=1.01e-6)


def test_reparametrisation_grad_and_vmap():
    p = interior()
    raw = unconstrain(p)
    # d constrain / d raw: softplus' = sigmoid(raw), sigmoid' = w (1 - w)
    g = jax.grad(lambda r: jnp.sum(constrain(r).weights) + constrain(r).lookahead_m)(raw)
    w = np.asarray(p.weights)
    np.testing.assert_allclose(np.asarray(g.weights), w * (1 - w), rtol=1e-12)
    np.testing.assert_allclose(
        float(g.lookahead_m), float(jax.nn.sigmoid(raw.lookahead_m)), rtol=1e-12
    )
    assert float(g.delay_s) == 0.0 and float(g.speed_mps) == 0.0 and float(g.speed_weight) == 0.0
    # and the inverse: d logit / d w = 1 / (w (1 - w)), d softplus^-1(y) / dy = 1 / sigmoid(x)
    gi = jax.grad(lambda q: jnp.sum(unconstrain(q).weights) + unconstrain(q).delay_s)(p)
    np.testing.assert_allclose(np.asarray(gi.weights), 1.0 / (w * (1 - w)), rtol=1e-9)
    expected = 1.0 / float(jax.nn.sigmoid(raw.delay_s))
    np.testing.assert_allclose(float(gi.delay_s), expected, rtol=1e-9)
    # vmapped over stacked parameter sets equals looping
    sets = [interior(lookahead_m=0.5 + k, delay_s=0.01 * (k + 1)) for k in range(3)]
    stacked = stack_params(sets)
    assert stacked.weights.shape == (3, 10)
    batched = eqx.filter_jit(jax.vmap(unconstrain))(stacked)
    for k, q in enumerate(sets):
        one = jax.tree.map(lambda a, k=k: a[k], batched)
        assert_params_close(one, unconstrain(q), atol=1e-12)
    back = jax.vmap(constrain)(batched)
    assert_params_close(back, stacked, atol=1e-12)


def test_stack_params_requires_shared_settings():
    with pytest.raises(ValueError, match="same Settings"):
        stack_params([interior(), interior(Settings(blend="heading"))])


def test_frenet_preset_holds_the_track_speed_and_decays_the_offset():
    from fpe_jax.geometry._track import Track
    from fpe_jax.model._rollout import State, rollout

    p = presets["frenet"]
    assert p.settings.model == "frenet" and float(p.offset_tau_s) == 1.0
    straight = Track.from_waypoints(np.stack([np.linspace(0, 50, 51), np.zeros(51)], 1))
    # 0.4 m left of a straight line, 3 m/s along it: x advances 0.3 m a step, y decays
    st = State(x_m=jnp.array(5.0), y_m=jnp.array(0.4), yaw_rad=jnp.array(0.2), v_mps=jnp.array(3.0))
    st = dataclasses.replace(st, course_rad=jnp.array(0.0))
    out = np.asarray(rollout(p, st, straight).packed())
    t = np.arange(1, 11) * 0.1
    np.testing.assert_allclose(out[:, 0], 5.0 + 3.0 * t, atol=1e-9)
    np.testing.assert_allclose(out[:, 1], 0.4 * np.exp(-t / 1.0), atol=1e-9)
    assert np.all(out[:, 2] < 0) and np.all(np.abs(out[:, 2]) < 0.2)  # heading back to the line
