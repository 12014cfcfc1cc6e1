"""CPU time of `fpe node`'s work per input message with every output subscribed, in process.

The node (`fpe_jax.node.Node` on the real transport: rospy with a roscore on 127.0.0.1, or
Cyclone DDS on loopback) gets the drive of node_latency.py at 40 Hz straight into its input
callback, while a second process (node_latency.py's sink) subscribes to every output, paths
included, so the node builds and sends all of them. Per input message (one observation of each
opponent) it reports the callback thread's CPU time (runner updates, covariances, message
building, encoding, the transport's write calls) and the whole process's (with the transport's
own threads: rospy's writer threads, Cyclone's). CPU time depends little on what else the
machine runs, where wall-clock tails do: the measure to compare code by on a shared machine.
Writes node_cpu.md beside this file (or --out).

    .venv/bin/python experiments/benchmarks/node_cpu.py [--seconds 8] [--runs 3]
        [--middleware both] [--out FILE]

Run against another checkout of the package (the same script): PYTHONPATH=<checkout> ...
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parents[1] / "tests"))

import node_latency as nl  # noqa: E402
from ros1_helpers import roscore  # noqa: E402
from ros2_helpers import LOOPBACK_URI  # noqa: E402

from fpe_jax.io.config import read_config  # noqa: E402
from fpe_jax.node import time_dict  # noqa: E402
from fpe_jax.node._core import Node, NodeOptions  # noqa: E402
from fpe_jax.runner._runner import load_waypoints_xy  # noqa: E402

WARM_UP = 80  # input messages before the measure: every track valid, every topic connected
NO_MARKERS = False  # the node without its MarkerArray output (--no-markers)


def run(flavour: str, n_opp: int, seconds: float, tmp: Path, env: dict) -> dict:
    """One run: {thread_ms, process_ms} per input message (medians of the callback's thread
    time; the process's over the run), and the outputs the sink received."""
    _, frames, topics, others = nl._setup(n_opp, seconds + WARM_UP / nl.RATE_HZ, tmp)
    others |= dict.fromkeys(topics, "nav_msgs/msg/Path")
    nl.LISTEN_ALL = True
    sink = nl._sink(flavour, others, env)
    if flavour == "ros1":
        from fpe_jax.node._ros1 import Ros1Transport

        transport = Ros1Transport("fpe_bench_cpu")
    else:
        from fpe_jax.node._dds import DdsTransport
        from fpe_jax.node._types import typestore

        transport = DdsTransport(typestore("ros2"), node_name="fpe_bench_cpu")
    path_out: list[int] = []  # thread CPU time at each path's write of the current callback
    advertise = transport.advertise

    def timed_advertise(topic: str, type_name: str):
        publish = advertise(topic, type_name)
        if type_name != "nav_msgs/msg/Path":
            return publish

        def publish_path(msg) -> None:
            publish(msg)
            path_out.append(time.thread_time_ns())

        return publish_path

    transport.advertise = timed_advertise
    pose = n_opp == 1
    opts = NodeOptions(input="pose" if pose else "obstacles",
                       topic="/opp/pose" if pose else "/perception/obstacles")  # fmt: skip
    if NO_MARKERS:
        opts.outputs["markers"] = None
    node = Node(transport, read_config(tmp / "cfg.json"), load_waypoints_xy(tmp / "wp.csv"), opts)
    node.start()
    callback = node._guard(opts.topic, node._on_pose if pose else node._on_obst)
    type_name = "geometry_msgs/msg/PoseStamped" if pose else "f110_msgs/msg/ObstacleArray"

    def message(ns: int, body: dict) -> dict:
        body = json.loads(json.dumps(body))  # a fresh message, as a transport delivers it
        for o in body.get("obstacles", []):  # the fields a transport's message always has
            o["is_static"] = False
        if "pose" in body:
            body["pose"]["position"]["z"] = 0.0
            body["pose"]["orientation"] = {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}
        return {"header": {"stamp": time_dict(flavour, ns), "frame_id": "map"}, **body}

    thread_ns, paths_ns = [], []
    period_ns = int(1e9 / nl.RATE_HZ)
    for k, (ns, body) in enumerate(frames):
        if k == WARM_UP:
            time.sleep(3.0)  # the per-opponent topics connect
            process_s = time.process_time()
        msg = message(ns, body)
        path_out.clear()
        t0, w0 = time.thread_time_ns(), time.perf_counter_ns()
        callback(msg, type_name, time.time_ns())
        if k >= WARM_UP:
            thread_ns.append(time.thread_time_ns() - t0)
            if path_out:
                paths_ns.append(path_out[-1] - t0)
        time.sleep(max(0.0, (period_ns - (time.perf_counter_ns() - w0)) * 1e-9))
    process_s = time.process_time() - process_s
    time.sleep(0.5)
    transport.close()
    received = nl._stop(sink)
    n = len(thread_ns)
    return {"thread_ms": float(np.median(thread_ns)) * 1e-6, "process_ms": process_s / n * 1e3,
            "paths_ms": float(np.median(paths_ns)) * 1e-6, "received": received,
            "messages": n}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=8.0, help="measured drive per run [s]")
    ap.add_argument("--runs", type=int, default=3, help="runs of each case; medians reported")
    ap.add_argument("--middleware", choices=["ros1", "ros2", "both"], default="both")
    ap.add_argument("--out", type=Path, default=HERE / "node_cpu.md")
    ap.add_argument("--no-markers", action="store_true", help="the node run with --no-markers")
    ap.add_argument("--one", nargs=3, help=argparse.SUPPRESS)  # a run: flavour, n_opp, tmp
    args = ap.parse_args()
    warnings.simplefilter("ignore", DeprecationWarning)
    if args.one:  # each run in its own process: rospy is one node per process, for good
        flavour, n_opp, tmp = args.one
        global NO_MARKERS
        NO_MARKERS = args.no_markers
        print(json.dumps(run(flavour, int(n_opp), args.seconds, Path(tmp), dict(os.environ))))
        return
    rows, start, load_start = [], time.monotonic(), os.getloadavg()

    def runs(flavour: str, tmp: Path, env: dict) -> None:
        for n_opp in (1, 4):
            for _ in range(args.runs):
                argv = ["--seconds", str(args.seconds), "--one", flavour, str(n_opp), str(tmp)]
                argv += ["--no-markers"] * args.no_markers
                out = subprocess.run([sys.executable, __file__, *argv], env=env, text=True,
                                     stdout=subprocess.PIPE, check=True).stdout  # fmt: skip
                rows.append((flavour, n_opp, json.loads(out.splitlines()[-1])))
                print(json.dumps(rows[-1]), flush=True)

    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        if args.middleware in ("ros1", "both"):
            with roscore(tmp) as env:
                runs("ros1", tmp, env)
        if args.middleware in ("ros2", "both"):
            env = dict(os.environ, CYCLONEDDS_URI=LOOPBACK_URI)
            runs("ros2", tmp, env | {"ROS_DOMAIN_ID": str(1 + os.getpid() % 200)})
    import fpe_jax

    lines = [
        "# `fpe node` CPU time per input message, every output subscribed",
        "",
        f"Command: `.venv/bin/python experiments/benchmarks/node_cpu.py --seconds "
        f"{args.seconds:g} --runs {args.runs} --middleware {args.middleware}"
        f"{' --no-markers' * args.no_markers}` "
        f"({(time.monotonic() - start) / 60:.0f} minutes; package at "
        f"`{Path(fpe_jax.__file__).parent.parent.name}`): node_latency.py's drive at "
        f"{nl.RATE_HZ:g} Hz into the node's input callback, a second process subscribed to every "
        "output (paths, markers, per-step covariances, predicted obstacles). Until the last "
        "path: the callback thread's CPU time from the input message to its last path written "
        "(median; what the planner waits for). Callback thread: "
        "median CPU time of one input message's callback (runner updates, covariances, "
        "messages built, encoded and written); process: the node process's CPU time over the "
        f"run per input message, the transport's threads included. Medians over {args.runs} runs.",
        "",
        "| middleware | opponents | input messages | outputs received (fewest) "
        "| until the last path [ms] | callback thread CPU [ms] | process CPU [ms] |",
        "|---|---|---|---|---|---|---|",
    ]
    for mw, n_opp in sorted({(mw, n) for mw, n, _ in rows}):
        runs = [r for m, n, r in rows if (m, n) == (mw, n_opp)]
        lines.append(
            f"| {mw} | {n_opp} | {runs[0]['messages']} | {min(r['received'] for r in runs)} | "
            f"{np.median([r['paths_ms'] for r in runs]):.2f} | "
            f"{np.median([r['thread_ms'] for r in runs]):.2f} | "
            f"{np.median([r['process_ms'] for r in runs]):.2f} |"
        )
    load_end = os.getloadavg()
    lines += ["", "Load average (1, 5, 15 min) at the start: "
              + ", ".join(f"{v:.2f}" for v in load_start) + "; at the end: "
              + ", ".join(f"{v:.2f}" for v in load_end) + " (2 cores)."]  # fmt: skip
    args.out.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
