"""Latency of `fpe node` on ROS 1 (loopback, a roscore on 127.0.0.1 started here).

For 1 opponent (PoseStamped input) and 4 opponents (one f110_msgs/ObstacleArray per tick) at
40 Hz it measures
- the node's own update time per opponent (runner update + covariance, inside the node), and
- end to end: from publishing an observation to receiving its nav_msgs/Path in this process.
p50 and p99 of each over `--seconds` of a simulated drive. Writes node_latency.md beside this file.

    .venv/bin/python experiments/benchmarks/node_latency.py [--seconds 30] [--middleware ros1]

`--middleware` names the transport (ros1 here; ros2 once its player is added below).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
import warnings
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from ros1_helpers import roscore  # noqa: E402

from fpe_jax.config import params_to_config, write_config  # noqa: E402
from fpe_jax.io.writers import write_xy_csv  # noqa: E402
from fpe_jax.params import presets  # noqa: E402
from fpe_jax.runner import RunnerPath  # noqa: E402
from fpe_jax.sim import simulate  # noqa: E402

RATE_HZ = 40.0
H = 10
COV = [[[0.01 * (k + 1), 0.002], [0.002, 0.004 * (k + 1)]] for k in range(H)]


def run_ros1(n_opp: int, seconds: float, tmp: Path, env: dict, r1) -> dict:
    res = simulate("oval", duration_s=seconds + 10.0, seed=0)
    truth_xy = np.column_stack([res.drive.truth_xy_m[:, 0], res.drive.truth_xy_m[:, 1]])
    write_xy_csv(tmp / "wp.csv", res.centerline_xy_m, force=True)
    cfg = params_to_config(presets["default"], uncertainty={"frame": "track", "cov_m2": COV})
    write_config(tmp / "cfg.json", cfg, force=True)
    path = RunnerPath(res.centerline_xy_m)
    stats = tmp / f"stats{n_opp}.json"
    args = ["--config", str(tmp / "cfg.json"), "--waypoints", str(tmp / "wp.csv")]
    args += ["--stats", str(stats)]
    if n_opp == 1:
        args += ["--pose-topic", "/opp/pose"]
        cls = r1.message_class("geometry_msgs/PoseStamped")
        pub = r1.rospy.Publisher("/opp/pose", cls, queue_size=100, tcp_nodelay=True)
        topics = ["/future_pose/path"]
    else:
        args += ["--obstacles-topic", "/perception/obstacles"]
        cls = r1.message_class("f110_msgs/ObstacleArray")
        pub = r1.rospy.Publisher("/perception/obstacles", cls, queue_size=100, tcp_nodelay=True)
        topics = [f"/future_pose/path/{i}" for i in range(n_opp)]
    sent: dict[int, int] = {}
    e2e: list[int] = []
    lock = threading.Lock()

    def got(m):
        now = time.time_ns()
        ns = m.header.stamp.secs * 10**9 + m.header.stamp.nsecs
        with lock:
            if ns in sent:
                e2e.append(now - sent[ns])

    proc = subprocess.Popen(
        [sys.executable, "-m", "fpe_jax.cli", "node", "--ros1", *args],
        env=env,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    path_cls = r1.message_class("nav_msgs/Path")
    subs = [
        r1.rospy.Subscriber(t, path_cls, got, queue_size=1000, tcp_nodelay=True) for t in topics
    ]
    deadline = time.monotonic() + 60
    while pub.get_num_connections() == 0 and time.monotonic() < deadline:
        time.sleep(0.05)
    t0_ns = 10**18
    n = int(seconds * RATE_HZ)
    step = 50.0 / RATE_HZ  # truth rows are at 50 Hz
    next_t = time.perf_counter()
    for j in range(n):
        ns = t0_ns + int(j * 1e9 / RATE_HZ)
        stamp = {"secs": ns // 10**9, "nsecs": ns % 10**9}
        if n_opp == 1:
            x, y = truth_xy[int(j * step)]
            msg = {"header": {"stamp": stamp, "frame_id": "map"},
                   "pose": {"position": {"x": float(x), "y": float(y)},
                            "orientation": {"w": 1.0}}}  # fmt: skip
        else:
            obst = []
            for k in range(n_opp):
                x, y = truth_xy[int(j * step) + 100 * k]
                s = path.project(float(x), float(y))
                cx, cy = path.point_at(s)
                h = path.heading_at(s)
                d = (y - cy) * np.cos(h) - (x - cx) * np.sin(h)
                obst.append({"id": k, "s_center": s, "d_center": float(d)})
            msg = {"header": {"stamp": stamp, "frame_id": "map"}, "obstacles": obst}
        m = r1.from_dict(cls, msg)
        with lock:
            sent[ns] = time.time_ns()
        pub.publish(m)
        next_t += 1.0 / RATE_HZ
        time.sleep(max(0.0, next_t - time.perf_counter()))
    time.sleep(1.0)
    proc.send_signal(2)
    proc.communicate(timeout=30)
    for s in subs:
        s.unregister()
    pub.unregister()
    upd = np.array(json.loads(stats.read_text())["update_ns"], dtype=np.float64) * 1e-6
    e = np.array(e2e, dtype=np.float64) * 1e-6
    return {
        "opponents": n_opp,
        "observations": n * n_opp,
        "predictions_received": len(e),
        "update_p50_ms": float(np.percentile(upd, 50)),
        "update_p99_ms": float(np.percentile(upd, 99)),
        "e2e_p50_ms": float(np.percentile(e, 50)),
        "e2e_p99_ms": float(np.percentile(e, 99)),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--middleware", choices=["ros1"], default="ros1")
    args = ap.parse_args()
    warnings.simplefilter("ignore", DeprecationWarning)
    rows = []
    with tempfile.TemporaryDirectory() as d, roscore(Path(d)) as env:
        os.environ.update(env)
        from fpe_jax.node import _ros1 as r1

        r1.rospy.init_node("fpe_bench_player", anonymous=True, disable_signals=True)
        for n_opp in (1, 4):
            rows.append(run_ros1(n_opp, args.seconds, Path(d), env, r1))
            print(json.dumps(rows[-1]), flush=True)
        r1.rospy.signal_shutdown("done")
    lines = [
        "# `fpe node` latency (ROS 1, loopback)",
        "",
        f"Command: `.venv/bin/python experiments/benchmarks/node_latency.py --seconds "
        f"{args.seconds:g}`; {RATE_HZ:g} Hz observations of a simulated drive, default preset with "
        "a per-step covariance (all outputs on). Own update: runner update + covariance per "
        "opponent, inside the node. End to end: publishing an observation to receiving its "
        "nav_msgs/Path in the publishing process.",
        "",
        "| middleware | opponents | observations | paths received | own update p50 / p99 [ms] "
        "| end to end p50 / p99 [ms] |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {args.middleware} | {r['opponents']} | {r['observations']} | "
            f"{r['predictions_received']} | {r['update_p50_ms']:.3f} / {r['update_p99_ms']:.3f} | "
            f"{r['e2e_p50_ms']:.2f} / {r['e2e_p99_ms']:.2f} |"
        )
    (HERE / "node_latency.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
