"""`fpe node --ros1` against a real roscore on 127.0.0.1: a simulated drive played into topics at
40 Hz, every published prediction compared with `fpe predict` / the runner on the same data."""

from __future__ import annotations

import json
import os
import subprocess
import threading
import time
import warnings

import node_helpers
import numpy as np
import pytest
from node_helpers import (
    COV,
    OPPONENT_IDS,
    RATE_HZ,
    H,
    make_drive,
    msg_dict,
    obstacle_frames,
    runner_predictions,
    stop_node,
    wait_for,
)
from ros1_helpers import need_ros1, node_connections, roscore

from fpe_jax.io.logs import open_log
from fpe_jax.runner._runner import Runner, load_waypoints_xy

# rospy (Debian's) calls threading APIs Python 3.11 deprecates, from its own threads
# and leaves its connection sockets to the garbage collector
pytestmark = [
    pytest.mark.filterwarnings("ignore::DeprecationWarning"),
    pytest.mark.filterwarnings("ignore::ResourceWarning"),
    pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning"),
]


@pytest.fixture(scope="module")
def ros(tmp_path_factory):
    """(environment, rospy) with a roscore running and this process a ROS node (the player)."""
    need_ros1()
    tmp = tmp_path_factory.mktemp("ros")
    with roscore(tmp) as env:
        saved = {k: os.environ.get(k) for k in env}
        os.environ.update(env)
        from fpe_jax.node import _ros1

        _ros1.rospy.init_node("fpe_test_player", anonymous=True, disable_signals=True)
        try:
            yield env, _ros1
        finally:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                _ros1.rospy.signal_shutdown("test done")
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    """An 8 s simulated drive in the seed's layout, a config with per-step covariance, and
    `fpe predict`'s CSV of it."""
    tmp = tmp_path_factory.mktemp("drive")
    return tmp, make_drive(tmp)


def start_node(env, *args) -> subprocess.Popen:
    return node_helpers.start_node("ros1", env, *args)


class Collector:
    def __init__(self, r1, topic, type_name):
        self.msgs, self.lock = [], threading.Lock()
        cls = r1.message_class(type_name)
        self.sub = r1.rospy.Subscriber(topic, cls, self.add, queue_size=1000, tcp_nodelay=True)

    def add(self, m):
        with self.lock:
            self.msgs.append(m)


def wait_connected(pubs, subs, proc, timeout=60.0):
    """Until this process's publishers `pubs` hold a connection to the node, and the node holds
    one to each subscriber of `subs` by its own account: the node builds no output it sees no
    subscriber for, and may see one later than the subscriber sees the node."""
    deadline = time.monotonic() + timeout
    outputs = {(s.resolved_name, "o") for s in subs}
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise AssertionError(f"the node exited: {proc.communicate()[1]}")
        if (
            all(p.get_num_connections() > 0 for p in pubs)
            and all(s.get_num_connections() > 0 for s in subs)
            and outputs <= node_connections()
        ):
            return
        time.sleep(0.1)
    raise AssertionError(f"the node did not connect: it holds {sorted(node_connections())}")


def ns_of(t) -> int:
    return t.secs * 1_000_000_000 + t.nsecs


def test_tag_input_matches_fpe_predict_none_dropped(ros, drive):
    env, r1 = ros
    tmp, _ = drive
    log = open_log(tmp / "sim" / "drive.mcap")
    msgs = list(log.messages(["/tf", "/tf_static", "/tag_detections"]))
    # a loaded machine can hold the TF thread back: a generous wait keeps every detection
    wp = str(tmp / "sim" / "waypoints.csv")
    proc = start_node(env, "--config", str(tmp / "cfg.json"), "--waypoints", wp, "--tf-wait", "5")
    try:
        pubs = {
            "/tf": r1.rospy.Publisher(
                "/tf", r1.message_class("tf2_msgs/TFMessage"), queue_size=1000
            ),
            "/tf_static": r1.rospy.Publisher(
                "/tf_static", r1.message_class("tf2_msgs/TFMessage"), queue_size=10, latch=True
            ),
            "/tag_detections": r1.rospy.Publisher(
                "/tag_detections",
                r1.message_class("apriltag_ros/AprilTagDetectionArray"),
                queue_size=1000,
            ),
        }
        paths = Collector(r1, "/future_pose/path", "nav_msgs/Path")
        markers = Collector(r1, "/future_pose", "visualization_msgs/MarkerArray")
        covs = Collector(r1, "/future_pose/covariance", "geometry_msgs/PoseWithCovarianceStamped")
        wait_connected(pubs.values(), [paths.sub, markers.sub, covs.sub], proc)
        static = [m for m in msgs if m[0] == "/tf_static"]
        for topic, msgtype, _, msg in static:  # latched: the node holds it before the drive
            pubs[topic].publish(r1.from_dict(r1.message_class(msgtype), msg_dict(msg, "ros1")))
        time.sleep(1.0)
        for topic, msgtype, _, msg in [m for m in msgs if m[0] != "/tf_static"]:
            cls = r1.message_class(msgtype)
            pubs[topic].publish(r1.from_dict(cls, msg_dict(msg, "ros1")))
            if topic == "/tag_detections":
                time.sleep(1.0 / RATE_HZ)
        pred = np.genfromtxt(tmp / "pred.csv", delimiter=",", names=True)
        valid = pred[pred["valid"] == 1]
        n_want = len(valid) // H
        wait_for(lambda: len(paths.msgs) >= n_want and len(covs.msgs) >= n_want * H)
    finally:
        err = stop_node(proc)
    by_stamp = {}
    for row in valid.reshape(-1, H):
        by_stamp[round(row["stamp"][0] * 1e9)] = row
    got = sorted(ns_of(m.header.stamp) for m in paths.msgs)
    missing = [k for k in sorted(by_stamp) if min(abs(k - g) for g in got) > 2]
    assert len(paths.msgs) == n_want, (missing, err)  # none dropped, none extra
    for m in paths.msgs:
        ns = ns_of(m.header.stamp)
        row = by_stamp[min(by_stamp, key=lambda k: abs(k - ns))]
        assert abs(row["stamp"][0] * 1e9 - ns) < 2.0  # the observation's stamp (CSV rounds to 1 ns)
        assert m.header.frame_id == "map"
        xy = np.array([[p.pose.position.x, p.pose.position.y] for p in m.poses])
        np.testing.assert_allclose(xy, np.column_stack([row["x"], row["y"]]), atol=1e-6, rtol=0)
        yaw = [2 * np.arctan2(p.pose.orientation.z, p.pose.orientation.w) for p in m.poses]
        dyaw = (np.array(yaw) - row["yaw"] + np.pi) % (2 * np.pi) - np.pi
        np.testing.assert_allclose(dyaw, 0.0, atol=1e-6)
        steps = [ns_of(p.header.stamp) - ns for p in m.poses]
        assert steps == [round(k * 0.1e9) for k in range(1, H + 1)]
    assert 0 < len(markers.msgs) <= n_want  # at most one every --markers-every (0.1 s)
    kinds = [mk.type for mk in markers.msgs[0].markers]
    assert kinds == [7, 4, 5]  # points, line, the ellipses
    assert len(covs.msgs) == n_want * H
    # covariance: the config's track-frame one turned into the map frame (trace is invariant)
    traces = sorted({round(c.pose.covariance[0] + c.pose.covariance[7], 9) for c in covs.msgs})
    assert traces == sorted({round(c[0][0] + c[1][1], 9) for c in COV})
    assert "stopped after" in err


def test_obstacle_input_four_opponents(ros, drive, tmp_path):
    """Four opponents in one ObstacleArray at 40 Hz: per-id paths equal each one's runner."""
    env, r1 = ros
    tmp, cfg = drive
    wp_file = tmp / "sim" / "waypoints.csv"
    xy_wp = load_waypoints_xy(wp_file)
    ids = OPPONENT_IDS
    frames = obstacle_frames(tmp / "sim" / "drive.mcap", xy_wp)
    proc = start_node(
        env, "--config", str(tmp / "cfg.json"), "--waypoints", str(wp_file),
        "--obstacles-topic", "/perception/obstacles",
    )  # fmt: skip
    try:
        cls = r1.message_class("f110_msgs/ObstacleArray")
        pub = r1.rospy.Publisher("/perception/obstacles", cls, queue_size=1000)
        subs = {i: Collector(r1, f"/future_pose/path/opp_{i}", "nav_msgs/Path") for i in ids}
        out = Collector(r1, "/future_pose/obstacles", "f110_msgs/ObstacleArray")
        wait_connected([pub], [out.sub], proc)
        # the per-opponent topics appear with the first valid prediction: warm up connections
        for ns, obst in frames:
            pub.publish(r1.from_dict(cls, {"header": {"stamp": {"secs": ns // 10**9,
                        "nsecs": ns % 10**9}, "frame_id": "map"}, "obstacles": obst}))  # fmt: skip
            time.sleep(1.0 / RATE_HZ)
        want = runner_predictions(cfg, xy_wp, frames)
        # one predicted ObstacleArray per input message with any valid prediction
        n_out = len({ns for w in want.values() for ns, _ in w})
        wait_for(lambda: len(out.msgs) >= n_out)
        time.sleep(0.3)
    finally:
        err = stop_node(proc)
    for i in ids:
        got = {ns_of(m.header.stamp): m for m in subs[i].msgs}
        # a subscriber connects to a per-opponent topic after its first message: from then on all
        assert len(got) >= len(want[i]) - 5, (i, len(got), len(want[i]), err)
        first = min(got)
        expect = [(ns, p) for ns, p in want[i] if ns >= first]
        assert sorted(got) == [ns for ns, _ in expect], err
        for ns, poses in expect:
            xy = np.array([[p.pose.position.x, p.pose.position.y] for p in got[ns].poses])
            np.testing.assert_allclose(xy, poses[:, :2], atol=1e-6, rtol=0)
    # the predicted ObstacleArray: one per input message once all four are valid, never id 99
    assert len(out.msgs) == n_out, (len(out.msgs), n_out, err)
    assert all(o.id in ids for m in out.msgs for o in m.obstacles)
    assert max(len(m.obstacles) for m in out.msgs) == 4
    assert json.dumps(sorted({o.id for m in out.msgs for o in m.obstacles})) == json.dumps(ids)


def test_bad_input_on_a_running_node(ros, drive):
    """NaN / inf poses, a wrong frame, stamps going backwards and a 1 kHz flood between good
    PoseStamped messages: the good ones predict as the runner does, SIGTERM ends the node."""
    env, r1 = ros
    tmp, cfg = drive
    wp = tmp / "sim" / "waypoints.csv"
    odom = [
        (msg.pose.pose.position.x, msg.pose.pose.position.y)
        for _, _, _, msg in open_log(tmp / "sim" / "drive.mcap").messages(["/opp/odom"])
    ]
    args = ["--config", str(tmp / "cfg.json"), "--waypoints", str(wp), "--no-markers"]
    proc = start_node(env, *args, "--pose-topic", "/opp/pose_bad_test", "--no-covariance")
    cls = r1.message_class("geometry_msgs/PoseStamped")

    def msg(ns, x, y, frame="map"):
        stamp = {"secs": ns // 10**9, "nsecs": ns % 10**9}
        return r1.from_dict(cls, {"header": {"stamp": stamp, "frame_id": frame},
                                  "pose": {"position": {"x": x, "y": y}}})  # fmt: skip

    try:
        pub = r1.rospy.Publisher("/opp/pose_bad_test", cls, queue_size=1000)
        paths = Collector(r1, "/future_pose/path", "nav_msgs/Path")
        wait_connected([pub], [paths.sub], proc)
        good, base = [], 5 * 10**9
        for j in range(80):
            ns = base + j * 25_000_000
            x, y = odom[2 * j]
            pub.publish(msg(ns, x, y))
            good.append((ns, x, y))
            kind = j % 4
            if kind == 0:
                pub.publish(msg(ns + 1, float("nan"), y))
            elif kind == 1:
                pub.publish(msg(ns + 1, x, float("inf")))
            elif kind == 2:
                pub.publish(msg(ns + 1, x, y, frame="odom"))
            else:
                pub.publish(msg(ns - 10_000_000, x + 1.0, y))  # stamp going backwards
            if j == 40:  # a 1 kHz flood of stale messages
                for _ in range(300):
                    pub.publish(msg(base, 0.0, 0.0))
                    time.sleep(0.001)
            time.sleep(1.0 / RATE_HZ)
        ref, want = Runner(cfg, load_waypoints_xy(wp)), []
        for ns, x, y in good:
            poses = ref.update((ns - base) * 1e-9, x, y, None)
            if ref.valid:
                want.append((ns, poses))
        wait_for(lambda: len(paths.msgs) >= len(want))
    finally:
        proc.send_signal(15)
        _, err = proc.communicate(timeout=20)
    assert proc.returncode == 0, err
    got = {ns_of(m.header.stamp): m for m in paths.msgs}
    assert sorted(got) == [ns for ns, _ in want], err
    for ns, poses in want:
        xy = np.array([[p.pose.position.x, p.pose.position.y] for p in got[ns].poses])
        np.testing.assert_allclose(xy, poses[:, :2], atol=1e-6, rtol=0)
    for problem in ("non-finite position", "frame 'odom'", "is not after"):
        assert problem in err, (problem, err)
    assert len(err.splitlines()) < 20, err  # rate-limited: not one line per bad message


def test_messages_from_dicts_equal_genpys_own():
    """`from_dict` (no roscore needed): given and missing fields, nested messages, times and
    arrays serialize to the bytes of the message genpy's constructors build; an unknown field
    is an error naming it."""
    import io

    need_ros1()
    from fpe_jax.node import _ros1 as r1

    def raw(msg) -> bytes:
        buf = io.BytesIO()
        msg.serialize(buf)
        return buf.getvalue()

    path, stamped = r1.message_class("nav_msgs/Path"), r1.message_class("geometry_msgs/PoseStamped")
    header, pose = r1.message_class("std_msgs/Header"), r1.message_class("geometry_msgs/Pose")
    point = r1.message_class("geometry_msgs/Point")
    stamp = {"secs": 7, "nsecs": 5}
    got = r1.from_dict(path, {"header": {"stamp": stamp, "frame_id": "map"},
                              "poses": [{"pose": {"position": {"x": 1.5}}}, {}]})  # fmt: skip
    want = path(
        header=header(stamp=r1.genpy.Time(7, 5), frame_id="map"),
        poses=[stamped(pose=pose(position=point(x=1.5))), stamped()],
    )
    assert raw(got) == raw(want)
    cov = r1.message_class("geometry_msgs/PoseWithCovarianceStamped")
    assert raw(r1.from_dict(cov, {})) == raw(cov())
    a, b = r1.from_dict(cov, {}), r1.from_dict(cov, {})
    a.pose.covariance[0] = 1.0  # defaults are never shared between messages
    assert b.pose.covariance[0] == 0.0
    marker = r1.message_class("visualization_msgs/Marker")
    assert raw(r1.from_dict(marker, {"points": [{"x": 2.0}]})) == raw(marker(points=[point(x=2.0)]))
    with pytest.raises(ValueError, match="geometry_msgs/Point has no field 'q'"):
        r1.from_dict(path, {"poses": [{"pose": {"position": {"q": 1.0}}}]})


def test_a_generated_message_class_leaves_no_folder_behind(tmp_path, monkeypatch):
    """A class generated for a type Debian does not ship (f110_msgs) leaves nothing in the
    temporary folder and nothing for the interpreter's exit to remove: `fpe node` ends without
    it, so every node would otherwise leave a genpy_* folder in /tmp. The class still works:
    a message of it survives serialization."""
    import atexit
    import io
    import tempfile

    need_ros1()
    from fpe_jax.node import _ros1 as r1

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    monkeypatch.setattr(r1, "_CLASSES", {})
    callbacks, path = atexit._ncallbacks(), list(r1.sys.path)
    cls = r1.message_class("f110_msgs/ObstacleArray")
    assert list(tmp_path.iterdir()) == []
    assert atexit._ncallbacks() == callbacks and r1.sys.path == path
    msg = r1.from_dict(
        cls, {"header": {"frame_id": "map"}, "obstacles": [{"id": 3, "s_center": 7.5}]}
    )
    buf = io.BytesIO()
    msg.serialize(buf)
    back = cls().deserialize(buf.getvalue())
    assert r1.to_dict(back) == r1.to_dict(msg) and back.obstacles[0].s_center == 7.5


def test_generated_ros1_bytes_equal_genpys():
    """The generated ROS 1 writers (no roscore needed): the zero message of every type of the
    ROS 1 store, and every message the node publishes for two opponents, serialize to the
    bytes genpy writes for the same dict (the node's bytes are genpy's of the message genpy
    reads from them); a value the checks refuse is refused."""
    import io

    need_ros1()
    from fpe_jax.io.config import params_to_config
    from fpe_jax.model._params import presets
    from fpe_jax.node import _ros1 as r1
    from fpe_jax.node._cdr import Ros1Writer
    from fpe_jax.node._core import Node, NodeOptions
    from fpe_jax.node._types import typestore
    from fpe_jax.sim._sim import simulate

    def genpy_bytes(type_name: str, msg: dict) -> bytes:
        buf = io.BytesIO()
        r1.from_dict(r1.message_class(type_name), msg).serialize(buf)
        return buf.getvalue()

    store = typestore("ros1")
    writer = Ros1Writer(store)
    n = 0
    for name in sorted(store.fielddefs):
        try:
            r1.message_class(name)
        except ValueError:  # a type genpy cannot build here (none is expected)
            continue
        assert writer.encode(name, {}) == genpy_bytes(name, {}), name
        n += 1
    assert n > 150

    class Collect:
        flavour = "ros1"

        def __init__(self):
            self.out: list[tuple[str, dict]] = []

        def subscribe(self, topic, type_name, callback):
            self.callback = callback

        def encode(self, type_name, msg):
            return writer.encode(type_name, msg)

        def advertise(self, topic, type_name):
            return lambda msg: self.out.append((type_name, msg))

        def subscriber_count(self, topic):
            return 1

        def spin(self, stop):
            pass

        def close(self):
            pass

    res = simulate("oval", duration_s=2.0, seed=5)
    cov = [[[0.01 * (k + 1), 0.002], [0.002, 0.004]] for k in range(H)]
    cfg = params_to_config(presets["default"], uncertainty={"frame": "track", "cov_m2": cov})
    t = Collect()
    opts = NodeOptions(input="obstacles", topic="/obst", markers_every_s=0.0)
    Node(t, cfg, res.centerline_xy_m, opts).start()
    for k, ts in enumerate(res.drive.t_s):
        obst = [{"id": i, "s_center": 2.0 * float(ts) + 3.0 * i, "d_center": 0.1 * i,
                 "is_static": False} for i in (1, 4)]  # fmt: skip
        hdr = {"stamp": {"secs": 1 + int(ts), "nsecs": int(ts % 1 * 1e9)}, "frame_id": "map"}
        t.callback({"header": hdr, "obstacles": obst}, "f110_msgs/msg/ObstacleArray", k)
    trajectory = {
        "header": {"stamp": {"secs": 3, "nsecs": 4}, "frame_id": "map"},
        "id": 2,
        "lap_count": 1.5,
        "opp_is_on_trajectory": True,
        "oppwpnts": [
            {
                "id": i,
                "s_m": 0.5 * i,
                "d_m": -0.1,
                "x_m": 1.0,
                "y_m": 2.0,
                "proj_vs_mps": 3.0,
                "d_var": 0.01,
            }
            for i in range(5)
        ],  # fmt: skip
    }
    t.out.append(("f110_msgs/msg/OpponentTrajectory", trajectory))
    kinds = {type_name for type_name, _ in t.out}
    assert len(kinds) == 5, kinds  # markers, path, covariance, obstacles, trajectory
    for type_name, msg in t.out:
        if isinstance(msg, bytes):  # the node's own bytes are genpy's of the message they hold
            data, msg = msg, r1.to_dict(r1.message_class(type_name)().deserialize(msg))
            assert genpy_bytes(type_name, msg) == data, type_name
        assert writer.encode(type_name, msg) == genpy_bytes(type_name, msg), type_name
    with pytest.raises(Exception):  # noqa: B017 - any: genpy's conversion then decides
        writer.encode("nav_msgs/msg/Path", {"header": {"stamp": {"secs": -1}}})
    with pytest.raises(Exception):  # noqa: B017
        writer.encode("nav_msgs/msg/Path", {"header": {"stamp": {"sec": 1}}})


def test_prepared_bytes_publish_as_the_message_with_rospys_sequence(ros):
    """What `Ros1Transport.advertise` publishes (the generated bytes in a subclass of the
    message class) reaches a subscriber as the message, with rospy's header sequence numbers."""
    _env, r1 = ros
    cls = r1.message_class("nav_msgs/Path")
    got = []
    sub = r1.rospy.Subscriber("/prepared", cls, got.append)
    pub = r1.rospy.Publisher("/prepared", cls, queue_size=10)
    wait_for(lambda: pub.get_num_connections() > 0, 10.0)
    assert pub.get_num_connections() == 1
    raw = r1._raw_class(cls)
    for k in range(3):
        msg = {"header": {"stamp": {"secs": 5, "nsecs": k}, "frame_id": "map"},
               "poses": [{"pose": {"position": {"x": 1.0 + k}}}]}  # fmt: skip
        pub.publish(raw.of(r1._writer().encode("nav_msgs/msg/Path", msg)))
    wait_for(lambda: len(got) == 3, 10.0)
    sub.unregister()
    pub.unregister()
    assert [m.header.seq for m in got] == [1, 2, 3]
    assert [m.header.stamp.nsecs for m in got] == [0, 1, 2]
    assert [m.poses[0].pose.position.x for m in got] == [1.0, 2.0, 3.0]
    assert all(m.header.frame_id == "map" for m in got)
