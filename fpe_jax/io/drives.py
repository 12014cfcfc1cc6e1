"""Drive logs -> `Drive`: topic choice, message extraction, cleaning; and `describe_log`.

Topic choice when the caller names none (documented in `load_drive`):
  pose:  the only PoseStamped / PoseWithCovarianceStamped topic; else the only TFMessage topic
         carrying the tf_parent -> tf_child transform; else the only AprilTagDetectionArray
         topic (composed into the map through the log's TF, see `fpe_jax.io.apriltag`); else the
         only Odometry topic. Two or more candidates at the first level that has any is an error
         listing them.
  truth: the only Odometry topic other than the pose topic, if exactly one has messages.
So a simulated drive (/opp/pose PoseStamped, /opp/odom Odometry, /tf) reads as
pose=/opp/pose, truth=/opp/odom.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from fpe_jax import spec
from fpe_jax.drive import Drive
from fpe_jax.errors import InputError
from fpe_jax.io import ros_msgs as rm
from fpe_jax.io import tables
from fpe_jax.io.logs import (
    DETECTION_TYPES,
    ODOMETRY_TYPES,
    POSE_TYPES,
    STAMPED_POSE_TYPES,
    TF_TYPES,
    Log,
    PoseRows,
    check_stamps_vary,
    is_log_path,
    open_log,
)

_POSE_EXPECTED = (
    "PoseStamped, PoseWithCovarianceStamped, Odometry, TFMessage or AprilTagDetectionArray"
)


def _topic_list(topics) -> str:
    return ", ".join(topics) if topics else "none"


def _tf_pairs(log: Log, topic: str, stop_at: tuple[str, str]) -> set[tuple[str, str]]:
    """Frame pairs (parent, child) of a TF topic, read until `stop_at` shows up (or to the end)."""
    pairs: set[tuple[str, str]] = set()
    for _, _, _, msg in log.messages([topic]):
        pairs.update(
            (t.header.frame_id.lstrip("/"), t.child_frame_id.lstrip("/")) for t in msg.transforms
        )
        if stop_at in pairs:
            break
    return pairs


def _check_topic(log: Log, topic: str, role: str, tf_pair: tuple[str, str]) -> None:
    """InputError unless `topic` exists, has a pose type, has messages (and the TF pair)."""
    info = log.topics.get(topic)
    if info is None:
        candidates = [t for t, i in log.topics.items() if i.msgtype in POSE_TYPES + DETECTION_TYPES]
        raise InputError(
            log.source,
            f"no {role} topic {topic!r}; topics of a usable type: {_topic_list(candidates)}",
            f"one of {_topic_list(list(log.topics))}" if not candidates else None,
        )
    if info.msgtype not in POSE_TYPES + DETECTION_TYPES:
        raise InputError(
            log.source,
            f"{role} topic {topic!r} has type {info.msgtype or 'unknown'}",
            _POSE_EXPECTED,
        )
    if info.count == 0:
        raise InputError(log.source, f"{role} topic {topic!r} has no messages")
    if info.msgtype in TF_TYPES and tf_pair not in (pairs := _tf_pairs(log, topic, tf_pair)):
        raise InputError(
            log.source,
            f"{role} topic {topic!r} has no transform {tf_pair[0]} -> {tf_pair[1]}",
            "one of the pairs present: " + _topic_list([f"{a} -> {b}" for a, b in sorted(pairs)]),
        )


def choose_topics(
    log: Log, pose_topic: str | None, truth_topic: str | None, tf_pair: tuple[str, str]
) -> tuple[str, str | None]:
    """(pose topic, truth topic or None) by the rules in the module docstring."""
    if pose_topic is None:
        for kind in (STAMPED_POSE_TYPES, TF_TYPES, DETECTION_TYPES, ODOMETRY_TYPES):
            found = [t for t, i in log.topics.items() if i.msgtype in kind and i.count]
            if kind is TF_TYPES:  # only decoded when no stamped pose topic exists
                found = [t for t in found if tf_pair in _tf_pairs(log, t, tf_pair)]
            if len(found) > 1:
                raise InputError(
                    log.source,
                    f"several pose topics: {_topic_list(found)}",
                    "--pose-topic to choose one",
                )
            if found:
                pose_topic = found[0]
                break
        else:
            tf_hint = ""
            if any(i.msgtype in TF_TYPES for i in log.topics.values()):
                tf_hint = (
                    f"; no TF topic has {tf_pair[0]} -> {tf_pair[1]} (see --tf-parent/--tf-child)"
                )
            raise InputError(
                log.source,
                f"no pose topic among {_topic_list(list(log.topics))}{tf_hint}",
                f"a topic of type {_POSE_EXPECTED}",
            )
    _check_topic(log, pose_topic, "pose", tf_pair)
    if truth_topic is None:
        odom = [
            t
            for t, i in log.topics.items()
            if i.msgtype in ODOMETRY_TYPES and i.count and t != pose_topic
        ]
        truth_topic = odom[0] if len(odom) == 1 else None
    else:
        _check_topic(log, truth_topic, "truth", tf_pair)
    return pose_topic, truth_topic


def _clean(source, what: str, t_ns: np.ndarray, cols: dict[str, np.ndarray], finite: list[str]):
    """Drop non-finite rows, sort by stamp, keep the last of exactly repeated stamps.

    Args:
        t_ns: (N,) int64 stamps [ns] in arrival order.
        cols: (N, ...) arrays to keep aligned with the stamps.
        finite: names in `cols` that must be finite for a row to be kept.
    Returns (t_s (M,) float64 [s], cols, counts) with counts of what was dropped or reordered;
    cols["t_ns"] (M,) holds the kept stamps as integers [ns].
    """
    n = len(t_ns)
    if n == 0:
        raise InputError(source, f"{what}: no poses", "at least one pose")
    ok = np.ones(n, dtype=bool)
    for k in finite:
        ok &= np.isfinite(cols[k]).reshape(n, -1).all(axis=1)
    if not ok.any():
        raise InputError(source, f"{what}: all {n} poses are NaN or infinite", "finite poses")
    # a corrupt value such as 1e308 is finite but overflows the estimate: refused, not predicted
    far = ok & (np.abs(cols["xy_m"]) > spec.MAX_COORD_M).any(axis=1)
    if far.any():
        k = int(np.argmax(far))
        raise InputError(
            source,
            f"{what}: {int(far.sum())} poses beyond ±{spec.MAX_COORD_M:g} m (first: data row "
            f"{k + 1}, x {cols['xy_m'][k, 0]:g}, y {cols['xy_m'][k, 1]:g})",
            "map coordinates in metres",
        )
    t_ns = t_ns[ok]
    cols = {k: v[ok] for k, v in cols.items()} | {"t_ns": t_ns}
    # A row is "reordered" when it arrived after a row with a later stamp.
    n_reordered = int(np.sum(t_ns[1:] < np.maximum.accumulate(t_ns)[:-1]))
    order = np.argsort(t_ns, kind="stable")
    t_s = rm.ns_to_seconds(t_ns[order])
    # Dedupe on the float seconds the Drive will hold (epoch stamps a few ns apart can collide).
    last = np.append(t_s[1:] != t_s[:-1], True)
    keep = order[last]
    counts = {
        "n_messages": n,
        "n_dropped_nonfinite": int(n - ok.sum()),
        "n_reordered": n_reordered,
        "n_duplicate_stamps": int(np.sum(~last)),
        "t0_ns": int(t_ns[order[0]]),
    }
    return t_s[last], {k: v[keep] for k, v in cols.items()}, counts


def _log_series(log: Log, topic: str, tf_pair, log_time: bool, tags: dict, read: dict):
    """Cleaned (t_s, cols, counts) of one pose-like topic; cols has xy_m, yaw_rad, v_mps, t_ns.

    read: `Log.pose_tables` of the topic, unless it is a detection topic, whose counts also hold
    "detection": `apriltag.detection_rows`' meta.
    """
    extra = {}
    if log.topics[topic].msgtype in DETECTION_TYPES:
        from fpe_jax.io import apriltag  # with the TF reader: only for detection topics

        tag_id = 0 if tags.get("tag_id") is None else tags["tag_id"]
        rows, extra["detection"] = apriltag.detection_rows(
            log,
            topic,
            tag_id=tag_id,
            tag_to_base=tags.get("tag_to_base"),
            map_frame=tf_pair[0],
            car_frame=tf_pair[1],
            drop_outside_tf=tags.get("drop_outside_tf", False),
            log_time=log_time,
            max_tf_gap_s=tags.get("max_tf_gap_s"),
        )
        table = PoseRows.of(rows)
    else:
        table = read[topic]
    t_ns = table.log_ns if log_time else table.stamp_ns
    if not log_time:
        check_stamps_vary(log.source, topic, t_ns)
    a = table.values
    cols = {"xy_m": a[:, 0:2], "quat": a[:, 2:6], "v_mps": a[:, 6]}
    t_s, cols, counts = _clean(log.source, topic, t_ns, cols, ["xy_m", "quat"])
    cols["yaw_rad"] = rm.quaternion_to_yaw(*cols.pop("quat").T)
    return t_s, cols, counts | extra


def _refuse_tag_options(source, topic: str, tags: dict) -> None:
    """InputError if an AprilTag option was given for a log or topic that has no detections."""
    given = [
        flag
        for flag, key in (
            ("--tag-id", "tag_id"),
            ("--tag-to-base", "tag_to_base"),
            ("--drop-outside-tf", "drop_outside_tf"),
            ("--max-tf-gap", "max_tf_gap_s"),
        )
        if tags.get(key) is not None and tags.get(key) is not False  # a tag id 0 counts
    ]
    if given:
        raise InputError(
            source,
            f"{', '.join(given)} applies to AprilTag detection topics, not {topic}",
            f"no {', '.join(given)}",
        )


def _drive_from_log(path, pose_topic, truth_topic, log_time, tf_pair, tags: dict) -> Drive:
    log = open_log(path)
    pose_topic, truth_topic = choose_topics(log, pose_topic, truth_topic, tf_pair)
    poses = [t for t in (pose_topic, truth_topic) if t is not None]
    read = log.pose_tables(
        [t for t in poses if log.topics[t].msgtype not in DETECTION_TYPES], tf_pair
    )
    t_s, cols, counts = _log_series(log, pose_topic, tf_pair, log_time, tags, read)
    if log.topics[pose_topic].msgtype not in DETECTION_TYPES:
        _refuse_tag_options(log.source, pose_topic, tags)
    meta: dict[str, Any] = {
        "source": str(path),
        "format": log.format,
        "pose_topic": pose_topic,
        "pose_type": rm.full_type(log.topics[pose_topic].msgtype),
        "truth_topic": truth_topic,
        "frames": {"tf_parent": tf_pair[0], "tf_child": tf_pair[1]},
        "time": "log" if log_time else "header.stamp",
        **counts,
    }
    truth = {}
    if truth_topic is not None:
        tt, tc, tcounts = _log_series(log, truth_topic, tf_pair, log_time, tags, read)
        truth = dict(truth_t_s=tt, **{f"truth_{k}": tc[k] for k in ("xy_m", "yaw_rad", "v_mps")})
        truth["truth_t_ns"] = tc["t_ns"]
        meta["truth_type"] = rm.full_type(log.topics[truth_topic].msgtype)
        meta.update({f"truth_{k}": v for k, v in tcounts.items()})
    return Drive(
        t_s=t_s, xy_m=cols["xy_m"], yaw_rad=cols["yaw_rad"], **truth, meta=meta, t_ns=cols["t_ns"]
    )


def dropped_note(drive: Drive) -> str | None:
    """One line on the detections `drop_outside_tf` dropped from a drive, or None."""
    det = drive.meta.get("detection") or {}
    n = det.get("n_dropped_outside_tf", 0)
    if not n:
        return None
    gap = det.get("n_dropped_tf_gap", 0)
    where = f", {gap} of them in TF gaps longer than the limit" if gap else ""
    return (
        f"dropped {n} detections of {det.get('n_tag_detections', n)} outside the TF buffer "
        f"of {drive.meta.get('source')}{where} (--drop-outside-tf)"
    )


def _drive_from_table(path, rate_hz) -> Drive:
    table = tables.read_table(path)
    data = table.data
    if table.header is None:
        # The 2019 project's saved poses: `x, y, z` rows at a fixed rate, no stamps.
        if data.shape[1] != 3:
            raise InputError(
                path,
                f"header-less CSV with {data.shape[1]} columns",
                "x,y,z rows, or a header line t,x,y[,yaw][,v]",
            )
        x, y, yaw, v, t = data[:, 0], data[:, 1], None, None, None
        fmt = "xyz-csv"
    else:
        x = table.column(tables.X_NAMES, "x")
        y = table.column(tables.Y_NAMES, "y")
        yaw = table.column(tables.YAW_NAMES, "yaw", required=False)
        v = table.column(tables.SPEED_NAMES, "speed", required=False)
        t = table.column(tables.T_NAMES, "time", required=False)
        fmt = "csv"
    if t is None:
        if rate_hz is None:
            what = "is a header-less x,y,z CSV" if table.header is None else "has no time column"
            raise InputError(path, f"{what}, so --rate HZ is required", "row k at t = k/HZ s")
        t = np.arange(len(x)) / spec.check_rate(rate_hz, path, "--rate")
    elif rate_hz is not None:
        raise InputError(path, "--rate given but the CSV has a time column", "no --rate")
    cols = {"t": t, "xy_m": np.column_stack([x, y])}
    cols |= {k: c for k, c in (("yaw_rad", yaw), ("v_mps", v)) if c is not None}
    finite = [k for k in cols if k != "v_mps"]
    # Rows with a non-finite stamp are dropped; the others keep the exact nanoseconds of the text.
    if table.t_ns is not None:
        t_ns = table.t_ns
        cols["t"] = np.where(table.t_ok, t, np.nan)
    else:
        t_ns = np.zeros(len(t), dtype=np.int64)
        good_t = np.isfinite(t)
        t_ns[good_t] = rm.seconds_to_ns(t[good_t])
    t_s, cols, counts = _clean(path, "CSV", t_ns, cols, finite)
    meta: dict[str, Any] = {
        "source": str(path),
        "format": fmt,
        "columns": list(table.header) if table.header else ["x", "y", "z"],
        "rate_hz": rate_hz,
        **counts,
    }
    if "v_mps" in cols:
        meta["v_mps"] = cols["v_mps"]
    yaw_rad = cols.get("yaw_rad", np.full(len(t_s), np.nan))
    return Drive(t_s=t_s, xy_m=cols["xy_m"], yaw_rad=yaw_rad, meta=meta, t_ns=cols["t_ns"])


def load_drive(
    path,
    *,
    pose_topic: str | None = None,
    truth_topic: str | None = None,
    rate_hz: float | None = None,
    log_time: bool = False,
    tf_parent: str = "map",
    tf_child: str = "other_base_link",
    tag_id: int | None = None,
    tag_to_base=None,
    drop_outside_tf: bool = False,
    max_tf_gap_s: float | None = None,
) -> Drive:
    """Read one drive of the leading car from a log or a CSV.

    Args:
        path: a ROS 2 `.mcap`, a rosbag2 folder (or its metadata.yaml / storage file), a ROS 1
            `.bag`, a CSV with header `t,x,y[,yaw][,v]` (t [s], x/y [m], yaw [rad], v [m/s];
            v is kept as meta["v_mps"] (N,)), or a header-less `x,y,z` CSV sampled at rate_hz.
        pose_topic: topic of the observed poses (PoseStamped, PoseWithCovarianceStamped,
            Odometry or TFMessage); default: see the module docstring.
        truth_topic: topic of ground truth (same types; speed from Odometry twist, else NaN);
            default: the only Odometry topic other than the pose topic, if there is one.
        rate_hz: sample rate [Hz] of a CSV without a time column (required there, refused else).
        log_time: stamp by recording time instead of header.stamp (logs only).
        tf_parent, tf_child: the transform to read from a TFMessage topic (leading '/' ignored);
            for a detection topic, the map frame and the leading car's frame of the composition.
        tag_id: the AprilTag id to follow on a detection topic (None: 0).
        tag_to_base: the tag's mount on the leading car, "x,y,z,yaw" or 4 numbers ([m], [rad],
            see `fpe_jax.io.apriltag`); None: a transform tag -> tf_child in the log.
        drop_outside_tf: drop detections stamped outside the TF buffer, or inside one of its
            gaps longer than the limit, instead of failing (counted in meta["detection"]).
        max_tf_gap_s: the longest gap [s] between two transforms of a TF edge that a lookup may
            interpolate across; None: each edge's own default (`fpe_jax.io.tf.default_max_gap_ns`).

    Returns a `Drive` with absolute stamps [s] (float64, computed from integer nanoseconds) and
    the integers themselves (t_ns, truth_t_ns), which `drive.local_frame` shifts exactly.
    A log topic whose header stamps are all equal (zero: unset) is an error unless log_time.
    Rows with a non-finite position or orientation are dropped, out-of-order stamps are sorted,
    and of exactly repeated stamps the last one is kept; meta counts each (n_dropped_nonfinite,
    n_reordered, n_duplicate_stamps) and holds source, format, topics, types, frames, t0_ns.
    Orientation given as an all-zero quaternion means "unknown" and gives yaw NaN.
    Raises InputError for anything it cannot read as asked.
    """
    if is_log_path(path):
        if rate_hz is not None:
            raise InputError(path, "--rate applies to header-less CSVs only", "no --rate for logs")
        tf_pair = (tf_parent.lstrip("/"), tf_child.lstrip("/"))
        tags = dict(tag_id=tag_id, tag_to_base=tag_to_base, drop_outside_tf=drop_outside_tf)
        tags["max_tf_gap_s"] = max_tf_gap_s
        return _drive_from_log(path, pose_topic, truth_topic, log_time, tf_pair, tags)
    if Path(path).suffix.lower() not in tables.TABLE_SUFFIXES:
        if not Path(path).exists():
            raise InputError(path, "does not exist")
        raise InputError(
            path,
            f"unknown drive format {Path(path).suffix or '(no suffix)'!r}",
            ".mcap, .bag, a rosbag2 folder or .csv",
        )
    for flag, value in (("--pose-topic", pose_topic), ("--truth-topic", truth_topic)):
        if value is not None:
            raise InputError(path, f"{flag} applies to ROS logs, not CSV", f"no {flag}")
    if log_time:
        raise InputError(path, "--log-time applies to ROS logs, not CSV", "no --log-time")
    tags = dict(tag_id=tag_id, tag_to_base=tag_to_base, drop_outside_tf=drop_outside_tf)
    tags["max_tf_gap_s"] = max_tf_gap_s
    _refuse_tag_options(path, "a CSV", tags)
    return _drive_from_table(path, rate_hz)


def describe_log(
    path,
    *,
    pose_topic: str | None = None,
    truth_topic: str | None = None,
    rate_hz: float | None = None,
    tf_parent: str = "map",
    tf_child: str = "other_base_link",
    tag_id: int | None = None,
    tag_to_base=None,
) -> dict[str, Any]:
    """Summary of a drive file, for `fpe info`.

    Returns a JSON-ready dict: source, format, duration_s and start_s (log time, [s]), topics
    (list of dicts: name, type, count, rate_hz (mean over the topic's span, or None)),
    pose_topic and truth_topic as `load_drive` would choose them (None plus `pose_error` when the
    automatic choice fails; an InputError when a topic named here is unusable). A CSV is read
    as a drive and described as one pseudo-topic "(csv)".
    Logs with TF topics add tf_tree (`TfBuffer.describe()`: parent, child, static, count,
    rate_hz, first_s, last_s, topics, depth per transform), and logs with AprilTag detection
    topics add detections (per topic: name, type and `apriltag.describe_detections`: the frame
    chain tf_parent <- camera <- tag <- tf_child and what each link comes from, or error).
    """
    if not is_log_path(path):
        drive = load_drive(path, rate_hz=rate_hz, tag_id=tag_id, tag_to_base=tag_to_base)
        n = len(drive.t_s)
        rate = (n - 1) / drive.duration_s if n > 1 and drive.duration_s > 0 else None
        return {
            "source": str(path),
            "format": drive.meta["format"],
            "duration_s": drive.duration_s,
            "start_s": float(drive.t_s[0]),
            "topics": [{"name": "(csv)", "type": "rows", "count": n, "rate_hz": rate}],
            "pose_topic": None,
            "truth_topic": None,
            "columns": drive.meta["columns"],
        }
    log = open_log(path)
    firsts = [i.first_ns for i in log.topics.values() if i.first_ns is not None]
    lasts = [i.last_ns for i in log.topics.values() if i.last_ns is not None]
    out: dict[str, Any] = {
        "source": str(path),
        "format": log.format,
        "duration_s": (max(lasts) - min(firsts)) * 1e-9 if firsts else 0.0,
        "start_s": float(rm.ns_to_seconds([min(firsts)])[0]) if firsts else None,
        "topics": [
            {
                "name": i.name,
                "type": rm.full_type(i.msgtype) if i.msgtype else "unknown",
                "count": i.count,
                "rate_hz": i.rate_hz,
            }
            for i in log.topics.values()
        ],
    }
    from fpe_jax.io import apriltag
    from fpe_jax.io.tf import TfBuffer

    tf_pair = (tf_parent.lstrip("/"), tf_child.lstrip("/"))
    if any(i.msgtype in TF_TYPES and i.count for i in log.topics.values()):
        try:
            out["tf_tree"] = TfBuffer.from_log(log).describe()
        except InputError as e:
            out["tf_tree"], out["tf_error"] = [], e.problem
    out["detections"] = [
        {
            "name": t,
            "type": rm.full_type(i.msgtype),
            **apriltag.describe_detections(
                log,
                t,
                tag_id=0 if tag_id is None else tag_id,
                tag_to_base=tag_to_base,
                map_frame=tf_pair[0],
                car_frame=tf_pair[1],
            ),
        }
        for t, i in log.topics.items()
        if i.msgtype in DETECTION_TYPES and i.count
    ]
    try:
        out["pose_topic"], out["truth_topic"] = choose_topics(log, pose_topic, truth_topic, tf_pair)
    except InputError as e:
        if pose_topic is not None or truth_topic is not None:
            raise  # the caller asked for these topics: not having them is an error
        out.update(pose_topic=None, truth_topic=None, pose_error=e.problem)
    return out
