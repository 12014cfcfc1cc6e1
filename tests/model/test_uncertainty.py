"""Per-prediction uncertainty: the Kalman filter's covariance carried through the rollout
(`fpe_jax.model.estimate_variance`), the fitted scale and model error on top
(`fpe_jax.evaluate.fit_variance_model`), and what a fit, a config and `fpe predict` make of it."""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import track_drive

from fpe_jax import Drive, Track, presets
from fpe_jax.errors import InputError
from fpe_jax.evaluate import _evaluate as E
from fpe_jax.evaluate._metrics import coverage, fit_variance_model, row_covariance
from fpe_jax.io.config import params_to_config, read_config
from fpe_jax.model._rollout import estimate_variance
from fpe_jax.model._state import State
from fpe_jax.predict._predict import states_from_drive, variance_rows

P_COV = np.array(
    [
        [0.04, 0.02, 0.0, 0.0],
        [0.02, 0.25, 0.0, 0.0],
        [0.0, 0.0, 0.01, 0.003],
        [0.0, 0.0, 0.003, 0.2],
    ]
)


def car(cov=P_COV) -> State:
    z = jnp.zeros(())
    return State(
        x_m=z, y_m=z, yaw_rad=z, v_mps=z, s_fit_m=z, sdot_mps=z, offset_m=z, sdot_age_s=z,
        filter_cov=None if cov is None else jnp.asarray(cov),
    )  # fmt: skip


def frenet(**values):
    p = presets["frenet"]
    return dataclasses.replace(p, **{k: jnp.asarray(v) for k, v in values.items()})


@pytest.mark.parametrize("w", [0.0, 0.3, 1.0])
def test_the_state_variance_is_the_filters_covariance_carried_along(w):
    """Along: var(s0) + 2 t P_sv + t^2 P_vv at t = delay + h dt, var(s0) = u r^2 + (1 - u) P_ss,
    u = (1 - w)^2; across: var(d0) exp(-2 t / tau) (frenet's plain decay)."""
    jax.config.update("jax_enable_x64", True)
    p = frenet(position_smoothing=w, filter_obs_m=0.2, delay_s=0.25, offset_tau_s=0.8)
    got = np.asarray(estimate_variance(p, car()))
    t = 0.25 + 0.1 * np.arange(1, 11)
    u = (1.0 - w) ** 2
    var_s0 = u * 0.04 + (1.0 - u) * 0.04  # r^2 = P_ss = 0.04 here
    want_along = var_s0 + 2.0 * t * 0.02 + t * t * 0.25
    want_cross = (u * 0.04 + (1.0 - u) * 0.01) * np.exp(-2.0 * t / 0.8)
    np.testing.assert_allclose(got[:, 0], want_along, rtol=1e-12)
    np.testing.assert_allclose(got[:, 1], want_cross, rtol=1e-12)


def test_no_filter_no_state_variance_and_jit_vmap_agree():
    jax.config.update("jax_enable_x64", True)
    p = frenet()
    assert np.all(np.asarray(estimate_variance(p, car(None))) == 0.0)
    batch = jax.tree.map(lambda x: jnp.stack([x, 2.0 * x]), car())
    out = jax.jit(jax.vmap(estimate_variance, in_axes=(None, 0)))(p, batch)
    np.testing.assert_allclose(out[0], estimate_variance(p, car()), rtol=1e-12)
    np.testing.assert_allclose(out[1], estimate_variance(p, car(2.0 * P_COV)), rtol=1e-12)
    g = jax.grad(lambda tau: jnp.sum(estimate_variance(frenet(offset_tau_s=tau), car())))(0.8)
    assert np.isfinite(float(g)) and float(g) > 0.0  # a slower decay keeps more of var(d0)


@pytest.mark.parametrize(("c", "q"), [(2.0, 0.05), (0.0, 0.3), (1.5, 1e-8)])
def test_the_fitted_scale_and_model_error_recover_the_true_ones(c, q):
    """Residuals drawn with variance c x + q (x: each one's state variance) give back c and q
    within a few percent (maximum likelihood on 40,000 residuals), on the boundary too."""
    rng = np.random.default_rng(0)
    n, h = 40_000, 2
    x = rng.uniform(0.01, 1.0, (n, h, 2))
    res = rng.normal(size=(n, h, 2)) * np.sqrt(c * x + q)
    terms = fit_variance_model(res, x, np.ones((n, h), bool))
    np.testing.assert_allclose(terms["state_scale"], c, rtol=0.05, atol=0.02)
    np.testing.assert_allclose(terms["model_var_m2"], q, rtol=0.05, atol=0.01)
    assert np.all(np.abs(terms["correlation"]) < 0.03)
    cov = row_covariance(x, **terms)
    cover = coverage(res, np.ones((n, h), bool), cov)
    assert abs(cover["coverage_1sigma"] - cover["ideal_1sigma"]) < 0.01
    assert abs(cover["coverage_2sigma"] - cover["ideal_2sigma"]) < 0.01


def test_the_predictions_after_a_dropout_are_less_certain():
    """A 0.6 s gap in the detections: the first predictions after it carry a larger along-track
    state variance than the same rows of the drive without the gap (the filter's speed has had
    fewer and older observations)."""
    jax.config.update("jax_enable_x64", True)
    wp, drive = track_drive("oval")
    track = Track.from_waypoints(wp)
    keep = (drive.t_s < 4.0) | (drive.t_s >= 4.6)
    gap = Drive(t_s=drive.t_s[keep], xy_m=drive.xy_m[keep], yaw_rad=drive.yaw_rad[keep])
    p = presets["frenet"]
    var_full = variance_rows(p, states_from_drive(p, drive, track), track)
    var_gap = variance_rows(p, states_from_drive(p, gap, track), track)
    after, after_gap = np.flatnonzero(drive.t_s >= 4.6)[0], np.flatnonzero(gap.t_s >= 4.6)[0]
    assert var_gap[after_gap, -1, 0] > 1.2 * var_full[after, -1, 0]


def test_a_fitted_filter_models_uncertainty_carries_its_terms_into_the_config(tmp_path):
    """fit_uncertainty of a Kalman model: cov_m2 is the mean of the per-prediction covariances;
    the terms round-trip through a config; a config with only some of them, or out of range,
    is refused naming the key."""
    jax.config.update("jax_enable_x64", True)
    wp, drive = track_drive("oval")
    track = Track.from_waypoints(wp)
    p = presets["frenet"]
    data = E.make_datasets([drive], [track], p.settings, "training")
    unc = E.fit_uncertainty(p, data)
    assert set(unc) >= {"cov_m2", "state_scale", "model_var_m2", "correlation"}
    per_row = E.prediction_covariance(p, data[0].states(p), track, unc)
    mask = data[0].targets.mask
    mean = np.sum(per_row * mask[..., None, None], 0) / mask.sum(0)[:, None, None]
    np.testing.assert_allclose(unc["cov_m2"], mean, rtol=1e-12)
    assert np.all(np.linalg.eigvalsh(per_row) > 0.0)

    cfg = params_to_config(p, uncertainty=unc)
    path = tmp_path / "c.json"
    path.write_text(json.dumps(cfg))
    assert read_config(path)["uncertainty"] == json.loads(json.dumps(unc))
    for key, value, what in (
        ("model_var_m2", None, "uncertainty has state_scale, correlation only"),
        ("correlation", [1.5] * 10, "uncertainty.correlation is"),
        ("state_scale", [[1.0, -1.0]] * 10, "uncertainty.state_scale is"),
        ("model_var_m2", [[1.0, 1.0]] * 9, "uncertainty.model_var_m2 is"),
    ):
        bad = json.loads(json.dumps(cfg))
        if value is None:
            del bad["uncertainty"][key]
        else:
            bad["uncertainty"][key] = value
        path.write_text(json.dumps(bad))
        with pytest.raises(InputError, match=what):
            read_config(path)


def test_a_datasets_cross_fitted_lines_are_learned_once(monkeypatch):
    """The cross-fitted lines depend on the dataset's drive alone: the long-horizon fit, a
    fit's second thread (while the solver runs) and the uncertainty share one learning of them,
    which gives the same lines as learning them afresh."""
    from fpe_jax.model import _line

    wp, drive = track_drive("oval")
    track = Track.from_waypoints(wp)
    p = presets["default"]
    (d,) = E.make_datasets([drive], [track], p.settings, "training")
    learned, learn = [], _line.line_from_samples
    monkeypatch.setattr(
        _line, "line_from_samples", lambda *a, **k: learned.append(1) or learn(*a, **k)
    )
    fold, lines = E.cross_fold_lines(d)
    assert len(learned) == len(lines) >= 2
    again = E.cross_fold_lines(d)
    assert len(learned) == len(lines) and again[0] is fold and again[1] is lines
    (fresh,) = E.make_datasets([drive], [track], p.settings, "training")
    fresh_fold, fresh_lines = E.cross_fold_lines(fresh)
    np.testing.assert_array_equal(fresh_fold, fold)
    for a, b in zip(fresh_lines, lines, strict=True):
        for k in a:
            np.testing.assert_array_equal(a[k], b[k])
