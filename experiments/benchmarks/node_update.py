"""The live node's own update time per opponent, in process, without middleware.

node_latency.py's drive (default preset, per-step covariance) goes at 40 Hz straight into the
input callback of a `fpe_jax.node.Node` whose in-memory transport has no subscriber (so the
node builds no output message): what is left is the "own update" that node_latency.md reports
(the runner's update, the off-track check and the covariance per opponent), with the idle gap
between input messages that a 40 Hz stream has (caches go cold in it; `--gap-ms 0` feeds the
messages back to back). Alongside, the same run's breakdown of each part of an update (wrapped
timers, < 1 us each). p50 / p99 over the updates after the first `WARM_UP` input messages; the
median over `--runs` runs. Prints a markdown table (and writes it to `--out` when given).

    .venv/bin/python experiments/benchmarks/node_update.py [--seconds 10] [--runs 3]
        [--gap-ms 25] [--out FILE]

Run against another checkout of the package (the same script): PYTHONPATH=<checkout> ...
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
import warnings
from collections import defaultdict
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parents[1] / "tests"))

import node_latency as nl  # noqa: E402

from fpe_jax.io.config import read_config  # noqa: E402
from fpe_jax.node import time_dict  # noqa: E402
from fpe_jax.node._cdr import CdrCodec  # noqa: E402
from fpe_jax.node._core import Node, NodeOptions  # noqa: E402
from fpe_jax.node._types import typestore  # noqa: E402
from fpe_jax.runner._runner import Runner, RunnerPath, load_waypoints_xy  # noqa: E402

WARM_UP = 20  # input messages before the measure (the first ones search the whole track)
PARTS = {  # the parts of an own update: (class, method)
    "runner update": (Runner, "update"),
    "off-track check": (Runner, "track_distance"),
    "covariance": (Node, "_covariance"),
    "  of it: step arc lengths": (RunnerPath, "project_chain"),
}


class Silent:
    """ROS 2 in memory with nobody subscribed: the node encodes its templates, sends nothing."""

    flavour = "ros2"

    def __init__(self):
        self.codec = CdrCodec(typestore("ros2"))

    def subscribe(self, topic, type_name, callback):
        pass

    def advertise(self, topic, type_name):
        return lambda msg: None

    def encode(self, type_name, msg):
        return self.codec.encode(type_name, msg)

    def subscriber_count(self, topic):
        return 0

    def spin(self, stop):
        pass

    def close(self):
        pass


def _timed(times: list, f):
    def wrapper(*args, **kwargs):
        t0 = time.perf_counter_ns()
        out = f(*args, **kwargs)
        times.append(time.perf_counter_ns() - t0)
        return out

    return wrapper


def run(n_opp: int, seconds: float, gap_s: float, tmp: Path) -> dict:
    """One run: {part: (p50, p99) [ms]} with "own update" the node's own measure."""
    _, frames, _, _ = nl._setup(n_opp, seconds + WARM_UP / nl.RATE_HZ, tmp)
    pose = n_opp == 1
    opts = NodeOptions(input="pose" if pose else "obstacles",
                       topic="/opp/pose" if pose else "/perception/obstacles")  # fmt: skip
    node = Node(Silent(), read_config(tmp / "cfg.json"), load_waypoints_xy(tmp / "wp.csv"), opts)
    node.start()
    callback = node._guard(opts.topic, node._on_pose if pose else node._on_obst)
    type_name = "geometry_msgs/msg/PoseStamped" if pose else "f110_msgs/msg/ObstacleArray"
    times: dict[str, list] = defaultdict(list)
    saved = [(cls, name, getattr(cls, name)) for cls, name in PARTS.values()]
    for part, (cls, name) in PARTS.items():
        setattr(cls, name, _timed(times[part], getattr(cls, name)))
    try:
        messages = []
        for ns, body in frames:
            body = json.loads(json.dumps(body))  # the fields a transport's message always has
            for o in body.get("obstacles", []):
                o["is_static"] = False
            if pose:
                body["pose"]["position"]["z"] = 0.0
                body["pose"]["orientation"] = {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}
            messages.append({"header": {"stamp": time_dict("ros2", ns), "frame_id": "map"}, **body})
        first: dict[str, int] = {}
        for k, msg in enumerate(messages):
            if k == WARM_UP:
                first = {"own update": len(node.update_ns)} | {p: len(times[p]) for p in PARTS}
            w0 = time.perf_counter()
            callback(msg, type_name, time.monotonic_ns())
            if gap_s:
                time.sleep(max(0.0, gap_s - (time.perf_counter() - w0)))
    finally:
        for cls, name, f in saved:
            setattr(cls, name, f)
    out = {}
    for part, values in {"own update": node.update_ns, **times}.items():
        v = np.array(values[first[part] :], dtype=np.float64) * 1e-6
        out[part] = (float(np.percentile(v, 50)), float(np.percentile(v, 99)), len(v))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0, help="measured drive per run [s]")
    ap.add_argument("--runs", type=int, default=3, help="runs of each case; medians reported")
    ap.add_argument("--gap-ms", type=float, default=1e3 / nl.RATE_HZ,
                    help="input message period [ms] (default 40 Hz; 0: back to back)")  # fmt: skip
    ap.add_argument("--out", type=Path, help="also write the table to this file")
    args = ap.parse_args()
    warnings.simplefilter("ignore", DeprecationWarning)
    load_start = os.getloadavg()
    results: dict[int, list] = {}
    with tempfile.TemporaryDirectory() as d:
        for n_opp in (1, 4):
            results[n_opp] = [run(n_opp, args.seconds, args.gap_ms * 1e-3, Path(d))
                              for _ in range(args.runs)]  # fmt: skip
    import fpe_jax

    lines = [
        "# `fpe node` own update time per opponent, in process",
        "",
        f"Command: `.venv/bin/python experiments/benchmarks/node_update.py --seconds "
        f"{args.seconds:g} --runs {args.runs} --gap-ms {args.gap_ms:g}` (package at "
        f"`{Path(fpe_jax.__file__).parent.parent.name}`); medians over {args.runs} runs of p50 "
        "/ p99 [ms] per opponent and update.",
        "",
        "| part | 1 opponent p50 / p99 [ms] | 4 opponents p50 / p99 [ms] |",
        "|---|---|---|",
    ]
    for part in ("own update", *PARTS):
        cells = []
        for n_opp in (1, 4):
            p50 = np.median([r[part][0] for r in results[n_opp]])
            p99 = np.median([r[part][1] for r in results[n_opp]])
            cells.append(f"{p50:.3f} / {p99:.3f}")
        lines.append(f"| {part} | {' | '.join(cells)} |")
    n = {k: results[k][0]["own update"][2] for k in results}
    lines += ["", f"Updates per run: {n[1]} (1 opponent), {n[4]} (4). Load average (1, 5, 15 "
              "min) at the start: " + ", ".join(f"{v:.2f}" for v in load_start) + "; at the "
              "end: " + ", ".join(f"{v:.2f}" for v in os.getloadavg()) + " (2 cores)."]  # fmt: skip
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        args.out.write_text(text)


if __name__ == "__main__":
    main()
