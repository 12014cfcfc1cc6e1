"""The middleware-neutral live node: input messages in, one `Runner` per opponent, outputs out.

The core reads messages as nested dicts (see `Transport`); ROS 1 and ROS 2 differ in the
header (`seq`, `secs`/`nsecs` against `sec`/`nanosec`), which `stamp_ns` reads and `header`
writes per flavour. It writes its per-prediction outputs as the transport's bytes, filled into
templates of each layout (`fpe_jax.node._wire`).

Inputs (one kind per node):
- `pose`: geometry_msgs/PoseStamped or nav_msgs/Odometry of the opponent in the map frame;
- `tags`: apriltag_ros AprilTagDetectionArray in the camera frame, placed in the map with /tf and
  /tf_static by `fpe_jax.io.apriltag.place_tag` (the code that reads such logs);
- `obstacles`: f110_msgs/ObstacleArray (s, d along the waypoints): one runner per obstacle id,
  static obstacles ignored, a track dropped after `drop_after_s` without updates.

Outputs per valid prediction (each one optional, see `OUTPUTS`): visualization_msgs/MarkerArray
(points, line, 1-sigma ellipses), nav_msgs/Path, one geometry_msgs/PoseWithCovarianceStamped per
step, f110_msgs/ObstacleArray of the predicted state and f110_msgs/OpponentTrajectory of a line
model's learned line (when it changed, or for a new subscriber).

Time: every output header carries the stamp of the observation the prediction was made from; step
k's pose is stamped with that stamp + k * dt_s (as `fpe predict`'s `stamp + horizon_s`). The
fitted delay moves the state from the observation's stamp to the car's true time inside the
model, so the step stamps are the times the poses predict.

Bad input never stops the node: each message that cannot be used gets a rate-limited warning
naming the topic and the problem, and nothing is published for it. An observation further from the
track than `fpe run` allows (`Runner.track_distance` > `Runner.on_track_m`) is such a message.
"""

from __future__ import annotations

import collections
import math
import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

from fpe_jax.errors import InputError
from fpe_jax.io import ros_msgs as rm
from fpe_jax.io.apriltag import parse_tag_to_base, place_tag, tag_frame_name, tag_mount
from fpe_jax.io.tf import STATIC_SUFFIX, Rigid, TfBuffer
from fpe_jax.node._types import OUTPUTS
from fpe_jax.node._wire import Wire, header
from fpe_jax.runner._runner import Runner

TF_KEEP_S = 10.0  # the live TF buffer keeps this much of each dynamic edge
MAX_PENDING = 64  # detections waiting for their TF

POSE_TYPES = ("geometry_msgs/msg/PoseStamped", "nav_msgs/msg/Odometry")
TAG_TYPE = "apriltag_ros/msg/AprilTagDetectionArray"
OBSTACLES_TYPE = "f110_msgs/msg/ObstacleArray"
TF_TYPE = "tf2_msgs/msg/TFMessage"


@runtime_checkable
class Transport(Protocol):
    """A middleware (ROS 1, ROS 2): messages as nested dicts; see docs/on-the-car.md.

    `advertise` returns publish(msg), msg a dict or bytes that `encode` made (or a `Template`
    filled from them): the node writes its outputs as bytes."""

    flavour: str

    def subscribe(
        self, topic: str, type_name: str | None, callback: Callable[[dict, str, int], None]
    ) -> None: ...

    def advertise(self, topic: str, type_name: str) -> Callable[[dict | bytes], None]: ...

    def encode(self, type_name: str, msg: dict) -> bytes: ...

    def subscriber_count(self, topic: str) -> int: ...

    def spin(self, stop: threading.Event) -> None: ...

    def close(self) -> None: ...


@dataclass
class NodeOptions:
    """What the node reads and writes (the `fpe node` flags).

    input: "pose", "tags" or "obstacles"; topic: its topic. outputs: {output name: topic or None
    (off)} over `OUTPUTS`. markers_every_s: each opponent's markers go out at most once in this
    time, one opponent's per input message (the MarkerArray, a view, is the costliest message to
    encode); trajectory_every_s: the OpponentTrajectory's period. The tag input's frames and
    mount as `fpe fit`'s flags.
    """

    input: str = "pose"
    topic: str = "/opp/pose"
    map_frame: str = "map"
    tf_topics: tuple[str, ...] = ("/tf", "/tf_static")
    tag_id: int = 0
    tag_to_base: Any = None
    car_frame: str = "other_base_link"
    drop_after_s: float = 1.0
    tf_wait_s: float = 0.5
    max_tracks: int = 16
    warn_every_s: float = 5.0
    trajectory_every_s: float = 1.0
    adapt: bool = False  # each opponent's runner learns its line and pace (fpe_jax.runner)
    delay_s: float | None = None  # with adapt and no config: the sensor's detection delay [s]
    # with adapt and a config with ellipses: each opponent's ellipses calibrated on its own
    # realised errors (`fpe_jax.runner.AdaptiveRunner`'s calibrate)
    calibrate: bool = False
    markers_every_s: float = 0.1
    outputs: dict[str, str | None] = field(
        default_factory=lambda: {k: v[0] for k, v in OUTPUTS.items()}
    )


# ---- message fields --------------------------------------------------------------------------


def stamp_ns(t: dict) -> int:
    """A ROS 1 ({secs, nsecs}) or ROS 2 ({sec, nanosec}) time as int nanoseconds."""
    if "sec" in t:
        return int(t["sec"]) * 1_000_000_000 + int(t["nanosec"])
    return int(t["secs"]) * 1_000_000_000 + int(t["nsecs"])


def _finite(*values) -> bool:
    return all(math.isfinite(v) for v in values)


class BadMessage(Exception):
    """A message the node cannot use: `problem` goes into the rate-limited warning."""


# ---- the node --------------------------------------------------------------------------------


class Node:
    """One runner per opponent behind a `Transport`.

    Args:
        transport: the middleware.
        config: a tuned config dict (`fpe_jax.io.config.read_config`), checked against
            `waypoints_xy_m` by the caller; None only with `options.adapt` (learn from the
            waypoints and the shape prior alone).
        waypoints_xy_m: (K, 2) waypoints [m] in the map frame.
        options: `NodeOptions`.
        scene: optional Foxglove `SceneSink` (observations and predictions are sent to it).
        warn: where warnings go (one line each; default stderr).
    """

    def __init__(self, transport: Transport, config: dict | None, waypoints_xy_m,
                 options: NodeOptions,
                 *, scene=None, warn: Callable[[str], None] | None = None):  # fmt: skip
        self.transport = transport
        self.flavour = transport.flavour
        self.opt = options
        if options.adapt:  # config may be None: the waypoints and the shape prior alone
            from fpe_jax.runner._adapt import AdaptiveRunner

            start = config

            def new_runner() -> Runner:
                return AdaptiveRunner(
                    start, waypoints_xy_m, delay_s=options.delay_s, calibrate=options.calibrate
                )

            self.template = new_runner()
            config = self.template.state_config()
        else:
            self.template = Runner(config, waypoints_xy_m, source="config")

            def new_runner() -> Runner:
                return self.template.with_params(self.config["params"])

        self._new_runner = new_runner
        self.config = config
        self.path = self.template.path
        self.dt_s = self.template.dt_s
        self.horizon = self.template.horizon
        unc = config.get("uncertainty")
        self.cov_track_m2 = None if unc is None else np.asarray(unc["cov_m2"], dtype=np.float64)
        # each step's track-frame covariance as (xx, xy, yx, yy) floats, for `_covariance`
        self._cov_rows = None if unc is None else self.cov_track_m2.reshape(-1, 4).tolist()
        self.runners: dict[str, Runner] = {}
        self.last_seen_ns: dict[str, int] = {}  # receive time (monotonic) of each track
        self.t0_ns: int | None = None  # stamps enter the runners as seconds after this one
        self.tf = TfBuffer(source="TF")
        self.pending: collections.deque = collections.deque()  # detections waiting for TF
        self.tag_to_base = parse_tag_to_base(options.tag_to_base)
        self.tag_frame = tag_frame_name(options.tag_id, "apriltag_ros")
        self.scene = scene
        self._warn_out = warn or _stderr
        self._warned: dict[tuple[str, str], list] = {}
        self._lock = threading.Lock()
        self._pub: dict[str, Callable[[dict], None]] = {}
        self._last_trajectory_ns = -(10**30)
        self._trajectory_sent: tuple | None = None  # the line last sent, and to how many
        self._trajectory_subs = 0
        self._last_markers_ns: dict[str, int] = {}  # monotonic time of each car's last markers
        self.n_published = 0
        self.update_ns: list[int] = []  # own time of each update (for the latency benchmark)
        self.wire = Wire(transport.encode, self.flavour, options.map_frame, self.horizon,
                         self.dt_s, self._obstacle_var())  # fmt: skip

    # -- setup

    def start(self) -> None:
        """Advertise the outputs and subscribe to the inputs."""
        o = self.opt
        for name, topic in o.outputs.items():
            if topic and not (name == "trajectory" and self.template.model != "line"):
                self._pub[name] = self.transport.advertise(topic, OUTPUTS[name][1])
        if o.input == "pose":
            self.transport.subscribe(o.topic, None, self._guard(o.topic, self._on_pose))
        elif o.input == "tags":
            for t in o.tf_topics:
                self.transport.subscribe(t, TF_TYPE, self._guard(t, self._on_tf))
            self.transport.subscribe(o.topic, TAG_TYPE, self._guard(o.topic, self._on_tags))
        elif o.input == "obstacles":
            self.transport.subscribe(o.topic, OBSTACLES_TYPE, self._guard(o.topic, self._on_obst))
        else:
            raise ValueError(f"NodeOptions.input: {o.input!r} is not pose, tags or obstacles")
        if self.scene is not None:
            self.scene.track(np.asarray(self.path._table[:, :2]))
        self.wire.prepare(self.cov_track_m2 is not None)
        self._publish_trajectory(time.monotonic_ns())

    # -- warnings

    def warn(self, topic: str, problem: str) -> None:
        """One line per (topic, kind of problem) every warn_every_s, counting the repeats."""
        kind = re.sub(r"[-+0-9.e]+|'[^']*'|\([^)]*\)", "#", problem)[:80]  # values vary, kinds not
        now = time.monotonic()
        last = self._warned.get((topic, kind))
        if last is not None and now - last[0] < self.opt.warn_every_s:
            last[1] += 1
            return
        more = f" ({last[1]} more since the last warning)" if last and last[1] else ""
        self._warned[(topic, kind)] = [now, 0]
        self._warn_out(f"fpe node: {topic}: {problem}; nothing published for it{more}")

    def _guard(self, topic: str, handler):
        """The callback the transport calls: every failure becomes a warning, never an exit."""

        def callback(msg: dict, type_name: str, receive_ns: int) -> None:
            try:
                with self._lock:
                    handler(topic, msg, type_name, receive_ns)
            except (BadMessage, InputError) as e:
                self.warn(topic, str(e.problem if isinstance(e, InputError) else e))
            except (KeyError, TypeError, ValueError, AttributeError, IndexError) as e:
                self.warn(topic, f"malformed message ({type(e).__name__}: {e})")
            except Exception as e:  # the node outlives any one message
                self.warn(topic, f"unexpected error ({type(e).__name__}: {e})")

        return callback

    # -- inputs

    def _check_frame(self, frame_id: str, what: str) -> None:
        if frame_id.lstrip("/") != self.opt.map_frame:
            raise BadMessage(
                f"{what} in frame {frame_id!r}, expected the map frame {self.opt.map_frame!r}"
            )

    def _on_pose(self, topic: str, msg: dict, type_name: str, receive_ns: int) -> None:
        if type_name not in POSE_TYPES:
            raise BadMessage(f"type {type_name} is not one of {', '.join(POSE_TYPES)}")
        hdr = msg["header"]
        self._check_frame(hdr["frame_id"], "pose")
        pose = msg["pose"]["pose"] if type_name.endswith("Odometry") else msg["pose"]
        p, q = pose["position"], pose["orientation"]
        yaw = rm.quaternion_yaw(float(q["x"]), float(q["y"]), float(q["z"]), float(q["w"]))
        self._predict("0", stamp_ns(hdr["stamp"]), float(p["x"]), float(p["y"]), yaw, receive_ns)

    def _on_tf(self, topic: str, msg: dict, type_name: str, receive_ns: int) -> None:
        static = topic.rstrip("/").endswith(STATIC_SUFFIX)
        rows = []
        for tr in msg["transforms"]:
            p, r = tr["transform"]["translation"], tr["transform"]["rotation"]
            rows.append((tr["header"]["frame_id"], tr["child_frame_id"],
                         stamp_ns(tr["header"]["stamp"]), (p["x"], p["y"], p["z"]),
                         (r["x"], r["y"], r["z"], r["w"]), static, topic))  # fmt: skip
        self.tf.add(rows, keep_ns=int(TF_KEEP_S * 1e9))
        self._place_pending(receive_ns)

    def _on_tags(self, topic: str, msg: dict, type_name: str, receive_ns: int) -> None:
        dets = msg["detections"]
        if not dets:
            return  # no tag in this image: nothing to say
        mine = [d for d in dets if list(np.atleast_1d(d["id"])) == [self.opt.tag_id]]
        if not mine:
            ids = sorted({int(i) for d in dets for i in np.atleast_1d(d["id"])})
            raise BadMessage(f"unknown tag id(s) {ids}, expected tag {self.opt.tag_id}")
        if len(mine) > 1:
            raise BadMessage(f"tag {self.opt.tag_id} detected {len(mine)} times in one image")
        det = mine[0]["pose"]
        ns = stamp_ns(det["header"]["stamp"]) or stamp_ns(msg["header"]["stamp"])
        camera = (det["header"]["frame_id"] or msg["header"]["frame_id"]).lstrip("/")
        pose = det["pose"]["pose"]
        p, q = pose["position"], pose["orientation"]
        vals = [float(v) for v in (p["x"], p["y"], p["z"], q["x"], q["y"], q["z"], q["w"])]
        if not _finite(*vals) or sum(v * v for v in vals[3:]) < 1e-18:
            raise BadMessage("the tag's pose is non-finite or has a zero quaternion")
        cam_tag = Rigid.make(vals[:3], vals[3:])
        if len(self.pending) >= MAX_PENDING:
            self.pending.popleft()
            self.warn(topic, f"more than {MAX_PENDING} detections wait for TF: the oldest dropped")
        self.pending.append((topic, ns, camera, cam_tag, receive_ns))
        self._place_pending(receive_ns)

    def _place_pending(self, now_ns: int) -> None:
        """Place the waiting detections, oldest first: each as soon as the TF buffer covers its
        stamp; one the TF has not reached yet waits up to tf_wait_s (receive time), then is
        dropped with a warning (TF extrapolation), as is one inside a TF gap."""
        keep: collections.deque = collections.deque()
        while self.pending:
            entry = self.pending.popleft()
            topic, ns, camera, cam_tag, receive_ns = entry
            expired = now_ns - receive_ns > self.opt.tf_wait_s * 1e9
            try:
                ahead = self._tf_behind(camera, ns)
            except InputError as e:  # no chain to this camera (yet): later detections go on
                if expired:
                    self.warn(topic, f"TF: {e.problem}")
                else:
                    keep.append(entry)
                continue
            if ahead:  # the TF has not reached this stamp: this and later ones wait
                if not expired:
                    keep.append(entry)
                    keep.extend(self.pending)
                    self.pending.clear()
                    break
                self.warn(topic, "TF extrapolation: no transform at or after the stamp arrived")
                continue
            try:
                if self.tag_to_base is not None:
                    tag_car = tag_mount(*self.tag_to_base).inv()
                else:
                    tag_car = self.tf.lookup(self.tag_frame, self.opt.car_frame, [ns], "detections")
                stamps = np.array([ns], dtype=np.int64)
                map_car = place_tag(self.tf, self.opt.map_frame, camera, stamps, cam_tag, tag_car)
                x, y = (float(v) for v in map_car.t_m[0, :2])
                self._predict("0", ns, x, y, float(map_car.yaw_rad()[0]), receive_ns)
            except (BadMessage, InputError) as e:
                self.warn(topic, f"TF: {e.problem}" if isinstance(e, InputError) else str(e))
        self.pending = keep

    def _tf_behind(self, camera: str, ns: int) -> bool:
        """Whether a dynamic TF edge between the map and `camera` ends before stamp ns [ns]."""
        up_a, up_b = self.tf.path(self.opt.map_frame, camera)
        return any(not e.static and e.stamps_ns[-1] < ns for e in up_a + up_b)

    def _on_obst(self, topic: str, msg: dict, type_name: str, receive_ns: int) -> None:
        ns = stamp_ns(msg["header"]["stamp"])
        moving = [o for o in msg["obstacles"] if not o["is_static"]]
        if len(moving) > self.opt.max_tracks:
            self.warn(topic, f"{len(moving)} moving obstacles, only the first "
                      f"{self.opt.max_tracks} (--max-tracks) are tracked")  # fmt: skip
            moving = moving[: self.opt.max_tracks]
        predicted = []
        for o in moving:
            car, s, d = str(int(o["id"])), float(o["s_center"]), float(o["d_center"])
            if not _finite(s, d):
                self.warn(topic, f"obstacle {car}: non-finite s, d ({s}, {d})")
                continue
            x, y = self._frenet_to_map(s, d)
            try:
                pred = self._observe(car, ns, x, y, math.nan, receive_ns)
            except (BadMessage, InputError) as e:
                self.warn(topic, f"obstacle {car}: {getattr(e, 'problem', e)}")
                continue
            if pred is not None:
                self._publish_paths([pred])  # each car's path as soon as it is known
                predicted.append(pred)
        stale = [c for c, t in self.last_seen_ns.items()
                 if receive_ns - t > self.opt.drop_after_s * 1e9]  # fmt: skip
        for c in stale:
            del self.runners[c], self.last_seen_ns[c]
            self._last_markers_ns.pop(c, None)
        if predicted:  # the covariances once every path is out
            self._publish_views([self._with_covariance(p) for p in predicted])

    def _frenet_to_map(self, s_m: float, d_m: float) -> tuple[float, float]:
        return frenet_to_map(self.path, s_m, d_m)

    # -- prediction

    def _runner(self, car: str) -> Runner:
        r = self.runners.get(car)
        if r is None:
            r = self.runners[car] = self._new_runner()
            # a new opponent's topics are advertised with its first observation, so that
            # subscribers have matched by its first valid prediction (a few samples later)
            for name in ("path", "covariance"):
                if name in self._pub and self._topic(name, car) is not None:
                    self._publisher(name, car)
        return r

    def _predict(self, car: str, ns: int, x: float, y: float, yaw: float, receive_ns: int):
        """One opponent's observation in, its outputs out: the path as soon as the runner has
        predicted, then the covariance and the other outputs."""
        pred = self._observe(car, ns, x, y, yaw, receive_ns)
        if pred is not None:
            self._publish_paths([pred])
            self._publish_views([self._with_covariance(pred)])

    def _observe(self, car: str, ns: int, x: float, y: float, yaw: float, receive_ns: int):
        """Feed one observation to the car's runner. Returns the prediction (car, stamp_ns,
        poses (H, 3), s_m: the arc length its steps are searched from, own time so far [ns]), or
        None when it is not valid (too little history); `_with_covariance` completes it."""
        if not _finite(x, y):
            raise BadMessage(f"non-finite position ({x}, {y})")
        t0 = time.perf_counter_ns()
        if self.t0_ns is None:
            self.t0_ns = ns  # stamps as seconds after the first keep nanoseconds in float64
        runner = self._runner(car)
        poses = runner.update((ns - self.t0_ns) * 1e-9, x, y, yaw)  # raises on stamps backwards
        self.last_seen_ns[car] = receive_ns
        # `fpe run`'s off-track check: far from the track (waypoints of another map frame, a
        # car in the pits) the predictions follow the nearest part of it, so none is published
        off_m = runner.track_distance(x, y)
        if off_m > runner.on_track_m:
            self.update_ns.append(time.perf_counter_ns() - t0)
            raise BadMessage(
                f"observation {off_m:.1f} m from the track (more than {runner.on_track_m:.3g} m; "
                "expected poses in the map frame of --waypoints)"
            )
        s_m = runner._s_m if runner._s_m is not None else self.path.project(x, y)
        took_ns = time.perf_counter_ns() - t0
        if self.scene is not None:
            self.scene.observation(car, ns, x, y, yaw)
        if not runner.valid:  # nothing is published: no covariance either
            self.update_ns.append(took_ns)
            return None
        return car, ns, poses, s_m, took_ns

    def _with_covariance(self, pred: tuple) -> tuple:
        """A valid prediction of `_observe` as (car, stamp_ns, poses (H, 3), cov (H, 2, 2) or
        None, arc lengths (H,)): its covariance, computed once its path is out; its own update
        time (the runner's update and this) recorded."""
        car, ns, poses, s_m, took_ns = pred
        t0 = time.perf_counter_ns()
        cov, along = self._covariance(poses, s_m, self.runners[car])
        self.update_ns.append(took_ns + time.perf_counter_ns() - t0)
        if self.scene is not None:
            steps = ns + self.wire.step_ns
            zero = np.zeros((self.horizon, 2, 2))
            self.scene.prediction(car, ns, poses, zero if cov is None else cov, steps, True)
        return car, ns, poses, cov, along

    def _covariance(self, poses: np.ndarray, s_m: float, runner: Runner):
        """(map-frame covariance (H, 2, 2) [m^2] or None, arc lengths (H,) [m] of the steps):
        the config's per-step track-frame covariance C (with calibrate, the car's runner's
        calibrated one) turned by the path heading h at each step (R C R^T, R the rotation by
        h; on floats: ten 2x2 products cost less in Python than NumPy's calls), each step's arc
        length searched in the window around the previous one's."""
        path = self.path
        along = path.project_chain(poses[:, :2], s_m)
        if self._cov_rows is None:
            return None, along
        rows = runner.covariance().reshape(-1, 4).tolist() if self.opt.calibrate else self._cov_rows
        cov = []
        for s, (a, b, c, d) in zip(along, rows):
            h = path.heading_at(s)
            co, si = math.cos(h), math.sin(h)
            ra, rb, rc, rd = co * a - si * c, co * b - si * d, si * a + co * c, si * b + co * d
            cov.append(
                [[ra * co - rb * si, ra * si + rb * co], [rc * co - rd * si, rc * si + rd * co]]
            )
        return np.array(cov), along

    # -- outputs

    def _topic(self, name: str, car: str) -> str | None:
        """Per-opponent topics of the per-car outputs when several opponents are tracked:
        `<topic>/opp_<id>` (a ROS name part must not start with a digit)."""
        return None if self.opt.input != "obstacles" else f"{self.opt.outputs[name]}/opp_{car}"

    def _publisher(self, name: str, car: str):
        sub = self._topic(name, car)
        if sub is None:
            return self._pub[name]
        key = f"{name}/{car}"
        if key not in self._pub:
            self._pub[key] = self.transport.advertise(sub, OUTPUTS[name][1])
        return self._pub[key]

    def _live(self, name: str, car: str | None = None) -> Callable[[Any], None] | None:
        """The publisher of output `name` (of a per-car output: the car's own topic when several
        opponents are tracked), or None when the output is off or nobody subscribes to its
        topic: a message nobody receives is neither built nor encoded."""
        if name not in self._pub:
            return None
        topic = None if car is None else self._topic(name, car)
        pub = self._pub[name] if topic is None else self._publisher(name, car)
        return pub if self.transport.subscriber_count(topic or self.opt.outputs[name]) else None

    def _publish_paths(self, preds: list) -> None:
        """The paths (what a planner waits for) of predictions, before anything else."""
        for car, ns, poses, *_ in preds:
            pub = self._live("path", car)
            if pub is not None:
                pub(self.wire.path(ns, poses))

    def _publish_views(self, outs: list) -> None:
        """The outputs after the paths: the predicted ObstacleArray, the markers, the
        covariances and (every trajectory_every_s, when it changed) the trajectory."""
        if self._live("obstacles") is not None:
            self._pub["obstacles"](self._obstacle_array(outs[0][1], outs))
        if self._live("markers") is not None:
            self._publish_markers(outs)
        for car, ns, poses, cov, _ in outs:
            pub = None if cov is None else self._live("covariance", car)
            if pub is None:
                continue
            for data in self.wire.covariances(ns, poses, cov):
                pub(data)
        self.n_published += len(outs)
        self._publish_trajectory(time.monotonic_ns())

    def _publish_markers(self, outs: list) -> None:
        """The markers of one opponent per input message: the one whose markers are oldest, if
        at least markers_every_s old. Every opponent's markers refresh at 1 / markers_every_s
        while the costliest message to encode stays one opponent's (their lifetime keeps the
        others' on screen)."""
        now_ns = time.monotonic_ns()
        last = self._last_markers_ns
        car, ns, poses, cov, _ = min(outs, key=lambda o: last.get(o[0], -(10**30)))
        if now_ns - last.get(car, -(10**30)) < self.opt.markers_every_s * 1e9:
            return
        last[car] = now_ns
        self._pub["markers"](self.wire.markers(car, ns, poses, cov))

    def _obstacle_array(self, ns: int, outs) -> bytes:
        """f110_msgs/ObstacleArray of the predicted state at the first step (stamp + dt_s)."""
        values = []
        for _, _, poses, _, along in outs:
            (x0, y0, _), (x1, y1, _) = poses[:2].tolist()
            s0, s1 = along[0], along[1]
            d0, d1 = self._offset(x0, y0, s0), self._offset(x1, y1, s1)
            values.append([s0 - 0.25, s0 + 0.25, d0 - 0.15, d0 + 0.15, s0, d0,
                           (s1 - s0) / self.dt_s, (d1 - d0) / self.dt_s])  # fmt: skip
        return self.wire.obstacles(ns, [int(o[0]) for o in outs], values)

    def _obstacle_var(self) -> dict | None:
        """The ROS 1 ObstacleArray's variances (None on ROS 2, whose definition has none): the
        first step's along / cross-track ones, the speeds' from steps 1 and 2 taken as
        independent."""
        if self.flavour != "ros1":
            return None
        if self.cov_track_m2 is None:
            return {"s_var": 0.0, "d_var": 0.0, "vs_var": 0.0, "vd_var": 0.0}
        var, var1 = np.diag(self.cov_track_m2[0]), np.diag(self.cov_track_m2[1])
        vvar = (var + var1) / self.dt_s**2
        return {"s_var": float(var[0]), "d_var": float(var[1]),
                "vs_var": float(vvar[0]), "vd_var": float(vvar[1])}  # fmt: skip

    def _offset(self, x: float, y: float, s_m: float) -> float:
        cx, cy = self.path.point_at(s_m)
        h = self.path.heading_at(s_m)
        return (y - cy) * math.cos(h) - (x - cx) * math.sin(h)

    def _publish_trajectory(self, now_ns: int) -> None:
        """The line model's learned line and speed profile: looked at every trajectory_every_s,
        sent when it changed since the last one sent or a subscriber joined since (a fixed
        config's line goes out once per new subscriber)."""
        if now_ns - self._last_trajectory_ns < self.opt.trajectory_every_s * 1e9:
            return
        self._last_trajectory_ns = now_ns
        if "trajectory" not in self._pub:
            return
        n_subs = self.transport.subscriber_count(self.opt.outputs["trajectory"])
        p = self._trajectory_params()
        line = (tuple(p["line_offset_m"]), tuple(p["line_speed_mps"]))
        if n_subs == 0 or (line == self._trajectory_sent and n_subs <= self._trajectory_subs):
            self._trajectory_subs = n_subs  # one that left: the next to join gets it again
            return
        self._pub["trajectory"](self.trajectory_message(params=p))
        self._trajectory_sent, self._trajectory_subs = line, n_subs

    def _trajectory_params(self) -> dict:
        """The params whose line the trajectory shows: the config's, with adapt the learned
        ones of the opponent seen most."""
        if self.opt.adapt and self.runners:
            return max(self.runners.values(), key=lambda r: r.samples).state_config()["params"]
        return self.config["params"]

    def trajectory_message(self, stamp: int = 0, params: dict | None = None) -> dict:
        """f110_msgs/OpponentTrajectory of the config's line (with adapt: the line learned by
        the opponent seen most; or `params`'): one OppWpnt per line point."""
        p = self._trajectory_params() if params is None else params
        offset, speed = p["line_offset_m"], p["line_speed_mps"]
        n = len(offset)
        length = self.path.length_m
        span = length / n if self.path.closed else length / max(n - 1, 1)
        d_var = 0.0 if self.cov_track_m2 is None else float(self.cov_track_m2[-1][1][1])
        wpnts = []
        for k in range(n):
            s = k * span
            x, y = self._frenet_to_map(s, float(offset[k]))
            wpnts.append({"id": k, "s_m": s, "d_m": float(offset[k]), "x_m": x, "y_m": y,
                          "proj_vs_mps": float(speed[k]), "vd_mps": 0.0, "d_var": d_var,
                          "vs_var": 0.0})  # fmt: skip
        msg = {"header": header(self.flavour, stamp, self.opt.map_frame),
               "lap_count": 0, "opp_is_on_trajectory": True, "oppwpnts": wpnts}  # fmt: skip
        if self.flavour == "ros1":
            msg["id"] = 0
        return msg


def frenet_to_map(path, s_m: float, d_m: float) -> tuple[float, float]:
    """Map position x [m], y [m] of arc length s [m] and offset d [m] (left positive) along a
    `RunnerPath` (the frame of ForzaETH's obstacles: the waypoints given to the node)."""
    cx, cy = path.point_at(s_m)
    h = path.heading_at(s_m)
    return cx - d_m * math.sin(h), cy + d_m * math.cos(h)


def _stderr(line: str) -> None:
    import sys

    print(line, file=sys.stderr, flush=True)
