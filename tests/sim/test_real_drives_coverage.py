"""The helpers of experiments/real_drives/coverage_sources.py (where the real drives' ellipses
miss): the smoothed and the recorded-pose references the calibration is replayed against, on a
clean synthetic circle."""

from __future__ import annotations

import math
import sys
import types
from pathlib import Path

import numpy as np
import pytest

from fpe_jax.drive import local_frame
from fpe_jax.sim._sim import Sensor, observe

HERE = Path(__file__).resolve().parents[2] / "experiments" / "real_drives"
LATENCY_S = 0.3


@pytest.fixture(scope="module")
def cs():
    sys.path.insert(0, str(HERE))
    try:
        import coverage_sources

        yield coverage_sources
    finally:
        sys.path.remove(str(HERE))
        for name in ("coverage_sources", "calibration", "diagnose"):
            sys.modules.pop(name, None)


def clean_circle(ccw: bool):
    """A 6 s constant-speed circle seen by a clean detector: (poses, drive, case-like with
    the exact circle's waypoints and the drive as its test part)."""
    rate, radius, v = 60.0, 1.2, 1.5
    t = np.arange(int(6.0 * rate)) / rate
    sign = 1.0 if ccw else -1.0
    ang = sign * v / radius * t
    xy = np.stack([0.5 + radius * np.cos(ang), -2.0 + radius * np.sin(ang)], axis=1)
    yaw = ang + sign * np.pi / 2
    wa = np.linspace(0.0, 2 * np.pi, 400, endpoint=False) * sign
    waypoints = np.stack([0.5 + radius * np.cos(wa), -2.0 + radius * np.sin(wa)], axis=1)
    drive = observe(t, xy, yaw, waypoints, latency_s=LATENCY_S, seed=2, sensor=Sensor.clean())
    poses = dict(t_s=t, xy_m=xy, yaw_rad=yaw)
    case = types.SimpleNamespace(waypoints_xy_m=waypoints, test_drive=drive)
    return poses, drive, case


def stream(drive, case, xy_local=None) -> dict:
    """A recorded stream as calibration.record_stream gives it: one observation event per
    detection (at the detections' local stamps) and one prediction event between them."""
    local, _, _, _ = local_frame(drive, case.waypoints_xy_m)
    events = []
    for k, t in enumerate(local.t_s.tolist()):
        x, y = (0.0, 0.0) if xy_local is None else xy_local[k]
        events.append((k, "o", t, x, y))
        events.append((k, "r", t, np.zeros((3, 2)), np.zeros(3)))
    return {"events": events, "delay": LATENCY_S}


def test_the_line_at_the_centre_is_exact_and_leaves_an_outlier_out(cs):
    t = np.linspace(0.0, 0.8, 9)
    y = 2.0 + 3.0 * (t - 0.4)
    value, var = cs._line_at_centre(t, y, 0.4)
    assert value == pytest.approx(2.0, abs=1e-12) and var == pytest.approx(0.0, abs=1e-20)
    y[2] += 1.0  # one detection jumps: left out, the line is exact again
    value, var = cs._line_at_centre(t, y, 0.4)
    assert value == pytest.approx(2.0, abs=1e-12) and var == pytest.approx(0.0, abs=1e-20)
    # noise: the variance is the scatter's times the centre's leverage (1 / n for the mean time)
    rng = np.random.default_rng(0)
    t = np.linspace(-1.0, 1.0, 2001)
    value, var = cs._line_at_centre(t, 1.0 + 0.5 * t + rng.normal(0.0, 0.1, t.size), 0.0)
    assert value == pytest.approx(1.0, abs=0.01)
    assert var == pytest.approx(0.01 / t.size, rel=0.1)


@pytest.mark.parametrize("ccw", [True, False])
def test_the_smoothed_reference_is_where_the_car_was(cs, ccw):
    poses, drive, case = clean_circle(ccw)
    d = stream(drive, case)
    out = cs.smoothed_reference(d, drive, case)
    _, _, t0, origin = local_frame(drive, case.waypoints_xy_m)
    obs = [e for e in out["events"] if e[1] == "o"]
    # the first SMOOTH_N - 1 detections have no window yet; the predictions pass unchanged
    assert len(obs) == len(drive.t_s) - cs.SMOOTH_N + 1
    assert sum(e[1] == "r" for e in out["events"]) == len(drive.t_s)
    for k, _, t_c, x, y, (var_s, var_d) in obs:
        middle = k - cs.SMOOTH_N // 2
        assert t_c == drive.t_s[middle] - t0
        cap = t_c + t0 - LATENCY_S
        true = [np.interp(cap, poses["t_s"], poses["xy_m"][:, i]) for i in (0, 1)]
        # on the circle to within the chords: the truth interpolated linearly between its
        # 60 Hz poses, (v dt)^2 / (8 r) = 6.5e-5 m, and the path's 0.1 m segments the arc
        # length and offset are taken on, 0.1^2 / (8 r) = 1.0e-3 m
        assert math.hypot(x + origin[0] - true[0], y + origin[1] - true[1]) < 1.1e-3
        assert var_s < 1e-6 and var_d < 1e-6  # the chords again: a millimetre


def test_the_smoothed_reference_follows_any_path(cs):
    """On a straight of a rectangular loop, a car 0.5 m left of the waypoints at constant
    speed: the reference is where it was, to rounding."""
    corners = np.array([[0.0, 0.0], [100.0, 0.0], [100.0, 60.0], [0.0, 60.0], [0.0, 0.0]])
    waypoints = np.concatenate(
        [np.linspace(a, b, 200, endpoint=False) for a, b in zip(corners[:-1], corners[1:])]
    )
    t = np.arange(0.0, 4.0, 1 / 25)
    xy = np.stack([20.0 + 8.0 * t, np.full_like(t, 0.5)], axis=1)
    drive = observe(t, xy, np.zeros_like(t), waypoints, latency_s=LATENCY_S, seed=2,
                    sensor=Sensor.clean())  # fmt: skip
    case = types.SimpleNamespace(waypoints_xy_m=waypoints, test_drive=drive)
    out = cs.smoothed_reference(stream(drive, case), drive, case)
    _, _, t0, origin = local_frame(drive, case.waypoints_xy_m)
    obs = np.array([e[2:5] for e in out["events"] if e[1] == "o"])
    assert len(obs) == len(drive.t_s) - cs.SMOOTH_N + 1
    cap = obs[:, 0] + t0 - LATENCY_S
    np.testing.assert_allclose(obs[:, 1] + origin[0], 20.0 + 8.0 * cap, atol=1e-9)
    np.testing.assert_allclose(obs[:, 2] + origin[1], 0.5, atol=1e-9)


def test_the_recorded_pose_reference_measures_the_runners_reference(cs):
    poses, drive, case = clean_circle(True)
    local, _, t0, origin = local_frame(drive, case.waypoints_xy_m)
    # a runner's reference 5 cm off to the left of the car (along +y where the car runs +x)
    cap = drive.t_s - LATENCY_S
    true = np.stack([np.interp(cap, poses["t_s"], poses["xy_m"][:, i]) for i in (0, 1)], 1)
    yaw = np.interp(cap, poses["t_s"], poses["yaw_rad"])
    left = np.stack([-np.sin(yaw), np.cos(yaw)], 1)
    d = stream(drive, case, true + 0.05 * left - origin)
    out, err = cs.true_reference(d, drive, poses, case)
    np.testing.assert_allclose(err[:, 0], 0.0, atol=1e-3)
    np.testing.assert_allclose(err[:, 1], 0.05, atol=1e-3)
    obs = np.array([e[3:5] for e in out["events"] if e[1] == "o"])
    np.testing.assert_allclose(obs + origin, true, atol=1e-9)
