"""Latency of `fpe node` on ROS 1 (a roscore on 127.0.0.1) and ROS 2 (Cyclone DDS on loopback).

For 1 opponent (PoseStamped input) and 4 opponents (one f110_msgs/ObstacleArray per tick) at
40 Hz it measures
- the node's own update time per opponent (runner update + covariance, inside the node),
- end to end: from publishing an observation to receiving its nav_msgs/Path in this process,
- the node process's CPU time per input message,
p50 and p99 of each over `--seconds` of a simulated drive, for each case of who listens:
`path` (only this process, to the paths: the node builds no other output), `all` (a second
process subscribes to every other output too: markers, per-step covariances, predicted
obstacles, trajectory) and `all-no-markers` (the same with the node run with --no-markers).
Writes node_latency.md beside this file (or --out).

    .venv/bin/python experiments/benchmarks/node_latency.py [--seconds 10] [--runs 3]
        [--middleware both] [--cases path,all,all-no-markers] [--out FILE]
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
from ros2_helpers import LOOPBACK_URI  # noqa: E402

from fpe_jax.io.config import params_to_config, write_config  # noqa: E402
from fpe_jax.io.writers import write_xy_csv  # noqa: E402
from fpe_jax.model._params import presets  # noqa: E402
from fpe_jax.node import time_dict  # noqa: E402
from fpe_jax.runner._runner import RunnerPath  # noqa: E402
from fpe_jax.sim._sim import simulate  # noqa: E402

RATE_HZ = 40.0
H = 10
CASES = {  # who listens: (a sink process subscribes to every output but the paths, node flags)
    "path": (False, []),
    "all": (True, []),
    "all-no-markers": (True, ["--no-markers"]),
}
NODE_ARGS: list[str] = []  # the current case's `fpe node` flags
LISTEN_ALL = False  # whether the current case's sink subscribes to every output but the paths
COV = [[[0.01 * (k + 1), 0.002], [0.002, 0.004 * (k + 1)]] for k in range(H)]


def _setup(n_opp: int, seconds: float, tmp: Path):
    """(node arguments, [(stamp [ns], message dict without its header)], output path topics,
    {every other output topic: its type})."""
    res = simulate("oval", duration_s=seconds + 10.0, seed=0)
    truth_xy = np.column_stack([res.drive.truth_xy_m[:, 0], res.drive.truth_xy_m[:, 1]])
    write_xy_csv(tmp / "wp.csv", res.centerline_xy_m, force=True)
    cfg = params_to_config(presets["default"], uncertainty={"frame": "track", "cov_m2": COV})
    write_config(tmp / "cfg.json", cfg, force=True)
    path = RunnerPath(res.centerline_xy_m)
    args = ["--config", str(tmp / "cfg.json"), "--waypoints", str(tmp / "wp.csv"), *NODE_ARGS]
    others = {
        "/future_pose": "visualization_msgs/msg/MarkerArray",
        "/future_pose/obstacles": "f110_msgs/msg/ObstacleArray",
        "/opponent_trajectory": "f110_msgs/msg/OpponentTrajectory",
    }
    cov_type = "geometry_msgs/msg/PoseWithCovarianceStamped"
    if n_opp == 1:
        args += ["--pose-topic", "/opp/pose"]
        topics = ["/future_pose/path"]
        others["/future_pose/covariance"] = cov_type
    else:
        args += ["--obstacles-topic", "/perception/obstacles"]
        topics = [f"/future_pose/path/opp_{i}" for i in range(n_opp)]
        others |= {f"/future_pose/covariance/opp_{i}": cov_type for i in range(n_opp)}
    t0_ns = 10**18
    step = 50.0 / RATE_HZ  # truth rows are at 50 Hz
    frames = []
    for j in range(int(seconds * RATE_HZ)):
        ns = t0_ns + int(j * 1e9 / RATE_HZ)
        if n_opp == 1:
            x, y = truth_xy[int(j * step)]
            msg = {"pose": {"position": {"x": float(x), "y": float(y)}, "orientation": {"w": 1.0}}}
        else:
            obst = []
            for k in range(n_opp):
                x, y = truth_xy[int(j * step) + 100 * k]
                s = path.project(float(x), float(y))
                cx, cy = path.point_at(s)
                h = path.heading_at(s)
                d = (y - cy) * np.cos(h) - (x - cx) * np.sin(h)
                obst.append({"id": k, "s_center": s, "d_center": float(d)})
            msg = {"obstacles": obst}
        frames.append((ns, msg))
    return args, frames, topics, others


def _cpu_s(pid: int) -> float:
    """CPU time [s] (user + system, all threads) a running process has used so far."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _play(frames, flavour: str, publish, sent: dict, lock) -> None:
    """Publish the frames at RATE_HZ, noting each one's send time [ns] by its stamp."""
    next_t = time.perf_counter()
    for ns, body in frames:
        msg = {"header": {"stamp": time_dict(flavour, ns), "frame_id": "map"}, **body}
        with lock:
            sent[ns] = time.time_ns()
        publish(msg)
        next_t += 1.0 / RATE_HZ
        time.sleep(max(0.0, next_t - time.perf_counter()))


def _sink(flavour: str, others: dict, env: dict) -> subprocess.Popen | None:
    """Listening `all`: a process subscribed to every output but the paths (it takes them
    undecoded), until SIGINT; None listening `path`."""
    if not LISTEN_ALL:
        return None
    spec = json.dumps({"flavour": flavour, "topics": others})
    return subprocess.Popen(
        [sys.executable, __file__, "--sink", spec], env=env, cwd=ROOT, stdout=subprocess.PIPE
    )


def _wait_for_sink(sink: subprocess.Popen | None) -> None:
    """Give the sink time to connect to the node's outputs (the per-opponent ones appear with
    each opponent's first observation, before its first valid prediction)."""
    if sink is not None:
        time.sleep(2.0)


def _stop(sink: subprocess.Popen | None) -> int:
    """Stop the sink; the number of messages it received (0 without one)."""
    if sink is None:
        return 0
    sink.send_signal(2)
    out, _ = sink.communicate(timeout=30)
    return sum(json.loads(out.splitlines()[-1]).values())


def run_sink(spec: str) -> None:
    """The listening-`all` subscriber process: counts what it receives, prints it at SIGINT."""
    import signal

    spec = json.loads(spec)
    counts = dict.fromkeys(spec["topics"], 0)
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())

    def counter(topic):
        def got(*_):
            counts[topic] += 1

        return got

    if spec["flavour"] == "ros1":
        from fpe_jax.node import _ros1 as r1

        r1.rospy.init_node("fpe_bench_sink", anonymous=True, disable_signals=True)
        subs = [r1.rospy.Subscriber(t, r1.rospy.AnyMsg, counter(t), tcp_nodelay=True)
                for t in spec["topics"]]  # fmt: skip
        stop.wait()
        for sub in subs:
            sub.unregister()
        r1.rospy.signal_shutdown("done")
    else:  # as on ROS 1 the samples are taken undecoded: a consumer's cost is not the node's
        from cyclonedds._clayer import ddspy_take
        from cyclonedds.core import (
            InstanceState,
            Policy,
            Qos,
            ReadCondition,
            SampleState,
            ViewState,
            WaitSet,
        )
        from cyclonedds.domain import DomainParticipant
        from cyclonedds.sub import DataReader
        from cyclonedds.topic import Topic
        from cyclonedds.util import duration

        from fpe_jax.node._dds import IdlCodec, dds_topic_name, type_hash_user_data
        from fpe_jax.node._types import typestore

        store = typestore("ros2")
        codec, dp = IdlCodec(store), DomainParticipant(int(os.environ["ROS_DOMAIN_ID"]))
        waitset, readers = WaitSet(dp), {}
        mask = SampleState.Any | ViewState.Any | InstanceState.Any
        for t, type_name in spec["topics"].items():
            qos = Qos(Policy.Reliability.Reliable(duration(milliseconds=100)),
                      Policy.Durability.Volatile, Policy.History.KeepLast(10),
                      Policy.Userdata(type_hash_user_data(store, type_name)))  # fmt: skip
            topic = Topic(dp, dds_topic_name(t), codec.idl_class(type_name))
            readers[t] = DataReader(dp, topic, qos=qos)
            waitset.attach(ReadCondition(readers[t], mask))
        while not stop.is_set():
            waitset.wait(duration(milliseconds=50))
            for t, reader in readers.items():
                while taken := ddspy_take(reader._ref, mask, 64):
                    counts[t] += sum(info.valid_data for _, info in taken)
    print(json.dumps(counts), flush=True)


def _start(flavour: str, args: list, stats: Path, env: dict) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "fpe_jax.cli", "node", f"--{flavour}", *args, "--stats", str(stats)],
        env=env,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )


def _summary(
    n_opp: int, n: int, stats: Path, e2e: list, others_received: int, cpu_s: float
) -> dict:
    upd = np.array(json.loads(stats.read_text())["update_ns"], dtype=np.float64) * 1e-6
    e = np.array(e2e, dtype=np.float64) * 1e-6
    return {
        "opponents": n_opp,
        "observations": n * n_opp,
        "predictions_received": len(e),
        "others_received": others_received,
        "node_cpu_ms": cpu_s / n * 1e3,
        "update_p50_ms": float(np.percentile(upd, 50)),
        "update_p99_ms": float(np.percentile(upd, 99)),
        "e2e_p50_ms": float(np.percentile(e, 50)),
        "e2e_p99_ms": float(np.percentile(e, 99)),
    }


def run_ros1(n_opp: int, seconds: float, tmp: Path, env: dict, r1) -> dict:
    args, frames, topics, others = _setup(n_opp, seconds, tmp)
    stats = tmp / f"stats_ros1_{n_opp}.json"
    in_topic, in_type = (
        ("/opp/pose", "geometry_msgs/PoseStamped")
        if n_opp == 1
        else ("/perception/obstacles", "f110_msgs/ObstacleArray")
    )
    cls = r1.message_class(in_type)
    pub = r1.rospy.Publisher(in_topic, cls, queue_size=100, tcp_nodelay=True)
    sent: dict[int, int] = {}
    e2e: list[int] = []
    lock = threading.Lock()

    def got(m):
        now = time.time_ns()
        ns = m.header.stamp.secs * 10**9 + m.header.stamp.nsecs
        with lock:
            if ns in sent:
                e2e.append(now - sent[ns])

    sink = _sink("ros1", others, env)
    proc = _start("ros1", args, stats, env)
    path_cls = r1.message_class("nav_msgs/Path")
    subs = [
        r1.rospy.Subscriber(t, path_cls, got, queue_size=1000, tcp_nodelay=True) for t in topics
    ]
    deadline = time.monotonic() + 60
    while pub.get_num_connections() == 0 and time.monotonic() < deadline:
        time.sleep(0.05)
    _wait_for_sink(sink)
    cpu_s = _cpu_s(proc.pid)
    _play(frames, "ros1", lambda msg: pub.publish(r1.from_dict(cls, msg)), sent, lock)
    time.sleep(1.0)
    cpu_s = _cpu_s(proc.pid) - cpu_s
    proc.send_signal(2)
    proc.communicate(timeout=30)
    others_received = _stop(sink)
    for s in subs:
        s.unregister()
    pub.unregister()
    return _summary(n_opp, len(frames), stats, e2e, others_received, cpu_s)


def run_ros2(n_opp: int, seconds: float, tmp: Path, env: dict) -> dict:
    """The same over DDS: this process publishes and receives with DdsTransport."""
    from fpe_jax.node._dds import DdsTransport
    from fpe_jax.node._types import typestore

    args, frames, topics, others = _setup(n_opp, seconds, tmp)
    stats = tmp / f"stats_ros2_{n_opp}.json"
    in_topic, in_type = (
        ("/opp/pose", "geometry_msgs/msg/PoseStamped")
        if n_opp == 1
        else ("/perception/obstacles", "f110_msgs/msg/ObstacleArray")
    )
    sent: dict[int, int] = {}
    e2e: list[int] = []
    lock = threading.Lock()

    def got(msg, type_name, receive_ns):
        t = msg["header"]["stamp"]
        ns = t["sec"] * 10**9 + t["nanosec"]
        with lock:
            if ns in sent:
                e2e.append(receive_ns - sent[ns])

    with DdsTransport(typestore("ros2"), node_name="fpe_bench_player") as player:
        publish = player.advertise(in_topic, in_type)
        for t in topics:
            player.subscribe(t, "nav_msgs/msg/Path", got)
        stop = threading.Event()
        spinner = threading.Thread(target=player.spin, args=(stop,))
        spinner.start()
        sink = _sink("ros2", others, env)
        proc = _start("ros2", args, stats, env)
        try:
            deadline = time.monotonic() + 60
            while player.subscriber_count(in_topic) == 0 and time.monotonic() < deadline:
                time.sleep(0.05)
            _wait_for_sink(sink)
            cpu_s = _cpu_s(proc.pid)
            _play(frames, "ros2", publish, sent, lock)
            time.sleep(1.0)
            cpu_s = _cpu_s(proc.pid) - cpu_s
        finally:
            proc.send_signal(2)
            proc.communicate(timeout=30)
            others_received = _stop(sink)
            stop.set()
            spinner.join(5.0)
    return _summary(n_opp, len(frames), stats, e2e, others_received, cpu_s)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--middleware", choices=["ros1", "ros2", "both"], default="both")
    ap.add_argument("--runs", type=int, default=3, help="runs of each case; medians reported")
    ap.add_argument(
        "--cases",
        default=",".join(CASES),
        help=f"who listens, comma-separated among {', '.join(CASES)} (default: all three)",
    )
    ap.add_argument("--out", type=Path, default=HERE / "node_latency.md",
                    help="the table file (default: node_latency.md here)")  # fmt: skip
    ap.add_argument("--sink", help=argparse.SUPPRESS)  # the listening-`all` subscriber process
    args = ap.parse_args()
    if args.sink:
        run_sink(args.sink)
        return
    cases = args.cases.split(",")
    if not cases or any(c not in CASES for c in cases):
        ap.error(f"--cases {args.cases}: expected names among {', '.join(CASES)}")
    warnings.simplefilter("ignore", DeprecationWarning)
    load_start = os.getloadavg()
    start = time.monotonic()
    rows = []
    with tempfile.TemporaryDirectory() as d:
        if args.middleware in ("ros1", "both"):
            with roscore(Path(d)) as env:
                saved = dict(os.environ)
                os.environ.update(env)
                from fpe_jax.node import _ros1 as r1

                r1.rospy.init_node("fpe_bench_player", anonymous=True, disable_signals=True)
                for case in cases:
                    _case(case)
                    for n_opp in (1, 4):
                        for _ in range(args.runs):
                            row = run_ros1(n_opp, args.seconds, Path(d), env, r1)
                            rows.append(("ros1", case, row))
                            print(json.dumps(rows[-1]), flush=True)
                r1.rospy.signal_shutdown("done")
                os.environ.clear()
                os.environ.update(saved)
        if args.middleware in ("ros2", "both"):
            # Cyclone DDS on loopback, in a domain of this run alone
            os.environ["CYCLONEDDS_URI"] = LOOPBACK_URI
            os.environ["ROS_DOMAIN_ID"] = str(1 + os.getpid() % 200)
            for case in cases:
                _case(case)
                for n_opp in (1, 4):
                    for _ in range(args.runs):
                        row = run_ros2(n_opp, args.seconds, Path(d), dict(os.environ))
                        rows.append(("ros2", case, row))
                        print(json.dumps(rows[-1]), flush=True)
    load_end = os.getloadavg()
    command = (
        f"`.venv/bin/python experiments/benchmarks/node_latency.py --seconds {args.seconds:g} "
        f"--runs {args.runs} --middleware {args.middleware} --cases {','.join(cases)}`"
    )
    lines = [
        "# `fpe node` latency (loopback)",
        "",
        f"Command: {command} ({(time.monotonic() - start) / 60:.0f} minutes); {RATE_HZ:g} Hz "
        "observations of a simulated drive, default preset with a per-step covariance (all "
        "outputs on, the markers of each opponent at most every 0.1 s). Own update: runner "
        "update + covariance per opponent, inside the node. End to end: publishing an "
        "observation to receiving its nav_msgs/Path in the publishing process (ROS 1: roscore "
        "on 127.0.0.1; ROS 2: Cyclone DDS on the loopback interface). Listening `path`: only "
        "the publishing process subscribes (to the paths), and the node builds no output nobody "
        "subscribes to; `all`: a second process subscribes to every other output too (markers, "
        "per-step covariances, predicted obstacles, trajectory), so the node builds and sends "
        "them all; `all-no-markers`: the same, the node run with --no-markers. Node CPU: the "
        "node process's CPU time (user + system, all threads) while the drive plays, per input "
        "message (one observation of each opponent); it depends little on what else the "
        "machine runs, where the latencies' tails do. "
        f"Each value: the median over {args.runs} runs.",
        "",
        "| middleware | listening | opponents | observations | paths received (fewest) "
        "| other outputs received (fewest) | node CPU per input message [ms] "
        "| own update p50 / p99 [ms] | end to end p50 / p99 [ms] |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    keys = sorted({(mw, case, r["opponents"]) for mw, case, r in rows},
                  key=lambda k: (k[0], cases.index(k[1]), k[2]))  # fmt: skip
    for mw, case, n_opp in keys:
        runs = [r for m, c, r in rows if (m, c, r["opponents"]) == (mw, case, n_opp)]
        r = {k: float(np.median([x[k] for x in runs])) for k in runs[0]}
        lines.append(
            f"| {mw} | {case} | {n_opp} | {runs[0]['observations']} | "
            f"{min(x['predictions_received'] for x in runs)} | "
            f"{min(x['others_received'] for x in runs)} | {r['node_cpu_ms']:.2f} | "
            f"{r['update_p50_ms']:.3f} / {r['update_p99_ms']:.3f} | "
            f"{r['e2e_p50_ms']:.2f} / {r['e2e_p99_ms']:.2f} |"
        )
    lines += [
        "",
        "Load average of the machine (1, 5, 15 min) at the start: "
        + ", ".join(f"{v:.2f}" for v in load_start)
        + "; at the end: "
        + ", ".join(f"{v:.2f}" for v in load_end)
        + " (2 cores).",
    ]
    args.out.write_text("\n".join(lines) + "\n")


def _case(name: str) -> None:
    global LISTEN_ALL
    LISTEN_ALL, flags = CASES[name]
    NODE_ARGS[:] = flags


if __name__ == "__main__":
    main()
