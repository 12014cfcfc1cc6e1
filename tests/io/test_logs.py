"""fpe_jax.io: round trips through every supported format and message type, and the real data.

Logs are written three ways -- mcap_ros2's writer (via the package's own writer), rosbags' rosbag2
writer (MCAP storage) and rosbags' ROS 1 writer -- and read back with `load_drive`; values are
compared exactly (positions, speeds, stamps) or to 1e-12 (yaw, which goes through a quaternion).
"""

from __future__ import annotations

import ast
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import (
    EPOCH_NS,
    ODOM,
    POSE_TYPES,
    PS,
    PWCS,
    TF,
    assert_series,
    make_series,
    pose_message,
    series_events,
    write_log,
    write_mcap,
)
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from fpe_jax import cli, io
from fpe_jax.errors import InputError
from fpe_jax.io import ros_msgs as rm

# ---------------------------------------------------------------- message definitions


# The shipped AprilTag types are not in ROS 2 Humble; test_apriltag checks them against upstream.
@pytest.mark.parametrize("name", sorted(set(rm._FIELDS) - set(rm.shipped_definitions())))
def test_definitions_match_ros2_humble(name):
    """Our hand-written .msg text gives exactly the field lists of the real ROS 2 types."""
    from mcap_ros2._dynamic import generate_dynamic

    full = rm.full_type(name)
    assert full in generate_dynamic(full, rm.definition(name))
    ours = get_types_from_msg(rm._FIELDS[name], full)[full][1]
    assert ours == get_typestore(Stores.ROS2_HUMBLE).fielddefs[full][1]


def test_stamp_conversions_are_nanosecond_exact():
    ns = np.array([0, 1, 999_999_999, EPOCH_NS, 5_000_000_001])
    assert rm.seconds_to_ns(np.array([0.1, 2.5, 1e-9])).tolist() == [100_000_000, 2_500_000_000, 1]
    assert (
        rm.seconds_to_ns(rm.ns_to_seconds(ns[[0, 1, 2, 4]])).tolist() == ns[[0, 1, 2, 4]].tolist()
    )
    assert rm.stamp_dict(EPOCH_NS) == {"sec": 1_700_000_000, "nanosec": 123_456_789}


def test_io_imports_no_jax():
    """The on-car runner may use fpe_jax.io without JAX: no io module may import it, even lazily,
    and importing the package loads no reader library either (they load on first use). The config
    and export modules import JAX-free code at module level; only turning a config into Params
    (config_to_params & co.) and the StableHLO export import the model, inside those functions."""
    code = (
        "import sys, fpe_jax.io, fpe_jax.io.config, fpe_jax.io.export;"
        " print(sorted({m.split('.')[0] for m in sys.modules}))"
    )
    loaded = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    )
    for lib in ("jax", "mcap", "mcap_ros2", "rosbags"):
        assert f"'{lib}'" not in loaded.stdout
    lazy_model = {"config.py", "export.py"}  # may import the model inside functions only
    for f in Path(io.__file__).parent.glob("*.py"):
        tree = ast.parse(f.read_text())
        nodes = tree.body if f.name in lazy_model else list(ast.walk(tree))
        for node in nodes:
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                names = [node.module or ""]
            for n in names:
                assert n.split(".")[0] not in ("jax", "jaxlib", "equinox", "optimistix"), f.name
                # geometry._path is the NumPy path module (waypoint checks, their hash)
                assert (
                    not n.startswith("fpe_jax.")
                    or n == "fpe_jax.geometry._path"
                    or n.split(".")[1]
                    in ("io", "drive", "errors", *(("spec",) if f.name in lazy_model else ()))
                ), f"{f.name} imports {n}"


# ---------------------------------------------------------------- logs -> Drive


@pytest.mark.parametrize(
    "container",
    ["mcap", "rosbag2", "rosbag2-metadata", "rosbag2-inner-mcap", "rosbag2-db3", "rosbag1"],
)
@pytest.mark.parametrize("msgtype", POSE_TYPES)
def test_log_roundtrip(tmp_path, container, msgtype):
    s = make_series()
    path = write_log(tmp_path, container, series_events("/car/pose", msgtype, s))
    d = io.load_drive(path)
    assert_series(d.t_s, d.xy_m, d.yaw_rad, s)
    assert d.meta["pose_topic"] == "/car/pose"
    assert d.meta["pose_type"] == rm.full_type(msgtype)
    assert d.meta["t0_ns"] == s["ns"][0]
    # The .mcap inside a rosbag2 folder is self-contained and is read as a plain MCAP.
    fmt = {"rosbag2-metadata": "rosbag2", "rosbag2-db3": "rosbag2", "rosbag2-inner-mcap": "mcap"}
    fmt = fmt.get(container, container)
    assert d.meta["format"] == fmt
    if msgtype == ODOM:  # alone, Odometry is the pose; as truth its speed is hypot(lin.x, lin.y)
        assert not d.has_truth
        t = io.load_drive(path, truth_topic="/car/pose")
        np.testing.assert_allclose(t.truth_v_mps, s["v"], rtol=1e-15)
        assert_series(t.truth_t_s, t.truth_xy_m, t.truth_yaw_rad, s)


@pytest.mark.parametrize("msgtype", [PS, PWCS, ODOM])
def test_cdr_rows_equal_the_decoders(tmp_path, msgtype, monkeypatch):
    """The fixed-layout reader gives the full decoder's rows for every frame id length (so every
    string alignment, several layouts in one batch and batches split across them), and bytes it
    does not understand go to the decoder."""
    from fpe_jax.io import logs
    from fpe_jax.io.logs import PoseRows, cdr_pose_table, open_log, pose_rows

    monkeypatch.setattr(logs, "POSE_BATCH", 5)
    s = make_series(24)
    events = series_events("/car/pose", msgtype, s)
    for k, (_, _, _, msg) in enumerate(events):
        msg["header"]["frame_id"] = "m" * (k % 9)
        if msgtype == ODOM:
            msg["child_frame_id"] = "c" * (k % 7)
            msg["twist"]["covariance"] = [float(i) for i in range(36)]
    log = open_log(write_mcap(tmp_path / "a.mcap", events))
    fast = log.pose_tables(["/car/pose"], ("map", "x"))["/car/pose"]
    slow = [r for _, t, ns, m in log.messages(["/car/pose"]) for r in pose_rows(t, m, ns, ("", ""))]
    slow = PoseRows.of(slow)
    assert len(fast.stamp_ns) == len(slow.stamp_ns) == 24
    for got, want in zip(fast, slow):
        np.testing.assert_array_equal(got, want)
        assert got.dtype == want.dtype
    data = [m.data for _, _, m, _ in log._mcap_messages(None)]
    stamp_ns, values, ok = cdr_pose_table(msgtype, data)
    assert ok.all()  # none fell back
    np.testing.assert_array_equal(stamp_ns, slow.stamp_ns)
    np.testing.assert_array_equal(values, slow.values)
    bad = [b"\x00\x00\x00\x00" + bytes(400), b"\x00\x01\x00\x00" + bytes(20), data[0][:40]]
    assert list(cdr_pose_table(msgtype, bad + data[:1])[2]) == [False, False, False, True]


def test_pose_rows_read_in_one_walk_in_log_time_order(tmp_path, monkeypatch):
    """Both pose-like topics of a drive come from one walk over the file, each in log-time
    order with equal times in file order, the same rows as the full decoder's."""
    from fpe_jax.io import logs
    from fpe_jax.io.logs import PoseRows, open_log, pose_rows

    monkeypatch.setattr(logs, "POSE_BATCH", 7)
    s = make_series(30)
    coarse = s["ns"] // 300_000_000 * 300_000_000  # about three messages share each log time
    events = series_events("/car/pose", PS, s, coarse) + series_events("/car/odom", ODOM, s)
    events = [events[k] for k in np.random.default_rng(1).permutation(len(events))]
    log = open_log(write_mcap(tmp_path / "a.mcap", events))
    walks = []
    scan = logs.scan_mcap
    monkeypatch.setattr(logs, "scan_mcap", lambda *a, **k: walks.append(a) or scan(*a, **k))
    got = log.pose_tables(["/car/odom", "/car/pose"], ("map", "x"))
    assert len(walks) == 1
    monkeypatch.setattr(logs, "scan_mcap", scan)
    for topic in ("/car/odom", "/car/pose"):
        decoded = [
            r for _, t, ns, m in log.messages([topic]) for r in pose_rows(t, m, ns, ("", ""))
        ]
        by_stamp = {r[0]: r for r in decoded}
        stamps = [(lg, m["header"]["stamp"]) for lg, t, _, m in events if t == topic]
        in_file = [(lg, st["sec"] * 1_000_000_000 + st["nanosec"]) for lg, st in stamps]
        want = PoseRows.of([by_stamp[n] for _, n in sorted(in_file, key=lambda e: e[0])])
        assert len(set(np.diff(want.log_ns) == 0)) == (2 if topic == "/car/pose" else 1)
        for a, b in zip(got[topic], want):
            np.testing.assert_array_equal(a, b)


def test_simulated_drive_roundtrip(tmp_path):
    """write_drive_mcap (the simulator's writer): pose + odom + tf; default topic choice."""
    p, o = make_series(20, seed=1), make_series(100, seed=2)
    p["yaw"][3] = np.nan  # a detection without heading survives as NaN
    t = lambda s: rm.ns_to_seconds(s["ns"])  # noqa: E731
    out = io.write_drive_mcap(
        tmp_path / "sim.mcap",
        pose=dict(t_s=t(p), xy_m=p["xy"], yaw_rad=p["yaw"]),
        odom=dict(t_s=t(o), xy_m=o["xy"], yaw_rad=o["yaw"], v_mps=o["v"], yaw_rate_rps=o["v"] / 9),
        tf=dict(t_s=t(o), xy_m=o["xy"][::-1], yaw_rad=o["yaw"]),
    )
    d = io.load_drive(out)
    assert (d.meta["pose_topic"], d.meta["truth_topic"]) == ("/opp/pose", "/opp/odom")
    # Float seconds -> int ns costs at most a few hundred ns at epoch scale.
    np.testing.assert_allclose(d.t_s, t(p), rtol=0, atol=5e-7)
    np.testing.assert_array_equal(d.xy_m, p["xy"])
    assert np.isnan(d.yaw_rad[3])
    np.testing.assert_allclose(np.delete(d.yaw_rad, 3), np.delete(p["yaw"], 3), atol=1e-12)
    np.testing.assert_array_equal(d.truth_xy_m, o["xy"])
    np.testing.assert_array_equal(d.truth_v_mps, o["v"])
    np.testing.assert_allclose(d.truth_yaw_rad, o["yaw"], atol=1e-12)
    tf = io.load_drive(out, pose_topic="/tf", truth_topic="/opp/pose")
    np.testing.assert_array_equal(tf.xy_m, o["xy"][::-1])
    assert np.isnan(tf.truth_v_mps).all()  # PoseStamped carries no speed
    # The yaw rate went in as angular.z: check the raw field with rosbags.
    from rosbags.highlevel import AnyReader

    with AnyReader([out]) as r:
        conn = [c for c in r.connections if c.topic == "/opp/odom"]
        raw = next(iter(r.messages(connections=conn)))[2]
        assert r.deserialize(raw, conn[0].msgtype).twist.twist.angular.z == o["v"][0] / 9


def test_small_stamps_are_exact(tmp_path):
    t_s = np.arange(10) * 0.1 + 3.0
    out = io.write_drive_mcap(
        tmp_path / "a.mcap", pose=dict(t_s=t_s, xy_m=np.ones((10, 2)) * t_s[:, None], yaw_rad=t_s)
    )
    d = io.load_drive(out)
    np.testing.assert_allclose(d.t_s, t_s, rtol=0, atol=1e-15)
    assert d.meta["t0_ns"] == 3_000_000_000


def test_log_time_and_tf_frames(tmp_path):
    s = make_series()
    log_ns = s["ns"] + 7_000_000  # recorded 7 ms after the stamp
    path = write_mcap(tmp_path / "a.mcap", series_events("/tf", TF, s, log_ns=log_ns))
    d = io.load_drive(path, log_time=True)
    np.testing.assert_array_equal(d.t_s, rm.ns_to_seconds(log_ns))
    assert d.meta["time"] == "log"
    decoy = io.load_drive(path, tf_parent="/map", tf_child="ego_base_link")  # '/' is ignored
    np.testing.assert_array_equal(decoy.xy_m, np.tile([-1.0, -2.0], (len(s["ns"]), 1)))


def test_pose_topic_preference(tmp_path):
    """Stamped poses beat /tf, which beats Odometry; Odometry then becomes the truth."""
    s = make_series()
    events = series_events("/tf", TF, s) + series_events("/odom", ODOM, s)
    only_tf = io.load_drive(write_mcap(tmp_path / "a.mcap", events))
    assert (only_tf.meta["pose_topic"], only_tf.meta["truth_topic"]) == ("/tf", "/odom")
    events += series_events("/det", PWCS, s)
    both = io.load_drive(write_mcap(tmp_path / "b.mcap", events))
    assert (both.meta["pose_topic"], both.meta["truth_topic"]) == ("/det", "/odom")


def test_cleaning_nonfinite_reordered_duplicates(tmp_path):
    s = make_series(8)
    s["xy"][2, 0] = np.nan
    order = [0, 1, 2, 4, 3, 5, 6, 7]  # 4 arrives before 3
    msgs = [pose_message(PS, int(s["ns"][i]), *s["xy"][i], s["yaw"][i]) for i in order]
    msgs[order.index(5)]["pose"]["orientation"]["w"] = np.inf  # a broken quaternion
    # Same stamp as row 6, sent last with new values: the later one wins.
    msgs.append(pose_message(PS, int(s["ns"][6]), 9.0, 9.5, 0.25))
    arrival_ns = EPOCH_NS + np.arange(len(msgs)) * 10**9  # log time = order of arrival
    d = io.load_drive(
        write_mcap(tmp_path / "a.mcap", [(int(a), "/p", PS, m) for a, m in zip(arrival_ns, msgs)])
    )
    keep = [0, 1, 3, 4, 6, 7]
    np.testing.assert_array_equal(d.t_s, rm.ns_to_seconds(s["ns"][keep]))
    expect_xy = s["xy"][keep].copy()
    expect_xy[keep.index(6)] = [9.0, 9.5]
    np.testing.assert_array_equal(d.xy_m, expect_xy)
    m = d.meta
    assert (m["n_messages"], m["n_dropped_nonfinite"], m["n_reordered"]) == (9, 2, 2)
    assert m["n_duplicate_stamps"] == 1


def test_zero_quaternion_means_unknown_yaw():
    assert np.isnan(rm.quaternion_to_yaw(0, 0, 0, 0))
    q = rm.yaw_to_quaternion(0.7)
    assert rm.quaternion_to_yaw(q["x"] * 2, q["y"] * 2, q["z"] * 2, q["w"] * 2) == pytest.approx(
        0.7
    )


def test_quaternion_yaw_on_floats_equals_the_array_form():
    """The one-quaternion form (the live node's) gives the array form's yaw: random and non-unit
    quaternions, the zero one (NaN), and a NaN component."""
    rng = np.random.default_rng(0)
    quats = [*rng.normal(0.0, 1.0, (200, 4)).tolist(), [0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 2.0],
             [0.0, 0.0, math.nan, 1.0], [1e-7, 0.0, 0.0, 0.0]]  # fmt: skip
    want = rm.quaternion_to_yaw(*np.array(quats).T)
    got = np.array([rm.quaternion_yaw(*q) for q in quats])
    np.testing.assert_allclose(got, want, rtol=0.0, atol=1e-15)
    assert np.isnan(got[200]) and np.isnan(got[202]) and got[201] == 0.0


# ---------------------------------------------------------------- CSV -> Drive


def test_csv_with_header(tmp_path):
    f = tmp_path / "d.csv"
    f.write_text(
        "t, x, y, yaw, v\n0.5,1.25,2,0.1,3\n0.25,1,2,0.2,4\n0.75,nan,2,0.3,5\n1.0,3,4,0.4,6\n"
    )
    d = io.load_drive(f)
    np.testing.assert_array_equal(d.t_s, [0.25, 0.5, 1.0])
    np.testing.assert_array_equal(d.xy_m, [[1, 2], [1.25, 2], [3, 4]])
    np.testing.assert_array_equal(d.yaw_rad, [0.2, 0.1, 0.4])
    np.testing.assert_array_equal(d.meta["v_mps"], [4, 3, 6])
    assert (d.meta["n_reordered"], d.meta["n_dropped_nonfinite"]) == (1, 1)


def test_csv_without_time_column_uses_rate(tmp_path):
    f = tmp_path / "d.csv"
    f.write_text("x,y\n0,0\n1,0\n2,0\n")
    d = io.load_drive(f, rate_hz=4)
    np.testing.assert_array_equal(d.t_s, [0, 0.25, 0.5])
    assert np.isnan(d.yaw_rad).all()


def test_levine_actual_poses(shared_data):
    d = io.load_drive(shared_data / "levine" / "actual-poses.csv", rate_hz=10)
    assert len(d.t_s) == 982  # repeated rows are kept: the estimator handles them
    assert d.t_s[-1] == pytest.approx(98.1, abs=1e-12)
    np.testing.assert_array_equal(d.xy_m[0], [2.480020, -0.082690])
    assert d.meta["format"] == "xyz-csv" and np.isnan(d.yaw_rad).all()


# ---------------------------------------------------------------- predictions out


def _predictions(n=5, h=4):
    rng = np.random.default_rng(3)
    return 100.0 + np.arange(n) * 0.1, rng.normal(size=(n, h, 3))


def test_write_predictions_csv(tmp_path):
    stamps, poses = _predictions()
    out = io.write_predictions(tmp_path / "p.csv", stamps, poses, 0.1)
    lines = out.read_text().splitlines()
    assert lines[0] == "stamp,step,horizon_s,x,y,yaw"
    rows = np.loadtxt(out, delimiter=",", skiprows=1)
    assert rows.shape == (20, 6)
    np.testing.assert_allclose(rows[:, 0], np.repeat(stamps, 4), atol=1e-9)
    np.testing.assert_array_equal(rows[:, 1], np.tile([1, 2, 3, 4], 5))
    np.testing.assert_allclose(rows[:, 2], rows[:, 1] * 0.1, atol=1e-9)
    np.testing.assert_allclose(rows[:, 3:], poses.reshape(20, 3), atol=5e-10)
    assert [p.name for p in tmp_path.iterdir()] == ["p.csv"]  # no temp file left


def test_write_predictions_mcap_reads_with_both_libraries(tmp_path):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    from rosbags.highlevel import AnyReader

    stamps, poses = _predictions()
    s = make_series(5)
    drive = io.load_drive(write_mcap(tmp_path / "obs.mcap", series_events("/x", PS, s)))
    out = io.write_predictions(tmp_path / "p.mcap", stamps, poses, 0.1, drive=drive)

    with open(out, "rb") as f:
        got = [
            (c.topic, m.log_time, d)
            for _, c, m, d in make_reader(
                f, decoder_factories=[DecoderFactory()]
            ).iter_decoded_messages()
        ]
    markers = [d for topic, _, d in got if topic == "/future_pose"]
    assert len(markers) == 5
    for k, arr in enumerate(markers):
        spheres = arr.markers[0]
        assert (spheres.type, spheres.header.frame_id) == (rm.MARKER_SPHERE_LIST, "map")
        ns = rm.seconds_to_ns(stamps[k : k + 1])[0]
        assert spheres.header.stamp.sec * 10**9 + spheres.header.stamp.nanosec == ns
        np.testing.assert_array_equal([[p.x, p.y] for p in spheres.points], poses[k, :, :2])
        assert arr.markers[1].type == rm.MARKER_LINE_STRIP
    obs = io.load_drive(out, pose_topic="/opp/pose")
    np.testing.assert_allclose(obs.t_s, drive.t_s, rtol=0, atol=5e-7)
    np.testing.assert_array_equal(obs.xy_m, drive.xy_m)

    with AnyReader([out]) as r:
        conns = [c for c in r.connections if c.topic == "/future_pose"]
        assert conns[0].msgtype == "visualization_msgs/msg/MarkerArray"
        first = r.deserialize(next(iter(r.messages(connections=conns)))[2], conns[0].msgtype)
        np.testing.assert_array_equal(
            [[p.x, p.y] for p in first.markers[0].points], poses[0, :, :2]
        )
        old = [c for c in r.connections if c.topic in ("/future_pose", "/opp/pose")]
        assert sum(1 for _ in r.messages(connections=old)) == 10
        # plus the scene's path and ellipses per prediction (tests/node/test_foxglove.py)
        assert sum(1 for _ in r.messages()) == 20


def test_writers_refuse_to_overwrite(tmp_path):
    stamps, poses = _predictions()
    target = tmp_path / "p.csv"
    target.write_text("keep me")
    with pytest.raises(InputError, match="--force"):
        io.write_predictions(target, stamps, poses, 0.1)
    assert target.read_text() == "keep me"
    io.write_predictions(target, stamps, poses, 0.1, force=True)
    assert target.read_text().startswith("stamp,")
    with pytest.raises(InputError, match="exists"):
        io.write_drive_mcap(target, pose=dict(t_s=[0.0], xy_m=[[0.0, 0.0]], yaw_rad=[0.0]))


# ---------------------------------------------------------------- waypoints


def test_waypoints_real_files(shared_data):
    w = io.load_waypoints(shared_data / "levine" / "levine-waypoints.csv")
    assert (w.xy_m.shape, w.format, w.speed_mps) == ((2720, 2), "xy-csv", None)
    np.testing.assert_array_equal(w.xy_m[0], [0.795073, -0.202772])
    for f in sorted((shared_data / "tracks").glob("*_centerline.csv")):
        c = io.load_waypoints(f)
        assert c.format == "f1tenth-centerline" and c.speed_mps is None and len(c.xy_m) > 500
        r = io.load_waypoints(f.with_name(f.name.replace("centerline", "raceline")))
        assert r.format == "f1tenth-raceline"
        assert r.speed_mps.shape == (len(r.xy_m),) and 4.0 < r.speed_mps.min() < 8.1
    r = io.load_waypoints(shared_data / "tracks" / "Austin_raceline.csv")
    np.testing.assert_array_equal(r.xy_m[0], [-0.4108859, -0.6907978])  # columns 2-3


def test_waypoints_header_csv_keeps_speed(tmp_path):
    f = tmp_path / "w.csv"
    f.write_text("# my track\nid,x_m,y_m,speed\n1,0,0,2\n2,1,0,3\n3,1,1,4\n")
    w = io.load_waypoints(f)
    np.testing.assert_array_equal(w.xy_m, [[0, 0], [1, 0], [1, 1]])
    np.testing.assert_array_equal(w.speed_mps, [2, 3, 4])
    assert w.format == "csv"


def _path_msg(ns, pts):
    return {
        "header": {"stamp": rm.stamp_dict(ns), "frame_id": "map"},
        "poses": [pose_message(PS, ns, x, y, 0.0) for x, y in pts],
    }


@pytest.mark.parametrize("container", ["mcap", "rosbag2", "rosbag1"])
def test_waypoints_from_path_message(tmp_path, container):
    old, new = [[0.0, 0.0], [1.0, 0.0], [2.0, 1.0]], [[0.5, 0.0], [1.5, 0.5], [2.5, 1.5], [3, 3]]
    events = [(10, "/plan", "nav_msgs/Path", _path_msg(10, old))]
    events += [(20, "/plan", "nav_msgs/Path", _path_msg(20, new))]
    w = io.load_waypoints(write_log(tmp_path, container, events))
    np.testing.assert_array_equal(w.xy_m, new)  # the last message wins
    assert (w.format, w.speed_mps) == ("path", None)


# ---------------------------------------------------------------- describe_log / fpe info


def test_describe_log_and_cli_info(tmp_path, capsys):
    s = make_series(11)
    events = series_events("/opp/pose", PS, s) + series_events("/opp/odom", ODOM, s)
    path = write_mcap(tmp_path / "a.mcap", events)
    info = io.describe_log(path)
    assert (info["pose_topic"], info["truth_topic"], info["format"]) == (
        "/opp/pose",
        "/opp/odom",
        "mcap",
    )
    topics = {t["name"]: t for t in info["topics"]}
    assert topics["/opp/odom"]["type"] == "nav_msgs/msg/Odometry"
    assert topics["/opp/pose"]["count"] == 11
    span_s = (s["ns"][-1] - s["ns"][0]) * 1e-9
    assert topics["/opp/pose"]["rate_hz"] == pytest.approx(10 / span_s)
    assert info["duration_s"] == pytest.approx(span_s)

    assert cli.main(["info", str(path), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["pose_topic"] == "/opp/pose"
    assert cli.main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "/opp/odom" in out and "pose:  /opp/pose" in out

    # Two stamped pose topics: info still lists them and says why there is no choice.
    events += series_events("/det2", PS, s)
    info = io.describe_log(write_mcap(tmp_path / "b.mcap", events))
    assert info["pose_topic"] is None and "/det2" in info["pose_error"]
    assert cli.main(["info", str(tmp_path / "b.mcap"), "--pose-topic", "/det2"]) == 0


def test_describe_csv(shared_data):
    info = io.describe_log(shared_data / "levine" / "actual-poses.csv", rate_hz=10)
    assert info["topics"][0]["count"] == 982 and info["format"] == "xyz-csv"
    assert info["topics"][0]["rate_hz"] == pytest.approx(10.0)
