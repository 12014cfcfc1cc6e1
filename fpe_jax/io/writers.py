"""Writing files: predictions (CSV or ROS 2 MCAP), simulated drives (ROS 2 MCAP) and the poses of
`fpe batch` (.npy or CSV).

Every file fpe-jax writes goes through `atomic_output` (or `write_text` / `write_bytes` on top of
it): it writes a uniquely named hidden temporary file next to the target and renames it into
place only when writing succeeded, so a failure, Ctrl-C or SIGTERM (the CLI turns it into
KeyboardInterrupt) never leaves a half-written or temporary file, and an existing file is only
replaced with `force`. `check_output_path` runs the same checks before any slow work starts.
"""

from __future__ import annotations

import contextlib
import io
import os
import secrets
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from fpe_jax.errors import InputError
from fpe_jax.io import ros_msgs as rm

PREDICTION_TOPIC = "/future_pose"
OBSERVATION_TOPIC = "/opp/pose"
# CSV rows formatted by one `%` at a time (`write_predictions`): each block's values as Python
# floats (24 bytes each) and its text are written out before the next block is made
CSV_BLOCK_ROWS = 1 << 14
_ZERO_COV = [0.0] * 36  # mcap_ros2 wants a list (not an array) for float64[36]


def check_not_input(path, inputs) -> None:
    """Raise InputError if the output `path` is the same file as any of `inputs` (paths, None
    skipped), however spelled: relative, through a symlink, or a hard link (same device and
    inode), so an output never replaces what the command reads, `--force` or not."""
    try:
        out = os.stat(path)
    except OSError:  # nothing there (or nothing reachable): it cannot be an input
        return
    for given in inputs:
        if given is None:
            continue
        try:
            st = os.stat(given)
        except (OSError, TypeError, ValueError):
            continue
        if (st.st_dev, st.st_ino) == (out.st_dev, out.st_ino):
            raise InputError(
                path,
                f"is the same file as the input {str(given)!r}; refusing to overwrite it",
                "an output path that is not one of the command's inputs",
            )


def check_output_path(path, force: bool, inputs=()) -> Path:
    """Fail early (before any work) if `path` cannot be written as asked.

    Raises InputError if its folder does not exist or cannot be written (read-only folder or file
    system), if it is a folder, if it is the same file as one of `inputs` (`check_not_input`,
    whatever `force` says), or if it exists and `force` is false. Returns it as a `Path`.
    """
    p = Path(path)
    check_not_input(p, inputs)
    try:
        os.stat(p.parent)  # is_dir() says False for a name too long, stat says why
        os.lstat(p) if p.name else None
    except FileNotFoundError:
        pass
    except OSError as e:  # a name too long, a folder that is a file, a loop of links
        raise InputError(p, f"cannot be used as an output path ({e.strerror})") from None
    if not p.parent.is_dir():
        raise InputError(p, f"its folder {str(p.parent)!r} does not exist", "an existing folder")
    if p.is_dir():
        raise InputError(p, "is a folder", "a file name to write")
    if p.exists() and not force:
        raise InputError(p, "exists; pass --force to overwrite")
    if not os.access(p.parent, os.W_OK | os.X_OK):
        raise InputError(p, f"its folder {str(p.parent)!r} is not writable", "a writable folder")
    # access() grants root everything; only creating a file shows a folder (such as /sys) that
    # refuses files: a hidden probe, created and removed at once
    probe = p.with_name(f".{_short_name(p)}.{os.getpid()}.{secrets.token_hex(4)}.probe")
    try:
        os.close(os.open(probe, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600))
    except OSError as e:
        raise InputError(
            p, f"its folder {str(p.parent)!r} is not writable ({e.strerror})", "a writable folder"
        ) from None
    probe.unlink(missing_ok=True)
    return p


def _short_name(p: Path, n_bytes: int = 64) -> str:
    """The start of p's name, at most n_bytes bytes (whole characters), for temporary names."""
    name = os.fsencode(p.name)[:n_bytes]
    return os.fsdecode(name).encode("utf-8", "surrogateescape").decode("utf-8", "ignore") or "out"


def check_output_paths(paths, force: bool, inputs=()) -> None:
    """`check_output_path` for each of several targets (all checked before any is written)."""
    for p in paths:
        check_output_path(p, force, inputs)


@contextlib.contextmanager
def atomic_output(path, force: bool) -> Iterator[Path]:
    """Yield a temporary path in the target's folder; rename it to `path` if the body succeeds.

    The temporary file is removed on every failure, KeyboardInterrupt included. A failure to
    write (disk full, permissions) is an InputError naming the target.
    """
    target = check_output_path(path, force)
    # Our own unique name (not mkstemp) so the file gets the user's umask permissions; short,
    # so a target name near the file system's 255-byte limit still has a temporary twin.
    tmp = target.with_name(f".{_short_name(target)}.{os.getpid()}.{secrets.token_hex(4)}.part")
    try:
        yield tmp
        if target.exists() and not force:  # appeared while we were writing
            raise InputError(target, "exists; pass --force to overwrite")
        os.replace(tmp, target)
    except OSError as e:
        raise InputError(target, f"cannot be written ({e.strerror or e})") from None
    finally:
        tmp.unlink(missing_ok=True)


def write_bytes(path, data: bytes | bytearray, *, force: bool = False) -> Path:
    """Write `data` to `path` atomically (see `atomic_output`); returns the path."""
    with atomic_output(path, force) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def write_text(path, text: str, *, force: bool = False) -> Path:
    """Write UTF-8 `text` to `path` atomically (see `atomic_output`); returns the path."""
    return write_bytes(path, text.encode("utf-8"), force=force)


def write_xy_csv(path, xy_m, *, fmt: str = "%.6f", force: bool = False) -> Path:
    """Write (K, 2) points x [m], y [m] as CSV with header `x,y` (`fmt`: 6 decimals), atomically."""
    with atomic_output(path, force) as tmp, open(tmp, "x", newline="") as f:
        np.savetxt(f, xy_m, fmt=fmt, delimiter=",", header="x,y", comments="")
    return Path(path)


def _write_ros2_mcap(path, events: list[tuple[int, str, str, dict]], force: bool = False) -> Path:
    """Write (log_time_ns, topic, msgtype, message) events, in time order, as a ROS 2 MCAP,
    atomically (see `atomic_output`); returns the path."""
    from mcap_ros2.writer import Writer  # imported here: only writers need it

    events = sorted(events, key=lambda e: e[0])  # stable: equal times keep their given order
    with atomic_output(path, force) as tmp, open(tmp, "xb") as f:
        writer = Writer(f)
        schemas: dict[str, Any] = {}
        for log_ns, topic, msgtype, msg in events:
            if msgtype not in schemas:
                schemas[msgtype] = writer.register_msgdef(
                    rm.full_type(msgtype), rm.definition(msgtype)
                )
            writer.write_message(topic, schemas[msgtype], msg, log_time=log_ns, publish_time=log_ns)
        writer.finish()
    return Path(path)


def _stamps_ns(source, t_s, what: str) -> np.ndarray:
    """(N,) stamps [s] -> (N,) int [ns], rejecting what a ROS stamp (and log time) cannot hold."""
    t = np.asarray(t_s, dtype=np.float64)
    if t.ndim != 1:
        raise InputError(source, f"{what}: stamps have shape {t.shape}", "a 1-D array")
    if not np.all(np.isfinite(t)) or np.any(t < 0) or np.any(t >= 2**31):
        raise InputError(source, f"{what}: stamps must be finite and in [0, 2^31) s")
    return rm.seconds_to_ns(t)


def _series(source, spec: dict, what: str, fields: tuple[str, ...]) -> tuple[np.ndarray, ...]:
    """Stamps [ns] plus the named (N, ...) arrays of one writer spec, checked for matching N."""
    missing = [k for k in ("t_s", *fields) if k not in spec]
    if missing:
        raise InputError(source, f"{what}: missing {', '.join(missing)}")
    ns = _stamps_ns(source, spec["t_s"], what)
    out = [np.asarray(spec[k], dtype=np.float64) for k in fields]
    for k, a in zip(fields, out):
        want = (len(ns), 2) if k == "xy_m" else (len(ns),)
        if a.shape != want:
            raise InputError(source, f"{what}: {k} has shape {a.shape}", f"shape {want}")
    return (ns, *out)


def _pose_msg(ns: int | np.integer, frame_id: str, x: float, y: float, yaw: float) -> dict:
    return {
        "header": {"stamp": rm.stamp_dict(ns), "frame_id": frame_id},
        "pose": {"position": {"x": x, "y": y, "z": 0.0}, "orientation": rm.yaw_to_quaternion(yaw)},
    }


def _pose_events(source, spec: dict, default_topic: str) -> list:
    ns, xy, yaw = _series(source, spec, "pose", ("xy_m", "yaw_rad"))
    topic, frame = spec.get("topic", default_topic), spec.get("frame_id", "map")
    return [
        (int(n), topic, "geometry_msgs/PoseStamped", _pose_msg(n, frame, *p, a))
        for n, p, a in zip(ns, xy.tolist(), yaw.tolist())
    ]


def _odom_events(source, spec: dict) -> list:
    ns, xy, yaw, v, w = _series(source, spec, "odom", ("xy_m", "yaw_rad", "v_mps", "yaw_rate_rps"))
    topic, frame = spec.get("topic", "/opp/odom"), spec.get("frame_id", "map")
    child = spec.get("child_frame_id", "other_base_link")
    events = []
    for n, p, a, vi, wi in zip(ns, xy.tolist(), yaw.tolist(), v.tolist(), w.tolist()):
        pose = _pose_msg(n, frame, *p, a)
        msg = {
            "header": pose["header"],
            "child_frame_id": child,
            "pose": {"pose": pose["pose"], "covariance": _ZERO_COV},
            # Twist is in the child (body) frame: forward speed along x, turn rate about z.
            "twist": {
                "twist": {
                    "linear": {"x": vi, "y": 0.0, "z": 0.0},
                    "angular": {"x": 0.0, "y": 0.0, "z": wi},
                },
                "covariance": _ZERO_COV,
            },
        }
        events.append((int(n), topic, "nav_msgs/Odometry", msg))
    return events


def _tf_events(source, spec: dict) -> list:
    ns, xy, yaw = _series(source, spec, "tf", ("xy_m", "yaw_rad"))
    topic = spec.get("topic", "/tf")
    parent, child = spec.get("parent", "map"), spec.get("child", "other_base_link")
    events = []
    for n, (x, y), a in zip(ns, xy.tolist(), yaw.tolist()):
        q = rm.yaw_to_quaternion(a).values()
        tr = rm.transform_stamped(parent, child, n, (x, y, 0.0), q)
        events.append((int(n), topic, "tf2_msgs/TFMessage", {"transforms": [tr]}))
    return events


def write_drive_mcap(path, *, pose=None, odom=None, tf=None, force: bool = False) -> Path:
    """Write a (simulated) drive as a ROS 2 MCAP that `load_drive` and ROS tools read.

    Args:
        path: the .mcap file to write.
        pose: dict(t_s (N,) [s], xy_m (N, 2) [m], yaw_rad (N,) [rad] (NaN: no heading, written
            as a zero quaternion), topic="/opp/pose", frame_id="map") ->
            geometry_msgs/msg/PoseStamped.
        odom: dict(t_s, xy_m, yaw_rad, v_mps (N,) [m/s], yaw_rate_rps (N,) [rad/s],
            topic="/opp/odom", frame_id="map", child_frame_id="other_base_link") ->
            nav_msgs/msg/Odometry (twist in the body frame: linear.x = speed, angular.z = yaw rate).
        tf: dict(t_s, xy_m, yaw_rad, topic="/tf", parent="map", child="other_base_link") ->
            tf2_msgs/msg/TFMessage with one transform per message.
        force: replace an existing file.

    Stamps are rounded to whole nanoseconds; every message's log time equals its header stamp.
    Returns the written path.
    """
    if pose is None and odom is None and tf is None:
        raise InputError(path, "nothing to write", "at least one of pose, odom, tf")
    events = []
    if pose is not None:
        events += _pose_events(path, pose, OBSERVATION_TOPIC)
    if odom is not None:
        events += _odom_events(path, odom)
    if tf is not None:
        events += _tf_events(path, tf)
    return _write_ros2_mcap(path, events, force)


def _marker(
    ns: int | np.integer, ident: int, kind: int, points: list, rgba: tuple, space="future_pose"
) -> dict:
    from fpe_jax.io import scene

    return scene.ros2_marker(ns, "map", space, ident, kind, rgba, points=points)


def write_predictions(
    path,
    stamps_s,
    poses,
    dt_s: float,
    *,
    drive=None,
    cov_m2=None,
    track_xy_m=None,
    track_closed: bool = False,
    valid=None,
    force: bool = False,
) -> Path:
    """Write predicted poses as CSV or ROS 2 MCAP, chosen by the suffix of `path`.

    Args:
        path: `*.csv` or `*.mcap`.
        stamps_s: (N,) observation stamps [s] the predictions were made at.
        poses: (N, H, 3) predicted x [m], y [m], yaw [rad] at stamps_s + step * dt_s, step 1..H.
        dt_s: prediction step [s].
        drive: the observed `Drive`; its poses are written alongside (MCAP only).
        cov_m2: optional (N, H, 2, 2) map-frame covariance of each predicted position [m^2]:
            in CSV three more columns `cov_xx_m2,cov_xy_m2,cov_yy_m2`; in MCAP the ellipses.
        track_xy_m: optional (K, 2) track line x [m], y [m] (the waypoints); MCAP only.
        track_closed: whether the track is a loop (its line is drawn closed).
        valid: optional (N,) bool, whether each prediction had enough history
            (`fpe_jax.model.history_valid`): CSV a last column `valid` (1 / 0); MCAP the
            markers of an invalid prediction in the namespace `future_pose/invalid`, grey, and
            its path and ellipses left out (`fpe_jax.io.scene`). Default: all valid.
        force: replace an existing file.

    CSV: header `stamp,step,horizon_s,x,y,yaw`, one row per (observation, step), 9 decimals.
    MCAP: one visualization_msgs/msg/MarkerArray per observation on /future_pose (frame `map`,
    stamp = observation stamp): a SPHERE_LIST of the H predicted points and a LINE_STRIP through
    them; plus the observations as geometry_msgs/msg/PoseStamped on /opp/pose. The scene of
    `fpe_jax.io.scene`, in ROS 2 types: nav_msgs/msg/Path on /future_pose/path (header.stamp =
    observation stamp, pose k stamped stamp + k * dt_s, yaw included), the 1-sigma ellipses as
    flat SPHERE markers on /future_pose/ellipses (when `cov_m2` is given), and the track as a
    LINE_STRIP on /track (once, at the first message's time, when `track_xy_m` is given).
    """
    suffix = Path(path).suffix.lower()
    if suffix not in (".csv", ".mcap"):
        raise InputError(
            path, f"unknown output format {suffix or '(no suffix)'!r}", ".csv or .mcap"
        )
    stamps = np.asarray(stamps_s, dtype=np.float64)
    poses = np.asarray(poses, dtype=np.float64)
    if stamps.ndim != 1 or poses.ndim != 3 or poses.shape[0] != len(stamps) or poses.shape[2] != 3:
        raise ValueError(
            f"write_predictions: stamps {stamps.shape} and poses {poses.shape} do not agree"
            " (expected (N,) and (N, H, 3))"
        )
    n, h, _ = poses.shape
    if suffix == ".csv":
        fmt = ["%.9f", "%d", "%.9f", "%.9f", "%.9f", "%.9f"]
        header = "stamp,step,horizon_s,x,y,yaw"
        cov = None if cov_m2 is None else np.asarray(cov_m2, dtype=np.float64).reshape(n, h, 4)
        if cov is not None:
            fmt += ["%.9g"] * 3
            header += ",cov_xx_m2,cov_xy_m2,cov_yy_m2"
        ok = None if valid is None else np.asarray(valid, dtype=np.int64)
        if ok is not None:
            fmt.append("%d")
            header += ",valid"

        def table(lo: int, hi: int) -> np.ndarray:
            """The CSV rows of observations lo..hi-1 ((hi - lo) * h, columns)."""
            k = hi - lo
            step = np.tile(np.arange(1, h + 1), k)
            cols = [np.repeat(stamps[lo:hi], h), step, step * float(dt_s)]
            cols.append(poses[lo:hi].reshape(k * h, 3))
            if cov is not None:
                c = cov[lo:hi].reshape(k * h, 4)  # xx, xy, yx, yy
                cols += [c[:, 0], c[:, 1], c[:, 3]]
            if ok is not None:
                cols.append(np.repeat(ok[lo:hi], h))
            return np.column_stack(cols)

        # np.savetxt's text to the byte (its rows are `line % tuple(row)` too), formatted by one
        # `%` per block of rows instead of one per row, in memory bounded by the block whatever
        # the log's length
        line = ",".join(fmt) + "\n"
        per_block = max(1, CSV_BLOCK_ROWS // max(h, 1))  # observations
        with atomic_output(path, force) as tmp, open(tmp, "x", newline="") as f:
            f.write(header + "\n")
            for lo in range(0, n, per_block):
                rows = table(lo, min(lo + per_block, n))
                f.write(line * len(rows) % tuple(rows.ravel().tolist()))
        return Path(path)

    from fpe_jax.io import scene  # the MCAP's prediction scene: not needed for CSV

    ns = _stamps_ns(path, stamps, "predictions")
    steps_ns = ns[:, None] + rm.seconds_to_ns(np.arange(1, h + 1) * float(dt_s))
    cov = np.full((n, h, 2, 2), np.nan) if cov_m2 is None else np.asarray(cov_m2, np.float64)
    ok = np.ones(n, dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    if cov.shape != (n, h, 2, 2) or ok.shape != (n,):
        raise ValueError(
            f"write_predictions: cov_m2 {cov.shape} or valid {ok.shape} does not match poses"
            f" {poses.shape} (expected (N, H, 2, 2) and (N,))"
        )
    events = []
    for k in range(n):
        pts = poses[k, :, :2].tolist()
        good = bool(ok[k])
        space, rgb = (
            ("future_pose", (1.0, 0.5, 0.0)) if good else ("future_pose/invalid", (0.5,) * 3)
        )
        markers = [
            _marker(ns[k], 0, rm.MARKER_SPHERE_LIST, pts, (*rgb, 1.0), space),
            _marker(ns[k], 1, rm.MARKER_LINE_STRIP, pts, (*rgb, 0.6), space),
        ]
        events.append(
            (int(ns[k]), PREDICTION_TOPIC, "visualization_msgs/MarkerArray", {"markers": markers})
        )
        drawn = scene.prediction_scene(int(ns[k]), poses[k], cov[k], steps_ns[k], good)
        events += [(int(ns[k]), *e) for e in scene.ros2_prediction(int(ns[k]), drawn, "map")]
    if drive is not None:
        obs = dict(t_s=drive.t_s, xy_m=drive.xy_m, yaw_rad=drive.yaw_rad)
        events += _pose_events(path, obs, OBSERVATION_TOPIC)
    if track_xy_m is not None and events:
        first_ns = min(e[0] for e in events)
        line = scene.ros2_track(track_xy_m, first_ns, "map", track_closed)
        events.insert(0, (first_ns, scene.TRACK_TOPIC, "visualization_msgs/MarkerArray", line))
    return _write_ros2_mcap(path, events, force)


def write_drive_csv(path, drive, *, force: bool = False) -> Path:
    """Write a `Drive`'s observations as CSV `t,x,y,yaw` (t [s], x/y [m], yaw [rad], 9 decimals):
    what `load_drive` reads back and `fpe run` reads on stdin.

    The yaw column is left out when some yaw is unknown (NaN), so every row still reads back.
    Truth is not written. A drive read from a file (with integer stamps, `Drive.t_ns`) gets its
    stamps written exactly, epoch stamps included. Returns the path.
    """
    t = np.asarray(drive.t_s, dtype=np.float64)
    cols, header = [t, drive.xy_m[:, 0], drive.xy_m[:, 1]], "t,x,y"
    if np.isfinite(drive.yaw_rad).all():
        cols.append(drive.yaw_rad)
        header += ",yaw"
    table = np.column_stack(cols)
    with atomic_output(path, force) as tmp, open(tmp, "x", newline="") as f:
        if drive.t_ns is None:
            np.savetxt(f, table, fmt="%.9f", delimiter=",", header=header, comments="")
            return Path(path)
        body = io.StringIO()
        np.savetxt(body, table[:, 1:], fmt="%.9f", delimiter=",")
        f.write(header + "\n")
        for ns, rest in zip(drive.t_ns.tolist(), body.getvalue().splitlines()):
            sign, a = ("-" if ns < 0 else ""), abs(ns)
            f.write(f"{sign}{a // 1_000_000_000}.{a % 1_000_000_000:09d},{rest}\n")
    return Path(path)


def write_poses(
    path, poses: np.ndarray, dt_s: float, *, force: bool = False, off_track=None
) -> Path:
    """Write (N, H, 3) poses as `.npy`, or as CSV with columns car,step,horizon_s,x,y,yaw, and
    off_track (1 for a car far from the track, 0 else) when `off_track` (N,) bool is given.

    Written to a temporary file in the target's folder and renamed into place, so a failure
    never leaves a partial file; an existing file is replaced only with `force`. `PosesFile`
    writes the same bytes a block of cars at a time.
    """
    n, h, _ = poses.shape
    with PosesFile(
        path, n, h, poses.dtype, dt_s, force=force, off_track=off_track is not None
    ) as f:
        f.write(poses, off_track)
    return Path(path)


class PosesFile:
    """`fpe batch`'s output (N, H, 3) written block by block, in car order, as `write_poses` writes
    it whole (the same bytes): a `.npy` (its header, then each block's bytes) or CSV rows.

        with PosesFile("out.npy", n, h, np.float32, dt_s) as out:
            for poses in blocks:        # (k, H, 3) each, k summing to n
                out.write(poses)

    The file is written under a temporary name in the target's folder and renamed into place
    when the `with` body ends normally having written all N cars; on any failure (Ctrl-C
    included) or a short count the temporary file is removed and nothing else changes. An
    existing target is replaced only with `force`.

    Args:
        path: OUT.npy or OUT.csv.
        n_cars, horizon: N and H.
        dtype: the .npy's dtype (blocks are cast to it); CSV writes every value as float64.
        dt_s: step [s] (CSV horizon_s column).
        off_track: whether the CSV has the off_track column (then each `write` gives it).
    """

    def __init__(
        self, path, n_cars: int, horizon: int, dtype, dt_s: float, *, force=False, off_track=False
    ):
        self.path = Path(path)
        suffix = self.path.suffix.lower()
        if suffix not in (".npy", ".csv"):
            raise InputError(self.path, f"unknown output type {suffix!r}", "OUT.npy or OUT.csv")
        self.csv = suffix == ".csv"
        self.n_cars, self.horizon, self.dtype = n_cars, horizon, np.dtype(dtype)
        self.dt_s, self.off_track, self.force = dt_s, off_track, force
        self.written = 0
        self._atomic = self._file = None
        self._data_start = 0

    def __enter__(self) -> PosesFile:
        self._atomic = atomic_output(self.path, self.force)
        tmp = self._atomic.__enter__()
        try:
            self._file = open(tmp, "x" if self.csv else "xb")
            if self.csv:
                cols = "car,step,horizon_s,x,y,yaw" + ",off_track" * self.off_track
                self._file.write(cols + "\n")
            else:  # the header np.save writes for this shape and dtype
                header = {
                    "descr": np.lib.format.dtype_to_descr(self.dtype),
                    "fortran_order": False,
                    "shape": (self.n_cars, self.horizon, 3),
                }
                np.lib.format.write_array_header_1_0(self._file, header)
                self._data_start = self._file.tell()
        except BaseException:
            self.__exit__(*sys.exc_info())
            raise
        return self

    def write(self, poses: np.ndarray, off_track=None) -> None:
        """Append the next k cars' poses (k, H, 3) [and their off_track flags (k,) bool]."""
        k = poses.shape[0]
        if poses.shape[1:] != (self.horizon, 3) or self.written + k > self.n_cars:
            raise ValueError(f"block of shape {poses.shape} after {self.written} of {self.n_cars}")
        if self.csv:
            _write_poses_csv(self._file, poses, self.dt_s, off_track, first_car=self.written)
        else:
            self._file.write(np.ascontiguousarray(poses, dtype=self.dtype).data)
        self.written += k

    def patch(self, rows: np.ndarray, poses: np.ndarray) -> None:
        """Rewrite the poses (k, H, 3) of cars `rows` (k,) (ascending, already written); .npy
        only (a CSV row's length depends on its values)."""
        rows = np.asarray(rows, dtype=np.int64)
        if self.csv or rows.size and (rows[0] < 0 or rows[-1] >= self.written):
            raise ValueError(f"cannot rewrite rows {rows[:3]}... of {self.path}")
        self._file.flush()
        data = np.ascontiguousarray(poses, dtype=self.dtype)
        row_bytes = self.horizon * 3 * self.dtype.itemsize
        runs = np.split(np.arange(rows.size), np.flatnonzero(np.diff(rows) != 1) + 1)
        for run in runs:  # consecutive cars in one write
            if run.size:
                offset = self._data_start + int(rows[run[0]]) * row_bytes
                os.pwrite(self._file.fileno(), data[run[0] : run[-1] + 1].tobytes(), offset)

    def __exit__(self, kind, value, tb) -> bool:
        if self._file is not None:
            self._file.close()
            self._file = None
        short = kind is None and self.written != self.n_cars
        if short:
            kind, tb = ValueError, None
            value = ValueError(f"{self.path}: wrote {self.written} of {self.n_cars} cars")
        atomic, self._atomic = self._atomic, None
        if atomic is not None:
            atomic.__exit__(kind, value, tb)  # renames into place, or removes the temporary file
        if short:
            raise value
        return False


def _write_poses_csv(
    f, poses: np.ndarray, dt_s: float, off_track=None, *, first_car=0, rows_per_block=200_000
):
    """CSV rows car,step,horizon_s,x,y,yaw[,off_track] of poses (k, H, 3), cars numbered from
    first_car, to the open text file f."""
    n, h, _ = poses.shape
    step = np.arange(1, h + 1)
    fmt = ["%d", "%d", "%.3f", "%.6f", "%.6f", "%.6f"] + ["%d"] * (off_track is not None)
    cars_per_block = max(rows_per_block // h, 1)
    for start in range(0, n, cars_per_block):
        block = poses[start : start + cars_per_block].astype(np.float64)
        k = block.shape[0]
        car = np.repeat(np.arange(first_car + start, first_car + start + k), h)
        st = np.tile(step, k)
        cols = [car, st, st * dt_s, block.reshape(-1, 3)]
        if off_track is not None:
            cols.append(np.repeat(np.asarray(off_track[start : start + k], dtype=int), h))
        np.savetxt(f, np.column_stack(cols), fmt=fmt, delimiter=",")
