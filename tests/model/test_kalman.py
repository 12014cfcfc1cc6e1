"""The track-frame Kalman filter (`fpe_jax.model`): exact on clean motion over irregular stamps
and gaps, outliers gated, wrap across s = 0, repeats carry no update, jit/vmap/grad, and the
filter end to end: states, settings, configs and the NumPy runner's parity."""

import dataclasses
import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import assert_jvp_matches_fd, track_drive

from fpe_jax import Drive, Params, Settings, Track, presets
from fpe_jax.errors import InputError
from fpe_jax.io.config import config_to_params, params_to_config, read_config
from fpe_jax.model._estimate import track_frame_lines
from fpe_jax.model._kalman import kalman_window
from fpe_jax.model._params import FILTER_DEFAULTS, constrain, unconstrain
from fpe_jax.predict._predict import predict_drive, states_from_drive

NOISE = tuple(jnp.asarray(FILTER_DEFAULTS[k]) for k in FILTER_DEFAULTS)
# a filter whose one-second window outweighs its prior (the defaults lean on the prior more):
# for what the observations alone must give
RESPONSIVE = tuple(jnp.asarray(v) for v in (3.0, 1.0, 0.15, 4.0))
W = 10
kalman = eqx.filter_jit(kalman_window)


def window(t_s, s_m, d_m, valid=None):
    """Arrays for `kalman_window` from stamps (oldest first), with the Theil-Sen prior."""
    t = jnp.asarray(t_s, dtype=float)
    s, d = jnp.asarray(s_m, dtype=float), jnp.asarray(d_m, dtype=float)
    valid = jnp.ones(t.shape, bool) if valid is None else jnp.asarray(valid)
    s_ts, sdot, d_ts, ddot, age = track_frame_lines(t, s, d, valid)
    return t[-1] - t, s, d, valid, jnp.stack([s_ts, sdot, d_ts, ddot, age])


def irregular_stamps(n=W, seed=0, gap_after=None, gap_s=0.0):
    dt = np.random.default_rng(seed).uniform(0.05, 0.13, n - 1)
    if gap_after is not None:
        dt[gap_after] += gap_s
    return np.concatenate([[0.0], np.cumsum(dt)])


# ---- clean motion, irregular stamps, gaps ------------------------------------------------------


@pytest.mark.parametrize("gap_s", [0.0, 0.4])
def test_constant_motion_is_recovered_exactly_over_irregular_stamps_and_gaps(gap_s):
    t = irregular_stamps(gap_after=4, gap_s=gap_s)
    t = t[t <= 1.0]  # the window spans at most 1 s
    s, d = 12.0 + 4.5 * t, 0.2 - 0.3 * t
    # a window shorter than W fills its oldest slots with invalid junk, as the estimator's
    # windows do (and every case then runs the one compiled W-slot filter)
    pad = W - len(t)
    valid = np.arange(W) >= pad
    t, s, d = (np.concatenate([np.full(pad, x[0]), x]) for x in (t, s, d))
    s[:pad], d[:pad] = -50.0, 9.0
    mean, cov, _ = kalman(*window(t, s, d, valid), *NOISE)
    np.testing.assert_allclose(np.asarray(mean), [s[-1], 4.5, d[-1], -0.3], atol=1e-9)
    c = np.asarray(cov)
    assert np.all(np.linalg.eigvalsh(c) > 0) and np.allclose(c, c.T)
    assert c[0, 2] == 0.0  # along and across are independent


@pytest.mark.parametrize("accel_mps2", [-3.0, 2.0])
def test_the_speed_age_is_when_an_accelerating_car_had_the_filtered_speed(accel_mps2):
    t = irregular_stamps(seed=4)
    t = t[t <= 1.0]
    s = 1.0 + 6.0 * t + 0.5 * accel_mps2 * t * t
    mean, _, age = kalman(*window(t, s, np.zeros(len(t))), *RESPONSIVE)
    speed_then = 6.0 + accel_mps2 * (t[-1] - float(age))
    assert 0.0 < float(age) < 0.6 * t[-1]
    # exact but for the prior's (medians, not a linear filter): measured 3e-3 m/s
    np.testing.assert_allclose(float(mean[1]), speed_then, atol=0.01)


def test_the_filter_corrects_a_wrong_prior_speed():
    """Started 1 m/s off (a prior from a window whose motion changed), the observations win."""
    t = np.arange(W) * 0.1
    s, d = 3.0 + 5.0 * t, np.zeros(W)
    age, s_m, d_m, valid, prior = window(t, s, d)
    off = prior.at[1].add(-1.0).at[0].add(-0.1)
    mean, _, _ = kalman(age, s_m, d_m, valid, off, *RESPONSIVE)
    assert abs(float(mean[1]) - 5.0) < 0.3 and abs(float(mean[0]) - s[-1]) < 0.05


def test_invalid_slots_are_skipped():
    t = np.arange(W) * 0.1
    s, d = 3.0 + 5.0 * t, 0.1 + 0.0 * t
    valid = np.arange(W) >= 4
    junk_s, junk_d = s.copy(), d.copy()
    junk_s[:4], junk_d[:4] = -50.0, 9.0  # what an invalid slot holds must not matter
    a = kalman(*window(t, s, d, valid), *NOISE)
    b = kalman(*window(t, junk_s, junk_d, valid), *NOISE)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    np.testing.assert_allclose(np.asarray(a[0])[:3], [s[-1], 5.0, 0.1], atol=1e-9)


# ---- outliers, wrap ------------------------------------------------------------------------------


# observations 3 cm apart from the truth, and a filter that knows it (noise 5 cm): a jump of
# 0.5 m is then 7 sigma of the innovation (a filter told 0.15 m, the simulator's noise, gates
# it only partly: 0.5 m is 3 sigma of such observations)
CLEAN = (*NOISE[:2], jnp.asarray(0.05), NOISE[3])


@pytest.mark.parametrize("jump_m", [0.5, 1.0, 2.0])
@pytest.mark.parametrize("direction", [(1.0, 0.0), (0.0, 1.0), (-0.6, -0.8)])
def test_a_jump_in_the_newest_observation_does_not_move_the_state(jump_m, direction):
    rng = np.random.default_rng(int(jump_m * 10))
    t = np.arange(W) * 0.09
    s = 20.0 + 6.0 * t + rng.normal(0.0, 0.03, W)
    d = -0.4 + 0.2 * t + rng.normal(0.0, 0.03, W)
    age, s_m, d_m, valid, prior = window(t, s, d)
    # the same window without its newest observation, carried to the newest stamp
    without, _, _ = kalman(age, s_m, d_m, valid.at[-1].set(False), prior, *CLEAN)
    jumped_s = s_m.at[-1].add(jump_m * direction[0])
    jumped_d = d_m.at[-1].add(jump_m * direction[1])
    mean, _, _ = kalman(age, jumped_s, jumped_d, valid, prior, *CLEAN)
    assert np.max(np.abs(np.asarray(mean - without))) < 1e-3
    # and an observation that fits is taken
    taken, _, _ = kalman(age, s_m, d_m, valid, prior, *CLEAN)
    assert np.max(np.abs(np.asarray(taken - without))) > 1e-3


def test_a_jump_end_to_end_moves_the_start_less_than_three_centimetres():
    """Through the whole estimator: the projection, the Theil-Sen prior (its medians see the
    jump too) and the filter, on a drive along the oval's centerline with 3 cm noise (measured:
    2.7 cm at 0.5 m)."""
    wp, _ = track_drive("oval")
    track = Track.from_waypoints(wp)
    p = dataclasses.replace(presets["frenet"], filter_obs_m=jnp.asarray(0.05))
    t = np.arange(40) * 0.1
    xy = np.stack([np.asarray(track.point_at(s)) for s in 2.0 + 4.0 * t])
    xy += np.random.default_rng(0).normal(0.0, 0.03, xy.shape)
    clean = Drive(t_s=t, xy_m=xy, yaw_rad=np.full(len(t), np.nan))
    base = states_from_drive(p, clean, track)
    for jump in (0.5, 1.0, 2.0):
        jumped_xy = xy.copy()
        jumped_xy[-1] += jump * np.array([0.6, 0.8])
        jumped = states_from_drive(p, dataclasses.replace(clean, xy_m=jumped_xy), track)
        for f in ("s_fit_m", "offset_m"):
            assert abs(float(getattr(jumped, f)[-1] - getattr(base, f)[-1])) < 0.03, (jump, f)


def test_innovations_wrap_across_the_seam_of_a_loop():
    length = 37.5
    t = np.arange(W) * 0.1
    s = length - 1.5 + 3.0 * t  # crosses s = L at t = 0.5
    d = np.full(W, 0.3)
    continuous = kalman(*window(t, s, d), *NOISE, length_m=length)
    age, s_m, d_m, valid, prior = window(t, s, d)
    wrapped = kalman(age, s_m % length, d_m, valid, prior, *NOISE, length_m=length)
    np.testing.assert_allclose(np.asarray(wrapped[0])[1:], np.asarray(continuous[0])[1:])
    ds = float(wrapped[0][0] - continuous[0][0])
    assert abs((ds + length / 2) % length - length / 2) < 1e-9
    np.testing.assert_allclose(np.asarray(continuous[0])[:2], [s[-1], 3.0], atol=1e-9)


# ---- repeats -------------------------------------------------------------------------------------


def test_repeated_rows_carry_no_update():
    """A log that repeats the last pose between detections gives, at every detection, the state
    of the same log without the repeats."""
    wp, drive = track_drive("oval")
    track = Track.from_waypoints(wp)
    n = 80
    t, xy = drive.t_s[:n], drive.xy_m[:n]
    # a repeat after every second detection, stamped between the two detections
    rep = np.arange(1, n, 2)
    t_all = np.sort(np.concatenate([t, t[rep] + 0.5 * (t[np.minimum(rep + 1, n - 1)] - t[rep])]))
    t_all = np.unique(t_all)
    src = np.searchsorted(t, t_all, side="right") - 1
    with_reps = Drive(t_s=t_all, xy_m=xy[src], yaw_rad=np.full(len(t_all), np.nan))
    plain = Drive(t_s=t, xy_m=xy, yaw_rad=np.full(n, np.nan))
    p = presets["frenet"]
    a = states_from_drive(p, with_reps, track)
    b = states_from_drive(p, plain, track)
    fresh = np.searchsorted(t_all, t)
    for f in ("s_fit_m", "sdot_mps", "offset_m"):
        np.testing.assert_allclose(getattr(a, f)[fresh], getattr(b, f), atol=1e-9, err_msg=f)


# ---- jit, vmap, grad -----------------------------------------------------------------------------


def test_jit_vmap_and_grad_against_finite_differences():
    jax.config.update("jax_enable_x64", True)
    rng = np.random.default_rng(1)
    t = irregular_stamps(seed=2)
    t = t[t <= 1.0]
    rows = [
        window(t, 5.0 + 4.0 * t + rng.normal(0, 0.05, len(t)), rng.normal(0, 0.05, len(t)))
        for _ in range(3)
    ]
    batch = jax.tree.map(lambda *a: jnp.stack(a), *rows)
    means, covs, _ = jax.jit(jax.vmap(kalman_window, in_axes=(0, 0, 0, 0, 0, *[None] * 4)))(
        *batch, *NOISE
    )
    for i, row in enumerate(rows):
        np.testing.assert_allclose(means[i], kalman_window(*row, *NOISE)[0], rtol=1e-12)
    assert covs.shape == (3, 4, 4)

    # an outlier near the gate, so the gate's weight has a gradient too
    age, s_m, d_m, valid, prior = rows[0]
    s_m = s_m.at[-3].add(0.55)

    def f(noise):
        mean, cov, speed_age = kalman_window(age, s_m, d_m, valid, prior, *noise)
        return jnp.sum(mean * jnp.array([1.0, 0.3, 2.0, 0.5])) + jnp.trace(cov) + speed_age

    # f, its gradient and its JVP each as one compiled program: op by op, the filter's scan
    # and gate would be dispatched (and compiled) primitive by primitive
    x = tuple(jnp.asarray(v) for v in (3.0, 1.0, 0.15, 4.0))
    g = jax.jit(jax.grad(f))(x)
    assert all(np.isfinite(float(v)) for v in g)
    assert abs(float(g[3])) > 1e-6  # the gate matters for this window
    tangent = tuple(jnp.asarray(v) for v in (0.3, -0.2, 0.01, 0.5))
    assert_jvp_matches_fd(jax.jit(f), x, tangent, 1e-6, rtol=1e-5, atol=1e-8)


def test_prediction_is_differentiable_in_the_filter_values():
    jax.config.update("jax_enable_x64", True)
    wp, drive = track_drive("oval")
    track = Track.from_waypoints(wp)
    p = presets["frenet"]
    states = states_from_drive(p, drive, track, keep_window=True)
    rows = jax.tree.map(lambda a: jnp.asarray(a[60:90]), states)
    from fpe_jax.predict._predict import predict

    raw = unconstrain(p)

    def loss(raw_obs):
        q = constrain(dataclasses.replace(raw, filter_obs_m=raw_obs))
        pred = jax.vmap(predict, in_axes=(None, 0, None))(q, rows, track)
        return jnp.sum(pred[..., :2] ** 2)

    g = jax.jit(jax.grad(loss))(raw.filter_obs_m)  # one program, not one per primitive
    assert np.isfinite(float(g)) and abs(float(g)) > 0.0


# ---- settings, configs -------------------------------------------------------------------------


def test_estimator_setting_is_validated():
    with pytest.raises(ValueError, match="settings.estimator"):
        Settings(estimator="median")
    assert Settings().estimator == "theil-sen"
    assert presets["frenet"].settings.estimator == "kalman"
    assert presets["seed"].settings.estimator == "theil-sen"


def test_a_schema_1_kalman_config_keeps_starting_from_the_filters_position(tmp_path):
    """Schema 1 ignored position_smoothing with the Kalman estimator (the rollout started at the
    filter's estimate); reading such a config sets it to 1, so it predicts as it did. A schema 2
    config keeps its value."""
    p = dataclasses.replace(presets["frenet"], position_smoothing=jnp.asarray(0.0))
    cfg = params_to_config(p)
    assert cfg["schema_version"] == 2
    path = tmp_path / "c.json"
    path.write_text(json.dumps(cfg))
    assert config_to_params(read_config(path)).physical()["position_smoothing"] == 0.0
    path.write_text(json.dumps(cfg | {"schema_version": 1}))
    old = config_to_params(read_config(path))
    assert old.physical()["position_smoothing"] == 1.0
    assert old.physical() == presets["frenet"].physical()


def test_config_round_trip_and_old_configs_without_the_keys(tmp_path):
    p = dataclasses.replace(
        presets["frenet"],
        filter_accel_mps2=jnp.asarray(2.5),
        filter_obs_m=jnp.asarray(0.08),
        filter_gate_sigma=jnp.asarray(5.0),
    )
    cfg = params_to_config(p)
    path = tmp_path / "c.json"
    path.write_text(json.dumps(cfg))
    back = config_to_params(read_config(path))
    assert back.settings == p.settings and back.physical() == p.physical()
    # a config written before the filter: Theil-Sen and the default noise values
    old = json.loads(json.dumps(cfg))
    del old["settings"]["estimator"]
    for k in FILTER_DEFAULTS:
        del old["params"][k]
    path.write_text(json.dumps(old))
    q = config_to_params(read_config(path))
    assert q.settings.estimator == "theil-sen"
    assert {k: q.physical()[k] for k in FILTER_DEFAULTS} == FILTER_DEFAULTS
    bad = json.loads(json.dumps(cfg))
    bad["settings"]["estimator"] = "ukf"
    path.write_text(json.dumps(bad))
    with pytest.raises(InputError, match="settings.estimator"):
        read_config(path)
    bad = json.loads(json.dumps(cfg))
    bad["params"]["filter_obs_m"] = 0.0
    path.write_text(json.dumps(bad))
    with pytest.raises(InputError, match="params.filter_obs_m"):
        read_config(path)


# ---- the NumPy runner ------------------------------------------------------------------------


def kalman_line(wp, drive) -> Params:
    from fpe_jax.model._line import learn_line

    profile = learn_line([drive], Track.from_waypoints(wp))
    return Params.create(
        Settings(model="line", estimator="kalman"),
        delay_s=0.1,
        offset_tau_s=0.8,
        speed_tau_s=0.3,
        filter_accel_mps2=2.0,
        filter_obs_m=0.1,
        filter_gate_sigma=3.5,
        **profile,
    )


def test_runner_parity_with_outliers_and_gaps():
    from helpers import assert_parity, run_drive

    from fpe_jax.geometry._path import waypoints_sha256
    from fpe_jax.runner._runner import Runner

    wp, drive = track_drive("oval")
    rng = np.random.default_rng(7)
    keep = np.ones(len(drive.t_s), bool)
    keep[60:66] = False  # a 0.5 s dropout
    keep[150:153] = False
    xy = drive.xy_m.copy()
    jumps = rng.choice(np.flatnonzero(keep), 12, replace=False)
    xy[jumps] += rng.uniform(0.5, 2.0, (12, 1)) * rng.normal(size=(12, 2))
    d = Drive(t_s=drive.t_s[keep], xy_m=xy[keep], yaw_rad=drive.yaw_rad[keep])
    p = kalman_line(wp, d)
    _, pred_jax = predict_drive(p, d, Track.from_waypoints(wp))
    cfg = params_to_config(p, line={"waypoints_sha256": waypoints_sha256(wp)})
    assert_parity(run_drive(Runner(cfg, wp), d), pred_jax)


def test_exports_carry_the_filter(tmp_path):
    """ROS 2 YAML holds the estimator and the noise values; the StableHLO artifact runs the
    filter on the window inputs (and, without them, takes the track-frame inputs as given)."""
    import yaml

    from fpe_jax.geometry._path import waypoints_sha256
    from fpe_jax.io.export import INPUTS, WINDOW_INPUTS, export_stablehlo, load, to_ros2_yaml
    from fpe_jax.predict._predict import predict_batch

    wp, drive = track_drive("oval")
    track = Track.from_waypoints(wp)
    p = kalman_line(wp, drive)
    cfg = params_to_config(p, line={"waypoints_sha256": waypoints_sha256(wp)})
    ros = yaml.safe_load(to_ros2_yaml(cfg))["future_pose_estimator"]["ros__parameters"]
    assert ros["estimator"] == "kalman"
    for k in FILTER_DEFAULTS:
        assert ros[k] == cfg["params"][k]
    out, _ = export_stablehlo(cfg, wp, tmp_path / "p.stablehlo", platforms=("cpu",))
    f = load(out)
    assert [i["name"] for i in f.meta["inputs"]] == [n for n, _ in INPUTS + WINDOW_INPUTS]
    states = states_from_drive(p, drive, track, keep_window=True)
    states = jax.tree.map(lambda a: a[::5], states)
    # the filter inside the artifact, under its own noise values: the window decides
    moved = dataclasses.replace(states, s_fit_m=states.s_fit_m + 5.0)
    got = f(**{n: np.asarray(getattr(moved, n)) for n, _ in INPUTS + WINDOW_INPUTS})
    want = np.asarray(predict_batch(p, states, track))
    assert np.max(np.abs(got - want)) <= 1e-6
    given = f(**{n: np.asarray(getattr(states, n)) for n, _ in INPUTS})
    assert np.max(np.abs(given - want)) <= 1e-6
