"""The node's output bytes from templates (`fpe_jax.node._cdr.Template`, `fpe_jax.node._wire`):
equal to the type's writer on the same message, to rosbags' CDR (ROS 2) and genpy's bytes
(ROS 1), for both flavours; a layout a template cannot hold is refused when it is made."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from ros2_helpers import rosbags_message

from fpe_jax.node._cdr import CdrCodec, Ros1Writer, Template
from fpe_jax.node._types import typestore
from fpe_jax.node._wire import Wire

H = 10
NS = 1_700_000_123_987_654_321
FLAVOURS = ("ros1", "ros2")


def encoder(flavour: str):
    store = typestore(flavour)
    return (Ros1Writer(store) if flavour == "ros1" else CdrCodec(store)).encode


def wire(flavour: str, horizon: int = H) -> Wire:
    var = {"s_var": 0.01, "d_var": 0.02, "vs_var": 0.5, "vd_var": 0.25}
    return Wire(encoder(flavour), flavour, "map", horizon, 0.1, var if flavour == "ros1" else None)


def prediction(seed: int, horizon: int = H):
    """(H, 3) poses (x, y, yaw; one yaw NaN: no orientation) and (H, 2, 2) covariances."""
    rng = np.random.default_rng(seed)
    poses = rng.normal(scale=20.0, size=(horizon, 3))
    poses[3, 2] = np.nan
    a = rng.normal(size=(horizon, 2, 2))
    return poses, a @ np.swapaxes(a, -1, -2)


@pytest.mark.parametrize("flavour", FLAVOURS)
def test_wire_bytes_equal_the_writers_on_the_same_message(flavour):
    """Every output, two different predictions each (the second from the kept template): the
    template's bytes are the type's writer's for the message dict that describes them."""
    w, encode = wire(flavour), encoder(flavour)
    for seed in (1, 2):
        poses, cov = prediction(seed)
        ns = NS + seed * 25_000_000
        assert w.path(ns, poses) == encode("nav_msgs/msg/Path", w.path_message(ns, poses))
        want = [encode("geometry_msgs/msg/PoseWithCovarianceStamped", m)
                for m in w.covariance_messages(ns, poses, cov)]  # fmt: skip
        assert w.covariances(ns, poses, cov) == want
        for car in ("3", "117", "8", "902"):  # one template per length of the id
            for c in (cov, None):
                msg = w.markers_message(car, ns, poses, c)
                assert w.markers(car, ns, poses, c) == encode(
                    "visualization_msgs/msg/MarkerArray", msg
                )
        for n in (1, 4):
            ids = list(range(7, 7 + n))
            values = np.random.default_rng(seed + n).normal(size=(n, 8))
            msg = w.obstacles_message(ns, ids, values)
            got = w.obstacles(ns, ids, values.tolist())
            assert got == encode("f110_msgs/msg/ObstacleArray", msg)


def test_wire_meaning_and_rosbags_cdr():
    """What the bytes hold (ROS 2, decoded by the codec): stamps ns and ns + k dt, the poses,
    the NaN yaw as the zero quaternion, the covariance's x, y block; and rosbags serializes the
    decoded message to the same bytes (an independent implementation)."""
    store = typestore("ros2")
    codec = CdrCodec(store)
    w = wire("ros2")
    poses, cov = prediction(5)
    path = codec.decode("nav_msgs/msg/Path", w.path(NS, poses))
    assert path["header"] == {"stamp": {"sec": NS // 10**9, "nanosec": NS % 10**9},
                              "frame_id": "map"}  # fmt: skip
    for k, p in enumerate(path["poses"], start=1):
        t = NS + k * 100_000_000
        assert p["header"]["stamp"] == {"sec": t // 10**9, "nanosec": t % 10**9}
        pos, q = p["pose"]["position"], p["pose"]["orientation"]
        assert [pos["x"], pos["y"], pos["z"]] == [*poses[k - 1, :2], 0.0]
        if k == 4:
            assert q == {"x": 0.0, "y": 0.0, "z": 0.0, "w": 0.0}
        else:
            turn = 2 * np.arctan2(q["z"], q["w"]) - poses[k - 1, 2]
            assert abs((turn + np.pi) % (2 * np.pi) - np.pi) < 1e-12
    covs = [codec.decode("geometry_msgs/msg/PoseWithCovarianceStamped", b)
            for b in w.covariances(NS, poses, cov)]  # fmt: skip
    for k, c in enumerate(covs):
        full = np.array(c["pose"]["covariance"]).reshape(6, 6)
        assert np.array_equal(full[:2, :2], cov[k])
        assert not full[2:].any() and not full[:, 2:].any()
    outputs = [
        ("nav_msgs/msg/Path", w.path(NS, poses)),
        ("geometry_msgs/msg/PoseWithCovarianceStamped", w.covariances(NS, poses, cov)[0]),
        ("visualization_msgs/msg/MarkerArray", w.markers("2", NS, poses, cov)),
        ("f110_msgs/msg/ObstacleArray", w.obstacles(NS, [2, 5], [[0.5] * 8, [-1.0] * 8])),
    ]
    for type_name, data in outputs:
        msg = rosbags_message(store, type_name, codec.decode(type_name, data))
        assert bytes(store.serialize_cdr(msg, type_name)) == data, type_name


def test_template_refuses_what_it_cannot_hold():
    """A number leaf on a string, an unknown struct code, a string leaf of another length, a
    value its field cannot hold and a wrong number of values are refused: a template never
    sends wrong bytes. A fixed-length string leaf is filled as the writer writes it."""
    encode = CdrCodec(typestore("ros2")).encode
    t = "std_msgs/msg/Header"
    msg = {"stamp": {"sec": 1, "nanosec": 2}, "frame_id": "map"}
    with pytest.raises(ValueError, match="string"):
        Template(lambda m: encode(t, m), msg, {"f": ("I", [("frame_id",)])})
    with pytest.raises(ValueError, match="struct code"):
        Template(lambda m: encode(t, m), msg, {"f": ("q", [("stamp", "sec")])})
    with pytest.raises(ValueError, match="length"):  # a string leaf of another length
        Template(lambda m: encode(t, m), msg, {"f": ("4s", [("frame_id",)])})
    frame = Template(lambda m: encode(t, m), msg, {"f": ("3s", [("frame_id",)])})
    assert frame.fill(f=[b"odm"]) == encode(t, msg | {"frame_id": "odm"})
    with pytest.raises(ValueError, match="3 bytes"):  # struct would cut or pad it silently
        frame.fill(f=[b"odom"])
    stamp = Template(lambda m: encode(t, m), msg, {"s": ("i", [("stamp", "sec")])})
    assert stamp.fill(s=[7]) == encode(t, msg | {"stamp": {"sec": 7, "nanosec": 2}})
    with pytest.raises(struct.error):
        stamp.fill(s=[2**31])  # past int32: refused, never wrapped
    with pytest.raises(ValueError):  # a value count other than the group's
        stamp.fill(s=[1, 2])
