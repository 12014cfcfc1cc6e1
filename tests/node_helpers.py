"""What the live node's tests share across middlewares: the simulated drive and its `fpe predict`
output, the four-opponent ObstacleArray frames and their runner predictions, log messages as
message dicts of either flavour, and starting / stopping `fpe node` as a subprocess."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from fpe_jax.cli import main
from fpe_jax.io.config import params_to_config, write_config
from fpe_jax.io.logs import open_log
from fpe_jax.model._params import presets
from fpe_jax.node._core import frenet_to_map
from fpe_jax.runner._runner import Runner, RunnerPath

ROOT = Path(__file__).resolve().parents[1]
RATE_HZ = 40.0
H = 10
COV = [[[0.01 * (k + 1), 0.002], [0.002, 0.004 * (k + 1)]] for k in range(H)]
OPPONENT_IDS = [3, 7, 11, 20]


def make_drive(tmp: Path) -> dict:
    """An 8 s simulated drive in the seed's layout (`fpe simulate --sensor apriltag`) under tmp,
    a config with per-step covariance, and `fpe predict`'s CSV of it. Returns the config dict."""
    argv = ["simulate", "--sensor", "apriltag", "--duration", "8", "--out", str(tmp / "sim")]
    assert main(argv) == 0
    cfg = params_to_config(presets["default"], uncertainty={"frame": "track", "cov_m2": COV})
    write_config(tmp / "cfg.json", cfg)
    wp, log = tmp / "sim" / "waypoints.csv", tmp / "sim" / "drive.mcap"
    argv = ["predict", str(log), "--config", str(tmp / "cfg.json"), "--waypoints", str(wp)]
    assert main([*argv, "--out", str(tmp / "pred.csv")]) == 0
    return cfg


def predicted_rows(pred_csv: Path) -> dict[int, np.ndarray]:
    """{observation stamp [ns]: its H rows} of the valid predictions in `fpe predict`'s CSV."""
    pred = np.genfromtxt(pred_csv, delimiter=",", names=True)
    valid = pred[pred["valid"] == 1]
    return {round(row["stamp"][0] * 1e9): row for row in valid.reshape(-1, H)}


def obstacle_frames(log_path: Path, waypoints_xy_m: np.ndarray, n_rows: int = 80) -> list:
    """[(stamp [ns], obstacles)] at 40 Hz: the drive's opponent at four lags as obstacles
    OPPONENT_IDS (s, d along the waypoints) plus a static obstacle 99 the node must ignore.
    Obstacle dicts carry the fields both f110_msgs flavours share."""
    path = RunnerPath(waypoints_xy_m)
    odom = [
        (msg.pose.pose.position.x, msg.pose.pose.position.y)
        for _, _, _, msg in open_log(log_path).messages(["/opp/odom"])
    ]
    frames, s_prev = [], {}
    for j in range(n_rows):
        obst = []
        for k, ident in enumerate(OPPONENT_IDS):
            x, y = odom[j * 2 + 60 * k]
            prev = s_prev.get(ident)
            s = path.project(x, y) if prev is None else path.project_window(x, y, prev)
            s_prev[ident] = s
            cx, cy = path.point_at(s)
            h = path.heading_at(s)
            d = (y - cy) * np.cos(h) - (x - cx) * np.sin(h)
            obst.append({"id": ident, "s_center": s % path.length_m, "d_center": float(d),
                         "is_static": False, "is_visible": True})  # fmt: skip
        obst.append({"id": 99, "s_center": 1.0, "d_center": 0.0, "is_static": True})
        frames.append((1_000_000_000 + j * 25_000_000, obst))
    return frames


def runner_predictions(cfg: dict, waypoints_xy_m: np.ndarray, frames: list) -> dict:
    """{obstacle id: [(stamp [ns], poses (H, 3))]} of the valid predictions a runner per
    obstacle makes from `frames` (what the node must publish)."""
    path = RunnerPath(waypoints_xy_m)
    want = {}
    for i in OPPONENT_IDS:
        r = Runner(cfg, waypoints_xy_m)
        want[i] = []
        for ns, obst in frames:
            o = next(o for o in obst if o["id"] == i)
            x, y = frenet_to_map(path, o["s_center"], o["d_center"])
            poses = r.update((ns - frames[0][0]) * 1e-9, x, y, None)
            if r.valid:
                want[i].append((ns, poses))
    return want


def msg_dict(msg, flavour: str):
    """A rosbags message object (as the log reader gives it) as a message dict of `flavour`
    (ROS 1 times {secs, nsecs}; ROS 2 headers without seq)."""
    fields = getattr(msg, "__dataclass_fields__", None) or getattr(msg, "__slots__", None)
    if isinstance(msg, str | bytes | int | float) or fields is None:
        if isinstance(msg, np.ndarray):
            return msg.tolist()
        if isinstance(msg, list | tuple):
            return [msg_dict(v, flavour) for v in msg]
        return msg
    if set(fields) == {"sec", "nanosec"} and flavour == "ros1":
        return {"secs": msg.sec, "nsecs": msg.nanosec}
    skip = {"__msgtype__"} | ({"seq"} if flavour == "ros2" else set())
    return {k: msg_dict(getattr(msg, k), flavour) for k in fields if k not in skip}


def start_node(flavour: str, env: dict, *args) -> subprocess.Popen:
    """`fpe node --ros1|--ros2 ARGS` in a subprocess (stdout and stderr piped)."""
    return subprocess.Popen(
        [sys.executable, "-m", "fpe_jax.cli", "node", f"--{flavour}", *args],
        env=env | {"PYTHONUNBUFFERED": "1"},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )


def stop_node(proc) -> str:
    """SIGINT the node; it must exit 0 within 20 s. Returns its stderr."""
    proc.send_signal(2)
    try:
        _, err = proc.communicate(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
        raise AssertionError(f"the node did not stop on SIGINT: {err}") from None
    assert proc.returncode == 0, err
    return err


def wait_for(pred, timeout=20.0) -> None:
    """Poll `pred` every 50 ms until it holds or `timeout` [s] has passed."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and not pred():
        time.sleep(0.05)
