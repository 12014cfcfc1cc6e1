"""State estimation from the observation history: exact on clean data, robust to repeated rows and
single outliers, wrap-free at +-pi, jit/vmap/grad."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import fd_gradient

from fpe_jax import Drive
from fpe_jax.geometry._path import wrap_angle
from fpe_jax.model._estimate import estimate_state
from fpe_jax.model._history import distinct_mask, history_windows

W = 6
DT = 0.1
# one compile for every window of width W (estimate_state is pure and shape-polymorphic in W)
estimate = eqx.filter_jit(estimate_state)


def window(xy, yaw=None, t0=2.0, t_now=None, valid=None):
    """A right-aligned window from (W, 2) positions at 10 Hz."""
    xy = np.asarray(xy, dtype=float)
    n = len(xy)
    t = t0 + DT * np.arange(n)
    yaw = np.full(n, np.nan) if yaw is None else np.asarray(yaw, dtype=float)
    valid = np.ones(n, dtype=bool) if valid is None else np.asarray(valid)
    t_now = t[-1] if t_now is None else t_now
    return (
        jnp.asarray(t),
        jnp.asarray(xy),
        jnp.asarray(yaw),
        jnp.asarray(valid),
        jnp.asarray(t_now),
    )


def straight_xy(v=3.0, course=0.6, n=W, x0=(1.0, -2.0)):
    s = v * DT * np.arange(n)
    return np.column_stack([x0[0] + s * np.cos(course), x0[1] + s * np.sin(course)])


# ---- clean data --------------------------------------------------------------------------------


@pytest.mark.parametrize("course", [0.6, -2.4, np.pi - 1e-3])
def test_constant_velocity_is_recovered_exactly(course):
    xy = straight_xy(3.0, course)
    st = estimate(*window(xy, t_now=2.0 + DT * (W - 1) + 0.03))
    assert float(st.v_mps) == pytest.approx(3.0, abs=1e-9)
    assert float(wrap_angle(st.course_rad - course)) == pytest.approx(0.0, abs=1e-9)
    assert float(wrap_angle(st.yaw_rad - course)) == pytest.approx(0.0, abs=1e-9)  # no yaw: course
    assert float(st.yaw_rate_rps) == pytest.approx(0.0, abs=1e-9)
    np.testing.assert_allclose([float(st.x_m), float(st.y_m)], xy[-1], atol=1e-12)
    assert st.s_m is None


def test_observed_yaw_is_used_when_present():
    """The body yaw differs from the course (a drifting car): observations win; its rate too."""
    xy = straight_xy(2.0, 0.3)
    yaw = 0.5 + 0.4 * DT * np.arange(W)  # turning at 0.4 rad/s while sliding along 0.3
    st = estimate(*window(xy, yaw))
    assert float(st.yaw_rad) == pytest.approx(yaw[-1], abs=1e-9)
    assert float(st.yaw_rate_rps) == pytest.approx(0.4, abs=1e-9)
    assert float(st.course_rad) == pytest.approx(0.3, abs=1e-9)
    # with the orientation missing (NaN) the direction of motion stands in
    st = estimate(*window(xy, np.full(W, np.nan)))
    assert float(st.yaw_rad) == pytest.approx(0.3, abs=1e-9)


def test_yaw_rate_from_the_course_on_a_circle():
    """Without orientation the yaw rate is the turn rate of the segment courses."""
    w, r = 0.8, 4.0
    a = w * DT * np.arange(W)
    xy = np.column_stack([r * np.sin(a), r - r * np.cos(a)])
    st = estimate(*window(xy))
    assert float(st.yaw_rate_rps) == pytest.approx(w, abs=1e-9)
    assert float(st.v_mps) == pytest.approx(r * w, rel=0.01)


# ---- +-pi --------------------------------------------------------------------------------------


def test_yaw_across_pi_has_no_wrap_jump():
    """Heading west and turning left at 0.1 rad/s, the observed yaw crosses pi -> -pi."""
    yaw = wrap_angle(np.pi - 0.025 + 0.1 * DT * np.arange(W))
    assert np.any(yaw > 3.1) and np.any(yaw < -3.1)
    xy = straight_xy(2.0, np.pi)
    st = estimate(*window(xy, yaw))
    assert float(wrap_angle(st.yaw_rad - yaw[-1])) == pytest.approx(0.0, abs=1e-9)
    assert abs(float(st.yaw_rad)) > 3.1
    assert float(st.yaw_rate_rps) == pytest.approx(0.1, abs=1e-9)  # not ~2 pi / dt
    # the same from the direction of motion: a westward arc through the cut
    w, r = 0.5, 5.0
    a = np.pi - 0.1 + w * DT * np.arange(W)
    xy = np.column_stack([r * np.sin(a), -r * np.cos(a)])  # course = a
    st = estimate(*window(xy))
    assert abs(float(st.yaw_rate_rps) - w) < 1e-6
    assert abs(float(wrap_angle(st.yaw_rad - np.pi))) < 0.2


# ---- repeated rows, outliers -------------------------------------------------------------------


def test_repeated_rows_are_ignored():
    """A log at 10 Hz repeats the last pose when no new detection came: the windows hold only
    distinct observations, the speed is not faked down, and a repeated row gets the state of the
    detection it repeats (predicted from as if fresh: the design's choice, see estimate.py)."""
    n = 14
    truth = straight_xy(2.0, 0.2, n=n)
    keep = np.array([0, 0, 2, 3, 3, 3, 6, 7, 8, 8, 10, 11, 11, 11])  # index of the row shown
    drive = Drive(t_s=DT * np.arange(n), xy_m=truth[keep], yaw_rad=np.full(n, np.nan))
    np.testing.assert_array_equal(distinct_mask(drive.xy_m), np.r_[True, keep[1:] != keep[:-1]])
    win = history_windows(drive, W)
    assert win["t_s"].shape == (n, W) and win["xy_m"].shape == (n, W, 2)
    # row 13 repeats row 11 (twice): its window ends at row 11, with distinct rows only
    np.testing.assert_allclose(win["t_s"][13], DT * np.array([3, 6, 7, 8, 10, 11]), atol=1e-12)
    assert np.all(win["valid"][13])
    assert not np.any(np.all(np.diff(win["xy_m"][13], axis=0) == 0, axis=1))
    # the start of the drive has fewer observations: invalid slots on the left
    np.testing.assert_array_equal(win["valid"][0], [False] * (W - 1) + [True])
    np.testing.assert_array_equal(win["valid"][3], [False] * (W - 3) + [True] * 3)

    keys = ("t_s", "xy_m", "yaw_rad", "valid", "t_now_s")
    rows = [estimate(*(jnp.asarray(win[k][i]) for k in keys)) for i in range(n)]
    states = jax.tree.map(lambda *a: jnp.stack(a), *rows)
    # the stamp of the newest distinct observation grows by dt per repeat behind the row's own
    np.testing.assert_allclose(win["t_now_s"] - win["t_s"][:, -1], DT * (np.arange(n) - keep))
    for name in ("x_m", "y_m", "v_mps", "yaw_rad", "yaw_rate_rps", "course_rad"):
        a = np.asarray(getattr(states, name))
        np.testing.assert_array_equal(a, a[keep], err_msg=name)
    np.testing.assert_allclose(np.asarray(states.v_mps)[2:], 2.0, atol=1e-9)
    np.testing.assert_allclose(np.asarray(states.course_rad)[2:], 0.2, atol=1e-9)
    np.testing.assert_allclose(np.asarray(states.x_m), truth[keep, 0], atol=1e-12)
    # a single observation: no motion known, but finite
    assert float(states.v_mps[0]) == 0.0 and np.isfinite(float(states.yaw_rad[0]))


def test_old_observations_leave_the_window():
    t = np.array([0.0, 0.1, 0.2, 1.25, 1.35])  # a 1 s gap: the first three describe the past
    xy = np.column_stack([t * 2.0, np.zeros(5)])
    drive = Drive(t_s=t, xy_m=xy, yaw_rad=np.full(5, np.nan))
    win = history_windows(drive, 4)
    np.testing.assert_array_equal(win["valid"][4], [False, False, True, True])


@pytest.mark.parametrize("where", [W - 1, W - 3])
def test_a_single_two_metre_outlier(where):
    rng = np.random.default_rng(where)
    course = 1.1
    truth = straight_xy(3.0, course)
    xy = truth + rng.normal(0.0, 0.01, truth.shape)
    jump = 2.0 * np.array([np.cos(course + 1.4), np.sin(course + 1.4)])
    xy[where] += jump
    st = estimate(*window(xy))
    assert abs(float(st.v_mps) - 3.0) < 0.3  # within 10 %
    assert abs(float(wrap_angle(st.course_rad - course))) < 0.1
    p = np.array([float(st.x_m), float(st.y_m)])
    if where == W - 1:  # the newest is the outlier: replaced by the robust line's position
        assert np.linalg.norm(p - truth[-1]) < 0.1
    else:  # an older outlier leaves the newest observation as it is
        np.testing.assert_array_equal(p, xy[-1])


# ---- jit / vmap / grad -------------------------------------------------------------------------


def test_estimate_state_under_jit_vmap_grad():
    rng = np.random.default_rng(3)
    wins = [
        window(straight_xy(1.0 + k, 0.5 * k) + rng.normal(0, 0.02, (W, 2)), t0=k) for k in range(3)
    ]
    eager = [estimate_state(*w) for w in wins]
    jitted = [estimate(*w) for w in wins]
    batched = jax.vmap(estimate)(*(jnp.stack(a) for a in zip(*wins)))
    for k in range(3):
        for name in ("x_m", "y_m", "yaw_rad", "v_mps", "yaw_rate_rps", "course_rad"):
            e = float(getattr(eager[k], name))
            assert float(getattr(jitted[k], name)) == pytest.approx(e, abs=1e-12), name
            assert float(getattr(batched, name)[k]) == pytest.approx(e, abs=1e-12), name
    # differentiable in the observed positions: the gradient of (speed, yaw) equals central
    # differences (Theil-Sen medians are piecewise linear; noisy data has no ties)
    t, xy, yaw, valid, t_now = wins[2]
    f = lambda q: estimate(t, q, yaw, valid, t_now).v_mps
    g = np.asarray(jax.jit(jax.grad(lambda q: estimate_state(t, q, yaw, valid, t_now).v_mps))(xy))
    fd = fd_gradient(lambda q: f(jnp.asarray(q)), xy, eps=1e-7)
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-6)
    assert np.abs(g).max() > 1.0


def test_masked_median_is_nanmedian_bitwise():
    """The rank-based median equals jnp.nanmedian of the masked values bit for bit: odd and even
    counts, ties, NaN values (masked out), a single value and an empty mask (0)."""
    from fpe_jax.model._estimate import _masked_median

    rng = np.random.default_rng(5)
    x = rng.normal(size=(400, 45))
    x[:100] = np.round(x[:100], 1)  # ties
    x[100:150, ::7] = np.nan
    mask = rng.random((400, 45)) < rng.random((400, 1))
    mask[150] = False
    mask[151] = np.arange(45) == 3
    x, mask = jnp.asarray(x), jnp.asarray(mask)

    def reference(v, m):
        ok = m & ~jnp.isnan(v)
        return jnp.where(jnp.any(ok), jnp.nanmedian(jnp.where(ok, v, jnp.nan)), 0.0)

    got = jax.jit(jax.vmap(_masked_median))(x, mask)
    want = jax.jit(jax.vmap(reference))(x, mask)
    np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
    assert float(got[150]) == 0.0 and float(got[151]) == float(x[151, 3])
