"""The node core without middleware: a fake in-memory transport, bad input between good ones."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fpe_jax.io.config import params_to_config
from fpe_jax.model._history import drive_valid
from fpe_jax.model._params import presets
from fpe_jax.node._cdr import CdrCodec
from fpe_jax.node._core import Node, NodeOptions
from fpe_jax.node._types import typestore
from fpe_jax.runner._runner import Runner
from fpe_jax.sim._sim import simulate

CODEC = CdrCodec(typestore("ros2"))


class FakeTransport:
    """ROS 2 in memory: what the node publishes, as the dicts its CDR bytes decode to."""

    flavour = "ros2"

    def __init__(self):
        self.subs, self.out = {}, {}

    def subscribe(self, topic, type_name, callback):
        self.subs[topic] = callback

    def encode(self, type_name, msg):
        return CODEC.encode(type_name, msg)

    def advertise(self, topic, type_name):
        self.out[topic] = []

        def publish(msg):
            self.out[topic].append(CODEC.decode(type_name, msg) if isinstance(msg, bytes) else msg)

        return publish

    def subscriber_count(self, topic):
        return 1 if topic in self.out else 0

    def spin(self, stop):
        pass

    def close(self):
        pass


def pose_msg(ns, x, y, frame="map"):
    return {
        "header": {"stamp": {"sec": ns // 10**9, "nanosec": ns % 10**9}, "frame_id": frame},
        "pose": {"position": {"x": x, "y": y, "z": 0.0},
                 "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 0.0}},
    }  # fmt: skip


def test_bad_input_between_good_messages_changes_nothing():
    res = simulate("oval", duration_s=6.0, seed=1)
    d = res.drive
    cfg = params_to_config(presets["default"])
    warnings = []
    t = FakeTransport()
    node = Node(t, cfg, res.centerline_xy_m, NodeOptions(input="pose", topic="/opp"),
                warn=warnings.append)  # fmt: skip
    node.start()
    cb = t.subs["/opp"]
    ps = "geometry_msgs/msg/PoseStamped"
    bad = [  # each builds a bad message from the stamp of the good one before it
        lambda ns: (pose_msg(ns + 1, math.nan, 1.0), ps),
        lambda ns: (pose_msg(ns + 1, math.inf, 1.0), ps),
        lambda ns: (pose_msg(ns + 1, 1.0, 1.0, frame="odom"), ps),
        lambda ns: (pose_msg(ns - 1, 1.0, 1.0), ps),  # stamp backwards
        lambda ns: ({"header": {}}, ps),  # malformed
        lambda ns: (pose_msg(ns + 1, 1.0, 1.0), "std_msgs/msg/String"),  # wrong type
    ]
    ref, want = Runner(cfg, res.centerline_xy_m), []
    base = 10**18
    for k, (ts, (x, y)) in enumerate(zip(d.t_s, d.xy_m)):
        ns = base + round(float(ts) * 1e9)
        cb(pose_msg(ns, float(x), float(y)), ps, 0)
        poses = ref.update((ns - base) * 1e-9, float(x), float(y), None)
        if ref.valid:
            want.append((ns, poses))
        if k and k < 40:
            cb(*bad[k % len(bad)](ns), 0)
    paths = t.out["/future_pose/path"]
    assert len(paths) == len(want)
    for m, (ns, poses) in zip(paths, want):
        assert m["header"]["stamp"] == {"sec": ns // 10**9, "nanosec": ns % 10**9}
        xy = [[p["pose"]["position"]["x"], p["pose"]["position"]["y"]] for p in m["poses"]]
        np.testing.assert_allclose(xy, poses[:, :2], atol=1e-9, rtol=0)
    # one rate-limited line per kind of problem, naming the topic
    # NaN and inf are one kind of problem: one line for both within the warning interval
    problems = ["non-finite position", "frame 'odom'", "is not after", "malformed", "type std_msgs"]
    assert len(warnings) == len(problems), warnings
    assert all(any(p in w for w in warnings) for p in problems), warnings
    assert all(w.startswith("fpe node: /opp: ") for w in warnings)
    # no prediction from too little history: the first published is the first valid row
    valid = drive_valid(d, cfg["settings"]["history"])
    assert len(want) == int(valid.sum())


def test_outputs_nobody_subscribes_to_are_not_built():
    """Per topic: nothing is built or sent while it has no subscriber; what is sent once one
    subscribes is what a node with every output subscribed sends. Several opponents: the
    per-opponent path and covariance topics count one by one."""
    res = simulate("oval", duration_s=3.0, seed=4)
    d = res.drive
    cov = [[[0.01 * (k + 1), 0.0], [0.0, 0.004]] for k in range(10)]
    cfg = params_to_config(presets["default"], uncertainty={"frame": "track", "cov_m2": cov})

    class Selective(FakeTransport):
        listened: set = set()

        def subscriber_count(self, topic):
            return int(topic in self.listened)

    every, some = FakeTransport(), Selective()
    opts = NodeOptions(input="obstacles", topic="/obst", markers_every_s=0.0)
    nodes = [Node(t, cfg, res.centerline_xy_m, opts) for t in (every, some)]
    for node in nodes:
        node.start()
    built, markers = [], nodes[1].wire.markers
    nodes[1].wire.markers = lambda *a: built.append(1) or markers(*a)
    assert nodes[0].wire.markers != nodes[1].wire.markers
    half = len(d.t_s) // 2
    for k, ts in enumerate(d.t_s):
        if k == half:
            some.listened = {"/future_pose/path/opp_2", "/future_pose/covariance/opp_7"}
        obst = [{"id": i, "s_center": 2.0 * float(ts) + 3.0 * i, "d_center": 0.1 * i,
                 "is_static": False} for i in (2, 7)]  # fmt: skip
        hdr = {"stamp": {"sec": 1 + int(ts), "nanosec": int(ts % 1 * 1e9)}, "frame_id": "map"}
        for t in (every, some):
            t.subs["/obst"]({"header": hdr, "obstacles": obst}, "f110_msgs/msg/ObstacleArray", k)
    assert not built  # no markers for /future_pose, which nobody subscribes to
    assert every.out["/future_pose"]
    assert {k: len(v) for k, v in some.out.items() if v} == {
        "/future_pose/path/opp_2": len(d.t_s) - half,
        "/future_pose/covariance/opp_7": 10 * (len(d.t_s) - half),
    }
    for topic, msgs in some.out.items():
        if msgs:
            assert msgs == every.out[topic][-len(msgs) :], topic


def test_runner_validity_equals_the_drive_rule():
    res = simulate("oval", duration_s=4.0, seed=2)
    d = res.drive
    cfg = params_to_config(presets["default"])
    r = Runner(cfg, res.centerline_xy_m)
    got = []
    for ts, (x, y), yaw in zip(d.t_s, d.xy_m, d.yaw_rad):
        r.update(float(ts), float(x), float(y), float(yaw))
        got.append(r.valid)
    want = drive_valid(d, cfg["settings"]["history"])
    assert got == want.tolist()
    assert not got[0] and any(got)


def ros2_dict(msg):
    """A log message object as a ROS 2 message dict (the fake transport's flavour)."""
    fields = getattr(msg, "__dataclass_fields__", None) or getattr(msg, "__slots__", None)
    if isinstance(msg, str | bytes | int | float) or fields is None:
        if isinstance(msg, np.ndarray):
            return msg.tolist()
        if isinstance(msg, list | tuple):
            return [ros2_dict(v) for v in msg]
        return msg
    return {k: ros2_dict(getattr(msg, k)) for k in fields if k != "__msgtype__"}


def test_tag_input_with_bad_detections_and_a_flood_of_obstacles(tmp_path):
    """The seed's layout through the core: unknown tag ids, NaN poses, an unknown camera frame
    and detections stamped before the TF buffer between good ones; the good ones predict as
    the runner does on the rows the log reader composes (the same placement code)."""
    import copy

    from fpe_jax.io.drives import load_drive
    from fpe_jax.io.logs import open_log
    from fpe_jax.sim._sim import Camera, write_simulation

    res = simulate("oval", duration_s=8.0, seed=3, camera=Camera())
    write_simulation(res, tmp_path / "sim")
    log = open_log(tmp_path / "sim" / "drive.mcap")
    cfg = params_to_config(presets["default"])
    t, warnings = FakeTransport(), []
    node = Node(t, cfg, res.centerline_xy_m, NodeOptions(input="tags", topic="/tag_detections"),
                warn=warnings.append)  # fmt: skip
    node.start()
    n_bad = 0
    for topic, msgtype, log_ns, msg in log.messages(["/tf", "/tf_static", "/tag_detections"]):
        d = ros2_dict(msg)
        t.subs[topic](d, msgtype, log_ns)
        if topic == "/tag_detections" and d["detections"]:
            n_bad += 1
            bad = copy.deepcopy(d)
            kind = n_bad % 4
            if kind == 0:
                bad["detections"][0]["id"] = [5]  # an unknown tag
            elif kind == 1:
                bad["detections"][0]["pose"]["pose"]["pose"]["position"]["x"] = math.nan
            elif kind == 2:
                bad["detections"][0]["pose"]["header"]["frame_id"] = "no_such_camera"
            else:  # before every transform of the buffer: TF extrapolation into the past
                bad["detections"][0]["pose"]["header"]["stamp"] = {"sec": 0, "nanosec": 1}
                bad["header"]["stamp"] = {"sec": 0, "nanosec": 1}
            t.subs[topic](bad, msgtype, log_ns)
    drive = load_drive(tmp_path / "sim" / "drive.mcap", pose_topic="/tag_detections")
    ref, want = Runner(cfg, res.centerline_xy_m), []
    for ts, (x, y), yaw in zip(drive.t_s, drive.xy_m, drive.yaw_rad):
        poses = ref.update(float(ts) - float(drive.t_s[0]), float(x), float(y), float(yaw))
        if ref.valid:
            want.append(poses)
    paths = t.out["/future_pose/path"]
    assert len(paths) == len(want)
    for m, poses in zip(paths, want):
        xy = [[p["pose"]["position"]["x"], p["pose"]["position"]["y"]] for p in m["poses"]]
        np.testing.assert_allclose(xy, poses[:, :2], atol=1e-6, rtol=0)
    for problem in ("unknown tag id", "non-finite", "no_such_camera", "TF"):
        assert any(problem in w for w in warnings), (problem, warnings)

    # 100 obstacles in one message: the first --max-tracks tracked, one warning
    t2, w2 = FakeTransport(), []
    opts = NodeOptions(input="obstacles", topic="/obst", max_tracks=8, drop_after_s=0.5)
    node2 = Node(t2, cfg, res.centerline_xy_m, opts, warn=w2.append)
    node2.start()
    for j in range(6):
        obst = [{"id": i, "s_center": 1.0 + 0.1 * j + i, "d_center": 0.0, "is_static": i % 2 == 0}
                for i in range(100)]  # fmt: skip
        hdr = {"stamp": {"sec": 1, "nanosec": j * 50_000_000}, "frame_id": "map"}
        t2.subs["/obst"]({"header": hdr, "obstacles": obst}, "f110_msgs/msg/ObstacleArray", j)
    assert set(node2.runners) == {str(i) for i in range(1, 16, 2)}  # moving ones only
    assert sum("moving obstacles" in w for w in w2) == 1
    # a track not updated for drop_after_s is dropped
    hdr = {"stamp": {"sec": 2, "nanosec": 0}, "frame_id": "map"}
    one = [{"id": 1, "s_center": 5.0, "d_center": 0.0, "is_static": False}]
    t2.subs["/obst"]({"header": hdr, "obstacles": one}, "f110_msgs/msg/ObstacleArray", 10**9)
    assert sorted(node2.runners) == ["1"]


def test_missing_files_and_mismatched_waypoints_stop_at_start(tmp_path, capsys):
    import argparse

    from fpe_jax.cli import main
    from fpe_jax.errors import InputError
    from fpe_jax.io.config import write_config
    from fpe_jax.io.writers import write_xy_csv
    from fpe_jax.node import _cli

    assert main(["node", "--ros1", "--config", str(tmp_path / "no.json"), "--waypoints", "x"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no.json: does not exist" in err[0]
    # --params-file: the exported YAML gives the config and the waypoints beside it
    res = simulate("oval", duration_s=2.0, seed=1)
    write_xy_csv(tmp_path / "wp.csv", res.centerline_xy_m)
    write_config(tmp_path / "cfg.json", params_to_config(presets["default"]))
    argv = ["export", str(tmp_path / "cfg.json"), "--format", "ros2", "--out"]
    assert main([*argv, str(tmp_path / "p.yaml"), "--waypoints", str(tmp_path / "wp.csv")]) == 0
    parser = argparse.ArgumentParser()
    _cli.add_parser(parser.add_subparsers())
    args = parser.parse_args(["node", "--ros2", "--params-file", str(tmp_path / "p.yaml")])
    cfg, xy, opts = _cli.options_from_args(args, FakeTransport())
    assert cfg["params"] == params_to_config(presets["default"])["params"]
    assert opts.input == "tags" and opts.topic == "/tag_detections"
    np.testing.assert_allclose(xy, res.centerline_xy_m, atol=1e-6)
    # no waypoints at all: refused
    args = parser.parse_args(["node", "--ros2", "--config", str(tmp_path / "cfg.json")])
    with pytest.raises(InputError, match="no waypoints"):
        _cli.options_from_args(args, FakeTransport())


def test_the_node_imports_no_jax():
    import subprocess
    import sys

    from helpers import CHECK_NO_JAX, NO_JAX

    code = NO_JAX + "import fpe_jax.node, fpe_jax.node._cli, fpe_jax.node._core\n" + CHECK_NO_JAX
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr


def test_adapting_node_predicts_as_the_adapting_runner_and_publishes_what_it_learned():
    """`fpe node --adapt` without a config: each opponent's runner is an AdaptiveRunner started
    from the waypoints alone; its predictions equal a reference AdaptiveRunner fed the same
    observations, and the OpponentTrajectory carries the line it learned."""
    from fpe_jax.runner._adapt import AdaptiveRunner

    res = simulate("oval", duration_s=30.0, seed=2)
    d = res.drive
    t = FakeTransport()
    node = Node(t, None, res.centerline_xy_m,
                NodeOptions(input="pose", topic="/opp", adapt=True, delay_s=0.1))  # fmt: skip
    node.start()
    ref, want = AdaptiveRunner(None, res.centerline_xy_m, delay_s=0.1), []
    base = 10**18
    for ts, (x, y) in zip(d.t_s, d.xy_m):
        ns = base + round(float(ts) * 1e9)
        t.subs["/opp"](pose_msg(ns, float(x), float(y)), "geometry_msgs/msg/PoseStamped", 0)
        poses = ref.update((ns - base) * 1e-9, float(x), float(y), None)
        if ref.valid:
            want.append(poses)
    paths = t.out["/future_pose/path"]
    assert len(paths) == len(want) > 0
    for m, poses in zip(paths, want):
        xy = [[p["pose"]["position"]["x"], p["pose"]["position"]["y"]] for p in m["poses"]]
        np.testing.assert_allclose(xy, poses[:, :2], atol=1e-9, rtol=0)
    assert ref.samples > 0 and node.runners["0"].samples == ref.samples
    learned = ref.state_config()["params"]["line_offset_m"]
    got = [w["d_m"] for w in node.trajectory_message()["oppwpnts"]]
    np.testing.assert_allclose(got, learned, atol=1e-12, rtol=0)


def test_calibrating_node_publishes_each_opponents_calibrated_ellipses():
    """`fpe node --adapt --config C --calibrate-ellipses`: each published covariance is the car's
    AdaptiveRunner(calibrate=True)'s track-frame ellipses turned by the path heading at each
    step, as a reference runner fed the same observations has them; they grow off the config's
    as the errors are realised."""
    from fpe_jax.runner._adapt import AdaptiveRunner, start_config

    res = simulate("oval", duration_s=20.0, seed=2)
    d, wp = res.drive, res.centerline_xy_m
    cfg = start_config(None, wp, delay_s=0.1)
    base = [[[0.0004 * (k + 1), 0.0], [0.0, 0.0001 * (k + 1)]] for k in range(10)]
    cfg["uncertainty"] = {"frame": "track", "cov_m2": base}
    t = FakeTransport()
    opts = NodeOptions(input="pose", topic="/opp", adapt=True, calibrate=True)
    node = Node(t, cfg, wp, opts)
    node.start()
    ref, want = AdaptiveRunner(cfg, wp, calibrate=True), []
    t0 = 10**18
    for ts, (x, y) in zip(d.t_s, d.xy_m):
        ns = t0 + round(float(ts) * 1e9)
        t.subs["/opp"](pose_msg(ns, float(x), float(y)), "geometry_msgs/msg/PoseStamped", 0)
        poses = ref.update((ns - t0) * 1e-9, float(x), float(y), None)
        if ref.valid:
            h = [ref.path.heading_at(s) for s in ref.path.project_chain(poses[:, :2], ref._s_m)]
            c, sn = np.cos(h), np.sin(h)
            rot = np.stack([np.stack([c, -sn], -1), np.stack([sn, c], -1)], -2)
            want.append(rot @ ref.covariance() @ np.swapaxes(rot, -1, -2))
    got = [m["pose"]["covariance"] for m in t.out["/future_pose/covariance"]]
    got = np.array([[[c[0], c[1]], [c[6], c[7]]] for c in got]).reshape(-1, 10, 2, 2)
    assert len(got) == len(want) > 0
    np.testing.assert_allclose(got, np.array(want), rtol=1e-9, atol=1e-15)
    assert ref.calibration.errors > 100
    assert node.runners["0"].calibration.errors == ref.calibration.errors
    # the made-up ellipses were too small for this drive: the last ones are larger
    assert np.trace(got[-1][9]) > 2 * np.trace(np.array(base[9]))


def _pose_paths(cfg, waypoints_xy_m, stamps_ns, xy_m):
    """Feed PoseStamped messages to a node: (its published paths, its warnings)."""
    t, warnings = FakeTransport(), []
    node = Node(t, cfg, waypoints_xy_m, NodeOptions(input="pose", topic="/opp"),
                warn=warnings.append)  # fmt: skip
    node.start()
    for ns, (x, y) in zip(stamps_ns, xy_m.tolist()):
        t.subs["/opp"](pose_msg(ns, x, y), "geometry_msgs/msg/PoseStamped", 0)
    return t.out["/future_pose/path"], warnings


def test_a_car_off_the_track_is_reported_and_not_predicted():
    """The runners' off-track check (`fpe run`'s): poses 100 m from the waypoints (waypoints of
    another map frame) publish nothing and warn, rate-limited; a car that leaves the track is
    predicted as the runner does until it leaves, then warned about; on the track, no warning."""
    res = simulate("oval", duration_s=10.0, seed=1)
    d = res.drive
    cfg = params_to_config(presets["default"])
    base = 10**18
    ns = [base + round(float(ts) * 1e9) for ts in d.t_s]
    far = d.xy_m + [100.0, 0.0]
    paths, warnings = _pose_paths(cfg, res.centerline_xy_m, ns, far)
    assert paths == []
    assert 1 <= len(warnings) <= 3, warnings  # one per 5 s (the node's warning interval)
    assert all("from the track" in w and w.startswith("fpe node: /opp: ") for w in warnings)

    leaving = d.xy_m.copy()
    leaving[60:] += [100.0, 0.0]
    paths, warnings = _pose_paths(cfg, res.centerline_xy_m, ns, leaving)
    ref, want = Runner(cfg, res.centerline_xy_m), []
    for k in range(60):
        poses = ref.update((ns[k] - base) * 1e-9, *leaving[k].tolist(), None)
        if ref.valid:
            want.append(poses)
    assert len(paths) == len(want) > 0
    for m, poses in zip(paths, want):
        xy = [[p["pose"]["position"]["x"], p["pose"]["position"]["y"]] for p in m["poses"]]
        np.testing.assert_allclose(xy, poses[:, :2], atol=1e-9, rtol=0)
    assert len(warnings) == 1 and "from the track" in warnings[0], warnings

    paths, warnings = _pose_paths(cfg, res.centerline_xy_m, ns, d.xy_m)
    assert len(paths) > 0 and warnings == []


def test_tag_detections_across_a_tf_dropout_are_dropped_with_a_warning(tmp_path):
    """A 3 s dropout of the car's own /tf: the detections inside it are not composed across the
    gap (as `fpe convert --drop-outside-tf`); the others predict as the runner does."""
    from fpe_jax.io.drives import load_drive
    from fpe_jax.io.logs import open_log
    from fpe_jax.sim._sim import Camera, write_simulation

    res = simulate("oval", duration_s=10.0, seed=3, camera=Camera())
    write_simulation(res, tmp_path / "sim")
    log = open_log(tmp_path / "sim" / "drive.mcap")
    cfg = params_to_config(presets["default"])
    t, warnings = FakeTransport(), []
    node = Node(t, cfg, res.centerline_xy_m, NodeOptions(input="tags", topic="/tag_detections"),
                warn=warnings.append)  # fmt: skip
    node.start()
    gap_ns = (3 * 10**9, 6 * 10**9)  # /tf transforms strictly inside are lost
    for topic, msgtype, log_ns, msg in log.messages(["/tf", "/tf_static", "/tag_detections"]):
        if topic == "/tf" and gap_ns[0] < log_ns < gap_ns[1]:
            continue
        t.subs[topic](ros2_dict(msg), msgtype, log_ns)
    drive = load_drive(tmp_path / "sim" / "drive.mcap", pose_topic="/tag_detections")
    t0_s = float(drive.t_s[0])
    keep = ~((drive.t_s > gap_ns[0] * 1e-9) & (drive.t_s < gap_ns[1] * 1e-9))
    assert 0 < np.sum(~keep) < len(keep)
    ref, want = Runner(cfg, res.centerline_xy_m), []
    for ts, (x, y), yaw in zip(drive.t_s[keep], drive.xy_m[keep], drive.yaw_rad[keep]):
        poses = ref.update(float(ts) - t0_s, float(x), float(y), float(yaw))
        if ref.valid:
            want.append(poses)
    paths = t.out["/future_pose/path"]
    assert len(paths) == len(want)
    for m, poses in zip(paths, want):
        xy = [[p["pose"]["position"]["x"], p["pose"]["position"]["y"]] for p in m["poses"]]
        np.testing.assert_allclose(xy, poses[:, :2], atol=1e-6, rtol=0)
    assert warnings and all("TF" in w for w in warnings), warnings
    assert len(warnings) <= 4, warnings


def test_an_obstacle_off_the_track_is_reported_and_not_predicted():
    """Obstacle input: one opponent 50 m beside the track (d) gets a warning naming it and no
    prediction; the one on the track beside it is predicted as before."""
    res = simulate("oval", duration_s=2.0, seed=1)
    cfg = params_to_config(presets["default"])
    t, warnings = FakeTransport(), []
    node = Node(t, cfg, res.centerline_xy_m, NodeOptions(input="obstacles", topic="/obst"),
                warn=warnings.append)  # fmt: skip
    node.start()
    for j in range(30):
        obst = [{"id": car, "s_center": 1.0 + 0.2 * j, "d_center": d, "is_static": False}
                for car, d in ((1, 0.0), (7, 50.0))]  # fmt: skip
        hdr = {"stamp": {"sec": 1, "nanosec": j * 25_000_000}, "frame_id": "map"}
        t.subs["/obst"]({"header": hdr, "obstacles": obst}, "f110_msgs/msg/ObstacleArray", j)
    assert t.out["/future_pose/path/opp_1"] and not t.out.get("/future_pose/path/opp_7")
    predicted = {o["id"] for m in t.out["/future_pose/obstacles"] for o in m["obstacles"]}
    assert predicted == {1}
    assert len(warnings) == 1 and "obstacle 7: observation" in warnings[0], warnings
    assert "m from the track" in warnings[0]


@pytest.mark.parametrize(
    "flags",
    [
        ["--drop-after", "inf"],
        ["--drop-after", "nan"],
        ["--tf-wait", "inf"],
        ["--max-tracks", "100000"],
        ["--max-tracks", "0"],
        ["--tag-id", "-1"],
        ["--markers-every", "inf"],
        ["--trajectory-every", "nan"],
    ],
)
def test_node_settings_out_of_range_are_refused_at_start(tmp_path, flags):
    import argparse

    from fpe_jax.errors import InputError
    from fpe_jax.io.config import write_config
    from fpe_jax.io.writers import write_xy_csv
    from fpe_jax.node import _cli

    res = simulate("oval", duration_s=2.0, seed=1)
    write_xy_csv(tmp_path / "wp.csv", res.centerline_xy_m)
    write_config(tmp_path / "cfg.json", params_to_config(presets["default"]))
    parser = argparse.ArgumentParser()
    _cli.add_parser(parser.add_subparsers())
    base = ["node", "--ros2", "--config", str(tmp_path / "cfg.json")]
    args = parser.parse_args([*base, "--waypoints", str(tmp_path / "wp.csv"), *flags])
    with pytest.raises(InputError, match=flags[0]):
        _cli.options_from_args(args, FakeTransport())


def test_trajectory_goes_out_when_it_changes_or_a_subscriber_joins():
    """The OpponentTrajectory is looked at every --trajectory-every (here every message): a
    fixed line goes out once, again when a subscriber joins (not when one leaves), and again
    when the line changes."""
    from fpe_jax.geometry._path import waypoints_sha256
    from fpe_jax.model._params import Params, Settings

    res = simulate("oval", duration_s=5.0, seed=6)
    d, n = res.drive, 24
    params = Params.create(
        Settings(model="line"), weights=1.0, line_offset_m=0.1 * np.sin(np.arange(n) * 0.4),
        line_speed_mps=np.full(n, 4.5), line_coverage=np.ones(n),
    )  # fmt: skip
    line = {"waypoints_sha256": waypoints_sha256(res.centerline_xy_m), "waypoints": "wp.csv"}
    cfg = params_to_config(params, line=line)

    class Counted(FakeTransport):
        subscribers = 1

        def subscriber_count(self, topic):
            return self.subscribers

    t = Counted()
    opts = NodeOptions(input="pose", topic="/opp", trajectory_every_s=0.0)
    node = Node(t, cfg, res.centerline_xy_m, opts)
    node.start()
    sent = t.out["/opponent_trajectory"]

    def feed(rows):
        for k in rows:
            ns = 10**9 + round(float(d.t_s[k]) * 1e9)
            x, y = (float(v) for v in d.xy_m[k])
            t.subs["/opp"](pose_msg(ns, x, y), "geometry_msgs/msg/PoseStamped", k)

    feed(range(0, 20))
    assert len(sent) == 1  # at start, then unchanged
    t.subscribers = 2
    feed(range(20, 25))
    assert len(sent) == 2  # a subscriber joined
    t.subscribers = 1
    feed(range(25, 30))
    t.subscribers = 2
    feed(range(30, 35))
    assert len(sent) == 3  # one left, one joined: the newcomer gets it
    node.config["params"]["line_offset_m"] = list(-0.2 * np.ones(n))
    feed(range(35, 40))
    assert len(sent) == 4  # the line changed
    assert [w["d_m"] for w in sent[-1]["oppwpnts"]] == [-0.2] * n
    np.testing.assert_allclose(
        [w["d_m"] for w in sent[0]["oppwpnts"]], 0.1 * np.sin(np.arange(n) * 0.4)
    )


def test_calibrate_ellipses_needs_adapt_and_a_config_with_ellipses(tmp_path):
    import argparse

    from fpe_jax.errors import InputError
    from fpe_jax.io.config import write_config
    from fpe_jax.node._cli import add_parser, options_from_args
    from fpe_jax.runner._adapt import start_config
    from fpe_jax.runner._runner import load_waypoints_xy
    from fpe_jax.sim._sim import write_simulation

    write_simulation(simulate("oval", duration_s=3.0, seed=2), tmp_path / "a")
    wp = str(tmp_path / "a" / "waypoints.csv")

    cfg = start_config(None, load_waypoints_xy(wp))
    write_config(tmp_path / "plain.json", cfg)
    unc = {"frame": "track", "cov_m2": [np.eye(2).tolist()] * 10}
    write_config(tmp_path / "ellipses.json", cfg | {"uncertainty": unc})
    parser = argparse.ArgumentParser()
    add_parser(parser.add_subparsers())

    def options(*flags):
        args = parser.parse_args(
            ["node", "--ros2", "--waypoints", wp, "--calibrate-ellipses", *flags]
        )
        return options_from_args(args, None)[2]

    for flags in [["--adapt"], ["--config", str(tmp_path / "ellipses.json")],
                  ["--adapt", "--config", str(tmp_path / "plain.json")]]:  # fmt: skip
        with pytest.raises(InputError, match="--calibrate-ellipses: given without --adapt or"):
            options(*flags)
    opts = options("--adapt", "--config", str(tmp_path / "ellipses.json"))
    assert opts.adapt and opts.calibrate
