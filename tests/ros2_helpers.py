"""ROS 2 test helpers: the type store, a catalogue of filled messages, dicts -> rosbags messages,
and the loopback-only Cyclone DDS configuration. Importable by the tests' subprocesses (no pytest,
no JAX)."""

import numpy as np
from rosbags.interfaces import Nodetype

# ForzaETH race_stack, utilities/libraries/f110_msgs on the ros2-humble / ros2-jazzy branches
F110_ROS2 = {
    "f110_msgs/msg/Obstacle": """
int32 id
float64 s_start
float64 s_end
float64 d_right
float64 d_left
bool is_actually_a_gap
float64 s_center
float64 d_center
float64 size
float64 vs
float64 vd
bool is_static
bool is_visible
""",
    "f110_msgs/msg/ObstacleArray": "std_msgs/Header header\nf110_msgs/Obstacle[] obstacles\n",
    "f110_msgs/msg/OppWpnt": """
int32 id
float64 s_m
float64 d_m
float64 x_m
float64 y_m
float64 proj_vs_mps
float64 vd_mps
float64 d_var
float64 vs_var
""",
    "f110_msgs/msg/OpponentTrajectory": (
        "std_msgs/Header header\nint64 lap_count\nbool opp_is_on_trajectory\n"
        "f110_msgs/OppWpnt[] oppwpnts\n"
    ),
}

# Cyclone DDS on the loopback interface only: tests never reach the network
LOOPBACK_URI = (
    "<CycloneDDS><Domain><General><Interfaces><NetworkInterface name='lo'/></Interfaces>"
    "</General></Domain></CycloneDDS>"
)


def ros2_typestore():
    """The node's ROS 2 type store when the package ships one, else ROS 2 Jazzy plus f110_msgs."""
    try:
        from fpe_jax.node._types import typestore
    except ImportError:
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        store = get_typestore(Stores.ROS2_JAZZY)
        types = {}
        for name, text in F110_ROS2.items():
            types.update(get_types_from_msg(text, name))
        store.register(types)
        return store
    return typestore("ros2")


def _header(sec: int, frame: str = "map") -> dict:
    return {"stamp": {"sec": sec, "nanosec": 123_456_789}, "frame_id": frame}


def _pose(x: float, y: float, yaw: float) -> dict:
    return {
        "position": {"x": x, "y": y, "z": 0.0},
        "orientation": {"x": 0.0, "y": 0.0, "z": np.sin(yaw / 2), "w": np.cos(yaw / 2)},
    }


def _covariance(k: int) -> list[float]:
    return [0.01 * (k + 1) * (i % 7 == 0) + 1e-4 * i for i in range(36)]


def catalogue(round_: int = 0) -> dict[str, tuple[str, dict]]:
    """{ROS topic: (type, message)} of every type the node reads or publishes, every field of
    interest filled with values that differ between rounds."""
    r = round_
    sec = 1_700_000_000 + r
    poses = [{"header": _header(sec), "pose": _pose(1.0 + k, -0.5 * k, 0.1 * k)} for k in range(10)]
    markers = [
        {
            "header": _header(sec),
            "ns": "future_pose",
            "id": k,
            "type": 2,
            "action": 0,
            "pose": _pose(2.0 * k, 1.0, 0.3),
            "scale": {"x": 0.2, "y": 0.3, "z": 0.01},
            "color": {"r": 0.0, "g": 1.0, "b": 0.25, "a": 0.8},
            "lifetime": {"sec": 0, "nanosec": 500_000_000},
            "frame_locked": k % 2 == 1,
            "points": [{"x": 0.5 * i, "y": -0.25 * i, "z": 0.0} for i in range(k)],
            "text": f"step {k}",
        }
        for k in range(4)
    ]
    obstacles = [
        {
            "id": 3 + k,
            "s_start": 10.0 + k,
            "s_end": 10.5 + k,
            "d_right": -0.3,
            "d_left": 0.3,
            "is_actually_a_gap": False,
            "s_center": 10.25 + k,
            "d_center": 0.01 * k,
            "size": 0.5,
            "vs": 4.5 + r,
            "vd": -0.1,
            "is_static": k == 1,
            "is_visible": True,
        }
        for k in range(3)
    ]
    wpnts = [
        {
            "id": i,
            "s_m": 0.1 * i,
            "d_m": 0.02 * i,
            "x_m": np.cos(0.1 * i),
            "y_m": np.sin(0.1 * i),
            "proj_vs_mps": 5.0 + 0.01 * i,
            "vd_mps": 0.0,
            "d_var": 0.001 * i,
            "vs_var": 0.05,
        }
        for i in range(50)
    ]
    return {
        "/opponent/pose": (
            "geometry_msgs/msg/PoseStamped",
            {"header": _header(sec), "pose": _pose(3.25 + r, -1.5, 0.7)},
        ),
        "/opponent/odom": (
            "nav_msgs/msg/Odometry",
            {
                "header": _header(sec),
                "child_frame_id": "opponent/base_link",
                "pose": {"pose": _pose(-4.0, 2.5 + r, -2.9), "covariance": _covariance(r)},
                "twist": {
                    "twist": {
                        "linear": {"x": 5.5, "y": 0.1, "z": 0.0},
                        "angular": {"x": 0.0, "y": 0.0, "z": 0.4},
                    },
                    "covariance": np.asarray(_covariance(r + 1)),
                },
            },
        ),
        "/future_pose": ("visualization_msgs/msg/MarkerArray", {"markers": markers}),
        "/future_pose/path": (
            "nav_msgs/msg/Path",
            {"header": _header(sec), "poses": poses},
        ),
        "/future_pose/covariance": (
            "geometry_msgs/msg/PoseWithCovarianceStamped",
            {
                "header": _header(sec),
                "pose": {"pose": _pose(1.0, 2.0, 0.5 + r), "covariance": _covariance(r)},
            },
        ),
        "/perception/obstacles": (
            "f110_msgs/msg/ObstacleArray",
            {"header": _header(sec, "frenet"), "obstacles": obstacles},
        ),
        "/opponent_trajectory": (
            "f110_msgs/msg/OpponentTrajectory",
            {
                "header": _header(sec),
                "lap_count": 2**40 + r,
                "opp_is_on_trajectory": True,
                "oppwpnts": wpnts,
            },
        ),
    }


def rosbags_message(store, type_name: str, msg: dict):
    """The rosbags message object of a nested dict (missing fields zero), built from rosbags'
    own field definitions, so that its CDR comes from an implementation independent of the
    transport's."""
    cls = store.types[type_name]
    _, fields = store.fielddefs[type_name]
    values = {}
    for name, (kind, spec) in fields:
        value = msg.get(name)
        if kind == Nodetype.BASE:
            base = spec[0]
            values[name] = _base_default(base) if value is None else value
        elif kind == Nodetype.NAME:
            values[name] = rosbags_message(store, spec, value or {})
        else:
            (subkind, subspec), size = spec
            if subkind == Nodetype.BASE:
                dtype = _NUMPY.get(subspec[0])
                if dtype is None:  # string arrays are lists in rosbags
                    default = [_base_default(subspec[0])] * size if kind == Nodetype.ARRAY else []
                    values[name] = list(value) if value is not None else default
                else:
                    n = size if kind == Nodetype.ARRAY else 0
                    values[name] = np.asarray(value if value is not None else [0] * n, dtype)
            else:
                items = value if value is not None else []
                if kind == Nodetype.ARRAY and value is None:
                    items = [{}] * size
                values[name] = [rosbags_message(store, subspec, item) for item in items]
    return cls(**values)


_NUMPY = {
    "bool": np.bool_,
    "byte": np.uint8,
    "char": np.uint8,
    "int8": np.int8,
    "uint8": np.uint8,
    "int16": np.int16,
    "uint16": np.uint16,
    "int32": np.int32,
    "uint32": np.uint32,
    "int64": np.int64,
    "uint64": np.uint64,
    "float32": np.float32,
    "float64": np.float64,
}


def _base_default(base: str):
    if base == "string":
        return ""
    if base == "bool":
        return False
    if base.startswith("float"):
        return 0.0
    return 0


def plain(value):
    """A nested structure with numpy arrays and scalars as Python lists and numbers."""
    if isinstance(value, dict):
        return {k: plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple | np.ndarray):
        return [plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


BEST_EFFORT_TOPIC = "/opponent/pose_sensor"  # a sensor-data (best effort) writer's topic


def wait_until(predicate, timeout_s: float, what: str) -> None:
    """Poll `predicate` every 10 ms; raise TimeoutError naming `what` after `timeout_s`."""
    import time

    end = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > end:
            raise TimeoutError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(0.01)


def publish_catalogue(rounds: int, readers: int, period_s: float) -> None:
    """The publisher process of the two-process tests (domain from ROS_DOMAIN_ID): advertise
    every catalogue topic with DdsTransport and PoseStamped on BEST_EFFORT_TOPIC with a plain
    cyclonedds sensor-data writer; once `readers` readers match each catalogue topic (and one the
    best-effort topic), print "matched", and after a line "go" on stdin publish `rounds` rounds
    every `period_s`; then stay until stdin closes."""
    import sys
    import time

    from cyclonedds.core import Policy, Qos
    from cyclonedds.pub import DataWriter
    from cyclonedds.topic import Topic

    from fpe_jax.node._dds import DdsTransport, dds_topic_name

    store = ros2_typestore()
    with DdsTransport(store, node_name="fpe_test_pub") as transport:
        publishers = {topic: transport.advertise(topic, t) for topic, (t, _) in catalogue().items()}
        pose_type = "geometry_msgs/msg/PoseStamped"
        sensor_qos = Qos(
            Policy.Reliability.BestEffort,
            Policy.Durability.Volatile,
            Policy.History.KeepLast(5),
        )
        sensor = DataWriter(
            transport._participant,
            Topic(
                transport._participant,
                dds_topic_name(BEST_EFFORT_TOPIC),
                transport.codec.idl_class(pose_type),
            ),
            qos=sensor_qos,
        )
        for topic in publishers:
            wait_until(lambda t=topic: transport.subscriber_count(t) >= readers, 30, topic)
        wait_until(
            lambda: sensor.get_publication_matched_status().current_count >= 1,
            30,
            BEST_EFFORT_TOPIC,
        )
        # a best-effort reader drops what arrives before it has matched the writer: the test
        # says "go" once its readers see every writer
        print("matched", flush=True)
        if sys.stdin.readline().strip() != "go":
            return
        for r in range(rounds):
            start = time.monotonic()
            for topic, (_, msg) in catalogue(r).items():
                publishers[topic](msg)
            pose = catalogue(r)["/opponent/pose"][1]
            sensor.write(transport.codec.from_dict(pose_type, pose))
            time.sleep(max(0.0, period_s - (time.monotonic() - start)))
        print("published", flush=True)
        sys.stdin.read()


if __name__ == "__main__":
    import sys

    publish_catalogue(int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3]))


def random_message(store, type_name: str, rng: np.random.Generator, depth: int = 0) -> dict:
    """A message of `type_name` with every field set to random values of its type's range
    (float32 fields to float32 values, strings with non-ASCII characters, sequences of 0-3)."""
    _, fields = store.fielddefs[type_name]
    return {name: _random_value(store, node, rng, depth) for name, node in fields}


def _random_value(store, node, rng, depth):
    kind, spec = node
    if kind == Nodetype.BASE:
        base, bound = spec
        if base == "string":
            text = "".join(rng.choice(list("abcXYZ_09 äéπ→")) for _ in range(rng.integers(0, 9)))
            return text[:bound] if bound else text
        if base == "bool":
            return bool(rng.integers(0, 2))
        if base.startswith("float"):
            value = float(rng.normal(0.0, 1e3))
            return float(np.float32(value)) if base == "float32" else value
        if base == "byte":  # an octet in ROS 2; rosbags packs a scalar byte signed: 0..127 agree
            return int(rng.integers(0, 128))
        info = np.iinfo(_NUMPY[base])
        return int(rng.integers(info.min, info.max, endpoint=True, dtype=_NUMPY[base]))
    if kind == Nodetype.NAME:
        return random_message(store, spec, rng, depth + 1)
    subnode, size = spec
    n = size if kind == Nodetype.ARRAY else int(rng.integers(0, 4 if depth < 3 else 1))
    if kind == Nodetype.SEQUENCE and size:
        n = min(n, size)
    return [_random_value(store, subnode, rng, depth + 1) for _ in range(n)]
