"""predict / predict_batch / predict_drive: every preset, batches over cars and parameter sets,
jit/vmap/grad, and a whole drive end to end."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fpe_jax import (
    Drive,
    Params,
    Settings,
    State,
    Track,
    predict,
    predict_batch,
    predict_drive,
    presets,
    stack_params,
)
from fpe_jax.predict._predict import predict_poses

H = 10
R = 5.0  # circle radius [m]


@pytest.fixture(scope="module")
def circle():
    a = np.linspace(0.0, 2 * np.pi, 200, endpoint=False)
    return Track.from_waypoints(R * np.column_stack([np.cos(a), np.sin(a)]))


def cars(angles, v=(2.0, 3.0, 1.5), radius=R + 0.1):
    """Cars near the circle, heading roughly along it (counter-clockwise)."""
    a = np.asarray(angles, dtype=float)
    n = len(a)
    return State(
        x_m=jnp.asarray(radius * np.cos(a)),
        y_m=jnp.asarray(radius * np.sin(a)),
        yaw_rad=jnp.asarray(a + 0.5 * np.pi - 0.05),
        v_mps=jnp.asarray(np.resize(v, n)),
        yaw_rate_rps=jnp.asarray(np.resize([0.4, 0.6, 0.3], n)),
        course_rad=jnp.asarray(a + 0.5 * np.pi),
    )


def pick(tree, i):
    return jax.tree.map(lambda a: a[i], tree)


STATES = cars([0.3, 2.5, -2.0])


# module-level wrapper: one compile per (settings, shapes), shared by the tests below
PREDICT = eqx.filter_jit(predict)


def test_every_preset_predicts_finite_poses(circle):
    start = np.column_stack([np.asarray(STATES.x_m), np.asarray(STATES.y_m)])
    for name in presets:
        p = presets[name]
        out = np.stack([np.asarray(PREDICT(p, pick(STATES, i), circle)) for i in range(3)])
        assert out.shape == (3, H, 3), name
        assert np.all(np.isfinite(out)), name
        # predictions move forward: the last point is farther than the first
        d1 = np.linalg.norm(out[:, 0, :2] - start, axis=1)
        dh = np.linalg.norm(out[:, -1, :2] - start, axis=1)
        assert np.all(dh > d1 + 0.5), name
        # the predicted yaw is the direction the car moves in (mod 2 pi: the seed's is unwrapped)
        xy = np.concatenate([start[:, None], out[:, :, :2]], axis=1)
        course = np.arctan2(np.diff(xy[..., 1], axis=1), np.diff(xy[..., 0], axis=1))
        assert np.all(np.abs(np.angle(np.exp(1j * (out[:, :, 2] - course)))) < 0.3), name


def test_predict_batch_over_cars_equals_looping_and_is_differentiable(circle):
    p = presets["default"]
    eager = np.asarray(predict(p, pick(STATES, 1), circle))
    np.testing.assert_allclose(np.asarray(PREDICT(p, pick(STATES, 1), circle)), eager, atol=1e-12)
    batched = np.asarray(predict_batch(p, STATES, circle))
    assert batched.shape == (3, H, 3)
    looped = np.stack([np.asarray(PREDICT(p, pick(STATES, i), circle)) for i in range(3)])
    np.testing.assert_allclose(batched, looped, rtol=0, atol=1e-12)
    # differentiable in every fitted value (the fitter's path: predict vmapped over cars); the
    # cars' measured speeds differ from the typical 2 m/s, so the speed shrinkage matters too
    g = eqx.filter_jit(jax.grad(lambda q: jnp.sum(predict_batch(q, STATES, circle)[..., :2])))(p)
    fitted = ("lookahead_m", "lookahead_gain_s", "weights", "delay_s", "speed_weight", "speed_mps")
    for name in fitted:
        v = np.asarray(getattr(g, name))
        assert np.all(np.isfinite(v)) and np.all(v != 0.0), name


def param_sets() -> list[Params]:
    """Four default presets with their own lookahead and delay (the tests below stack the same
    four: one compiled program of each shape serves them all)."""
    base = presets["default"]
    return [
        dataclasses.replace(
            base, lookahead_m=jnp.asarray(0.6 + 0.5 * k), delay_s=jnp.asarray(0.05 * k)
        )
        for k in range(4)
    ]


def test_predict_batch_over_parameter_sets(circle):
    sets = param_sets()
    stacked = stack_params(sets)
    out = np.asarray(predict_batch(stacked, STATES, circle))
    assert out.shape == (4, 3, H, 3)
    for k, q in enumerate(sets):
        np.testing.assert_allclose(
            out[k], np.asarray(predict_batch(q, STATES, circle)), rtol=0, atol=1e-12
        )
    assert np.abs(out[0] - out[3]).max() > 0.05  # the sets do differ
    # stack of one is the same as the single set, with a leading axis
    one = np.asarray(predict_batch(stack_params(sets[:1]), STATES, circle))
    np.testing.assert_allclose(one[0], out[0], rtol=0, atol=1e-12)


def test_poses_are_the_columns_of_the_packed_predictions(circle):
    """predict_poses' fields are predict_batch's columns x, y, yaw (under P parameter sets too);
    NumPy poses (the commands' finished predictions) pack to a writable NumPy array."""
    p = presets["default"]
    for q in (p, stack_params(param_sets())):
        poses = eqx.filter_jit(predict_poses)(q, STATES, circle)
        packed = np.asarray(predict_batch(q, STATES, circle))
        assert poses.x_m.shape == packed.shape[:-1]
        for k, field in enumerate(("x_m", "y_m", "yaw_rad")):
            np.testing.assert_allclose(getattr(poses, field), packed[..., k], rtol=0, atol=1e-12)
        np.testing.assert_allclose(poses.xy_m, packed[..., :2], rtol=0, atol=1e-12)
    out = jax.tree.map(np.asarray, poses).packed()
    assert isinstance(out, np.ndarray) and out.flags.writeable and out.shape == packed.shape


def test_predict_drive_around_a_circle(circle):
    """A car circling at 2 m/s, observed at 10 Hz with repeated rows: pure pursuit follows the
    circle (1 s ahead within 10 cm), the linear predictor cuts the chord, and a repeated row is
    predicted from exactly as the detection it repeats."""
    n = 40
    t = 0.1 * np.arange(n)
    w = 2.0 / R
    shown = np.arange(n)
    shown[7::5] = shown[6::5][: len(shown[7::5])]  # every fifth row repeats the previous one
    a = w * t[shown]
    drive = Drive(
        t_s=t, xy_m=R * np.column_stack([np.cos(a), np.sin(a)]), yaw_rad=np.full(n, np.nan)
    )
    pp = Params.create(Settings(), lookahead_m=0.8, weights=0.0)
    stamps, poses = predict_drive(pp, drive, circle)
    np.testing.assert_array_equal(stamps, t)
    assert poses.shape == (n, H, 3)
    np.testing.assert_array_equal(poses, poses[shown])
    # the truth H steps after the detection each row shows
    ahead = a[:, None] + w * 0.1 * np.arange(1, H + 1)[None, :]
    truth = R * np.stack([np.cos(ahead), np.sin(ahead)], axis=-1)
    err = np.linalg.norm(poses[10:, :, :2] - truth[10:], axis=-1)
    assert err.max() < 0.1, err.max()
    _, lin = predict_drive(presets["linear"], drive, circle)
    err_lin = np.linalg.norm(lin[10:, -1, :2] - truth[10:, -1], axis=-1)
    assert err_lin.min() > 0.3


def test_public_api_names_the_functions():
    """`fpe_jax.predict` is the function even after its submodule of the same name was imported
    (the lazy package once returned the module here)."""
    import fpe_jax
    from fpe_jax.predict import _predict as _  # noqa: F401  (binds the package: shadows)

    assert fpe_jax.predict is predict and callable(fpe_jax.predict)
    assert fpe_jax.predict_batch is predict_batch
    for name in fpe_jax.__all__:
        assert not isinstance(getattr(fpe_jax, name), type(fpe_jax)), name
