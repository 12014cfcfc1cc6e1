"""ROS 2 on the wire (fpe_jax/node/_dds.py): real Cyclone DDS on the loopback interface, in a
test-private domain, against rosbags as an independent CDR implementation and type hasher."""

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

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

from cyclonedds.builtin import (
    BuiltinTopicDcpsPublication,
    BuiltinTopicDcpsSubscription,
)
from cyclonedds.core import Policy, Qos
from cyclonedds.domain import DomainParticipant
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from ros2_helpers import (
    BEST_EFFORT_TOPIC,
    LOOPBACK_URI,
    catalogue,
    endpoints,
    padded,
    plain,
    random_message,
    raw_take,
    ros2_typestore,
    rosbags_message,
    wait_until,
)

from fpe_jax.node._cdr import CdrCodec
from fpe_jax.node._dds import (
    DISCOVERY_TOPIC,
    DdsTransport,
    IdlCodec,
    dds_topic_name,
    dds_type_name,
    resolve_domain_id,
    ros_type_name,
)

HELPERS = Path(__file__).parents[1] / "ros2_helpers.py"
ROUNDS = 8  # 0.2 s of messages at 40 Hz


@pytest.fixture(scope="module")
def store():
    return ros2_typestore()


@pytest.fixture(scope="module")
def domain_id():
    """A domain of this test run alone, and Cyclone DDS on loopback, for this process and the
    processes it starts."""
    saved = {k: os.environ.get(k) for k in ("CYCLONEDDS_URI", "ROS_DOMAIN_ID")}
    domain = 1 + os.getpid() % 200
    os.environ["CYCLONEDDS_URI"] = LOOPBACK_URI
    os.environ["ROS_DOMAIN_ID"] = str(domain)
    yield domain
    for key, value in saved.items():
        if value is None:
            os.environ.pop(key, None)
        else:
            os.environ[key] = value


def _assert_values(received, sent, where: str = "msg") -> None:
    """Every value `sent` sets is what was received (float32 fields to float32 precision)."""
    if isinstance(sent, dict):
        for key, value in sent.items():
            _assert_values(received[key], value, f"{where}.{key}")
    elif isinstance(sent, list):
        assert len(received) == len(sent), where
        for i, (a, b) in enumerate(zip(received, sent)):
            _assert_values(a, b, f"{where}[{i}]")
    elif isinstance(sent, float):
        assert received == pytest.approx(sent, rel=1e-7, abs=1e-30), where
    else:
        assert received == sent, where


# --- names, domain, codec ---------------------------------------------------------------------


def test_names():
    assert dds_topic_name("/future_pose/path") == "rt/future_pose/path"
    assert dds_topic_name("tag_detections") == "rt/tag_detections"
    assert (
        dds_type_name("geometry_msgs/msg/PoseStamped") == "geometry_msgs::msg::dds_::PoseStamped_"
    )
    assert ros_type_name("f110_msgs::msg::dds_::ObstacleArray_") == "f110_msgs/msg/ObstacleArray"
    assert ros_type_name("PoseStamped") is None
    for bad in ("", "/", "/a//b", "/a/", "/1a", "/a b", "~/a", "/a/{b}", "rt/a-b"):
        with pytest.raises(ValueError, match="not a valid topic name"):
            dds_topic_name(bad)
    with pytest.raises(ValueError, match="pkg/msg/Type"):
        dds_type_name("geometry_msgs/PoseStamped")


def test_domain_id(monkeypatch):
    monkeypatch.delenv("ROS_DOMAIN_ID", raising=False)
    assert resolve_domain_id(None) == 0
    monkeypatch.setenv("ROS_DOMAIN_ID", " 42 ")
    assert resolve_domain_id(None) == 42
    assert resolve_domain_id(7) == 7
    monkeypatch.setenv("ROS_DOMAIN_ID", "x")
    with pytest.raises(ValueError, match="ROS_DOMAIN_ID='x'"):
        resolve_domain_id(None)
    monkeypatch.setenv("ROS_DOMAIN_ID", "233")
    with pytest.raises(ValueError, match="0..232"):
        resolve_domain_id(None)
    with pytest.raises(ValueError, match="domain_id=-1"):
        resolve_domain_id(-1)


def test_transport_takes_ros_domain_id(store, domain_id):
    with DdsTransport(store) as transport:
        assert transport.domain_id == domain_id
        assert transport._participant.domain_id == domain_id


@pytest.mark.parametrize("topic", list(catalogue()))
def test_cdr_equals_rosbags(store, topic):
    """The transport's CDR of each message the node reads or writes is rosbags' CDR, byte for
    byte with the encapsulation header, and decodes back to the same values."""
    codec = IdlCodec(store)
    for r in range(2):
        type_name, msg = catalogue(r)[topic]
        data = codec.encode(type_name, msg)
        expected = bytes(store.serialize_cdr(rosbags_message(store, type_name, msg), type_name))
        assert data[:4] == b"\x00\x01\x00\x00"  # CDR_LE, no options
        assert data == expected
        back = codec.decode(type_name, data)
        _assert_values(back, plain(msg))
        assert codec.encode(type_name, back) == data


def test_every_type_of_the_store(store):
    """Every message type of the ROS 2 store (standard, AprilTag and f110_msgs types alike) gets
    a DDS type whose zero message is rosbags' zero message, byte for byte."""
    codec = IdlCodec(store)
    names = sorted(store.fielddefs)
    assert len(names) > 150
    for name in names:
        expected = bytes(store.serialize_cdr(rosbags_message(store, name, {}), name))
        assert codec.encode(name, {}) == expected, name


def test_random_messages_of_every_type(store):
    """Random values in every field of every type: the bytes are rosbags', and decoding gives
    the same values back."""
    codec = IdlCodec(store)
    rng = np.random.default_rng(33)
    for name in sorted(store.fielddefs):
        msg = random_message(store, name, rng)
        data = codec.encode(name, msg)
        expected = bytes(store.serialize_cdr(rosbags_message(store, name, msg), name))
        assert data == expected, name
        assert codec.decode(name, data) == msg, name


def test_generated_codec_of_every_type(store):
    """The generated writers and readers alone (no fallback to the IDL samples): zero and
    random messages of every type are rosbags' bytes, and read back as cyclonedds' own
    deserializer reads them."""
    fast, idl = CdrCodec(store), IdlCodec(store)
    rng = np.random.default_rng(34)
    for name in sorted(store.fielddefs):
        for msg in ({}, random_message(store, name, rng), random_message(store, name, rng)):
            data = fast.encode(name, msg)
            assert data == bytes(store.serialize_cdr(rosbags_message(store, name, msg), name)), name
            reference = idl.to_dict(name, idl.idl_class(name).deserialize(data))
            assert fast.decode(name, data) == reference, name
    for topic, (name, msg) in catalogue(1).items():
        assert fast.encode(name, msg) == bytes(
            store.serialize_cdr(rosbags_message(store, name, msg), name)
        ), topic


def test_missing_fields_are_zero(store):
    codec = IdlCodec(store)
    empty = codec.encode("nav_msgs/msg/Odometry", {})
    zero = rosbags_message(store, "nav_msgs/msg/Odometry", {})
    assert empty == bytes(store.serialize_cdr(zero, "nav_msgs/msg/Odometry"))
    msg = codec.decode("nav_msgs/msg/Odometry", empty)
    assert msg["pose"]["covariance"] == [0.0] * 36
    assert msg["header"] == {"stamp": {"sec": 0, "nanosec": 0}, "frame_id": ""}


@pytest.mark.parametrize(
    ("type_name", "msg", "match"),
    [
        ("geometry_msgs/msg/PoseStamped", {"hedaer": {}}, r"PoseStamped: unknown field 'hedaer'"),
        (
            "geometry_msgs/msg/PoseStamped",
            {"pose": {"position": {"x": 1.0, "q": 2.0}}},
            r"PoseStamped\.pose\.position: unknown field 'q' of geometry_msgs/msg/Point",
        ),
        (
            "nav_msgs/msg/Path",
            {"poses": [{}, {"pose": {"orientation": {"W": 1.0}}}]},
            r"Path\.poses\[1\]\.pose\.orientation: unknown field 'W'",
        ),
        (
            "geometry_msgs/msg/PoseStamped",
            {"pose": {"position": {"x": "1.0"}}},
            r"position\.x: expected a number \(float64\), got '1.0'",
        ),
        (
            "geometry_msgs/msg/PoseStamped",
            {"header": {"stamp": {"sec": 1.5}}},
            r"stamp\.sec: expected an integer \(int32\), got 1.5",
        ),
        (
            "geometry_msgs/msg/PoseStamped",
            {"header": {"stamp": {"nanosec": -1}}},
            r"stamp\.nanosec: -1 is out of the range of uint32",
        ),
        (
            "geometry_msgs/msg/PoseWithCovarianceStamped",
            {"pose": {"covariance": [0.0] * 35}},
            r"pose\.covariance: expected 36 elements, got 35",
        ),
        ("geometry_msgs/msg/PoseStamped", {"header": 3}, r"header: expected a dict"),
        (
            "f110_msgs/msg/ObstacleArray",
            {"obstacles": [{"is_static": 1.0}]},
            r"obstacles\[0\]\.is_static: expected a bool",
        ),
        ("f110_msgs/msg/ObstacleArray", {"obstacles": {}}, r"obstacles: expected a list"),
        ("geometry_msgs/msg/PoseStamped", {"header": {"frame_id": 5}}, r"expected a string"),
        ("geometry_msgs/PoseStamped", {}, r"pkg/msg/Type"),
        ("nope_msgs/msg/Nope", {}, r"'nope_msgs/msg/Nope' is not in the type store"),
    ],
)
def test_bad_messages_raise(store, domain_id, type_name, msg, match):
    with pytest.raises(ValueError, match=match):
        IdlCodec(store).encode(type_name, msg)
    if type_name in store.fielddefs:  # the generated writer refuses it too
        with pytest.raises(Exception):  # noqa: B017 - any: IdlCodec then names the problem
            CdrCodec(store).encode(type_name, msg)


@pytest.mark.parametrize(
    ("type_name", "msg"),
    [
        ("geometry_msgs/msg/PoseStamped", {"pose": {"position": {"x": True}}}),
        ("geometry_msgs/msg/PoseStamped", {"header": {"stamp": {"sec": np.True_}}}),
        ("geometry_msgs/msg/PoseStamped", {"header": {"stamp": {"sec": 2**31}}}),
        ("geometry_msgs/msg/PoseStamped", {"header": None}),
        ("geometry_msgs/msg/PoseWithCovarianceStamped", {"pose": {"covariance": [True] * 36}}),
        ("geometry_msgs/msg/PoseWithCovarianceStamped", {"pose": {"covariance": None}}),
        ("nav_msgs/msg/Path", {"poses": "abc"}),
        ("sensor_msgs/msg/CompressedImage", {"data": [256]}),
        ("sensor_msgs/msg/CompressedImage", {"data": [False]}),
        ("sensor_msgs/msg/JointState", {"name": "abc"}),
        ("sensor_msgs/msg/JointState", {"name": ["a", 3]}),
        ("f110_msgs/msg/ObstacleArray", {"obstacles": [{"is_static": 0}]}),
    ],
)
def test_generated_writer_refuses_what_the_checks_refuse(store, type_name, msg):
    """Values the field checks refuse (bools as numbers, out of range, None, a string as a
    list) are refused by the generated writer as well, never written as something else."""
    with pytest.raises(ValueError, match=type_name.rsplit("/", 1)[1]):
        IdlCodec(store).encode(type_name, msg)
    with pytest.raises(Exception):  # noqa: B017 - any: IdlCodec then names the problem
        CdrCodec(store).encode(type_name, msg)


def test_publish_checks_fields(store, domain_id):
    with DdsTransport(store) as transport:
        publish = transport.advertise("/checked", "geometry_msgs/msg/PoseStamped")
        with pytest.raises(ValueError, match="PoseStamped: unknown field 'pos'"):
            publish({"pos": {}})
        with pytest.raises(ValueError, match="already advertised as geometry_msgs/msg/PoseStamp"):
            transport.advertise("checked", "nav_msgs/msg/Odometry")  # the same topic
        with pytest.raises(ValueError, match="not in the type store"):
            transport.advertise("/other", "geometry_msgs/msg/PoseStampd")


def test_spin_stops_promptly_and_close_is_final(store, domain_id):
    transport = DdsTransport(store)
    transport.subscribe("/idle", None, lambda *a: None)
    stop = threading.Event()
    thread = threading.Thread(target=transport.spin, args=(stop,))
    thread.start()
    time.sleep(0.1)
    start = time.monotonic()
    stop.set()
    thread.join(2.0)
    assert not thread.is_alive()
    assert time.monotonic() - start < 0.2
    # closing from another thread ends a running spin
    thread = threading.Thread(target=transport.spin, args=(threading.Event(),))
    thread.start()
    time.sleep(0.05)
    transport.close()
    thread.join(2.0)
    assert not thread.is_alive()
    transport.close()
    with pytest.raises(RuntimeError, match="after close"):
        transport.advertise("/x", "geometry_msgs/msg/PoseStamped")


# --- two processes on loopback --------------------------------------------------------------


def test_two_processes(store, domain_id):
    """A publisher process (the transport, plus a plain cyclonedds best-effort writer) and this
    process: every message arrives with its values; the bytes on the wire are rosbags' CDR; the
    DDS type names, QoS and RIHS01 type hashes are ROS 2's; subscriptions without a type take it
    from discovery; the publisher node announces its endpoints on ros_discovery_info."""
    topics = catalogue()
    received: dict[str, list] = {topic: [] for topic in [*topics, BEST_EFFORT_TOPIC]}
    lock = threading.Lock()

    def on(topic):
        def callback(msg, type_name, receive_ns):
            with lock:
                received[topic].append((msg, type_name, receive_ns))

        return callback

    transport = DdsTransport(store, node_name="fpe_test_sub")
    raw_participant = DomainParticipant(domain_id)
    raw_readers = {}
    for topic, (type_name, _) in topics.items():
        # the two input topics learn their type from the publisher's announcement
        transport.subscribe(topic, None if topic.startswith("/opponent/") else type_name, on(topic))
        raw_readers[topic] = DataReader(
            raw_participant,
            Topic(raw_participant, dds_topic_name(topic), transport.codec.idl_class(type_name)),
            qos=Qos(Policy.Reliability.Reliable(0), Policy.History.KeepAll),
        )
    transport.subscribe(BEST_EFFORT_TOPIC, "geometry_msgs/msg/PoseStamped", on(BEST_EFFORT_TOPIC))
    assert transport.topic_type("/opponent/odom") is None  # no writer seen yet

    stop = threading.Event()
    spinner = threading.Thread(target=transport.spin, args=(stop,))
    spinner.start()
    publisher = subprocess.Popen(
        [sys.executable, str(HELPERS), str(ROUNDS), "2", "0.025"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert publisher.stdout.readline() == "matched\n", publisher.communicate()
        for topic in received:
            wait_until(
                lambda t=topic: transport.publisher_count(t) >= 1, 20, f"a writer of {topic}"
            )
        publisher.stdin.write("go\n")
        publisher.stdin.flush()
        end = time.monotonic() + 30
        while time.monotonic() < end and publisher.poll() is None:
            if all(len(v) >= ROUNDS for v in received.values()):
                break
            time.sleep(0.01)
        stop.set()
        spinner.join(5.0)
        missing = {topic: ROUNDS - len(v) for topic, v in received.items() if len(v) != ROUNDS}
        assert not missing, f"messages missing (or extra) per topic: {missing}"
        assert publisher.poll() is None, publisher.communicate()
        publications = endpoints(raw_participant, BuiltinTopicDcpsPublication)
        subscriptions = endpoints(raw_participant, BuiltinTopicDcpsSubscription)
        announced = DataReader(
            raw_participant,
            Topic(
                raw_participant,
                DISCOVERY_TOPIC,
                transport.codec.idl_class("rmw_dds_common/msg/ParticipantEntitiesInfo"),
            ),
            qos=Qos(
                Policy.Reliability.Reliable(0),
                Policy.Durability.TransientLocal,
                Policy.History.KeepLast(16),  # keyless: one history for all writers
            ),
        )
        wait_until(lambda: len(announced.read(N=16)) >= 2, 5, "ros_discovery_info")
        infos = [
            transport.codec.to_dict("rmw_dds_common/msg/ParticipantEntitiesInfo", s)
            for s in announced.read(N=16)
        ]
    finally:
        _, errors = publisher.communicate(timeout=10)  # closing stdin ends the publisher
        transport.close()
    assert publisher.returncode == 0, errors

    # (a) every message of every round arrived, types included; none dropped at 40 Hz
    for topic, (type_name, _) in topics.items():
        got = received[topic]
        assert len(got) == ROUNDS, topic
        for r, (msg, got_type, receive_ns) in enumerate(got):
            assert got_type == type_name
            assert abs(receive_ns - time.time_ns()) < 120e9
            _assert_values(msg, plain(catalogue(r)[topic][1]), topic)
    assert [m["pose"] for m, _, _ in received[BEST_EFFORT_TOPIC]] == [
        m["pose"] for m, _, _ in received["/opponent/pose"]
    ]

    # (b) the wire bytes are rosbags' CDR (the writer pads samples to a multiple of 4 bytes)
    for topic, (type_name, _) in topics.items():
        wire = raw_take(raw_readers[topic])
        assert len(wire) == ROUNDS, topic
        for r, data in enumerate(wire):
            msg = rosbags_message(store, type_name, catalogue(r)[topic][1])
            assert data == padded(bytes(store.serialize_cdr(msg, type_name))), (topic, r)

    # (c) DDS names, QoS and the RIHS01 hashes rosbags computes, on writers and readers
    for topic, (type_name, _) in topics.items():
        user_data = f"typehash={store.hash_rihs01(type_name)};".encode()
        writers = [p for p in publications if p.topic_name == dds_topic_name(topic)]
        assert len(writers) == 1, topic
        assert writers[0].type_name == dds_type_name(type_name)
        qos = writers[0].qos
        assert qos[Policy.Userdata] == Policy.Userdata(user_data)
        assert isinstance(qos[Policy.Reliability], Policy.Reliability.Reliable)
        assert qos[Policy.Durability] == Policy.Durability.Volatile
        assert qos[Policy.History] == Policy.History.KeepLast(10)
        readers = [
            s
            for s in subscriptions
            if s.topic_name == dds_topic_name(topic) and Policy.Userdata in s.qos
        ]
        assert len(readers) == 1, topic
        assert readers[0].type_name == dds_type_name(type_name)
        assert readers[0].qos[Policy.Userdata] == Policy.Userdata(user_data)
        # reliable writers only: a reliable reader, which loses nothing
        assert isinstance(readers[0].qos[Policy.Reliability], Policy.Reliability.Reliable)
    (reader,) = [s for s in subscriptions if s.topic_name == dds_topic_name(BEST_EFFORT_TOPIC)]
    assert reader.qos[Policy.Reliability] == Policy.Reliability.BestEffort

    # ros_discovery_info: the publisher's node owns exactly its writers of the catalogue topics
    pub_info = [i for i in infos if i["node_entities_info_seq"][0]["node_name"] == "fpe_test_pub"]
    assert len(pub_info) == 1
    node = pub_info[0]["node_entities_info_seq"][0]
    assert node["node_namespace"] == "/"
    writer_keys = {
        p.key.bytes for p in publications if p.topic_name in {dds_topic_name(t) for t in topics}
    }
    assert {bytes(g["data"]) for g in node["writer_gid_seq"]} == writer_keys
    participant = {p.participant_key.bytes for p in publications if p.key.bytes in writer_keys}
    assert {bytes(pub_info[0]["gid"]["data"])} == participant


def test_subscribe_without_type_learns_it_in_process(store, domain_id):
    """One process, two participants: a subscription with type None before the writer exists,
    and the reader follows once the writer appears."""
    with DdsTransport(store, node_name="a") as a, DdsTransport(store, node_name="b") as b:
        got = []
        b.subscribe("/late", None, lambda m, t, ns: got.append((m, t)))
        stop = threading.Event()
        thread = threading.Thread(target=b.spin, args=(stop,))
        thread.start()
        try:
            time.sleep(0.1)
            publish = a.advertise("/late", "nav_msgs/msg/Odometry")
            wait_until(lambda: a.subscriber_count("/late") == 1, 10, "the late reader")
            assert b.publisher_count("/late") == 1
            publish({"child_frame_id": "car", "twist": {"twist": {"linear": {"x": 2.5}}}})
            wait_until(lambda: got, 5, "the message")
        finally:
            stop.set()
            thread.join(2.0)
        msg, type_name = got[0]
        assert type_name == "nav_msgs/msg/Odometry"
        assert msg["child_frame_id"] == "car"
        assert msg["twist"]["twist"]["linear"] == {"x": 2.5, "y": 0.0, "z": 0.0}
        assert np.array_equal(msg["pose"]["covariance"], np.zeros(36))


def _tf(k: int) -> dict:
    return {"transforms": [{"header": {"stamp": {"sec": k}, "frame_id": "map"},
                            "child_frame_id": f"car{k}"}]}  # fmt: skip


def test_tf_takes_tf2s_qos(store, domain_id):
    """TF as tf2_ros has it: /tf_static is transient local (a reader that subscribes after the
    static broadcaster published still gets its transforms), and TF readers and writers keep
    100 samples, so a burst of transforms between two spins loses none."""
    with DdsTransport(store, node_name="a") as a, DdsTransport(store, node_name="b") as b:
        static = a.advertise("/tf_static", "tf2_msgs/msg/TFMessage")
        dynamic = a.advertise("/tf", "tf2_msgs/msg/TFMessage")
        static(_tf(0))
        got = {"/tf": [], "/tf_static": []}
        for topic, out in got.items():
            b.subscribe(topic, "tf2_msgs/msg/TFMessage", lambda m, t, ns, o=out: o.append(m))
        wait_until(lambda: a.subscriber_count("/tf") == 1, 10, "the /tf reader")
        wait_until(lambda: a.subscriber_count("/tf_static") == 1, 10, "the /tf_static reader")
        for k in range(1, 61):  # nobody spins: the reader holds them
            dynamic(_tf(k))
        time.sleep(0.5)
        stop = threading.Event()
        thread = threading.Thread(target=b.spin, args=(stop,))
        thread.start()
        try:
            wait_until(lambda: len(got["/tf"]) >= 60 and got["/tf_static"], 5, "the transforms")
        except TimeoutError:
            pass
        finally:
            stop.set()
            thread.join(2.0)
    assert [m["transforms"][0]["child_frame_id"] for m in got["/tf_static"]] == ["car0"]
    assert [m["transforms"][0]["header"]["stamp"]["sec"] for m in got["/tf"]] == list(range(1, 61))


def test_subscribe_without_type_waits_out_unknown_types(store, domain_id, caplog):
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    other = get_typestore(Stores.ROS2_JAZZY)
    other.register(get_types_from_msg("float64 speed_mps", "team_msgs/msg/Speed"))
    with DdsTransport(other, node_name="a") as a, DdsTransport(store, node_name="b") as b:
        b.subscribe("/speed", None, lambda *args: pytest.fail("a message of an unknown type"))
        a.advertise("/speed", "team_msgs/msg/Speed")({"speed_mps": 3.0})
        stop = threading.Event()
        timer = threading.Timer(0.5, stop.set)
        timer.start()
        with caplog.at_level("WARNING", logger="fpe_jax.node._dds"):
            b.spin(stop)
        timer.join()
        assert b.topic_type("/speed") is None
        assert (
            "ROS 2 topic /speed: writers announce type team_msgs::msg::dds_::Speed_" in caplog.text
        )


def test_discovery_info_follows_the_store(domain_id):
    """A Humble store announces the node with Humble's 24-byte GIDs (the GUID, zero-padded)."""
    from rosbags.typesys import Stores, get_typestore

    humble = get_typestore(Stores.ROS2_HUMBLE)
    with DdsTransport(humble, node_name="humble_node") as transport:
        transport.advertise("/h", "geometry_msgs/msg/PoseStamped")
        type_name = "rmw_dds_common/msg/ParticipantEntitiesInfo"
        participant = DomainParticipant(domain_id)
        reader = DataReader(
            participant,
            Topic(participant, DISCOVERY_TOPIC, transport.codec.idl_class(type_name)),
            qos=Qos(Policy.Reliability.Reliable(0), Policy.Durability.TransientLocal),
        )
        infos = []

        def mine():
            infos.extend(transport.codec.to_dict(type_name, s) for s in reader.take(N=16))
            return [
                i for i in infos if i["node_entities_info_seq"][0]["node_name"] == "humble_node"
            ]

        wait_until(
            lambda: any(i["node_entities_info_seq"][0]["writer_gid_seq"] for i in mine()),
            5,
            "the node's announcement",
        )
        info = mine()[-1]
        assert bytes(info["gid"]["data"]) == transport._participant.guid.bytes + bytes(8)
        (writer,) = info["node_entities_info_seq"][0]["writer_gid_seq"]
        assert len(writer["data"]) == 24


def test_a_sample_that_does_not_decode_is_dropped_with_a_warning(store, domain_id, caplog):
    """A sample whose bytes do not hold the type (as from a writer whose layout differs under
    the same type name; here a frame_id that is not UTF-8, which Cyclone DDS' own checks of
    the layout let through) is dropped with a warning naming the topic, and the next one is
    delivered."""
    from cyclonedds._clayer import ddspy_write

    type_name = "geometry_msgs/msg/PoseStamped"
    with DdsTransport(store, node_name="a") as a, DdsTransport(store, node_name="b") as b:
        got = []
        b.subscribe("/flaky", type_name, lambda m, t, ns: got.append(m))
        publish = a.advertise("/flaky", type_name)
        wait_until(lambda: a.subscriber_count("/flaky") == 1, 10, "the reader")
        good = a.codec.encode(type_name, {"header": {"frame_id": "ab"}})
        bad = good.replace(b"ab\0", b"\xff\xfe\0")
        assert ddspy_write(a._writers["/flaky"][0]._ref, bad + bytes(-len(bad) & 3)) == 0
        publish({"pose": {"position": {"x": 2.0}}})
        stop = threading.Event()
        with caplog.at_level("WARNING", logger="fpe_jax.node._dds"):
            thread = threading.Thread(target=b.spin, args=(stop,))
            thread.start()
            try:
                wait_until(lambda: got, 5, "the second message")
            finally:
                stop.set()
                thread.join(2.0)
        assert [m["pose"]["position"]["x"] for m in got] == [2.0]
        assert "ROS 2 topic /flaky: dropped a sample that is not a valid" in caplog.text
        assert "geometry_msgs/msg/PoseStamped (" in caplog.text
