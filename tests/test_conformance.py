"""The `seed` preset reproduces the original node's recorded predictions (../shared/data/levine).

Each recorded set's input pose was not recorded, so it is recovered from the set itself: the
first step is purely linear (w = 1), so the pose after it is the first point with the initial yaw;
the second step's direction then fixes that yaw (a 1-D root, found by bisection). All ten points
are then compared with the preset's output, which the recovery used only to two points' depth.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fpe_jax import State, Track, predict_batch, presets
from fpe_jax.cli import main

DT_S, V_MPS, WHEELBASE_M, LOOKAHEAD_M, CLIP_RAD, ALPHA = 0.1, 1.0, 0.325, 2.0, 0.5236, 0.7


def recover_initial_poses(waypoints: np.ndarray, sets: np.ndarray) -> np.ndarray:
    """(S, 10, 2) recorded sets -> (S, 3) x, y, yaw of the pose each set was predicted from."""
    p1, p2 = sets[:, 0], sets[:, 1]
    d_all = np.linalg.norm(waypoints[None] - p1[:, None], axis=2)  # (S, K)
    within = d_all <= LOOKAHEAD_M
    last = waypoints.shape[0] - 1 - np.argmax(within[:, ::-1], axis=1)
    goal = waypoints[np.where(within.any(axis=1), last, 0)]
    d = np.linalg.norm(goal - p1, axis=1)
    phi = np.arctan2(goal[:, 1] - p1[:, 1], goal[:, 0] - p1[:, 0])
    theta = np.arctan2(p2[:, 1] - p1[:, 1], p2[:, 0] - p1[:, 0])  # heading of the second step

    def residual(yaw0):  # second step: yaw1 = yaw0 + (1 - alpha) dt v / L tan(steer(p1, yaw0))
        steer = np.clip(2 * np.sin(phi - yaw0) / d, -CLIP_RAD, CLIP_RAD)
        yaw1 = yaw0 + (1 - ALPHA) * DT_S * V_MPS / WHEELBASE_M * np.tan(steer)
        return np.angle(np.exp(1j * (yaw1 - theta)))

    lo, hi = theta - 0.1, theta + 0.1  # |turn of one step| <= 0.053 rad brackets the root
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        neg = residual(mid) < 0
        lo, hi = np.where(neg, mid, lo), np.where(neg, hi, mid)
    yaw0 = 0.5 * (lo + hi)
    xy0 = p1 - DT_S * V_MPS * np.stack([np.cos(yaw0), np.sin(yaw0)], axis=1)
    return np.column_stack([xy0, yaw0])


@pytest.fixture(scope="module")
def levine(shared_data):
    wps = np.loadtxt(shared_data / "levine" / "levine-waypoints.csv", delimiter=",")[:, :2]
    sets = np.loadtxt(shared_data / "levine" / "predicted-poses.csv", delimiter=",")[:, :2]
    sets = sets.reshape(-1, 10, 2)
    return wps, sets, recover_initial_poses(wps, sets)


def _fraction_within_1mm(pred_xy, sets):
    err = np.linalg.norm(pred_xy - sets, axis=2).max(axis=1)
    return np.mean(err <= 1e-3), err


def test_seed_reproduces_recorded_sets(levine):
    wps, sets, init = levine
    assert sets.shape == (544, 10, 2)
    track = Track.from_waypoints(wps)
    states = State(
        x_m=jnp.asarray(init[:, 0]),
        y_m=jnp.asarray(init[:, 1]),
        yaw_rad=jnp.asarray(init[:, 2]),
        v_mps=jnp.zeros(len(init)),
        yaw_rate_rps=jnp.zeros(len(init)),
    )
    pred = np.asarray(predict_batch(presets["seed"], states, track))
    frac, err = _fraction_within_1mm(pred[:, :, :2], sets)
    assert frac >= 0.995, f"only {frac:.3%} within 1 mm; worst {err.max():.4f} m"


def test_seed_measured_speed_differs_only_in_speed(levine):
    """With a measured speed of exactly 1 m/s the two seed presets agree bit for bit."""
    wps, _, init = levine
    track = Track.from_waypoints(wps)
    ones = jnp.ones(len(init))
    states = State(
        x_m=jnp.asarray(init[:, 0]),
        y_m=jnp.asarray(init[:, 1]),
        yaw_rad=jnp.asarray(init[:, 2]),
        v_mps=ones,
    )
    a = predict_batch(presets["seed"], states, track)
    b = predict_batch(presets["seed-measured-speed"], states, track)
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    faster = jax.tree.map(lambda x: x, states)
    faster = State(x_m=faster.x_m, y_m=faster.y_m, yaw_rad=faster.yaw_rad, v_mps=2 * ones)
    c = predict_batch(presets["seed-measured-speed"], faster, track)
    assert not np.allclose(np.asarray(a), np.asarray(c))


def test_seed_conformance_through_cli(levine, shared_data, tmp_path):
    _, sets, init = levine
    obs = tmp_path / "initial-poses.csv"
    t = 0.1 * np.arange(len(init))
    np.savetxt(
        obs, np.column_stack([t, init]), delimiter=",", header="t,x,y,yaw", comments="", fmt="%.12f"
    )
    out = tmp_path / "pred.csv"
    wps = shared_data / "levine" / "levine-waypoints.csv"
    rc = main(["predict", str(obs), "--waypoints", str(wps), "--preset", "seed", "--out", str(out)])
    assert rc == 0
    rows = np.genfromtxt(out, delimiter=",", names=True)
    # the columns `fpe predict` writes; `valid` marks rows predicted from too little history
    assert rows.dtype.names == ("stamp", "step", "horizon_s", "x", "y", "yaw", "valid")
    pred = np.column_stack([rows["x"], rows["y"]]).reshape(-1, 10, 2)
    np.testing.assert_allclose(rows["horizon_s"][:10], 0.1 * np.arange(1, 11), atol=1e-12)
    frac, err = _fraction_within_1mm(pred, sets)
    assert frac >= 0.995, f"only {frac:.3%} within 1 mm through the CLI; worst {err.max():.4f} m"
