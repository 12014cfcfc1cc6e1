"""Track: loop detection, resampling, arc-length geometry, projections (global, windowed, local).

Synthetic tracks are small (a few hundred points) so each compiled shape is cheap; the real ones
(Levine, the F1TENTH centerlines) come from ../shared/data and skip when it is absent.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fpe_jax import Track
from fpe_jax.geometry._path import wrap_angle
from fpe_jax.geometry._track import arclength_along

F1TENTH = ("Austin", "Catalunya", "Monza", "Silverstone", "Spielberg")


def stadium_xy(straight_m=10.0, radius_m=3.0, step_m=0.05):
    """Counter-clockwise stadium: bottom straight heading east, top straight heading west."""
    n_s = int(round(straight_m / step_m))
    n_a = int(round(np.pi * radius_m / step_m))
    bottom = np.column_stack([np.arange(n_s) * step_m, np.zeros(n_s)])
    a = -0.5 * np.pi + np.pi * np.arange(n_a) / n_a
    right = np.column_stack([straight_m + radius_m * np.cos(a), radius_m + radius_m * np.sin(a)])
    top = np.column_stack([straight_m - np.arange(n_s) * step_m, np.full(n_s, 2 * radius_m)])
    left = np.column_stack([-radius_m * np.cos(a), radius_m - radius_m * np.sin(a)])
    return np.vstack([bottom, right, top, left])


def hairpin_xy(leg_m=10.0, radius_m=0.6, step_m=0.05):
    """Open U-turn: east along y = 0, a half circle, back west along y = 2 * radius."""
    n_s = int(round(leg_m / step_m))
    n_a = int(round(np.pi * radius_m / step_m))
    out = np.column_stack([np.arange(n_s) * step_m, np.zeros(n_s)])
    a = -0.5 * np.pi + np.pi * np.arange(n_a) / n_a
    turn = np.column_stack([leg_m + radius_m * np.cos(a), radius_m + radius_m * np.sin(a)])
    back = np.column_stack([leg_m - np.arange(n_s + 1) * step_m, np.full(n_s + 1, 2 * radius_m)])
    return np.vstack([out, turn, back])


@pytest.fixture(scope="module")
def stadium():
    return Track.from_waypoints(stadium_xy())


@pytest.fixture(scope="module")
def straight():
    x = np.linspace(0.0, 20.0, 41)
    return Track.from_waypoints(np.column_stack([x, np.zeros_like(x)]))


@pytest.fixture(scope="module")
def levine(shared_data):
    wps = np.loadtxt(shared_data / "levine" / "levine-waypoints.csv", delimiter=",")[:, :2]
    return Track.from_waypoints(wps)


# jitted batch queries: one compile per (track shape, batch shape) instead of op-by-op dispatch
points_at = jax.jit(lambda t, s: jax.vmap(t.point_at)(s))
headings_at = jax.jit(lambda t, s: jax.vmap(t.heading_at)(s))
projects = jax.jit(lambda t, p: jax.vmap(t.project)(p))
projects_local = jax.jit(lambda t, p, s: jax.vmap(t.project_local)(p, s))


def chords(track):
    xy = np.asarray(track.xy_m)
    ring = np.vstack([xy, xy[:1]]) if track.closed else xy
    return np.hypot(*np.diff(ring, axis=0).T)


# ---- loop detection ----------------------------------------------------------------------------


def test_levine_is_closed(levine):
    assert levine.closed
    assert 55.0 < float(levine.length_m) < 85.0


@pytest.mark.parametrize("name", F1TENTH)
def test_f1tenth_centerlines_are_closed(shared_data, name):
    path = shared_data / "tracks" / f"{name}_centerline.csv"
    xy = np.loadtxt(path, delimiter=",", comments="#")[:, :2]
    track = Track.from_waypoints(xy)
    assert track.closed
    assert 300.0 < float(track.length_m) < 500.0


def test_synthetic_loop_closed_and_open_paths_open(stadium, straight):
    assert stadium.closed
    np.testing.assert_allclose(float(stadium.length_m), 20.0 + 6.0 * np.pi, rtol=5e-3)
    assert not straight.closed
    ell = np.vstack(
        [
            np.column_stack([np.linspace(0, 10, 21), np.zeros(21)]),
            np.column_stack([np.full(20, 10.0), np.linspace(0.5, 10, 20)]),
        ]
    )
    assert not Track.from_waypoints(ell).closed
    # forcing works both ways
    assert not Track.from_waypoints(stadium_xy(), closed=False).closed


def test_bad_waypoints_raise():
    with pytest.raises(ValueError, match="NaN"):
        Track.from_waypoints(np.array([[0.0, 0.0], [1.0, np.nan], [2.0, 0.0]]))
    with pytest.raises(ValueError, match="distinct"):
        Track.from_waypoints(np.zeros((10, 2)))
    with pytest.raises(ValueError, match="shape"):
        Track.from_waypoints(np.zeros((10, 3)))


# ---- resampling --------------------------------------------------------------------------------


def test_spacing_exact_on_a_straight(straight):
    """On a straight line resampling cuts no corner: every chord equals ds_m."""
    np.testing.assert_allclose(chords(straight), float(straight.ds_m), rtol=1e-9)
    np.testing.assert_allclose(float(straight.length_m), 20.0, rtol=1e-12)
    assert straight.ds_m == pytest.approx(0.1, rel=1e-12)
    np.testing.assert_array_equal(np.asarray(straight.xy_m[:, 1]), 0.0)


@pytest.mark.parametrize("name", ["stadium", "levine"])
def test_spacing_uniform_on_curves(request, name):
    """What the code guarantees on curves: points are uniform in arc length of the polyline they
    were interpolated on, so a chord across a bend is a little shorter than ds_m (< 0.5 % here);
    the chords add up to length_m exactly and ds_m * (number of segments) == length_m."""
    track = request.getfixturevalue(name)  # levine skips without ../shared/data
    c = chords(track)
    ds = float(track.ds_m)
    assert np.all(np.abs(c / ds - 1.0) < 5e-3), (c.min() / ds, c.max() / ds)
    np.testing.assert_allclose(c.sum(), float(track.length_m), rtol=1e-12)
    np.testing.assert_allclose(ds * len(c), float(track.length_m), rtol=1e-12)
    assert abs(ds - 0.1) < 1e-3


# ---- point_at / heading_at ---------------------------------------------------------------------


def test_point_at_knots_wrap_and_clamp(stadium, straight):
    ds, length = float(stadium.ds_m), float(stadium.length_m)
    k = np.arange(0, stadium.n_points, 7)
    pts = points_at(stadium, jnp.asarray(k * ds))
    np.testing.assert_allclose(np.asarray(pts), np.asarray(stadium.xy_m)[k], atol=1e-9)

    s = jnp.linspace(-3.0, length + 3.0, 97)
    here = points_at(stadium, s)
    for shift in (length, -length, 2 * length):
        there = points_at(stadium, s + shift)
        np.testing.assert_allclose(np.asarray(there), np.asarray(here), atol=1e-9)
    # the closing segment joins the last point to the first
    mid = stadium.point_at(jnp.asarray(length - 0.5 * ds))
    expected = 0.5 * (np.asarray(stadium.xy_m[-1]) + np.asarray(stadium.xy_m[0]))
    np.testing.assert_allclose(np.asarray(mid), expected, atol=1e-9)

    xy = np.asarray(straight.xy_m)
    np.testing.assert_array_equal(np.asarray(straight.point_at(jnp.asarray(-1.0))), xy[0])
    end = straight.point_at(straight.length_m + 1.0)
    np.testing.assert_allclose(np.asarray(end), xy[-1], atol=1e-12)
    np.testing.assert_allclose(np.asarray(straight.point_at(jnp.asarray(7.25))), [7.25, 0.0])


def test_point_at_gradient_is_the_segment_direction(stadium):
    ds = float(stadium.ds_m)
    xy = np.asarray(stadium.xy_m)
    m = stadium.n_points
    k = np.arange(0, m, 11)
    s = jnp.asarray((k + 0.37) * ds)
    jac = jax.jit(jax.vmap(jax.jacfwd(lambda t, s_: t.point_at(s_), 1), (None, 0)))(stadium, s)
    expected = (xy[(k + 1) % m] - xy[k]) / ds
    np.testing.assert_allclose(np.asarray(jac), expected, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(jac), axis=1), 1.0, atol=5e-3)
    # reverse mode agrees, also for the last (closing) segment
    gx = jax.grad(lambda s_: stadium.point_at(s_)[0])(jnp.asarray((m - 0.5) * ds))
    np.testing.assert_allclose(float(gx), (xy[0, 0] - xy[-1, 0]) / ds, rtol=1e-9)


def test_heading_at_follows_the_path_and_has_no_seam_jump(stadium):
    length = float(stadium.length_m)
    # the top straight heads west: headings near +-pi must interpolate to pi, not to 0
    s_top = jnp.linspace(10.0 + 3.0 * np.pi + 1.0, 20.0 + 3.0 * np.pi - 1.0, 200)
    h_top = headings_at(stadium, s_top)
    assert np.max(np.abs(np.asarray(wrap_angle(h_top - np.pi)))) < 1e-6
    # across the seam of the loop (s = 0 = length) the heading changes smoothly
    s = jnp.linspace(length - 1.0, length + 1.0, 401)
    h = np.asarray(headings_at(stadium, s))
    assert np.max(np.abs(wrap_angle(np.diff(h)))) < 0.02
    # and it matches the direction of the path itself
    eps = 1e-4
    for s0 in (0.3, 5.0, 11.7, 25.0, length - 0.05):
        d = np.asarray(stadium.point_at(jnp.asarray(s0 + eps)) - stadium.point_at(jnp.asarray(s0)))
        hd = np.arctan2(d[1], d[0])
        assert abs(wrap_angle(float(stadium.heading_at(jnp.asarray(s0))) - hd)) < 0.03


# ---- projections -------------------------------------------------------------------------------


def test_project_returns_arc_length_of_path_points(stadium, straight):
    length = float(stadium.length_m)
    s = jnp.linspace(0.05, length - 0.05, 151) + 0.0123
    p = points_at(stadium, s)
    got = projects(stadium, p)
    np.testing.assert_allclose(np.asarray(got), np.asarray(s), atol=1e-9)
    # a point beside a straight projects to the foot of its perpendicular
    assert float(straight.project(jnp.array([7.3, 0.4]))) == pytest.approx(7.3, abs=1e-12)
    assert float(straight.project(jnp.array([-2.0, 0.4]))) == 0.0
    assert float(straight.project(jnp.array([25.0, -1.0]))) == pytest.approx(20.0, abs=1e-12)


def test_project_window_never_snaps_to_the_far_side_of_a_hairpin():
    track = Track.from_waypoints(hairpin_xy(), smooth_m=0.0)
    assert not track.closed
    gap = float(track.xy_m[:, 1].max())  # distance between the two legs
    assert 1.0 < gap < 1.3
    p = jnp.array([5.0, 0.62 * gap])  # beside the outbound leg, but nearer the return leg
    far = float(track.project(p))
    assert far > 12.0  # the global projection picks the return leg: the trap is real
    # (arc length is the track's own parametrisation: compare with the foot point's)
    foot = float(track.project(jnp.array([5.0, 0.0])))
    assert foot == pytest.approx(5.0, abs=1e-3)
    near = float(track.project_window(p, jnp.asarray(4.9)))
    assert near == pytest.approx(foot, abs=1e-9)

    # a car driving the outbound leg with that offset stays on it while the return leg's
    # nearer part lies beyond the window (4 m ahead of the hint)
    x = jnp.linspace(0.5, 8.0, 60)
    drive = jnp.column_stack([x, jnp.full(60, 0.62 * gap)])
    s = np.asarray(arclength_along(track, drive.at[0].set(jnp.array([0.5, 0.0]))))
    feet = projects(track, jnp.column_stack([x, jnp.zeros(60)]))
    np.testing.assert_allclose(s, np.asarray(feet), atol=1e-9)

    # a noisy drive around the whole hairpin (noise well under half the gap) never jumps legs
    rng = np.random.default_rng(1)
    k = np.linspace(0, track.n_points - 1, 60).astype(int)  # 60 points: the same compile
    noisy = np.asarray(track.xy_m)[k] + rng.normal(0.0, 0.08, (60, 2))
    s = np.asarray(arclength_along(track, jnp.asarray(noisy)))
    truth = k * float(track.ds_m)
    assert np.abs(s - truth).max() < 0.4


def test_project_window_is_continuous_across_the_seam(stadium):
    length = float(stadium.length_m)
    p = stadium.point_at(jnp.asarray(0.05))
    assert float(stadium.project_window(p, jnp.asarray(length - 0.05))) == pytest.approx(
        length + 0.05, abs=1e-9
    )
    p = stadium.point_at(jnp.asarray(length - 0.05))
    assert float(stadium.project_window(p, jnp.asarray(0.05))) == pytest.approx(-0.05, abs=1e-9)


def test_project_local_converges_near_the_hint(stadium, straight):
    assert float(straight.project_local(jnp.array([7.3, 0.4]), jnp.asarray(6.8))) == pytest.approx(
        7.3, abs=1e-12
    )
    s = jnp.linspace(0.0, float(stadium.length_m), 60, endpoint=False) + 0.041
    p = points_at(stadium, s)
    got = projects_local(stadium, p, s - 0.3)
    np.testing.assert_allclose(np.asarray(got), np.asarray(s), atol=1e-3)


def test_project_local_is_continuous_in_the_hint(stadium):
    """A car well off the path, hints just either side of every point of the curve: the result
    must not depend on which segment the hint falls in (4 cm apart with chord directions)."""
    ds = float(stadium.ds_m)
    k = np.arange(int(10.0 / ds) + 2, int((10.0 + 3.0 * np.pi) / ds) - 2)  # the right-hand bend
    p = points_at(stadium, jnp.asarray(k * ds))
    inward = np.asarray(p) - np.array([10.0, 3.0])
    p = np.asarray(p) - 0.8 * inward / np.linalg.norm(inward, axis=1, keepdims=True)
    below = projects_local(stadium, jnp.asarray(p), jnp.asarray(k * ds - 1e-9))
    above = projects_local(stadium, jnp.asarray(p), jnp.asarray(k * ds + 1e-9))
    np.testing.assert_allclose(np.asarray(below), np.asarray(above), rtol=0, atol=1e-7)


def test_arclength_along_levine_is_monotone_across_the_seam(levine):
    xy = np.asarray(levine.xy_m)
    m, ds, length = levine.n_points, float(levine.ds_m), float(levine.length_m)
    lap = np.roll(xy, -m // 2, axis=0)  # start mid-lap so the seam is crossed inside the drive
    drive = np.vstack([lap, lap[: m // 4]])  # and a bit more than one lap
    s = np.asarray(arclength_along(levine, jnp.asarray(drive)))
    np.testing.assert_allclose(np.diff(s), ds, rtol=1e-6)
    np.testing.assert_allclose(s[-1] - s[0], length + (m // 4 - 1) * ds, rtol=1e-9)

    rng = np.random.default_rng(0)
    noisy = drive + rng.normal(0.0, 0.1, drive.shape)
    sn = np.asarray(arclength_along(levine, jnp.asarray(noisy)))
    # up to the noise: each step is ds +- a few noise sigmas, never a jump
    assert np.all(np.diff(sn) > -0.6) and np.all(np.diff(sn) < 0.8)
    assert np.abs(sn - s).max() < 0.6
    assert np.mean(np.diff(sn) > 0) > 0.6


@jax.jit
def goal_forward(track, p, yaw, hint, lookahead_m):
    """(N,) forward distance [m] in the car frame of the pure-pursuit goal, as a rollout finds it:
    the car's arc length near the hint, plus the lookahead."""

    def one(p, yaw, hint):
        g = track.point_at(track.project_local(p, hint) + lookahead_m) - p
        return jnp.cos(yaw) * g[0] + jnp.sin(yaw) * g[1]

    return jax.vmap(one)(p, yaw, hint)


@pytest.mark.parametrize("lookahead_m", [0.5, 2.0])
def test_goal_is_ahead_everywhere_on_levine(levine, lookahead_m):
    """At every resampled point (seam included), the pure-pursuit goal is in front of the car,
    also for a car 0.2 m to either side of the line; the arc-length hint comes from the windowed
    projection along the lap, as in a rollout."""
    m = levine.n_points
    order = np.roll(np.arange(m), -m // 2)
    xy, heading = levine.xy_m[order], levine.heading_rad[order]
    hints = arclength_along(levine, xy)
    normal = jnp.stack([-jnp.sin(heading), jnp.cos(heading)], axis=1)

    for offset in (0.0, 0.2, -0.2):
        fwd = np.asarray(goal_forward(levine, xy + offset * normal, heading, hints, lookahead_m))
        assert np.all(fwd > 0.2 * lookahead_m), (offset, fwd.min(), order[np.argmin(fwd)])


# ---- jit / vmap / grad of every public function ------------------------------------------------


def test_track_functions_under_jit_vmap_grad(stadium):
    s = jnp.asarray(3.21)
    p = jnp.array([4.0, 0.15])
    cases = {
        "point_at": (lambda t, s_: t.point_at(s_), s),
        "heading_at": (lambda t, s_: t.heading_at(s_), s),
        "project": (lambda t, p_: t.project(p_), p),
        "project_window": (lambda t, p_: t.project_window(p_, jnp.asarray(3.5)), p),
        "project_local": (lambda t, p_: t.project_local(p_, jnp.asarray(3.5)), p),
    }

    def batched_and_grads(t, s_, p_):  # everything in one compiled call (one compile)
        out = {}
        for name, (f, x) in cases.items():
            x = s_ if x is s else p_
            xs = jnp.stack([x, x + 0.05, x + 0.1])
            grad = jax.grad(lambda t_, x_, f=f: jnp.sum(f(t_, x_)), 1)(t, x)
            out[name] = (jax.vmap(f, in_axes=(None, 0))(t, xs), grad)
        return out

    results = jax.jit(batched_and_grads)(stadium, s, p)
    grads = {}
    for name, (f, x) in cases.items():
        eager = np.stack([np.asarray(f(stadium, x + d)) for d in (0.0, 0.05, 0.1)])
        batched, grads[name] = np.asarray(results[name][0]), np.asarray(results[name][1])
        np.testing.assert_allclose(batched, eager, rtol=0, atol=1e-12, err_msg=name)
        assert np.all(np.isfinite(grads[name])), name
    # on the bottom straight (heading east) the projections move with x (1:1 up to the chord /
    # ds_m ratio of the segment) and not with y; the heading does not change along it
    k = int(float(p[0]) / float(stadium.ds_m))
    chord = float(jnp.linalg.norm(stadium.xy_m[k + 1] - stadium.xy_m[k]))
    for name in ("project", "project_window"):
        expected = [float(stadium.ds_m) / chord, 0.0]
        np.testing.assert_allclose(grads[name], expected, atol=1e-9, err_msg=name)
    np.testing.assert_allclose(grads["project_local"], [1.0, 0.0], atol=5e-3)
    np.testing.assert_allclose(grads["heading_at"], 0.0, atol=1e-9)
    np.testing.assert_allclose(grads["point_at"], chord / float(stadium.ds_m), atol=1e-9)

    # arclength_along is jitted itself; vmap it over drives and differentiate it
    drive = jnp.column_stack([jnp.linspace(1.0, 6.0, 20), jnp.full(20, 0.1)])
    drives = jnp.stack([drive, drive + jnp.array([[0.5, -0.2]])])
    s_b = jax.jit(jax.vmap(arclength_along, in_axes=(None, 0)))(stadium, drives)
    for i in range(2):
        np.testing.assert_allclose(
            np.asarray(s_b[i]), np.asarray(arclength_along(stadium, drives[i])), atol=1e-12
        )
    feet = projects(stadium, drive.at[:, 1].set(0.0))
    np.testing.assert_allclose(np.asarray(s_b[0]), np.asarray(feet), atol=1e-9)
    g = np.asarray(jax.jit(jax.grad(lambda d: jnp.sum(arclength_along(stadium, d))))(drive))
    np.testing.assert_allclose(g[:, 0], 1.0, atol=5e-3)
    np.testing.assert_allclose(g[:, 1], 0.0, atol=1e-12)
