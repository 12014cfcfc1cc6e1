"""ROS 2 message definitions (.msg text) for writing MCAP without a ROS installation.

mcap_ros2's writer needs a *full* definition per schema: the root type's fields, then each type
it depends on, separated by a line of 80 `=` and a `MSG: pkg/Type` line. We keep each type's own
fields once below and assemble the full text on demand, so a definition can never drift between
two schemas. Field references are always fully qualified (`pkg/Type`) so the assembler needs no
ROS package-resolution rules. Field lists follow ROS 2 Humble/Jazzy, so the files can be played
back into a real ROS 2 system.

Message types outside the common ROS packages (the AprilTag detectors') are shipped as .msg files
under `fpe_jax/io/msgs/PKG/TYPE.msg` and loaded into the same table (`shipped_definitions`), so
the writers, the mcap_ros2 fallback for schema-less channels and the rosbags typestore all use one
text per type.

Also here: the stamp and quaternion conversions every reader and writer shares.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from fpe_jax.drive import seconds_from_ns

_FIELDS: dict[str, str] = {
    "builtin_interfaces/Time": "int32 sec\nuint32 nanosec",
    "builtin_interfaces/Duration": "int32 sec\nuint32 nanosec",
    "std_msgs/Header": "builtin_interfaces/Time stamp\nstring frame_id",
    "std_msgs/ColorRGBA": "float32 r\nfloat32 g\nfloat32 b\nfloat32 a",
    "geometry_msgs/Point": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/Vector3": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1",
    "geometry_msgs/Pose": "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation",
    "geometry_msgs/PoseStamped": "std_msgs/Header header\ngeometry_msgs/Pose pose",
    "geometry_msgs/PoseWithCovariance": "geometry_msgs/Pose pose\nfloat64[36] covariance",
    "geometry_msgs/PoseWithCovarianceStamped": (
        "std_msgs/Header header\ngeometry_msgs/PoseWithCovariance pose"
    ),
    "geometry_msgs/Twist": "geometry_msgs/Vector3 linear\ngeometry_msgs/Vector3 angular",
    "geometry_msgs/TwistWithCovariance": "geometry_msgs/Twist twist\nfloat64[36] covariance",
    "geometry_msgs/Transform": (
        "geometry_msgs/Vector3 translation\ngeometry_msgs/Quaternion rotation"
    ),
    "geometry_msgs/TransformStamped": (
        "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/Transform transform"
    ),
    "tf2_msgs/TFMessage": "geometry_msgs/TransformStamped[] transforms",
    "nav_msgs/Odometry": (
        "std_msgs/Header header\n"
        "string child_frame_id\n"
        "geometry_msgs/PoseWithCovariance pose\n"
        "geometry_msgs/TwistWithCovariance twist"
    ),
    "nav_msgs/Path": "std_msgs/Header header\ngeometry_msgs/PoseStamped[] poses",
    "sensor_msgs/CompressedImage": "std_msgs/Header header\nstring format\nuint8[] data",
    "visualization_msgs/UVCoordinate": "float32 u\nfloat32 v",
    "visualization_msgs/MeshFile": "string filename\nuint8[] data",
    "visualization_msgs/Marker": (
        "int32 ARROW=0\nint32 CUBE=1\nint32 SPHERE=2\nint32 CYLINDER=3\nint32 LINE_STRIP=4\n"
        "int32 LINE_LIST=5\nint32 CUBE_LIST=6\nint32 SPHERE_LIST=7\nint32 POINTS=8\n"
        "int32 TEXT_VIEW_FACING=9\nint32 MESH_RESOURCE=10\nint32 TRIANGLE_LIST=11\n"
        "int32 ADD=0\nint32 MODIFY=0\nint32 DELETE=2\nint32 DELETEALL=3\n"
        "std_msgs/Header header\n"
        "string ns\n"
        "int32 id\n"
        "int32 type\n"
        "int32 action\n"
        "geometry_msgs/Pose pose\n"
        "geometry_msgs/Vector3 scale\n"
        "std_msgs/ColorRGBA color\n"
        "builtin_interfaces/Duration lifetime\n"
        "bool frame_locked\n"
        "geometry_msgs/Point[] points\n"
        "std_msgs/ColorRGBA[] colors\n"
        "string texture_resource\n"
        "sensor_msgs/CompressedImage texture\n"
        "visualization_msgs/UVCoordinate[] uv_coordinates\n"
        "string text\n"
        "string mesh_resource\n"
        "visualization_msgs/MeshFile mesh_file\n"
        "bool mesh_use_embedded_materials"
    ),
    "visualization_msgs/MarkerArray": "visualization_msgs/Marker[] markers",
}

_MSG_DIR = Path(__file__).with_name("msgs")
_PRIMITIVES = {
    "bool", "byte", "char", "int8", "uint8", "int16", "uint16", "int32", "uint32", "int64",
    "uint64", "float32", "float64", "string", "wstring", "time", "duration",
}  # fmt: skip


def _qualified_fields(pkg: str, text: str) -> str:
    """A .msg file's field lines without comments or blank lines, every type as `pkg/Type`."""
    lines = []
    for raw in text.splitlines():
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        ftype, rest = line.split(None, 1)
        base, array = re.match(r"([^\[]+)(.*)", ftype).groups()
        if "/" not in base and base not in _PRIMITIVES:
            base = "std_msgs/Header" if base == "Header" else f"{pkg}/{base}"
        lines.append(f"{base}{array} {rest}")
    return "\n".join(lines)


def shipped_definitions() -> dict[str, str]:
    """{`pkg/Type`: field lines} of every .msg file shipped under fpe_jax/io/msgs."""
    return {
        f"{f.parent.name}/{f.stem}": _qualified_fields(f.parent.name, f.read_text())
        for f in sorted(_MSG_DIR.glob("*/*.msg"))
    }


_FIELDS.update(shipped_definitions())


def known_type(msgtype: str) -> bool:
    """Whether a full definition of `msgtype` (either spelling) can be assembled here."""
    return short_type(msgtype) in _FIELDS


# Marker.type values we write.
MARKER_SPHERE = 2
MARKER_LINE_STRIP = 4
MARKER_SPHERE_LIST = 7

_SEPARATOR = "=" * 80


def short_type(msgtype: str) -> str:
    """`pkg/msg/Type` (ROS 2) or `pkg/Type` (ROS 1) -> `pkg/Type`, the key used everywhere here."""
    return msgtype.replace("/msg/", "/")


def full_type(msgtype: str) -> str:
    """`pkg/Type` -> `pkg/msg/Type`, the schema name ROS 2 tools expect."""
    pkg, _, name = short_type(msgtype).partition("/")
    return f"{pkg}/msg/{name}"


def _dependencies(msgtype: str, seen: list[str]) -> list[str]:
    """Types `msgtype` refers to, depth first, each once, in first-use order."""
    for line in _FIELDS[msgtype].splitlines():
        ftype = re.sub(r"\[.*\]$", "", line.split()[0])
        if "/" in ftype and ftype not in seen:
            seen.append(ftype)
            _dependencies(ftype, seen)
    return seen


def definition(msgtype: str) -> str:
    """The full .msg text of `msgtype` (either spelling) with all its dependencies appended."""
    root = short_type(msgtype)
    parts = [_FIELDS[root]]
    for dep in _dependencies(root, []):
        parts += [_SEPARATOR, f"MSG: {dep}", _FIELDS[dep]]
    return "\n".join(parts) + "\n"


def seconds_to_ns(t_s) -> np.ndarray:
    """(N,) stamps [s] -> (N,) int64 [ns], rounded to the nearest nanosecond.

    Splitting off whole seconds first keeps nanosecond precision for absolute (epoch) stamps,
    where `t * 1e9` alone would already be rounded to ~256 ns in float64.
    """
    t = np.asarray(t_s, dtype=np.float64)
    whole = np.floor(t)
    return whole.astype(np.int64) * 1_000_000_000 + np.round((t - whole) * 1e9).astype(np.int64)


def ns_to_seconds(ns) -> np.ndarray:
    """(N,) int64 [ns] -> (N,) float64 [s], rounding only once (in the final addition)."""
    return seconds_from_ns(ns)


def stamp_dict(ns: int | np.integer) -> dict[str, int]:
    """builtin_interfaces/Time fields of an int stamp [ns] (nanosec always in [0, 1e9))."""
    sec, nanosec = divmod(int(ns), 1_000_000_000)
    return {"sec": sec, "nanosec": nanosec}


def transform_stamped(parent: str, child: str, ns: int | np.integer, t, q) -> dict:
    """geometry_msgs/TransformStamped fields of T_parent_child at stamp ns [ns]: translation t
    (x, y, z) [m] and rotation q (x, y, z, w)."""
    return {
        "header": {"stamp": stamp_dict(ns), "frame_id": parent},
        "child_frame_id": child,
        "transform": {"translation": dict(zip("xyz", t)), "rotation": dict(zip("xyzw", q))},
    }


def yaw_to_quaternion(yaw_rad: float) -> dict[str, float]:
    """Planar rotation about z. A NaN yaw (unknown heading) becomes the all-zero quaternion,
    which `quaternion_to_yaw` maps back to NaN, so "no orientation" survives a round trip."""
    if not np.isfinite(yaw_rad):
        return {"x": 0.0, "y": 0.0, "z": 0.0, "w": 0.0}
    return {"x": 0.0, "y": 0.0, "z": float(np.sin(yaw_rad / 2)), "w": float(np.cos(yaw_rad / 2))}


def quaternion_to_yaw(x, y, z, w) -> np.ndarray:
    """Yaw [rad] (rotation about z, ZYX convention) of quaternion arrays; NaN for a zero
    quaternion, which detectors publish when they measure no orientation.

    Written in the scale-free form, so slightly non-unit quaternions (float32 sources) still give
    the right angle."""
    x, y, z, w = (np.asarray(a, dtype=np.float64) for a in (x, y, z, w))
    yaw = np.arctan2(2.0 * (w * z + x * y), w * w + x * x - y * y - z * z)
    return np.where(x * x + y * y + z * z + w * w < 1e-12, np.nan, yaw)


def quaternion_yaw(x: float, y: float, z: float, w: float) -> float:
    """`quaternion_to_yaw` of one quaternion's numbers, on floats (a live node converts one
    message at a time: NumPy's calls on single numbers cost far more than the arithmetic)."""
    if x * x + y * y + z * z + w * w < 1e-12:
        return math.nan
    return math.atan2(2.0 * (w * z + x * y), w * w + x * x - y * y - z * z)
