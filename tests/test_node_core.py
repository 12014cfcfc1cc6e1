"""The node core without middleware: a fake in-memory transport, bad input between good ones."""

from __future__ import annotations

import math

import numpy as np

from fpe_jax.config import params_to_config
from fpe_jax.history import drive_valid
from fpe_jax.node._core import Node, NodeOptions
from fpe_jax.params import presets
from fpe_jax.runner import Runner
from fpe_jax.sim import simulate


class FakeTransport:
    flavour = "ros2"

    def __init__(self):
        self.subs, self.out = {}, {}

    def subscribe(self, topic, type_name, callback):
        self.subs[topic] = callback

    def advertise(self, topic, type_name):
        self.out[topic] = []
        return self.out[topic].append

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
