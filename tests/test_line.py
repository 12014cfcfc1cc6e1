"""The learned line's prior where the fit drives never went (`fpe_jax.line`)."""

from __future__ import annotations

import numpy as np
import pytest

from fpe_jax.line import PRIOR_FOLDS, _shrunk_fit, learn_line
from fpe_jax.sim import simulate
from fpe_jax.track import Track


@pytest.fixture(scope="module")
def partial():
    """A drive over part of the hairpin track (less than a lap) and its track."""
    res = simulate("hairpin", duration_s=8.0, seed=3)
    return res.drive, Track.from_waypoints(res.centerline_xy_m)


def test_uncovered_points_get_a_prior_within_the_covered_range(partial):
    drive, track = partial
    line = learn_line([drive], track)
    c, d, v = line["line_coverage"], line["line_offset_m"], line["line_speed_mps"]
    seen, unseen = c >= 0.5, c == 0.0
    assert unseen.any() and seen.any()  # less than a lap: the prior is needed and fitted
    assert np.all(np.isfinite(d)) and np.all(np.isfinite(v))
    assert np.all(v[unseen] >= v[seen].min() - 1e-9) and np.all(v[unseen] <= v[seen].max() + 1e-9)
    assert np.all(np.abs(d[unseen]) <= np.abs(d[seen]).max() + 1e-9)
    assert np.ptp(v[unseen]) > 0.0  # shaped by the track, not a constant


def test_shrinkage_trusts_a_predictive_prior_and_not_noise():
    rng = np.random.default_rng(0)
    n = 400
    x = np.sin(np.arange(n) / 15.0)
    feats = np.column_stack([np.ones(n), x])
    w = np.ones(n)
    w[300:] = 0.0  # uncovered
    exact = _shrunk_fit(feats, 1.0 + 0.5 * x, w, lag=8)
    # predictive held out: kept whole (only the ridge penalty shrinks it), uncovered part too
    assert np.corrcoef(exact, x)[0, 1] > 0.999
    assert 0.7 * np.ptp(0.5 * x) < np.ptp(exact) <= np.ptp(0.5 * x)
    noise = rng.normal(size=n)
    flat = _shrunk_fit(feats, noise, w, lag=8)
    # unrelated to the features: the prior falls back to (nearly) the covered mean
    assert np.ptp(flat) < 0.1 * np.ptp(noise[:300]) and PRIOR_FOLDS >= 2
