"""AprilTag detections in a trailing car's camera, composed into the leading car's pose in the map.

The 2019 node's recordings hold no map-frame pose of the leading car: a detector (apriltags2_ros)
publishes where tag 0 is in the trailing car's camera frame, and /tf holds the trailing car's own
chain map -> base_link (its localisation) -> laser -> camera (static mounts). Here every detection
of the chosen tag becomes

    T_map_car = T_map_camera(at the detection's stamp) @ T_camera_tag(the detection) @ T_tag_car

reduced to the plane (x, y and the yaw of the result), the leading car's base frame ("car",
default other_base_link) given by `--tag-to-base` or by a transform tag -> car in the log.

Detection messages (definitions shipped under fpe_jax/io/msgs):
- `apriltag_ros/AprilTagDetectionArray` (ROS 1 apriltag_ros 3 and ROS 2 forks of it) and its old
  name `apriltags2_ros/...`: each detection carries `id[]`, `size[]` and the tag's pose in the
  camera frame (PoseWithCovarianceStamped). Only standalone detections (one id) are used.
- `apriltag_msgs/AprilTagDetectionArray` (ROS 2's apriltag_ros): `family`, `id` and image data but
  no pose: that detector publishes the pose as the TF camera -> "<family>:<id>" at the image's
  stamp, so the transform with exactly the detection's stamp is used (never interpolated).
Fields are read by name, so forks that add or narrow fields (a scalar id, a PoseStamped pose) read
too when the log embeds their definitions.

The tag frame follows apriltag_ros: x right, y up, z out of the tag's face. `--tag-to-base
X,Y,Z,YAW` says where the tag sits on the leading car: its centre at (X, Y, Z) [m] in the car's
base frame, upright, its face pointing YAW [rad] in that frame (pi: a rear-mounted tag looking
back at the trailing car, as in the thesis).

Also here: the writer of this layout (`write_apriltag_mcap`), used by the simulator.
"""

from __future__ import annotations

import collections
import dataclasses
import math
from typing import Any

import numpy as np

from fpe_jax import spec
from fpe_jax.errors import InputError
from fpe_jax.io import ros_msgs as rm
from fpe_jax.io import tables
from fpe_jax.io.logs import DETECTION_TYPES as DETECTION_TYPES  # re-exported
from fpe_jax.io.logs import check_stamps_vary
from fpe_jax.io.tf import Rigid, TfBuffer, format_stamp, quat_from_matrix

DETECTION_TOPIC = "/tag_detections"
FAMILY = "tag36h11"  # the detector library's name for the 36h11 family
TAG_SIZE_M = 0.1085  # the thesis' tag
FRAMES = dict(map="map", base="base_link", laser="laser", camera="camera", car="other_base_link")
_REMEDY = "--drop-outside-tf to drop those detections"
# Camera optical frame (x right, y down, z forward) in a body frame (x forward, y left, z up).
OPTICAL_IN_BODY = Rigid.make([0.0, 0.0, 0.0], [-0.5, 0.5, -0.5, 0.5])


def tag_frame_name(tag_id: int, style: str, family: str = FAMILY) -> str:
    """The detectors' default tag frame: `tag_<id>` (apriltag_ros) or `<family>:<id>` (ROS 2)."""
    return f"{family}:{tag_id}" if style == "apriltag_msgs" else f"tag_{tag_id}"


def tag_mount(x_m: float, y_m: float, z_m: float, yaw_rad: float) -> Rigid:
    """T_car_tag of an upright tag centred at (x, y, z) [m] in the car frame, facing yaw [rad].

    Tag frame (apriltag_ros): z out of the face (horizontal, along yaw), y up, x = y cross z.
    """
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    r = np.array([[-s, 0.0, c], [c, 0.0, s], [0.0, 1.0, 0.0]])  # columns: tag x, y, z in car
    return Rigid.make([x_m, y_m, z_m], quat_from_matrix(r))


def parse_tag_to_base(value, source: str = "--tag-to-base") -> tuple[float, ...] | None:
    """`"x,y,z,yaw"` or a sequence of 4 numbers -> (x [m], y [m], z [m], yaw [rad]); None stays.
    The ranges are `spec.check_tag_mount`'s."""
    if value is None:
        return None
    if not isinstance(value, str):
        return spec.check_tag_mount(list(value), source)
    try:
        parts = [tables.plain_number(p) for p in value.split(",")]
    except ValueError:
        parts = []
    if len(parts) != 4:  # the message shows the text as given
        spec.check_tag_mount(value, source)
    return spec.check_tag_mount(parts, source)


# --- reading --------------------------------------------------------------------------------------


def _stamp_ns(stamp) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


@dataclasses.dataclass
class _Detections:
    """The chosen tag's detections of one topic.

    stamp_ns / log_ns: (N,) int64 header stamps and log times [ns]; frame: (N,) camera frame of
    each; cam_tag: T_camera_tag (N) from the messages, or None when the pose comes from TF;
    tag_frame: the TF frame of a pose-less detection (else None); counts: what was read / skipped.
    """

    stamp_ns: np.ndarray
    log_ns: np.ndarray
    frame: np.ndarray
    cam_tag: Rigid | None
    tag_frame: str | None
    counts: dict[str, Any]


def _detection_pose(det):
    """The Pose of a pose-carrying detection (PoseWithCovarianceStamped or PoseStamped)."""
    pose = det.pose.pose
    return pose.pose if hasattr(pose, "pose") else pose


def _read_detections(log, topic: str, tag_id: int) -> _Detections:
    stamps, logs, frames, poses, tag_frames = [], [], [], [], set()
    ids_seen: collections.Counter = collections.Counter()
    n_arrays = n_empty = n_bundles = n_ambiguous = 0
    with_pose = None
    for _, _, log_ns, msg in log.messages([topic]):
        n_arrays += 1
        if len(msg.detections) == 0:
            n_empty += 1
            continue
        mine = []
        for det in msg.detections:
            has_pose = hasattr(det, "pose")
            with_pose = has_pose if with_pose is None else with_pose
            ids = [int(i) for i in np.atleast_1d(np.asarray(det.id))]
            if len(ids) != 1:  # a tag bundle: its pose is the bundle's, not one tag's
                n_bundles += tag_id in ids
                continue
            ids_seen[ids[0]] += 1
            if ids[0] == tag_id:
                mine.append(det)
        if len(mine) > 1:  # two detections of one tag in one image: no way to tell which is right
            n_ambiguous += 1
            continue
        if not mine:
            continue
        det, header = mine[0], msg.header
        stamp, frame = _stamp_ns(header.stamp), header.frame_id
        if with_pose:
            # apriltag_ros stamps each pose with the image's header; prefer it where it is set.
            if _stamp_ns(det.pose.header.stamp) != 0:
                stamp = _stamp_ns(det.pose.header.stamp)
            frame = det.pose.header.frame_id or frame
            pose = _detection_pose(det)
            p, q = pose.position, pose.orientation
            poses.append((p.x, p.y, p.z, q.x, q.y, q.z, q.w))
        else:
            tag_frames.add(f"{det.family}:{tag_id}")
        stamps.append(stamp)
        logs.append(int(log_ns))
        frames.append(frame.lstrip("/"))
    counts = {
        "n_arrays": n_arrays,
        "n_empty_arrays": n_empty,
        "n_tag_detections": len(stamps),
        "n_other_ids": sum(n for i, n in ids_seen.items() if i != tag_id),
        "n_bundles_with_tag": n_bundles,
        "n_ambiguous_arrays": n_ambiguous,
    }
    if not stamps:
        _raise_no_detections(log, topic, tag_id, counts, ids_seen)
    if len(tag_frames) > 1:
        raise InputError(
            log.source,
            f"detection topic {topic!r}: tag {tag_id} is detected in several families "
            f"({', '.join(sorted(tag_frames))})",
            "one family per tag id",
        )
    cam_tag = None
    if with_pose:
        a = np.array(poses, dtype=np.float64)
        norm = np.linalg.norm(a[:, 3:], axis=1)
        if not (np.isfinite(a).all() and (norm > 1e-9).all()):
            k = int(np.argmax(~np.isfinite(a).all(axis=1) | ~(norm > 1e-9)))
            raise InputError(
                log.source,
                f"detection topic {topic!r}: the tag's pose at {format_stamp(stamps[k])} is "
                "non-finite or has a zero quaternion",
                "finite tag poses",
            )
        cam_tag = Rigid.make(a[:, :3], a[:, 3:])
    return _Detections(
        np.array(stamps, dtype=np.int64),
        np.array(logs, dtype=np.int64),
        np.array(frames, dtype=object),
        cam_tag,
        None if with_pose else tag_frames.pop(),
        counts,
    )


def _raise_no_detections(log, topic, tag_id, counts, ids_seen) -> None:
    n = counts["n_arrays"]
    if counts["n_empty_arrays"] == n:
        raise InputError(
            log.source,
            f"detection topic {topic!r}: all {n} detection arrays are empty (no tag was seen)",
            f"detections of tag {tag_id}",
        )
    if counts["n_ambiguous_arrays"] and not counts["n_bundles_with_tag"]:
        raise InputError(
            log.source,
            f"detection topic {topic!r}: tag {tag_id} is detected more than once in each of the "
            f"{counts['n_ambiguous_arrays']} images that hold it (no way to tell which is right)",
            "one detection of the tag per image (distinct tag ids on one car)",
        )
    if any(i != tag_id for i in ids_seen):
        seen = ", ".join(f"{i} ({c}x)" for i, c in sorted(ids_seen.items()))
        raise InputError(
            log.source,
            f"detection topic {topic!r} has no detection of tag {tag_id}; tag ids seen: {seen}",
            f"--tag-id one of {', '.join(str(i) for i in sorted(ids_seen))}",
        )
    why = []
    if counts["n_bundles_with_tag"]:
        why.append(f"{counts['n_bundles_with_tag']} bundle detections contain it")
    if counts["n_ambiguous_arrays"]:
        why.append(f"{counts['n_ambiguous_arrays']} arrays hold it more than once")
    raise InputError(
        log.source,
        f"detection topic {topic!r} has no usable detection of tag {tag_id}"
        + (f" ({'; '.join(why)})" if why else ""),
        "standalone detections, one per image",
    )


# --- the chain ------------------------------------------------------------------------------------


@dataclasses.dataclass
class _Plan:
    """How one topic's detections reach the map: frames and where each link comes from."""

    tag_frame: str
    camera_frames: list[str]
    tag_car: Rigid | None  # T_tag_car from --tag-to-base, or None: looked up in the TF buffer
    tag_car_source: str
    pose_source: str


def _plan(buf: TfBuffer, dets: _Detections, tag_id, tag_to_base, map_frame, car_frame) -> _Plan:
    source = buf.source
    if dets.cam_tag is None:
        tag_frame = dets.tag_frame
        parents = buf.parents.get(tag_frame, [])
        if len(parents) > 1:
            raise InputError(
                source,
                f"TF frame {tag_frame!r} has several parents ({', '.join(parents)})",
                "a TF tree (one parent per frame)",
            )
        if not parents:
            raise InputError(
                source,
                f"the detections carry no pose and the log has no TF to their tag frame "
                f"{tag_frame!r} (frames: {', '.join(buf.frames) or 'none'})",
                "the detector's TF camera -> <family>:<id> on /tf",
            )
        camera_frames = [parents[0]]
        pose_source = f"TF {parents[0]} -> {tag_frame} at each detection's stamp"
    else:
        camera_frames = sorted(set(dets.frame))
        pose_source = "the detection's pose"
        tag_frame = tag_frame_name(tag_id, "apriltag_ros")
        if tag_frame not in buf.frames and tag_to_base is None:
            tag_frame = _tag_frame_from_tree(buf, map_frame, car_frame, camera_frames) or tag_frame
    if tag_to_base is not None:
        tag_car = tag_mount(*tag_to_base).inv()
        x, y, z, yaw = tag_to_base
        src = f"--tag-to-base {x:g},{y:g},{z:g},{yaw:g}"
    else:
        if tag_frame not in buf.frames or car_frame not in buf.frames:
            raise InputError(
                source,
                f"no transform from the tag frame {tag_frame!r} to {car_frame!r} in the log",
                f"--tag-to-base X,Y,Z,YAW (the tag's mount on the car) or a static transform "
                f"{tag_frame} -> {car_frame} on /tf_static",
            )
        edges_a, edges_b = buf.path(tag_frame, car_frame)
        kinds = {"static" if e.static else "dynamic" for e in edges_a + edges_b}
        tag_car = None
        src = f"{'/'.join(sorted(kinds))} TF " + " -> ".join(buf.chain_frames(tag_frame, car_frame))
    return _Plan(tag_frame, camera_frames, tag_car, src, pose_source)


def _tag_frame_from_tree(buf: TfBuffer, map_frame, car_frame, camera_frames) -> str | None:
    """A tag frame named otherwise than `tag_<id>`: the car frame's parent, if that parent is a
    frame of its own (not joined to the map) or hangs off the detections' camera frame."""
    parents = buf.parents.get(car_frame, [])
    if len(parents) != 1:
        return None
    p = parents[0]
    if p == map_frame:
        return None
    if buf.parents.get(p, [None])[0] in camera_frames:
        return p
    try:
        joined = map_frame in buf.frames and buf.root(p) == buf.root(map_frame)
    except InputError:
        return None
    return None if joined else p


def _compose(log, topic, dets: _Detections, buf: TfBuffer, plan: _Plan, map_frame, car_frame,
             drop_outside_tf: bool, log_time: bool = False):  # fmt: skip
    """(kept mask (N,), T_map_car (kept) of the detections, number dropped outside the TF,
    number of those dropped in a TF gap). The TF is looked up at the header stamps, or at the
    log times with `log_time`; a detector's own TF pose is matched by header stamp."""
    n = len(dets.stamp_ns)
    at_ns = dets.log_ns if log_time else dets.stamp_ns
    what = f"detections on {topic}"
    keep = np.ones(n, dtype=bool)
    if dets.cam_tag is None:  # the pose is the detector's TF sample with the detection's stamp
        edge = buf.edges[(plan.camera_frames[0], plan.tag_frame)]
        pos = np.minimum(np.searchsorted(edge.stamps_ns, dets.stamp_ns), len(edge.stamps_ns) - 1)
        exact = edge.stamps_ns[pos] == dets.stamp_ns
        if not exact.all() and not drop_outside_tf:
            k = int(np.argmax(~exact))
            raise InputError(
                log.source,
                f"{int((~exact).sum())} of {n} {what} have no TF {edge.name} at their stamp "
                f"(the first at {format_stamp(dets.stamp_ns[k])})",
                "the detector's transform at each detection's stamp (or --drop-outside-tf)",
            )
        keep &= exact
        frames = np.full(n, plan.camera_frames[0], dtype=object)
    else:
        frames = dets.frame
    in_gap = np.zeros(n, dtype=bool)
    if drop_outside_tf:
        for cam in plan.camera_frames:
            sel = frames == cam
            keep[sel] &= buf.covers(map_frame, cam, at_ns[sel])
            in_gap[sel] |= buf.in_gap(map_frame, cam, at_ns[sel])
        if plan.tag_car is None:
            keep &= buf.covers(plan.tag_frame, car_frame, at_ns)
            in_gap |= buf.in_gap(plan.tag_frame, car_frame, at_ns)
        if not keep.any():
            raise InputError(
                log.source,
                f"none of the {n} {what} lie within the TF buffer",
                f"transforms {map_frame} -> {plan.camera_frames[0]} around the detections' stamps",
            )
    stamps, frames = at_ns[keep], frames[keep]
    if dets.cam_tag is not None:
        cam_tag = dets.cam_tag.take(keep)
    else:
        cam_tag = edge.transform.take(pos[keep])
    if plan.tag_car is not None:
        tag_car = Rigid(
            *(np.repeat(a, len(stamps), axis=0) for a in (plan.tag_car.t_m, plan.tag_car.q))
        )
    else:
        tag_car = buf.lookup(plan.tag_frame, car_frame, stamps, what, _REMEDY)
    t = np.empty((len(stamps), 3))
    q = np.empty((len(stamps), 4))
    for cam in sorted(set(frames)):
        sel = frames == cam
        out = place_tag(
            buf, map_frame, cam, stamps[sel], cam_tag.take(sel), tag_car.take(sel), what
        )
        t[sel], q[sel] = out.t_m, out.q
    return keep, Rigid(t, q), int(n - keep.sum()), int((in_gap & ~keep).sum())


def place_tag(
    buf: TfBuffer, map_frame: str, camera_frame: str, stamps_ns, cam_tag: Rigid, tag_car: Rigid,
    what: str = "detections", remedy: str | None = _REMEDY,
) -> Rigid:  # fmt: skip
    """T_map_car of N detections in one camera frame: T_map_camera (TF at each stamp (N,) [ns])
    @ T_camera_tag (the detections) @ T_tag_car (the tag's mount). Raises InputError when the
    TF buffer does not join the frames or a stamp lies outside it (`what` names the stamps)."""
    return buf.lookup(map_frame, camera_frame, stamps_ns, what, remedy) @ cam_tag @ tag_car


def detection_rows(
    log,
    topic: str,
    *,
    tag_id: int = 0,
    tag_to_base=None,
    map_frame: str = "map",
    car_frame: str = "other_base_link",
    drop_outside_tf: bool = False,
    log_time: bool = False,
    max_tf_gap_s: float | None = None,
) -> tuple[list[tuple], dict[str, Any]]:
    """The leading car's map-frame poses from one detection topic, as rows for the drive reader.

    Returns (rows, meta): rows (stamp_ns, log_ns, x, y, qx, qy, qz, qw, nan) per placed
    detection (the planar reduction happens in the reader: it keeps x, y and the yaw of q);
    meta: the chain, the tag frame, where the tag -> car link came from, and counts.
    Raises InputError for a topic without usable detections of `tag_id`, a missing TF link,
    detections whose header stamps are all equal (zero: unset; unless `log_time`), or a
    detection stamped outside the TF buffer or inside a TF gap longer than the limit
    (`max_tf_gap_s`, see `fpe_jax.io.tf`; with `drop_outside_tf` it is dropped and counted).
    With `log_time` the TF is looked up at each detection's log time (the time it is stamped
    with in the drive too).
    """
    if isinstance(tag_id, bool) or not isinstance(tag_id, int | np.integer):
        raise InputError("--tag-id", f"{tag_id!r} is not an integer", "an AprilTag id such as 0")
    tag_to_base = parse_tag_to_base(tag_to_base)
    dets = _read_detections(log, topic, tag_id)
    if not log_time:
        check_stamps_vary(log.source, topic, dets.stamp_ns, f"detections of tag {tag_id}")
    buf = TfBuffer.from_log(log, max_gap_s=max_tf_gap_s)
    plan = _plan(buf, dets, tag_id, tag_to_base, map_frame, car_frame)
    keep, map_car, n_dropped, n_gap = _compose(
        log, topic, dets, buf, plan, map_frame, car_frame, drop_outside_tf, log_time
    )
    stamps, logs = dets.stamp_ns[keep], dets.log_ns[keep]
    rows = [
        (int(s), int(lg), t[0], t[1], *q, np.nan)
        for s, lg, t, q in zip(stamps, logs, map_car.t_m.tolist(), map_car.q.tolist())
    ]
    meta = {
        "tag_id": int(tag_id),
        **_plan_summary(buf, plan, map_frame, car_frame),
        **dets.counts,
        "n_dropped_outside_tf": n_dropped,
        "n_dropped_tf_gap": n_gap,
    }
    return rows, meta


def _plan_summary(buf: TfBuffer, plan: _Plan, map_frame, car_frame) -> dict[str, Any]:
    cam = plan.camera_frames[0]
    ego = buf.chain_frames(map_frame, cam)
    return {
        "camera_frames": plan.camera_frames,
        "tag_frame": plan.tag_frame,
        "chain": ego + [plan.tag_frame, car_frame],
        "links": [
            {"link": " -> ".join(ego), "from": "TF at each detection's stamp"},
            {"link": f"{cam} -> {plan.tag_frame}", "from": plan.pose_source},
            {"link": f"{plan.tag_frame} -> {car_frame}", "from": plan.tag_car_source},
        ],
    }


def describe_detections(
    log,
    topic: str,
    *,
    tag_id: int = 0,
    tag_to_base=None,
    map_frame="map",
    car_frame="other_base_link",
) -> dict[str, Any]:
    """For `fpe info`: the chain `detection_rows` would use for `topic`, and the detection counts;
    {"error": problem} instead when it could not compose them."""
    try:
        dets = _read_detections(log, topic, tag_id)
        buf = TfBuffer.from_log(log)
        plan = _plan(buf, dets, tag_id, parse_tag_to_base(tag_to_base), map_frame, car_frame)
        summary = _plan_summary(buf, plan, map_frame, car_frame)
        return {"tag_id": int(tag_id), **summary, **dets.counts}
    except InputError as e:
        return {"tag_id": int(tag_id), "error": e.problem}


# --- writing --------------------------------------------------------------------------------------


def _detection_dict(style, ns, frame, tag_id, size_m, family, t, q) -> dict:
    header = {"stamp": rm.stamp_dict(ns), "frame_id": frame}
    if style == "apriltag_msgs":  # image-space fields stay zero: the simulator renders no image
        return {
            "family": family,
            "id": tag_id,
            "hamming": 0,
            "goodness": 0.0,
            "decision_margin": 0.0,
            "centre": {"x": 0.0, "y": 0.0},
            "corners": [{"x": 0.0, "y": 0.0}] * 4,
            "homography": [0.0] * 9,
        }
    pose = {"position": dict(zip("xyz", t)), "orientation": dict(zip("xyzw", q))}
    return {
        "id": [tag_id],
        "size": [size_m],
        "pose": {"header": header, "pose": {"pose": pose, "covariance": [0.0] * 36}},
    }


def apriltag_events(
    source,
    *,
    detections: dict,
    ego: dict,
    laser_in_base: Rigid,
    camera_in_laser: Rigid,
    tag_in_car: Rigid,
    empty_t_s=None,
    tag_id: int = 0,
    tag_size_m: float = TAG_SIZE_M,
    family: str = FAMILY,
    style: str = "apriltag_ros",
    topic: str = DETECTION_TOPIC,
) -> list[tuple[int, str, str, dict]]:
    """(log_ns, topic, type, message) events of the AprilTag layout (frames: `FRAMES`).

    Args:
        detections: dict(t_s (N,) [s], xy_m (N, 2), yaw_rad (N,)): where the leading car's base
            frame is in the map at each detection; each is written as the tag's pose in the
            camera frame that composes back to exactly this through the written TF.
        ego: dict(t_s (M,), xy_m (M, 2), yaw_rad (M,)): the trailing car, map -> base_link on /tf.
            Its stamps must cover the detections' (lookups never extrapolate).
        laser_in_base, camera_in_laser: T_base_laser and T_laser_camera (camera: optical frame),
            written once on /tf_static with the tag -> car link (the inverse of `tag_in_car`,
            T_car_tag, see `tag_mount`).
        empty_t_s: (E,) stamps [s] of images without a detection: empty arrays.
        style: "apriltag_ros" or "apriltags2_ros" (the pose in each detection) or "apriltag_msgs"
            (no pose; the TF camera -> <family>:<id> at each detection's stamp on /tf).
    """
    from fpe_jax.io.writers import _series, _stamps_ns

    if style not in ("apriltag_ros", "apriltags2_ros", "apriltag_msgs"):
        raise ValueError(f"apriltag_events: unknown style {style!r}")
    f = FRAMES
    det_ns, det_xy, det_yaw = _series(source, detections, "detections", ("xy_m", "yaw_rad"))
    ego_ns, ego_xy, ego_yaw = _series(source, ego, "ego", ("xy_m", "yaw_rad"))
    tag_frame = tag_frame_name(tag_id, style, family)
    ego_tf = Rigid.planar(ego_xy[:, 0], ego_xy[:, 1], ego_yaw)
    statics = [
        (f["base"], f["laser"], laser_in_base),
        (f["laser"], f["camera"], camera_in_laser),
        (tag_frame, f["car"], tag_in_car.inv()),
    ]
    buf = TfBuffer(
        [
            (f["map"], f["base"], n, t, q, False, "/tf")
            for n, t, q in zip(ego_ns, ego_tf.t_m, ego_tf.q)
        ]
        + [(p, c, 0, r.t_m[0], r.q[0], True, "/tf_static") for p, c, r in statics],
        source=source,
    )
    # The camera-frame pose the reader's composition maps back onto the requested map pose.
    map_cam = buf.lookup(f["map"], f["camera"], det_ns, "detections")
    map_car = Rigid.planar(det_xy[:, 0], det_xy[:, 1], det_yaw)
    cam_tag = map_cam.inv() @ map_car @ tag_in_car
    msgtype = f"{'apriltag_msgs' if style == 'apriltag_msgs' else style}/AprilTagDetectionArray"
    t0 = int(min(ego_ns.min(), det_ns.min()))
    mounts = [
        rm.transform_stamped(p, c, 0, r.t_m[0].tolist(), r.q[0].tolist()) for p, c, r in statics
    ]
    events = [(t0, "/tf_static", "tf2_msgs/TFMessage", {"transforms": mounts})]
    for n, t, q in zip(ego_ns.tolist(), ego_tf.t_m.tolist(), ego_tf.q.tolist()):
        tf = rm.transform_stamped(f["map"], f["base"], n, t, q)
        events.append((n, "/tf", "tf2_msgs/TFMessage", {"transforms": [tf]}))
    for n, t, q in zip(det_ns.tolist(), cam_tag.t_m.tolist(), cam_tag.q.tolist()):
        det = _detection_dict(style, n, f["camera"], tag_id, tag_size_m, family, t, q)
        header = {"stamp": rm.stamp_dict(n), "frame_id": f["camera"]}
        events.append((n, topic, msgtype, {"header": header, "detections": [det]}))
        if style == "apriltag_msgs":
            tf = rm.transform_stamped(f["camera"], tag_frame, n, t, q)
            events.append((n, "/tf", "tf2_msgs/TFMessage", {"transforms": [tf]}))
    if empty_t_s is not None and len(empty_t_s):
        for n in _stamps_ns(source, empty_t_s, "empty detections").tolist():
            header = {"stamp": rm.stamp_dict(n), "frame_id": f["camera"]}
            events.append((n, topic, msgtype, {"header": header, "detections": []}))
    return events


def write_apriltag_mcap(path, *, odom: dict | None = None, force: bool = False, **layout) -> Any:
    """Write the AprilTag layout (`apriltag_events(**layout)`) plus optional truth odometry
    (`odom` as in `fpe_jax.io.write_drive_mcap`) as a ROS 2 MCAP. Returns the path."""
    from fpe_jax.io.writers import _odom_events, _write_ros2_mcap

    events = apriltag_events(path, **layout)
    if odom is not None:
        events += _odom_events(path, odom)
    return _write_ros2_mcap(path, events, force)
