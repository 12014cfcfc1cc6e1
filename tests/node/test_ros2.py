"""`fpe node --ros2` over real Cyclone DDS on loopback, in a test-private domain: a simulated drive
played into topics at 40 Hz from this process, every published prediction compared with `fpe
predict` / the runner on the same data, and every output sample's bytes, DDS type name and RIHS01
hash compared with what rosbags (an independent implementation) computes."""

import os
import time

import numpy as np
import pytest

try:
    import cyclonedds  # noqa: F401
except ImportError:
    if os.environ.get("CI"):
        raise
    pytest.skip(
        "cyclonedds is not installed (pip install 'fpe-jax[ros2]')", allow_module_level=True
    )

from cyclonedds.builtin import BuiltinTopicDcpsPublication
from cyclonedds.core import Policy, Qos
from cyclonedds.domain import DomainParticipant
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from node_helpers import (
    COV,
    OPPONENT_IDS,
    RATE_HZ,
    H,
    make_drive,
    msg_dict,
    obstacle_frames,
    predicted_rows,
    runner_predictions,
    start_node,
    stop_node,
    wait_for,
)
from ros2_helpers import LOOPBACK_URI, endpoints, padded, raw_take, rosbags_message

from fpe_jax.geometry._path import waypoints_sha256
from fpe_jax.io.config import params_to_config, write_config
from fpe_jax.io.logs import open_log
from fpe_jax.model._params import Params, Settings
from fpe_jax.node._core import OUTPUTS
from fpe_jax.node._dds import DdsTransport, dds_topic_name, dds_type_name
from fpe_jax.node._types import typestore
from fpe_jax.runner._runner import load_waypoints_xy


@pytest.fixture(scope="module")
def dds(tmp_path_factory):
    """(environment of the node, player transport, raw participant) in a domain of this test
    run alone, Cyclone DDS on loopback in this process and the node's."""
    saved = {k: os.environ.get(k) for k in ("CYCLONEDDS_URI", "ROS_DOMAIN_ID")}
    os.environ["CYCLONEDDS_URI"] = LOOPBACK_URI
    os.environ["ROS_DOMAIN_ID"] = str(1 + (os.getpid() + 101) % 200)
    transport = DdsTransport(typestore("ros2"), node_name="fpe_test_player")
    raw = DomainParticipant(transport.domain_id)
    try:
        yield dict(os.environ), transport, raw
    finally:
        transport.close()
        raw.__del__()
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("drive")
    return tmp, make_drive(tmp)


class Outputs:
    """A reliable keep-all reader per output topic in a plain cyclonedds participant: the
    samples exactly as they arrive, taken as they come."""

    def __init__(self, raw, codec, topics: dict[str, str]):
        self.types = topics
        self.readers = {
            t: DataReader(
                raw,
                Topic(raw, dds_topic_name(t), codec.idl_class(type_name)),
                qos=Qos(Policy.Reliability.Reliable(0), Policy.History.KeepAll),
            )
            for t, type_name in topics.items()
        }
        self.data: dict[str, list[bytes]] = {t: [] for t in topics}

    def take(self) -> dict[str, list[bytes]]:
        for t, reader in self.readers.items():
            self.data[t] += raw_take(reader)
        return self.data

    def count(self, topic: str) -> int:
        return len(self.take()[topic])


def wait_matched(node, transport, inputs, outputs, timeout_s=60.0):
    """Until the node's readers match this process's writers on `inputs` and its writers the
    raw readers of `outputs`."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if node.poll() is not None:
            raise AssertionError(f"the node exited: {node.communicate()[1]}")
        if all(transport.subscriber_count(t) >= 1 for t in inputs) and all(
            r.get_subscription_matched_status().current_count >= 1 for r in outputs
        ):
            return
        time.sleep(0.05)
    raise AssertionError("the node did not match the test's endpoints")


def node_writers(raw, outputs: Outputs) -> dict:
    """{DDS topic: publication} of the ROS 2 writers (those with USER_DATA) on the output topics
    that `raw` has discovered (called while the node runs)."""
    names = {dds_topic_name(t) for t in outputs.types}
    return {
        e.topic_name: e
        for e in endpoints(raw, BuiltinTopicDcpsPublication)
        if Policy.Userdata in e.qos and e.topic_name in names
    }


def check_wire(store, codec, writers: dict, outputs: Outputs) -> dict[str, list[dict]]:
    """Every sample the node wrote on each output topic: its bytes are rosbags' CDR of the
    message it decodes to, and the node's writer (`writers`, see `node_writers`) announces the
    DDS type name and the RIHS01 hash rosbags computes. Returns {topic: decoded messages}."""
    decoded = {}
    for topic, data in outputs.take().items():
        type_name = outputs.types[topic]
        decoded[topic] = []
        for sample in data:
            msg = codec.decode(type_name, sample)
            want = bytes(store.serialize_cdr(rosbags_message(store, type_name, msg), type_name))
            assert sample == padded(want), (topic, msg)
            decoded[topic].append(msg)
    for topic, type_name in outputs.types.items():
        if not outputs.data[topic]:
            continue
        w = writers[dds_topic_name(topic)]
        assert w.type_name == dds_type_name(type_name)
        hash_data = f"typehash={store.hash_rihs01(type_name)};".encode()
        assert w.qos[Policy.Userdata] == Policy.Userdata(hash_data)
        assert isinstance(w.qos[Policy.Reliability], Policy.Reliability.Reliable)
        assert w.qos[Policy.History] == Policy.History.KeepLast(10)
    return decoded


def ns_of(t: dict) -> int:
    return t["sec"] * 1_000_000_000 + t["nanosec"]


def test_tag_input_matches_fpe_predict_none_dropped(dds, drive):
    """One opponent from AprilTag detections + TF at 40 Hz: every published path equals
    `fpe predict` on the same log within 1e-6 m, none dropped, every output sample rosbags'."""
    env, player, raw = dds
    tmp, _ = drive
    store = typestore("ros2")
    log = open_log(tmp / "sim" / "drive.mcap")
    msgs = list(log.messages(["/tf", "/tf_static", "/tag_detections"]))
    full = {t: msgtype.replace("/", "/msg/", 1) for t, msgtype, _, _ in msgs}
    pubs = {t: player.advertise(t, type_name) for t, type_name in full.items()}
    out_types = {OUTPUTS[k][0]: OUTPUTS[k][1] for k in ("markers", "path", "covariance")}
    out_types[OUTPUTS["obstacles"][0]] = OUTPUTS["obstacles"][1]
    outputs = Outputs(raw, player.codec, out_types)
    wp = tmp / "sim" / "waypoints.csv"
    node = start_node("ros2", env, "--config", str(tmp / "cfg.json"), "--waypoints", str(wp))
    try:
        wait_matched(node, player, pubs, outputs.readers.values())
        for topic, _, _, msg in [m for m in msgs if m[0] == "/tf_static"]:
            pubs[topic](msg_dict(msg, "ros2"))
        time.sleep(0.5)
        for topic, _, _, msg in [m for m in msgs if m[0] != "/tf_static"]:
            pubs[topic](msg_dict(msg, "ros2"))
            if topic == "/tag_detections":
                time.sleep(1.0 / RATE_HZ)
        by_stamp = predicted_rows(tmp / "pred.csv")
        n_want = len(by_stamp)
        wait_for(
            lambda: (
                outputs.count("/future_pose/path") >= n_want
                and outputs.count("/future_pose/covariance") >= n_want * H
            )
        )
        writers = node_writers(raw, outputs)
    finally:
        err = stop_node(node)
    got = check_wire(store, player.codec, writers, outputs)
    paths = got["/future_pose/path"]
    stamps = sorted(ns_of(m["header"]["stamp"]) for m in paths)
    missing = [k for k in sorted(by_stamp) if min(abs(k - g) for g in stamps) > 2]
    assert len(paths) == n_want, (missing, err)  # none dropped, none extra
    for m in paths:
        ns = ns_of(m["header"]["stamp"])
        row = by_stamp[min(by_stamp, key=lambda k: abs(k - ns))]
        assert abs(row["stamp"][0] * 1e9 - ns) < 2.0  # the observation's stamp (CSV rounds to 1 ns)
        assert m["header"]["frame_id"] == "map"
        xy = np.array(
            [[p["pose"]["position"]["x"], p["pose"]["position"]["y"]] for p in m["poses"]]
        )
        np.testing.assert_allclose(xy, np.column_stack([row["x"], row["y"]]), atol=1e-6, rtol=0)
        q = [p["pose"]["orientation"] for p in m["poses"]]
        yaw = np.array([2 * np.arctan2(o["z"], o["w"]) for o in q])
        np.testing.assert_allclose((yaw - row["yaw"] + np.pi) % (2 * np.pi) - np.pi, 0, atol=1e-6)
        steps = [ns_of(p["header"]["stamp"]) - ns for p in m["poses"]]
        assert steps == [round(k * 0.1e9) for k in range(1, H + 1)]
    markers = got["/future_pose"]  # at most one prediction's every --markers-every (0.1 s)
    assert 0 < len(markers) <= n_want
    assert {ns_of(m["markers"][0]["header"]["stamp"]) for m in markers} <= set(stamps)
    assert [mk["type"] for mk in markers[0]["markers"]] == [7, 4, 5]  # points, line, ellipses
    covs = got["/future_pose/covariance"]
    assert len(covs) == n_want * H
    traces = sorted(
        {round(c["pose"]["covariance"][0] + c["pose"]["covariance"][7], 9) for c in covs}
    )
    assert traces == sorted({round(c[0][0] + c[1][1], 9) for c in COV})
    assert len(got["/future_pose/obstacles"]) == n_want
    assert "stopped after" in err


def test_obstacle_input_four_opponents(dds, drive, tmp_path):
    """Four opponents in one ROS 2 ObstacleArray (no variance fields) at 40 Hz, a line model:
    every per-opponent path equals its runner's prediction, none dropped; the predicted
    ObstacleArray and the OpponentTrajectory are rosbags' CDR of the ROS 2 definitions."""
    env, player, raw = dds
    tmp, _ = drive
    store = typestore("ros2")
    wp_file = tmp / "sim" / "waypoints.csv"
    xy_wp = load_waypoints_xy(wp_file)
    n = 32
    params = Params.create(
        Settings(model="line"), weights=1.0, line_offset_m=0.1 * np.sin(np.arange(n) * 0.4),
        line_speed_mps=np.full(n, 4.5), line_coverage=np.ones(n),
    )  # fmt: skip
    line = {"waypoints_sha256": waypoints_sha256(xy_wp), "waypoints": str(wp_file)}
    cfg = params_to_config(params, uncertainty={"frame": "track", "cov_m2": COV}, line=line)
    write_config(tmp_path / "line.json", cfg)
    frames = obstacle_frames(tmp / "sim" / "drive.mcap", xy_wp)
    want = runner_predictions(cfg, xy_wp, frames)
    out_types = {f"/future_pose/path/opp_{i}": "nav_msgs/msg/Path" for i in OPPONENT_IDS}
    out_types["/future_pose/obstacles"] = "f110_msgs/msg/ObstacleArray"
    out_types["/opponent_trajectory"] = "f110_msgs/msg/OpponentTrajectory"
    outputs = Outputs(raw, player.codec, out_types)
    pub = player.advertise("/perception/obstacles", "f110_msgs/msg/ObstacleArray")
    node = start_node(
        "ros2", env, "--config", str(tmp_path / "line.json"), "--waypoints", str(wp_file),
        "--obstacles-topic", "/perception/obstacles",
    )  # fmt: skip
    try:
        always = [outputs.readers[t] for t in ("/future_pose/obstacles", "/opponent_trajectory")]
        wait_matched(node, player, ["/perception/obstacles"], always)
        for ns, obst in frames:
            stamp = {"sec": ns // 10**9, "nanosec": ns % 10**9}
            pub({"header": {"stamp": stamp, "frame_id": "map"}, "obstacles": obst})
            time.sleep(1.0 / RATE_HZ)
        n_want = {f"/future_pose/path/opp_{i}": len(w) for i, w in want.items()}
        wait_for(lambda: all(outputs.count(t) >= n for t, n in n_want.items()))
        time.sleep(0.3)
        writers = node_writers(raw, outputs)
    finally:
        err = stop_node(node)
    got = check_wire(store, player.codec, writers, outputs)
    for i in OPPONENT_IDS:
        paths = {ns_of(m["header"]["stamp"]): m for m in got[f"/future_pose/path/opp_{i}"]}
        assert sorted(paths) == [ns for ns, _ in want[i]], (i, err)  # none dropped, none extra
        for ns, poses in want[i]:
            m = paths[ns]
            xy = [[p["pose"]["position"]["x"], p["pose"]["position"]["y"]] for p in m["poses"]]
            np.testing.assert_allclose(np.array(xy), poses[:, :2], atol=1e-6, rtol=0)
    predicted = got["/future_pose/obstacles"]
    assert {o["id"] for m in predicted for o in m["obstacles"]} == set(OPPONENT_IDS)  # never 99
    assert max(len(m["obstacles"]) for m in predicted) == 4
    assert "s_var" not in predicted[0]["obstacles"][0]  # the ROS 2 definition
    traj = got["/opponent_trajectory"]
    assert traj, err
    wpnts = traj[-1]["oppwpnts"]
    assert len(wpnts) == n
    np.testing.assert_allclose([w["d_m"] for w in wpnts], params.physical()["line_offset_m"])
    np.testing.assert_allclose([w["proj_vs_mps"] for w in wpnts], 4.5)
