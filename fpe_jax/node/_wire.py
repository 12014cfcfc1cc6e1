"""The node's per-prediction output messages as the transport's bytes, built from NumPy arrays.

Each layout (a Path of H poses, a per-step PoseWithCovarianceStamped, an ObstacleArray of n
opponents, one opponent's MarkerArray) is encoded once by the transport's own writer into a
`Template`, and every message after that is those bytes with the stamps and numbers written in
by NumPy: no dict per pose, no per-field conversion. The messages are the ones the dicts below
describe (`path_message`, ...), byte for byte (`Template` checks its layout when it is made).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from fpe_jax.io import ros_msgs as rm
from fpe_jax.node._cdr import Template

MARKER_LINE_LIST = 5
MARKER_LINE_STRIP = rm.MARKER_LINE_STRIP
MARKER_SPHERE_LIST = rm.MARKER_SPHERE_LIST
MARKERS_LIFETIME_NS = 500_000_000  # a track that stops being predicted disappears from RViz
ELLIPSE_POINTS = 16  # segments of each 1-sigma ellipse

PATH_TYPE = "nav_msgs/msg/Path"
COVARIANCE_TYPE = "geometry_msgs/msg/PoseWithCovarianceStamped"
OBSTACLES_TYPE = "f110_msgs/msg/ObstacleArray"
MARKERS_TYPE = "visualization_msgs/msg/MarkerArray"

_SEC_NS = 1_000_000_000


def time_dict(flavour: str, ns: int) -> dict:
    """Time (or Duration) fields of `ns` nanoseconds in the flavour's spelling."""
    sec, nsec = divmod(int(ns), _SEC_NS)
    return {"secs": sec, "nsecs": nsec} if flavour == "ros1" else {"sec": sec, "nanosec": nsec}


def header(flavour: str, ns: int, frame_id: str) -> dict:
    return {"stamp": time_dict(flavour, ns), "frame_id": frame_id}


def _stamp_groups(flavour: str, prefixes: list[tuple]) -> dict:
    """Template groups "sec" and "nsec" of the header stamps at `prefixes` (ROS 1: unsigned
    secs; ROS 2: signed sec)."""
    sec, nsec = ("secs", "nsecs") if flavour == "ros1" else ("sec", "nanosec")
    return {"sec": ("I" if flavour == "ros1" else "i", [(*p, "stamp", sec) for p in prefixes]),
            "nsec": ("I", [(*p, "stamp", nsec) for p in prefixes])}  # fmt: skip


def _stamps(ns: int, step_ns: list[int]) -> tuple[list[int], list[int]]:
    """(seconds, nanoseconds) of stamp ns [ns] and of ns + each of step_ns [ns]."""
    sec, nsec = [], []
    for t in (ns, *(ns + k for k in step_ns)):
        s, n = divmod(t, _SEC_NS)
        sec.append(s)
        nsec.append(n)
    return sec, nsec


def quaternion_zw(yaw_rad: list[float]) -> tuple[list[float], list[float]]:
    """z, w of the planar rotations by yaws [rad]; a NaN yaw the all-zero quaternion
    (`fpe_jax.io.ros_msgs.yaw_to_quaternion` on a list: H floats cost less in `math` than in
    NumPy's calls)."""
    z, w = [], []
    for yaw in yaw_rad:
        half = 0.5 * yaw
        known = math.isfinite(half)
        z.append(math.sin(half) if known else 0.0)
        w.append(math.cos(half) if known else 0.0)
    return z, w


def _pose(x: float = 0.0, y: float = 0.0, qz: float = 0.0, qw: float = 1.0) -> dict:
    return {"position": {"x": x, "y": y, "z": 0.0},
            "orientation": {"x": 0.0, "y": 0.0, "z": qz, "w": qw}}  # fmt: skip


def _pose_paths(prefix: tuple) -> list[tuple]:
    return [(*prefix, "position", "x"), (*prefix, "position", "y"),
            (*prefix, "orientation", "z"), (*prefix, "orientation", "w")]  # fmt: skip


def _pose_values(poses: np.ndarray) -> list[list[float]]:
    """H rows x, y, qz, qw of poses (H, 3) x [m], y [m], yaw [rad]."""
    rows = poses.tolist()
    qz, qw = quaternion_zw([r[2] for r in rows])
    return [[x, y, z, w] for (x, y, _), z, w in zip(rows, qz, qw)]


def ellipse_points(center_m: np.ndarray, cov_m2: np.ndarray, n: int = ELLIPSE_POINTS):
    """(..., n + 1, 2) closed rings x [m], y [m] on the 1-sigma ellipses of (..., 2, 2)
    covariances [m^2] around (..., 2) centres."""
    vals, vecs = np.linalg.eigh(cov_m2)
    a = np.linspace(0.0, 2.0 * np.pi, n + 1)
    axes = vecs * np.sqrt(np.maximum(vals, 0.0))[..., None, :]  # columns: the scaled axes
    ring = np.einsum("...ij,jk->...ki", axes, np.stack([np.cos(a), np.sin(a)]))
    return ring + center_m[..., None, :]


class Wire:
    """The output messages of one node as bytes of its transport.

    Args:
        encode: (type name, message dict) -> the bytes the transport publishes.
        flavour: "ros1" or "ros2" (the header spelling).
        frame_id: the map frame every output is in.
        horizon: H predicted steps, dt_s [s] apart.
        obstacle_var: ROS 1 ObstacleArray variances {s_var, d_var, vs_var, vd_var} (the same
            for every prediction), or None for the ROS 2 definition, which has none.

    The path and the covariances of one prediction share its stamps and quaternions: a poses
    array is read once per stamp (pass a new array for new values, as a runner's update does).
    """

    def __init__(self, encode: Callable[[str, dict], bytes], flavour: str, frame_id: str,
                 horizon: int, dt_s: float, obstacle_var: dict | None):  # fmt: skip
        self.encode = encode
        self.flavour = flavour
        self.frame_id = frame_id
        self.horizon = horizon
        self.dt_s = dt_s
        self.obstacle_var = obstacle_var
        self.step_ns = np.round(np.arange(1, horizon + 1) * dt_s * 1e9).astype(np.int64)
        self._steps = self.step_ns.tolist()
        self._last: tuple = (None, None, None)  # (poses, ns, their stamps and pose values)
        self._templates: dict[tuple, Template] = {}

    def _template(self, key: tuple, make: Callable[[], tuple[str, dict, dict]]) -> Template:
        t = self._templates.get(key)
        if t is None:
            type_name, msg, groups = make()
            t = self._templates[key] = Template(lambda m: self.encode(type_name, m), msg, groups)
        return t

    def _prediction(self, ns: int, poses: np.ndarray) -> tuple[list, list, list]:
        """(seconds, nanoseconds) of the stamp and the H step stamps, and `_pose_values`, of
        one prediction: its path and its covariances share them."""
        last_poses, last_ns, out = self._last
        if poses is not last_poses or ns != last_ns:
            out = (*_stamps(ns, self._steps), _pose_values(poses))
            self._last = (poses, ns, out)
        return out

    def prepare(self, with_cov: bool) -> None:
        """Build the templates of a first prediction's messages (a path, its covariances, a
        one-opponent ObstacleArray, the markers of an opponent with a one-character id) now,
        rather than in the callback of that prediction (a few milliseconds each)."""
        poses = np.zeros((self.horizon, 3))
        cov = np.zeros((self.horizon, 2, 2)) if with_cov else None
        self.path(0, poses)
        if with_cov:
            self.covariances(0, poses, cov)
        self.obstacles(0, [0], [[0.0] * 8])
        self.markers("0", 0, poses, cov)

    def _header(self, ns: int = 0) -> dict:
        return header(self.flavour, ns, self.frame_id)

    # -- nav_msgs/Path

    def path_message(self, ns: int, poses: np.ndarray) -> dict:
        """The Path of one prediction: header stamp ns [ns]; step k's pose stamped ns + k dt_s."""
        qz, qw = quaternion_zw(poses[:, 2].tolist())
        steps = zip((ns + self.step_ns).tolist(), poses.tolist(), qz, qw)
        return {"header": self._header(ns),
                "poses": [{"header": self._header(t), "pose": _pose(x, y, z, w)}
                          for t, (x, y, _), z, w in steps]}  # fmt: skip

    def path(self, ns: int, poses: np.ndarray) -> bytes:
        """`path_message` as bytes; poses (H, 3) x [m], y [m], yaw [rad]."""
        t = self._template(("path",), self._path_layout)
        sec, nsec, values = self._prediction(ns, poses)
        return t.fill(sec=sec, nsec=nsec, value=[v for row in values for v in row])

    def _path_layout(self):
        h = self.horizon
        values = []
        for k in range(h):
            values += _pose_paths(("poses", k, "pose"))
        headers = [("header",)] + [("poses", k, "header") for k in range(h)]
        groups = _stamp_groups(self.flavour, headers) | {"value": ("d", values)}
        return PATH_TYPE, self.path_message(0, np.zeros((h, 3))), groups

    # -- geometry_msgs/PoseWithCovarianceStamped, one per step

    def covariance_messages(self, ns: int, poses: np.ndarray, cov_m2: np.ndarray) -> list[dict]:
        """One PoseWithCovarianceStamped per step: stamped ns + k dt_s [ns], the step's pose,
        the x, y block of the covariance (H, 2, 2) [m^2] (row-major 6x6, the rest zero)."""
        qz, qw = quaternion_zw(poses[:, 2].tolist())
        out = []
        rows = zip((ns + self.step_ns).tolist(), poses.tolist(), qz, qw)
        for (t, (x, y, _), z, w), c in zip(rows, cov_m2.tolist()):
            full = [0.0] * 36
            full[0], full[1], full[6], full[7] = c[0][0], c[0][1], c[1][0], c[1][1]
            out.append({"header": self._header(t),
                        "pose": {"pose": _pose(x, y, z, w), "covariance": full}})  # fmt: skip
        return out

    def covariances(self, ns: int, poses: np.ndarray, cov_m2: np.ndarray) -> list[bytes]:
        """`covariance_messages` as bytes."""
        fill = self._template(("covariance",), self._covariance_layout).fill
        sec, nsec, values = self._prediction(ns, poses)
        values = [row + c for row, c in zip(values, cov_m2.reshape(-1, 4).tolist())]
        return [fill(sec=(s,), nsec=(n,), value=v) for s, n, v in zip(sec[1:], nsec[1:], values)]

    def _covariance_layout(self):
        values = _pose_paths(("pose", "pose")) + [("pose", "covariance", i) for i in (0, 1, 6, 7)]
        msg = self.covariance_messages(0, np.zeros((1, 3)), np.zeros((1, 2, 2)))[0]
        groups = _stamp_groups(self.flavour, [("header",)]) | {"value": ("d", values)}
        return COVARIANCE_TYPE, msg, groups

    # -- f110_msgs/ObstacleArray

    OBSTACLE_VALUES = ("s_start", "s_end", "d_right", "d_left", "s_center", "d_center", "vs", "vd")

    def obstacles_message(self, ns: int, ids: list[int], values: np.ndarray) -> dict:
        """The ObstacleArray of n opponents `ids`, their OBSTACLE_VALUES (n, 8) [m, m/s]; size
        0.5 m, moving and visible, ROS 1 variances from `obstacle_var`."""
        obstacles = []
        for i, row in zip(ids, values.tolist()):
            o = {"id": i, **dict(zip(self.OBSTACLE_VALUES, row)), "size": 0.5,
                 "is_static": False, "is_visible": True}  # fmt: skip
            if self.obstacle_var is not None:
                o |= self.obstacle_var
            obstacles.append(o)
        return {"header": self._header(ns), "obstacles": obstacles}

    def obstacles(self, ns: int, ids: list[int], values: list[list[float]]) -> bytes:
        """`obstacles_message` as bytes."""
        t = self._template(("obstacles", len(ids)), lambda: self._obstacles_layout(len(ids)))
        sec, nsec = divmod(ns, _SEC_NS)
        return t.fill(sec=(sec,), nsec=(nsec,), id=ids, value=[v for row in values for v in row])

    def _obstacles_layout(self, n: int):
        msg = self.obstacles_message(0, [0] * n, np.zeros((n, 8)))
        ids = [("obstacles", k, "id") for k in range(n)]
        values = [("obstacles", k, f) for k in range(n) for f in self.OBSTACLE_VALUES]
        groups = _stamp_groups(self.flavour, [("header",)])
        return OBSTACLES_TYPE, msg, groups | {"id": ("i", ids), "value": ("d", values)}

    # -- visualization_msgs/MarkerArray

    def _marker(self, car: str, ns: int, ident: int, kind: int, points: list, rgba, width) -> dict:
        r, g, b, a = rgba
        return {
            "header": self._header(ns),
            "ns": f"future_pose/{car}",
            "id": ident,
            "type": kind,
            "action": 0,
            "pose": _pose(),
            "scale": {"x": width, "y": width, "z": width},
            "color": {"r": r, "g": g, "b": b, "a": a},
            "lifetime": time_dict(self.flavour, MARKERS_LIFETIME_NS),
            "points": [{"x": x, "y": y, "z": 0.0} for x, y in points],
        }

    def _marker_points(self, poses: np.ndarray, cov_m2: np.ndarray | None) -> list[np.ndarray]:
        pts = poses[:, :2]
        if cov_m2 is None:
            return [pts, pts]
        rings = ellipse_points(pts, cov_m2)  # (H, n + 1, 2)
        return [pts, pts, np.stack([rings[:, :-1], rings[:, 1:]], axis=2).reshape(-1, 2)]

    def markers_message(self, car: str, ns: int, poses: np.ndarray, cov_m2) -> dict:
        """One opponent's MarkerArray (namespace future_pose/<car>): its H predicted points
        (SPHERE_LIST), the line through them (LINE_STRIP) and, with a covariance (H, 2, 2)
        [m^2], each step's 1-sigma ellipse (LINE_LIST)."""
        looks = [(MARKER_SPHERE_LIST, (0.0, 1.0, 0.0, 1.0), 0.08),
                 (MARKER_LINE_STRIP, (0.0, 1.0, 0.0, 0.6), 0.03),
                 (MARKER_LINE_LIST, (0.0, 0.6, 1.0, 0.8), 0.02)]  # fmt: skip
        points = self._marker_points(poses, cov_m2)
        return {
            "markers": [
                self._marker(car, ns, i, kind, p.tolist(), rgba, width)
                for i, ((kind, rgba, width), p) in enumerate(zip(looks, points))
            ]
        }

    def markers(self, car: str, ns: int, poses: np.ndarray, cov_m2) -> bytes:
        """`markers_message` as bytes (one template for every opponent whose namespace has the
        same length)."""
        space = f"future_pose/{car}".encode()
        with_cov = cov_m2 is not None
        key = ("markers", len(space), with_cov)
        t = self._template(key, lambda: self._markers_layout("0" * len(car.encode()), with_cov))
        points = np.concatenate(self._marker_points(poses, cov_m2)).ravel().tolist()
        sec, nsec = divmod(ns, _SEC_NS)
        n = 2 + with_cov
        return t.fill(sec=(sec,) * n, nsec=(nsec,) * n, space=(space,) * n, value=points)

    def _markers_layout(self, car: str, with_cov: bool):
        cov = np.ones((self.horizon, 1, 1)) * np.eye(2) if with_cov else None
        msg = self.markers_message(car, 0, np.zeros((self.horizon, 3)), cov)
        values = []
        for i, marker in enumerate(msg["markers"]):
            for k in range(len(marker["points"])):
                values += [("markers", i, "points", k, "x"), ("markers", i, "points", k, "y")]
        n = len(msg["markers"])
        groups = _stamp_groups(self.flavour, [("markers", i, "header") for i in range(n)])
        space = (
            f"{len(msg['markers'][0]['ns'].encode())}s",
            [("markers", i, "ns") for i in range(n)],
        )
        return MARKERS_TYPE, msg, groups | {"space": space, "value": ("d", values)}
