"""ROS 2 wire latency of the node's DDS transport: PoseStamped published at 40 Hz by one process,
received by another, on the loopback interface only (Cyclone DDS), through `DdsTransport` on both
sides. Latency = the subscriber's receive time (the `receive_time_ns` the node core gets) minus
the publisher's wall clock just before `publish` (carried in header.stamp); both processes read
the same system clock.

Also the Python cost of each message type the node reads or writes (the message catalogue of the
ROS 2 tests, tests/ros2_helpers.py): dict -> sample -> CDR bytes, and CDR bytes -> dict.

Usage: python experiments/benchmarks/dds_roundtrip.py [--count 400] [--rate-hz 40] [--runs 5]
Writes dds_roundtrip.md beside this file (--out to change). Nothing here gates CI.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
TOPIC = "/bench/opponent_pose"
TYPE = "geometry_msgs/msg/PoseStamped"
LOOPBACK_URI = (
    "<CycloneDDS><Domain><General><Interfaces><NetworkInterface name='lo'/></Interfaces>"
    "</General></Domain></CycloneDDS>"
)


def _store():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def publisher(count: int, rate_hz: float) -> None:
    """The publishing process: waits for the subscriber, then sends `count` poses at `rate_hz`."""
    from fpe_jax.node._dds import DdsTransport

    with DdsTransport(_store(), node_name="bench_pub") as transport:
        publish = transport.advertise(TOPIC, TYPE)
        end = time.monotonic() + 30
        while transport.subscriber_count(TOPIC) == 0:
            if time.monotonic() > end:
                sys.exit("dds_roundtrip: no subscriber matched within 30 s")
            time.sleep(0.01)
        time.sleep(0.2)  # the subscriber's spin loop is running
        period_s = 1.0 / rate_hz
        next_s = time.monotonic()
        for i in range(count):
            now_ns = time.time_ns()
            sec, nanosec = divmod(now_ns, 1_000_000_000)
            publish(
                {
                    "header": {"stamp": {"sec": sec, "nanosec": nanosec}, "frame_id": "map"},
                    "pose": {"position": {"x": 0.01 * i, "y": 1.0}, "orientation": {"w": 1.0}},
                }
            )
            next_s += period_s
            time.sleep(max(0.0, next_s - time.monotonic()))
        time.sleep(0.5)  # reliable writer: let the last samples go out before deleting it


def measure(count: int = 400, rate_hz: float = 40.0) -> dict:
    """One run: start a publisher process, receive in this one. Returns the one-way latencies
    (ms, numpy array) and the number of messages received."""
    from fpe_jax.node._dds import DdsTransport

    latencies_ms: list[float] = []
    done = threading.Event()

    def on_pose(msg: dict, type_name: str, receive_ns: int) -> None:
        stamp = msg["header"]["stamp"]
        latencies_ms.append((receive_ns - (stamp["sec"] * 1_000_000_000 + stamp["nanosec"])) / 1e6)
        if len(latencies_ms) >= count:
            done.set()

    with DdsTransport(_store(), node_name="bench_sub") as transport:
        transport.subscribe(TOPIC, TYPE, on_pose)
        child = subprocess.Popen(
            [
                sys.executable,
                __file__,
                "--publisher",
                "--count",
                str(count),
                "--rate-hz",
                str(rate_hz),
            ]
        )
        timer = threading.Timer(count / rate_hz + 30, done.set)
        timer.start()
        try:
            transport.spin(done)
        finally:
            timer.cancel()
            child.wait(30)
    if child.returncode != 0:
        raise RuntimeError(f"dds_roundtrip: publisher exited with {child.returncode}")
    return {"latency_ms": np.asarray(latencies_ms), "received": len(latencies_ms), "sent": count}


def codec_costs(runs: int, iterations: int = 100) -> list[dict]:
    """Median over `runs` of the mean time [us] to encode (dict -> CDR) and decode (CDR -> dict)
    each catalogue message."""
    sys.path.insert(0, str(HERE.parents[1] / "tests"))
    from ros2_helpers import catalogue, ros2_typestore

    from fpe_jax.node._dds import IdlCodec

    codec = IdlCodec(ros2_typestore())
    rows = []
    for topic, (type_name, msg) in catalogue().items():
        data = codec.encode(type_name, msg)
        enc, dec = [], []
        for _ in range(runs):
            start = time.perf_counter()
            for _ in range(iterations):
                codec.encode(type_name, msg)
            middle = time.perf_counter()
            for _ in range(iterations):
                codec.decode(type_name, data)
            enc.append((middle - start) / iterations * 1e6)
            dec.append((time.perf_counter() - middle) / iterations * 1e6)
        rows.append(
            {
                "topic": topic,
                "type": type_name,
                "bytes": len(data),
                "encode_us": statistics.median(enc),
                "decode_us": statistics.median(dec),
            }
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=400, help="messages per run")
    parser.add_argument("--rate-hz", type=float, default=40.0)
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--out", type=Path, default=HERE / "dds_roundtrip.md")
    parser.add_argument("--publisher", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    os.environ.setdefault("CYCLONEDDS_URI", LOOPBACK_URI)
    os.environ.setdefault("ROS_DOMAIN_ID", str(1 + os.getpid() % 200))
    if args.publisher:
        publisher(args.count, args.rate_hz)
        return
    load_start = os.getloadavg()[0]
    rows = []
    for run in range(args.runs):
        result = measure(args.count, args.rate_hz)
        lat = result["latency_ms"]
        rows.append(
            {
                "run": run + 1,
                "received": f"{result['received']}/{result['sent']}",
                "p50": float(np.percentile(lat, 50)),
                "p99": float(np.percentile(lat, 99)),
                "max": float(lat.max()),
            }
        )
        print(rows[-1], flush=True)
    from importlib.metadata import version

    costs = codec_costs(args.runs)

    load = os.getloadavg()
    lines = [
        "# ROS 2 wire latency: DdsTransport to DdsTransport, two processes, loopback",
        "",
        f"PoseStamped at {args.rate_hz:g} Hz, {args.count} messages per run, one-way time from",
        "the publisher's clock before `publish` to the subscriber's `receive_time_ns` (the time",
        "the node core gets), Cyclone DDS on `lo` only, the node's QoS (reliable writer; the",
        "reader is reliable since the writer is). Command:",
        "",
        "```",
        f"python experiments/benchmarks/dds_roundtrip.py --count {args.count} "
        f"--rate-hz {args.rate_hz:g} --runs {args.runs}",
        "```",
        "",
        "| run | received | p50 [ms] | p99 [ms] | max [ms] |",
        "| --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        lines.append(
            f"| {r['run']} | {r['received']} | {r['p50']:.3f} | {r['p99']:.3f} | {r['max']:.3f} |"
        )
    lines += [
        f"| median of runs | | {statistics.median(r['p50'] for r in rows):.3f} | "
        f"{statistics.median(r['p99'] for r in rows):.3f} | |",
        "",
        "## Python cost per message (median of the runs' means, 100 messages each)",
        "",
        "Encode = dict -> CDR bytes by the type's generated writer (what `publish` does before",
        "the write); decode = CDR bytes -> dict by its generated reader (what the reader does",
        "before the callback); fpe_jax/node/_cdr.py. Messages: the",
        "catalogue of tests/ros2_helpers.py (e.g. a 4-marker MarkerArray, a 10-pose Path, a",
        "50-point OpponentTrajectory).",
        "",
        "| topic | type | bytes | encode [us] | decode [us] |",
        "| --- | --- | --- | --- | --- |",
        *(
            f"| {c['topic']} | {c['type']} | {c['bytes']} | {c['encode_us']:.0f} | "
            f"{c['decode_us']:.0f} |"
            for c in costs
        ),
        "",
        f"Machine: {platform.platform()}, Python {platform.python_version()}, "
        f"{os.cpu_count()} CPUs, cyclonedds {version('cyclonedds')}; 1-minute load average "
        f"{load_start:.2f} at the start, {load[0]:.2f} at the end (a shared machine: other "
        f"processes' load shows in p99 and max). Written {datetime.date.today().isoformat()}.",
        "",
    ]
    args.out.write_text("\n".join(lines))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
