"""The learned line's prior where the fit drives never went (`fpe_jax.model`)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fpe_jax.geometry._track import Track
from fpe_jax.model import _line
from fpe_jax.model._line import (
    PRIOR_FOLDS,
    PROFILE_DS_M,
    _shrunk_fit,
    learn_line,
    limit_speed,
    line_from_samples,
    line_samples,
    min_curvature_offset,
)
from fpe_jax.sim._sim import simulate


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


def test_a_covered_track_gets_the_samples_line_without_computing_a_prior(monkeypatch):
    """The prior's weight is 1 - coverage: on a track covered everywhere the line is the
    samples' own, the values that blending in the prior gives, and the prior is not computed."""
    res = simulate("oval", duration_s=60.0, seed=5)
    track = Track.from_waypoints(res.centerline_xy_m)
    samples = [line_samples(res.drive, track)]
    prior = _line._prior

    def refuse(*args):
        raise AssertionError("the prior was computed on a covered track")

    monkeypatch.setattr(_line, "_prior", refuse)
    got = line_from_samples(samples, track)
    c, d, v = got["line_coverage"], got["line_offset_m"], got["line_speed_mps"]
    assert np.all(c == 1.0)
    n = max(int(round(float(track.length_m) / PROFILE_DS_M)), 8)
    prior_d, prior_v = prior(track, d, v, c, float(track.length_m) / n)  # a loop: length / n
    assert np.all(np.isfinite(prior_d)) and np.all(np.isfinite(prior_v))
    np.testing.assert_array_equal(d, c * d + (1.0 - c) * prior_d)
    np.testing.assert_array_equal(v, c * v + (1.0 - c) * prior_v)


def test_samples_outside_a_time_range_are_the_samples_of_the_parts_around_it():
    """The cross-fitted uncertainty projects a drive once and leaves out one fold at a time:
    what remains must be what projecting the parts before and after the fold gives."""
    res = simulate("oval", duration_s=20.0, seed=4)
    drive, track = res.drive, Track.from_waypoints(res.centerline_xy_m)
    whole = line_samples(drive, track)
    length = float(track.length_m)
    for lo, hi in ((-np.inf, 7.0), (7.0, 13.0), (13.0, np.inf)):
        got = whole.outside(lo, hi)
        parts = [drive.slice_time(-np.inf, lo), drive.slice_time(hi, np.inf)]
        want = [line_samples(p, track) for p in parts if len(p.t_s)]
        t, s, d, v = (np.concatenate(a) for a in zip(*want))
        np.testing.assert_array_equal(got.t_s, t)
        ds = np.mod(got.s_m - s + 0.5 * length, length) - 0.5 * length  # a lap apart is equal
        np.testing.assert_allclose(ds, 0.0, atol=1e-9)
        np.testing.assert_allclose(got.d_m, d, atol=1e-9)
        np.testing.assert_array_equal(np.isnan(got.v_mps), np.isnan(v))
        np.testing.assert_allclose(got.v_mps, v, atol=1e-9)  # NaN where a neighbour is left out


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


def test_min_curvature_offset_solves_its_problem():
    """Constant curvature cannot be cancelled by any loop offset: d = 0. Where the bound is not
    reached, d is the unconstrained minimiser (in Fourier space); where it is, d stays within it
    and touches it."""
    n, h = 400, 0.5
    np.testing.assert_allclose(min_curvature_offset(np.full(n, 0.2), h, 1.0), 0.0, atol=1e-12)
    s = np.arange(n) * h
    kappa = 0.01 * np.cos(2 * np.pi * 4 * s / (n * h))
    lam = (2 * np.cos(2 * np.pi * 4 / n) - 2) / h**2
    exact = -lam * kappa / (lam**2 + 1e-4)  # one Fourier mode: kappa's own
    np.testing.assert_allclose(min_curvature_offset(kappa, h, 10.0), exact, atol=1e-6)
    tight = min_curvature_offset(kappa, h, 0.3)
    assert np.abs(tight).max() <= 0.3 + 1e-12 and np.abs(tight).max() == pytest.approx(0.3)


def _silverstone_raceline(shared_data):
    """Silverstone's centerline Track, its profile points' arc lengths `at` (P,) [m] (0.5 m
    apart), and the raceline's (the file's repeated first point dropped) offset from the
    centerline (P,) [m] and speed along the centerline (P,) [m/s] there."""
    from fpe_jax.io import load_waypoints

    tracks = shared_data / "tracks"
    track = Track.from_waypoints(load_waypoints(tracks / "Silverstone_centerline.csv").xy_m)
    rl = load_waypoints(tracks / "Silverstone_raceline.csv")
    step = np.hypot(*np.diff(np.vstack([rl.xy_m, rl.xy_m[:1]]), axis=0).T)
    xy, v = rl.xy_m[step > 1e-6], rl.speed_mps[step > 1e-6]
    length = float(track.length_m)
    n = int(round(length / 0.5))
    at = np.arange(n) * length / n
    s = np.asarray(jax.vmap(track.project)(jnp.asarray(xy)))
    centre = np.asarray(jax.vmap(track.point_at)(jnp.asarray(s)))
    heading = np.asarray(jax.vmap(track.heading_at)(jnp.asarray(s)))
    d = (xy[:, 1] - centre[:, 1]) * np.cos(heading) - (xy[:, 0] - centre[:, 0]) * np.sin(heading)
    # along the centerline: the raceline's speed times centerline metres per raceline metre
    ds = np.mod(np.diff(np.append(s, s[0])), length)
    v_track = v * ds / np.hypot(*np.diff(np.vstack([xy, xy[:1]]), axis=0).T)
    order = np.argsort(s)
    d_at, v_at = (np.interp(at, s[order], a[order], period=length) for a in (d, v_track))
    return track, at, d_at, v_at


def test_prior_carries_a_racing_line_onto_unseen_stretches(shared_data):
    """Silverstone's raceline offsets seen on the first 40 % of the lap: the prior predicts the
    other 60 % within 0.2 m RMS (the centerline-curvature regression: 0.48 m)."""
    from fpe_jax.model._line import _prior

    track, at, truth, _ = _silverstone_raceline(shared_data)
    coverage = (at < 0.4 * float(track.length_m)).astype(float)
    speed = np.where(coverage > 0, 3.0, 0.0)
    prior, _ = _prior(track, truth * coverage, speed, coverage, at[1])
    unseen = coverage == 0
    assert np.sqrt(np.mean((prior - truth)[unseen] ** 2)) < 0.2


def test_limit_speed_is_the_fastest_profile_within_the_limits():
    """One corner on a loop of straights: the speed rises from the corner's grip limit at the
    accelerating rate, v^2 = v_c^2 + 2 a x, falls toward it at the braking rate, and is capped
    at the top speed; a loop of constant curvature is at its grip limit everywhere."""
    n, h, k = 200, 0.5, 50
    kappa = np.zeros(n)
    kappa[k] = 0.5
    ahead = np.mod(np.arange(n) - k, n) * h  # from the corner forward to each point [m]
    behind = np.mod(k - np.arange(n), n) * h  # from each point forward to the corner [m]
    v_c2 = 4.0 / 0.5
    exact = np.sqrt(np.minimum(49.0, np.minimum(v_c2 + 2 * 3.0 * ahead, v_c2 + 2 * 2.0 * behind)))
    np.testing.assert_allclose(limit_speed(kappa, np.full(n, h), 4.0, 3.0, 2.0, 7.0), exact)
    circle = limit_speed(np.full(n, -0.25), np.full(n, h), 4.0, 3.0, 2.0, 7.0)
    np.testing.assert_allclose(circle, 4.0)


def test_speed_prior_follows_a_racing_lines_speed_onto_unseen_stretches(shared_data):
    """Silverstone's raceline speeds (the track file's own, along the centerline) seen on the
    first 40 % of the lap: the prior predicts their change over 4 m on the other 60 % within
    0.07 in log speed RMS (0.059; without the grip-limited profile on the prior line 0.082, a
    constant speed 0.125)."""
    from fpe_jax.model._line import _prior

    track, at, truth_d, truth_v = _silverstone_raceline(shared_data)
    n = len(at)
    coverage = (at < 0.4 * float(track.length_m)).astype(float)
    _, prior = _prior(track, truth_d * coverage, truth_v * coverage, coverage, at[1])
    unseen = coverage == 0
    i = np.flatnonzero(unseen & np.roll(unseen, -8))
    j = (i + 8) % n
    err = np.log(prior[j] / prior[i]) - np.log(truth_v[j] / truth_v[i])
    assert np.sqrt(np.mean(err**2)) < 0.07
