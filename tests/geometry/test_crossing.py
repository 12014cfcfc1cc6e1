"""Self-crossing tracks (a figure-eight): a car at the crossing is projected onto the branch that
agrees with its heading, in the runner, in the JAX drive projection and in batch."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fpe_jax.drive import Drive
from fpe_jax.geometry._track import Track
from fpe_jax.model._params import presets
from fpe_jax.predict._predict import predict_drive
from fpe_jax.runner._runner import Runner

A_M = 15.0  # lobe size of the lemniscate x = a sin t, y = a sin t cos t [m]
V_MPS = 3.0


def figure_eight(n: int = 1200) -> np.ndarray:
    """(n, 2) waypoints [m]; the path crosses itself at the origin, at t = 0 heading 45 degrees
    and at t = pi heading 135 degrees."""
    t = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    return A_M * np.stack([np.sin(t), np.sin(t) * np.cos(t)], axis=1)


def _along(t0: float, dist_m: np.ndarray) -> np.ndarray:
    """Points (len(dist), 2) [m] `dist` metres along the lemniscate from parameter t0."""
    t = np.linspace(t0, t0 + 2 * np.pi, 200_001)
    xy = A_M * np.stack([np.sin(t), np.sin(t) * np.cos(t)], axis=1)
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
    return np.stack([np.interp(dist_m, s, xy[:, 0]), np.interp(dist_m, s, xy[:, 1])], axis=1)


def _yaw(xy: np.ndarray) -> np.ndarray:
    d = np.gradient(xy, axis=0)
    return np.arctan2(d[:, 1], d[:, 0])


def crossing_drive(t0: float, with_yaw: bool = True) -> Drive:
    """4 s at 3 m/s from the crossing along the branch of parameter t0 (0 or pi), observed at
    10 Hz (with yaw, or without), truth at 50 Hz."""
    t_obs = np.arange(0.0, 4.0, 0.1)
    t_truth = np.arange(0.0, 6.0, 0.02)
    xy, truth = _along(t0, V_MPS * t_obs), _along(t0, V_MPS * t_truth)
    yaw = _yaw(xy) if with_yaw else np.full(len(t_obs), np.nan)
    return Drive(t_s=t_obs, xy_m=xy, yaw_rad=yaw, truth_t_s=t_truth, truth_xy_m=truth)


CASES = [
    (t0, preset, yaw)
    for t0 in (0.0, np.pi)
    for preset in ("default", "frenet")
    for yaw in (True, False)
]


def _fde_1s(poses: np.ndarray, drive: Drive) -> np.ndarray:
    """(N,) distance [m] of each observation's 1 s prediction from the truth."""
    when = drive.t_s + 1.0
    tx = np.interp(when, drive.truth_t_s, drive.truth_xy_m[:, 0])
    ty = np.interp(when, drive.truth_t_s, drive.truth_xy_m[:, 1])
    return np.hypot(poses[:, 9, 0] - tx, poses[:, 9, 1] - ty)


def test_the_crossing_is_where_the_branches_meet():
    track = Track.from_waypoints(figure_eight())
    assert track.closed
    s = np.arange(track.n_points) * float(track.ds_m)
    near = np.flatnonzero(np.hypot(*np.asarray(track.xy_m).T) < 0.05)
    assert np.ptp(s[near]) > 0.4 * float(track.length_m)  # two branches through the origin


def _runner_poses(params, drive: Drive) -> np.ndarray:
    from fpe_jax.io.config import params_to_config

    runner = Runner(params_to_config(params), figure_eight())
    rows = zip(drive.t_s, drive.xy_m, drive.yaw_rad, strict=True)
    return np.stack([runner.update(t, x, y, yaw) for t, (x, y), yaw in rows])


@pytest.mark.parametrize("t0, preset, with_yaw", CASES)
def test_a_drive_starting_at_the_crossing_follows_its_branch(t0, preset, with_yaw):
    """Runner and JAX: the 1 s predictions from the second observation on (the first has no
    speed yet) stay on the car's own branch, and the two agree to 1e-6 m."""
    drive, params = crossing_drive(t0, with_yaw), presets[preset]
    _, poses = predict_drive(params, drive, Track.from_waypoints(figure_eight()))
    err = _fde_1s(np.asarray(poses), drive)[1:]
    assert err.max() < 1.0, err.round(2)
    mirror = _runner_poses(params, drive)
    np.testing.assert_allclose(mirror[..., :2], np.asarray(poses)[..., :2], atol=1e-6)


def test_batch_car_at_the_crossing_drives_on_along_its_heading():
    from fpe_jax.predict._batch import predict_chunked

    track = Track.from_waypoints(figure_eight())
    yaw2 = 0.75 * math.pi  # the second branch's heading at the origin
    cars = np.array([[0.0, 0.0, yaw2, V_MPS], [0.0, 0.0, 0.25 * math.pi, V_MPS]])
    poses = predict_chunked(presets["default"], cars, track, dtype="float64", chunk=8)
    truth = [_along(np.pi, np.array([V_MPS]))[0], _along(0.0, np.array([V_MPS]))[0]]
    for k in range(2):
        moved = np.hypot(*(poses[k, 9, :2] - cars[k, :2]))
        assert moved > 2.5, poses[k, 9]
        assert np.hypot(*(poses[k, 9, :2] - truth[k])) < 0.5, (k, poses[k, 9], truth[k])
        assert abs(math.remainder(poses[k, 0, 2] - cars[k, 2], 2 * math.pi)) < 0.3
