"""TF without ROS: rigid transforms in NumPy, and a time-indexed buffer of a log's TF topics.

A `Rigid` holds N transforms as translations (N, 3) [m] and unit quaternions (N, 4) (x, y, z, w).
`T_a_b` is frame b's pose in frame a -- the TF edge a -> b (parent a, child b) -- so a point maps
as p_a = R(q_ab) p_b + t_ab, and `T_a_b @ T_b_c` is `T_a_c`.

`TfBuffer` keeps every transform of a log by edge. Dynamic edges are interpolated in time (linear in
translation, slerp in rotation) and never extrapolated: a stamp before an edge's first transform or
after its last is an error naming the edge and the gap. Nor is a dropout bridged: a stamp between
two transforms further apart than the edge's gap limit is an error naming the edge and the gap
(`max_gap_s`; default per edge max(4 x its median sample period, 0.2 s), see
`default_max_gap_ns`): interpolating a moving car across a 3 s dropout is metres off. Static
edges (from a topic named `.../tf_static`) hold at every time; the transforms of one static edge
must agree (a latched topic repeats them) to `STATIC_TOL_M` / `STATIC_TOL_RAD`.
`lookup(a, b, stamps)` walks the tree from b up to the common ancestor and down to a, so any
chain (map -> base_link -> laser -> camera) is one call. As in tf2 every frame has one parent; a
frame with two is an error only when a lookup passes through it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from typing import Any

import numpy as np

from fpe_jax.errors import InputError
from fpe_jax.io import ros_msgs as rm
from fpe_jax.io.logs import TF_TYPES

# /tf_static, /robot/tf_static: static transforms; other TF topics: dynamic
STATIC_SUFFIX = "tf_static"
GAP_PERIODS = 4  # a dynamic edge's default gap limit: this many median sample periods ...
MIN_GAP_NS = 200_000_000  # ... but at least 0.2 s (a 100 Hz edge may miss a few samples)
STATIC_TOL_M = 1e-3  # transforms of one static edge that differ more are not one mount
STATIC_TOL_RAD = 1e-3
QUAT_NORM_TOL = 1e-2  # |q|^2 - 1 beyond this is not a rounded unit quaternion (tf2's tolerance)


# --- quaternions and rigid transforms -------------------------------------------------------------


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a * b of (..., 4) x, y, z, w quaternions (broadcasting)."""
    ax, ay, az, aw = np.moveaxis(a, -1, 0)
    bx, by, bz, bw = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ],
        axis=-1,
    )


def quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate (..., 3) vectors v by (..., 4) unit quaternions q (broadcasting)."""
    u, w = q[..., :3], q[..., 3:]
    uv = np.cross(u, v)
    return v + 2.0 * (w * uv + np.cross(u, uv))


def quat_from_matrix(r: np.ndarray) -> np.ndarray:
    """(4,) unit quaternion (x, y, z, w, w >= 0) of one (3, 3) rotation matrix."""
    r = np.asarray(r, dtype=np.float64)
    # The largest of the four squared components divides the others, so no step loses precision.
    sq = np.array(
        [
            1 + r[0, 0] - r[1, 1] - r[2, 2],
            1 - r[0, 0] + r[1, 1] - r[2, 2],
            1 - r[0, 0] - r[1, 1] + r[2, 2],
            1 + r[0, 0] + r[1, 1] + r[2, 2],
        ]
    )
    k = int(np.argmax(sq))
    s = 2.0 * np.sqrt(sq[k])
    if k == 0:
        q = [s / 4, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s]
    elif k == 1:
        q = [(r[0, 1] + r[1, 0]) / s, s / 4, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s]
    elif k == 2:
        q = [(r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, s / 4, (r[1, 0] - r[0, 1]) / s]
    else:
        q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, s / 4]
    q = np.array(q)
    return q if q[3] >= 0 else -q


def slerp(q0: np.ndarray, q1: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Spherical interpolation between (N, 4) unit quaternions at fractions u (N,) in [0, 1].

    Takes the short way round (q and -q are the same rotation); nearly equal rotations fall back
    to normalized linear interpolation, where slerp's sin(theta) denominator would vanish.
    """
    u = np.asarray(u, dtype=np.float64)[:, None]
    d = np.sum(q0 * q1, axis=1, keepdims=True)
    q1 = np.where(d < 0, -q1, q1)
    d = np.abs(d)
    theta = np.arccos(np.clip(d, -1.0, 1.0))
    near = d > 1.0 - 1e-12
    sin_t = np.where(near, 1.0, np.sin(theta))
    w0 = np.where(near, 1.0 - u, np.sin((1.0 - u) * theta) / sin_t)
    w1 = np.where(near, u, np.sin(u * theta) / sin_t)
    q = w0 * q0 + w1 * q1
    return q / np.linalg.norm(q, axis=1, keepdims=True)


@dataclasses.dataclass(frozen=True)
class Rigid:
    """N rigid transforms: t_m (N, 3) translation [m], q (N, 4) unit quaternion (x, y, z, w).

    A single transform (N = 1) broadcasts against N of them in `@`.
    """

    t_m: np.ndarray
    q: np.ndarray

    @classmethod
    def make(cls, t_m, q) -> Rigid:
        """From (3,)/(N, 3) translations and (4,)/(N, 4) quaternions (normalized here)."""
        t = np.atleast_2d(np.asarray(t_m, dtype=np.float64))
        q = np.atleast_2d(np.asarray(q, dtype=np.float64))
        return cls(t, q / np.linalg.norm(q, axis=1, keepdims=True))

    @classmethod
    def planar(cls, x_m, y_m, yaw_rad, z_m=0.0) -> Rigid:
        """Transforms at (x, y, z) [m] rotated by yaw [rad] about z; arrays (N,) or scalars."""
        x, y, yaw = (np.atleast_1d(np.asarray(a, dtype=np.float64)) for a in (x_m, y_m, yaw_rad))
        z = np.broadcast_to(np.asarray(z_m, dtype=np.float64), x.shape)
        zero = np.zeros_like(yaw)
        q = np.stack([zero, zero, np.sin(yaw / 2), np.cos(yaw / 2)], axis=1)
        return cls(np.stack([x, y, z], axis=1), q)

    def __len__(self) -> int:
        return len(self.t_m)

    def __matmul__(self, other: Rigid) -> Rigid:
        """Composition: (T_a_b @ T_b_c) = T_a_c."""
        return Rigid(self.t_m + quat_rotate(self.q, other.t_m), quat_multiply(self.q, other.q))

    def inv(self) -> Rigid:
        """T_a_b -> T_b_a."""
        q_inv = self.q * np.array([-1.0, -1.0, -1.0, 1.0])
        return Rigid(-quat_rotate(q_inv, self.t_m), q_inv)

    def take(self, idx) -> Rigid:
        """The transforms at index array / mask `idx`."""
        return Rigid(self.t_m[idx], self.q[idx])

    def yaw_rad(self) -> np.ndarray:
        """(N,) yaw [rad] of the rotations (ZYX convention): the planar heading of frame b in a."""
        return rm.quaternion_to_yaw(*self.q.T)


# --- the buffer ---------------------------------------------------------------------------------


def format_stamp(ns: int | np.integer) -> str:
    """A stamp [ns] as error messages show it: seconds to the millisecond."""
    return f"{float(rm.ns_to_seconds([ns])[0]):.3f} s"


@dataclasses.dataclass
class Edge:
    """Every transform of one TF edge parent -> child, sorted by stamp (one per stamp: the last).

    stamps_ns: (K,) int64 header stamps [ns]; transform: K transforms T_parent_child.
    A static edge holds its last transform at every time (stamps_ns has one entry).
    max_gap_ns: the longest interval between two transforms that a lookup interpolates across.
    """

    parent: str
    child: str
    static: bool
    stamps_ns: np.ndarray
    transform: Rigid
    topics: tuple[str, ...]
    max_gap_ns: int = 0

    @property
    def name(self) -> str:
        return f"{self.parent} -> {self.child}"

    def in_span(self, stamps_ns: np.ndarray) -> np.ndarray:
        """(N,) whether each stamp lies within the edge's time span (no extrapolation)."""
        if self.static:
            return np.ones(len(stamps_ns), dtype=bool)
        return (stamps_ns >= self.stamps_ns[0]) & (stamps_ns <= self.stamps_ns[-1])

    def in_gap(self, stamps_ns: np.ndarray) -> np.ndarray:
        """(N,) whether each stamp falls strictly inside an interval between two transforms
        longer than max_gap_ns (a stamp on a transform is never in a gap)."""
        s = self.stamps_ns
        if self.static or len(s) < 2:
            return np.zeros(len(stamps_ns), dtype=bool)
        i = np.clip(np.searchsorted(s, stamps_ns, side="right") - 1, 0, len(s) - 2)
        inside = (stamps_ns > s[i]) & (stamps_ns < s[i + 1])
        return inside & (s[i + 1] - s[i] > self.max_gap_ns)

    def covers(self, stamps_ns: np.ndarray) -> np.ndarray:
        """(N,) whether each stamp can be looked up: within the span and not in a long gap."""
        return self.in_span(stamps_ns) & ~self.in_gap(stamps_ns)

    def at(self, stamps_ns: np.ndarray) -> Rigid:
        """T_parent_child at each stamp (N,) [ns]; every stamp must be covered (see `covers`)."""
        n = len(stamps_ns)
        if self.static or len(self.stamps_ns) == 1:
            return self.transform.take(np.zeros(n, dtype=np.int64))
        s = self.stamps_ns
        i = np.clip(np.searchsorted(s, stamps_ns, side="right") - 1, 0, len(s) - 2)
        # Integer differences first: epoch stamps in float64 would lose the nanoseconds.
        u = (stamps_ns - s[i]).astype(np.float64) / (s[i + 1] - s[i]).astype(np.float64)
        t0, t1 = self.transform.t_m[i], self.transform.t_m[i + 1]
        q = slerp(self.transform.q[i], self.transform.q[i + 1], u)
        return Rigid(t0 + u[:, None] * (t1 - t0), q)

    def describe(self) -> dict[str, Any]:
        """JSON-ready summary: frames, static, count, rate (mean over the span) and span [s]."""
        k = len(self.stamps_ns)
        span_ns = int(self.stamps_ns[-1] - self.stamps_ns[0])
        return {
            "parent": self.parent,
            "child": self.child,
            "static": self.static,
            "count": k,
            "rate_hz": (k - 1) / (span_ns * 1e-9) if k > 1 and span_ns > 0 else None,
            "first_s": None if self.static else float(rm.ns_to_seconds(self.stamps_ns[:1])[0]),
            "last_s": None if self.static else float(rm.ns_to_seconds(self.stamps_ns[-1:])[0]),
            "max_gap_s": float(np.max(np.diff(self.stamps_ns))) * 1e-9 if k > 1 else None,
            "gap_limit_s": None if self.static else self.max_gap_ns * 1e-9,
            "topics": list(self.topics),
        }


def default_max_gap_ns(stamps_ns: np.ndarray) -> int:
    """A dynamic edge's default gap limit [ns]: GAP_PERIODS x its median sample period, at least
    MIN_GAP_NS (a single transform: MIN_GAP_NS)."""
    if len(stamps_ns) < 2:
        return MIN_GAP_NS
    return max(int(GAP_PERIODS * np.median(np.diff(stamps_ns))), MIN_GAP_NS)


class TfBuffer:
    """All transforms of a log, by edge; see the module docstring.

    Args:
        transforms: (parent, child, stamp_ns, translation (3,) [m], quaternion (4,) xyzw, static,
            topic) tuples in arrival order. Leading '/' of frame names is dropped (ROS 1 habit).
        source: what to name in errors (the log's path).
        max_gap_s: the gap limit [s] of every dynamic edge; None: each edge's default
            (`default_max_gap_ns`).
    """

    def __init__(self, transforms: Iterable[tuple] = (), source: Any = "TF", max_gap_s=None):
        self.source = source
        self.max_gap_ns = None
        if max_gap_s is not None:
            from fpe_jax import spec

            self.max_gap_ns = int(round(spec.check_tf_gap(max_gap_s, "max_gap_s", "value") * 1e9))
        self._raw: dict[tuple[str, str, bool], list] = {}
        self.edges: dict[tuple[str, str], Edge] = {}
        self._both: set[tuple[str, str]] = set()  # edges on both a static and a dynamic topic
        self.parents: dict[str, list[str]] = {}
        self.add(transforms)

    def add(self, transforms: Iterable[tuple], keep_ns: int | None = None) -> None:
        """Add transforms (tuples as the constructor takes) to the buffer, as a live node receives
        them. With `keep_ns`, a dynamic edge keeps only the transforms no older than that before
        its newest (a bounded buffer). Raises InputError for a non-finite, zero, non-unit or
        absurdly far transform, or static repeats that disagree, before any of `transforms` is
        added."""
        rows = list(transforms)
        by_key: dict[tuple[str, str, bool], list] = {}
        for parent, child, stamp_ns, t, q, static, topic in rows:
            key = (parent.lstrip("/"), child.lstrip("/"), bool(static))
            by_key.setdefault(key, []).append((int(stamp_ns), t, q, topic))
        for (parent, child, static), new in sorted(by_key.items()):
            self._check_rows(f"TF {parent} -> {child}", new)
            if static:
                self._check_static_rows(
                    f"TF {parent} -> {child}", self._raw.get((parent, child, True), []) + new
                )
        new_edge = False
        for key, new in sorted(by_key.items()):
            parent, child, static = key
            self._raw.setdefault(key, []).extend(new)
            if keep_ns is not None and not static:
                newest = max(r[0] for r in self._raw[key])
                self._raw[key] = [r for r in self._raw[key] if r[0] >= newest - keep_ns]
            if (parent, child) in self.edges and self.edges[(parent, child)].static != static:
                self._both.add((parent, child))
            new_edge |= (parent, child) not in self.edges
            self.edges[(parent, child)] = self._edge(parent, child, static, self._raw[key])
        if new_edge:
            self.parents = {}
            for parent, child in sorted(self.edges):
                self.parents.setdefault(child, []).append(parent)

    def _check_rows(self, name: str, rows: list) -> None:
        """InputError when a transform (stamp_ns, t, q, topic) of `rows` is not a rigid one."""
        from fpe_jax import spec

        stamps = [r[0] for r in rows]
        t = np.array([r[1] for r in rows], dtype=np.float64).reshape(-1, 3)
        q = np.array([r[2] for r in rows], dtype=np.float64).reshape(-1, 4)
        norm = np.linalg.norm(q, axis=1)
        bad = ~(np.isfinite(norm) & (norm > 1e-9)) | ~np.isfinite(t).all(axis=1)
        if bad.any():
            k = int(np.argmax(bad))
            raise InputError(
                self.source,
                f"{name}: transform at {format_stamp(stamps[k])} has a zero or "
                "non-finite rotation or translation",
                "finite translations and non-zero quaternions",
            )
        off = np.abs(norm**2 - 1.0) > QUAT_NORM_TOL
        if off.any():
            k = int(np.argmax(off))
            raise InputError(
                self.source,
                f"{name}: the rotation at {format_stamp(stamps[k])} is not a unit quaternion "
                f"(norm {norm[k]:.6g})",
                f"quaternions of norm 1 (|q|^2 within {QUAT_NORM_TOL:g} of 1)",
            )
        far = np.abs(t).max(axis=1) > spec.MAX_COORD_M
        if far.any():
            k = int(np.argmax(far))
            raise InputError(
                self.source,
                f"{name}: the translation at {format_stamp(stamps[k])} is "
                f"{np.abs(t[k]).max():.6g} m",
                f"translations within ±{spec.MAX_COORD_M:g} m",
            )

    def _check_static_rows(self, name: str, rows: list) -> None:
        """InputError when the transforms of one static edge are not one mount."""
        if len(rows) < 2:
            return
        t = np.array([r[1] for r in rows], dtype=np.float64).reshape(-1, 3)
        q = np.array([r[2] for r in rows], dtype=np.float64).reshape(-1, 4)
        topics = sorted({r[3] for r in rows})
        r = Rigid.make(t, q)
        dt_m = float(np.linalg.norm(r.t_m - r.t_m[-1], axis=1).max())
        dot = np.clip(np.abs(np.sum(r.q * r.q[-1], axis=1)), 0.0, 1.0)
        da_rad = float(2.0 * np.arccos(dot).max())
        if dt_m > STATIC_TOL_M or da_rad > STATIC_TOL_RAD:
            raise InputError(
                self.source,
                f"{name} has {len(t)} transforms on {', '.join(topics)} that differ by up to "
                f"{dt_m:.4g} m and {da_rad:.4g} rad",
                f"one transform per static edge (repeats within {STATIC_TOL_M:g} m and "
                f"{STATIC_TOL_RAD:g} rad); a moving link belongs on /tf",
            )

    def _edge(self, parent: str, child: str, static: bool, rows: list) -> Edge:
        stamps = np.array([r[0] for r in rows], dtype=np.int64)
        t = np.array([r[1] for r in rows], dtype=np.float64).reshape(-1, 3)
        q = np.array([r[2] for r in rows], dtype=np.float64).reshape(-1, 4)
        topics = tuple(sorted({r[3] for r in rows}))
        if static:  # one mount (checked on arrival): the last one published
            keep = np.array([len(rows) - 1])
        else:  # sorted by stamp; of repeated stamps the last to arrive
            order = np.argsort(stamps, kind="stable")
            last = np.append(stamps[order][1:] != stamps[order][:-1], True)
            keep = order[last]
        gap = 0
        if not static:
            gap = (
                self.max_gap_ns if self.max_gap_ns is not None else default_max_gap_ns(stamps[keep])
            )
        rigid = Rigid.make(t[keep], q[keep])
        return Edge(parent, child, static, stamps[keep], rigid, topics, gap)

    @classmethod
    def from_log(cls, log, max_gap_s=None) -> TfBuffer:
        """Every transform on the log's TF topics (tf2_msgs/TFMessage, tf/tfMessage);
        `max_gap_s` as in the constructor."""
        topics = [t for t, i in log.topics.items() if i.msgtype in TF_TYPES and i.count]

        def rows():
            for topic, _, _, msg in log.messages(topics):
                static = topic.rstrip("/").endswith(STATIC_SUFFIX)
                for tr in msg.transforms:
                    p, r = tr.transform.translation, tr.transform.rotation
                    stamp = int(tr.header.stamp.sec) * 1_000_000_000 + int(tr.header.stamp.nanosec)
                    frames = (tr.header.frame_id, tr.child_frame_id)
                    yield (*frames, stamp, (p.x, p.y, p.z), (r.x, r.y, r.z, r.w), static, topic)

        return cls(rows(), source=log.source, max_gap_s=max_gap_s)

    # --- the tree

    @property
    def frames(self) -> list[str]:
        return sorted({f for e in self.edges for f in e})

    def _frame_list(self, frames) -> str:
        frames = sorted(frames)
        more = f", ... ({len(frames)} in all)" if len(frames) > 12 else ""
        return ", ".join(frames[:12]) + more if frames else "none"

    def _up(self, frame: str) -> list[tuple[str, Edge]]:
        """[(frame, edge to its parent), ...] from `frame` up to its root (the root has no edge)."""
        out, seen = [], {frame}
        while True:
            parents = self.parents.get(frame, [])
            if len(parents) > 1:
                raise InputError(
                    self.source,
                    f"TF frame {frame!r} has several parents ({', '.join(parents)})",
                    "a TF tree (one parent per frame)",
                )
            if not parents:
                return out
            edge = self.edges[(parents[0], frame)]
            if (edge.parent, edge.child) in self._both:
                raise InputError(
                    self.source,
                    f"TF {edge.name} is published both as static and as dynamic transforms",
                    "each transform on either /tf or /tf_static",
                )
            out.append((frame, edge))
            frame = parents[0]
            if frame in seen:
                raise InputError(self.source, f"the TF frames around {frame!r} form a cycle")
            seen.add(frame)

    def root(self, frame: str) -> str:
        up = self._up(frame)
        return up[-1][1].parent if up else frame

    def tree_of(self, frame: str) -> set[str]:
        """Every frame connected to `frame` (its whole tree)."""
        r = self.root(frame)
        return {f for f in self.frames if self._reaches(f, r)} | {frame}

    def _reaches(self, frame: str, root: str) -> bool:
        try:
            return self.root(frame) == root
        except InputError:
            return False

    def _check_frame(self, frame: str) -> None:
        if frame not in self.parents and not any(p == frame for p, _ in self.edges):
            raise InputError(
                self.source,
                f"TF frame {frame!r} is not in the log's TF tree "
                f"(frames: {self._frame_list(self.frames)})",
                "a transform to or from it on /tf or /tf_static",
            )

    def path(self, a: str, b: str) -> tuple[list[Edge], list[Edge]]:
        """(edges from a up to the common ancestor, edges from b up to it): T_a_b is the
        inverse of the first chain's product times the second's."""
        a, b = a.lstrip("/"), b.lstrip("/")
        self._check_frame(a)
        self._check_frame(b)
        up_a, up_b = self._up(a), self._up(b)
        chain_a = [a] + [e.parent for _, e in up_a]
        chain_b = [b] + [e.parent for _, e in up_b]
        common = next((f for f in chain_b if f in chain_a), None)
        if common is None:
            raise InputError(
                self.source,
                f"no TF chain joins {a} and {b}: {a} is in the tree of "
                f"{{{self._frame_list(self.tree_of(a))}}}, {b} in that of "
                f"{{{self._frame_list(self.tree_of(b))}}}, and no transform links the two",
                "a transform between the two trees on /tf or /tf_static",
            )
        edges_a = [e for _, e in up_a[: chain_a.index(common)]]
        edges_b = [e for _, e in up_b[: chain_b.index(common)]]
        return edges_a, edges_b

    def chain_frames(self, a: str, b: str) -> list[str]:
        """The frames from a to b along the tree, both included."""
        edges_a, edges_b = self.path(a, b)
        down = [e.child for e in reversed(edges_b)]
        return [a.lstrip("/")] + [e.parent for e in edges_a] + down

    def covers(self, a: str, b: str, stamps_ns) -> np.ndarray:
        """(N,) whether T_a_b can be looked up at each stamp: no edge extrapolated, none across a
        gap longer than its limit."""
        stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
        edges_a, edges_b = self.path(a, b)
        ok = np.ones(len(stamps_ns), dtype=bool)
        for e in edges_a + edges_b:
            ok &= e.covers(stamps_ns)
        return ok

    def in_gap(self, a: str, b: str, stamps_ns) -> np.ndarray:
        """(N,) whether a lookup of T_a_b at each stamp would cross a gap longer than the limit
        of some edge of the chain."""
        stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
        edges_a, edges_b = self.path(a, b)
        out = np.zeros(len(stamps_ns), dtype=bool)
        for e in edges_a + edges_b:
            out |= e.in_gap(stamps_ns)
        return out

    def lookup(
        self, a: str, b: str, stamps_ns, what: str = "lookups", remedy: str | None = None
    ) -> Rigid:
        """T_a_b (frame b's pose in frame a) at each stamp (N,) [ns].

        Raises InputError naming the frames if no chain joins them, or naming the edge, the first
        offending stamp and its distance from the edge's transforms if any stamp lies outside a
        dynamic edge's time span (`what` names the stamps in that message, `remedy` is offered).
        """
        stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
        edges_a, edges_b = self.path(a, b)
        n = len(stamps_ns)
        for e in edges_a + edges_b:
            ok = e.in_span(stamps_ns)
            if not ok.all():
                self._raise_outside(e, stamps_ns, ok, what, remedy)
            gap = e.in_gap(stamps_ns)
            if gap.any():
                self._raise_gap(e, stamps_ns, gap, what, remedy)
        identity = Rigid(np.zeros((n, 3)), np.tile([0.0, 0.0, 0.0, 1.0], (n, 1)))
        t_c_a, t_c_b = identity, identity
        for e in edges_a:  # up from a: T_c_a = T_c_p @ T_p_a
            t_c_a = e.at(stamps_ns) @ t_c_a
        for e in edges_b:
            t_c_b = e.at(stamps_ns) @ t_c_b
        return t_c_a.inv() @ t_c_b

    def _raise_outside(self, e: Edge, stamps_ns, ok, what: str, remedy: str | None):
        bad = stamps_ns[~ok]
        early = bad[bad < e.stamps_ns[0]]
        if len(early):
            k = int(early.min())
            where = f"{(int(e.stamps_ns[0]) - k) * 1e-9:.3f} s before its first transform"
        else:
            k = int(bad.max())
            where = f"{(k - int(e.stamps_ns[-1])) * 1e-9:.3f} s after its last transform"
        span = f"{len(e.stamps_ns)} transforms in [{format_stamp(e.stamps_ns[0])}, "
        span += f"{format_stamp(e.stamps_ns[-1])}]"
        raise InputError(
            self.source,
            f"{len(bad)} of {len(stamps_ns)} {what} lie outside the TF buffer of {e.name} "
            f"({span} on {', '.join(e.topics)}): the one at {format_stamp(k)} is {where}",
            "stamps within the transforms' time span (no extrapolation)"
            + (f"; or {remedy}" if remedy else ""),
        )

    def _raise_gap(self, e: Edge, stamps_ns, gap, what: str, remedy: str | None):
        k = int(stamps_ns[gap][0])
        s = e.stamps_ns
        i = int(np.searchsorted(s, k, side="right") - 1)
        limit = f"{e.max_gap_ns * 1e-9:.3f} s"
        if self.max_gap_ns is None:
            period = float(np.median(np.diff(s))) * 1e-9
            limit += (
                f" (max({GAP_PERIODS} x its median period {period:.3f} s, {MIN_GAP_NS * 1e-9:g} s))"
            )
        raise InputError(
            self.source,
            f"{int(gap.sum())} of {len(stamps_ns)} {what} fall in a gap of "
            f"{(int(s[i + 1]) - int(s[i])) * 1e-9:.3f} s in the TF of {e.name} (no transform "
            f"between {format_stamp(s[i])} and {format_stamp(s[i + 1])}; the first at "
            f"{format_stamp(k)}); lookups across gaps longer than {limit} are refused",
            "TF without such dropouts, --max-tf-gap SECONDS to interpolate across longer gaps"
            + (f", or {remedy}" if remedy else ""),
        )

    def describe(self) -> list[dict[str, Any]]:
        """Every edge as `Edge.describe()` plus its depth, tree order (roots first, depth first)."""
        children: dict[str, list[str]] = {}
        for parent, child in sorted(self.edges):
            children.setdefault(parent, []).append(child)
        roots = sorted(f for f in self.frames if f not in self.parents)
        out: list[dict[str, Any]] = []
        seen: set[tuple[str, str]] = set()
        for r in roots:  # depth first with an explicit stack: trees thousands of frames deep
            stack = [(r, child, 0) for child in reversed(children.get(r, []))]
            while stack:
                frame, child, depth = stack.pop()
                if (frame, child) in seen:
                    continue
                seen.add((frame, child))
                out.append(dict(self.edges[(frame, child)].describe(), depth=depth))
                stack += [(child, c, depth + 1) for c in reversed(children.get(child, []))]
        for key in sorted(set(self.edges) - seen):  # edges in cycles
            out.append(dict(self.edges[key].describe(), depth=0))
        return out
