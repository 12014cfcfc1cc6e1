"""TF without ROS: rigid transforms in NumPy, and a time-indexed buffer of a log's TF topics.

A `Rigid` holds N transforms as translations (N, 3) [m] and unit quaternions (N, 4) (x, y, z, w).
`T_a_b` is frame b's pose in frame a -- the TF edge a -> b (parent a, child b) -- so a point maps
as p_a = R(q_ab) p_b + t_ab, and `T_a_b @ T_b_c` is `T_a_c`.

`TfBuffer` keeps every transform of a log by edge. Dynamic edges are interpolated in time (linear in
translation, slerp in rotation) and never extrapolated: a stamp before an edge's first transform or
after its last is an error naming the edge and the gap. Static edges (from a topic named
`.../tf_static`) hold at every time. `lookup(a, b, stamps)` walks the tree from b up to the common
ancestor and down to a, so any chain (map -> base_link -> laser -> camera) is one call. As in tf2
every frame has one parent; a frame with two is an error only when a lookup passes through it.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable
from typing import Any

import numpy as np

from fpe_jax.errors import InputError
from fpe_jax.io import ros_msgs as rm
from fpe_jax.io.logs import TF_TYPES

# /tf_static, /robot/tf_static: static transforms; other TF topics: dynamic
STATIC_SUFFIX = "tf_static"


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
    """

    parent: str
    child: str
    static: bool
    stamps_ns: np.ndarray
    transform: Rigid
    topics: tuple[str, ...]

    @property
    def name(self) -> str:
        return f"{self.parent} -> {self.child}"

    def covers(self, stamps_ns: np.ndarray) -> np.ndarray:
        """(N,) whether each stamp can be looked up without extrapolating."""
        if self.static:
            return np.ones(len(stamps_ns), dtype=bool)
        return (stamps_ns >= self.stamps_ns[0]) & (stamps_ns <= self.stamps_ns[-1])

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
            "topics": list(self.topics),
        }


class TfBuffer:
    """All transforms of a log, by edge; see the module docstring.

    Args:
        transforms: (parent, child, stamp_ns, translation (3,) [m], quaternion (4,) xyzw, static,
            topic) tuples in arrival order. Leading '/' of frame names is dropped (ROS 1 habit).
        source: what to name in errors (the log's path).
    """

    def __init__(self, transforms: Iterable[tuple] = (), source: Any = "TF"):
        self.source = source
        self._raw: dict[tuple[str, str, bool], list] = {}
        self.edges: dict[tuple[str, str], Edge] = {}
        self._both: set[tuple[str, str]] = set()  # edges on both a static and a dynamic topic
        self.parents: dict[str, list[str]] = {}
        self.add(transforms)

    def add(self, transforms: Iterable[tuple], keep_ns: int | None = None) -> None:
        """Add transforms (tuples as the constructor takes) to the buffer, as a live node receives
        them. With `keep_ns`, a dynamic edge keeps only the transforms no older than that before
        its newest (a bounded buffer). Raises InputError for a non-finite or zero transform,
        before any of `transforms` is added."""
        rows = list(transforms)
        for parent, child, stamp_ns, t, q, *_ in rows:
            norm2 = sum(float(v) * float(v) for v in q)
            if not (all(math.isfinite(float(v)) for v in (*t, *q)) and norm2 > 1e-18):
                raise InputError(
                    self.source,
                    f"TF {parent.lstrip('/')} -> {child.lstrip('/')}: transform at "
                    f"{format_stamp(stamp_ns)} has a zero or non-finite rotation or translation",
                    "finite translations and non-zero quaternions",
                )
        changed = set()
        for parent, child, stamp_ns, t, q, static, topic in rows:
            key = (parent.lstrip("/"), child.lstrip("/"), bool(static))
            self._raw.setdefault(key, []).append((int(stamp_ns), t, q, topic))
            changed.add(key)
        new_edge = False
        for key in sorted(changed):
            parent, child, static = key
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

    def _edge(self, parent: str, child: str, static: bool, rows: list) -> Edge:
        stamps = np.array([r[0] for r in rows], dtype=np.int64)
        t = np.array([r[1] for r in rows], dtype=np.float64).reshape(-1, 3)
        q = np.array([r[2] for r in rows], dtype=np.float64).reshape(-1, 4)
        if static:  # the last one published wins (a latched topic may repeat or update it)
            keep = np.array([len(rows) - 1])
        else:  # sorted by stamp; of repeated stamps the last to arrive
            order = np.argsort(stamps, kind="stable")
            last = np.append(stamps[order][1:] != stamps[order][:-1], True)
            keep = order[last]
        topics = tuple(sorted({r[3] for r in rows}))
        return Edge(parent, child, static, stamps[keep], Rigid.make(t[keep], q[keep]), topics)

    @classmethod
    def from_log(cls, log) -> TfBuffer:
        """Every transform on the log's TF topics (tf2_msgs/TFMessage, tf/tfMessage)."""
        topics = [t for t, i in log.topics.items() if i.msgtype in TF_TYPES and i.count]

        def rows():
            for topic, _, _, msg in log.messages(topics):
                static = topic.rstrip("/").endswith(STATIC_SUFFIX)
                for tr in msg.transforms:
                    p, r = tr.transform.translation, tr.transform.rotation
                    stamp = int(tr.header.stamp.sec) * 1_000_000_000 + int(tr.header.stamp.nanosec)
                    frames = (tr.header.frame_id, tr.child_frame_id)
                    yield (*frames, stamp, (p.x, p.y, p.z), (r.x, r.y, r.z, r.w), static, topic)

        return cls(rows(), source=log.source)

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
        """(N,) whether T_a_b can be looked up at each stamp without extrapolating any edge."""
        stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
        edges_a, edges_b = self.path(a, b)
        ok = np.ones(len(stamps_ns), dtype=bool)
        for e in edges_a + edges_b:
            ok &= e.covers(stamps_ns)
        return ok

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
            ok = e.covers(stamps_ns)
            if not ok.all():
                self._raise_outside(e, stamps_ns, ok, what, remedy)
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

    def describe(self) -> list[dict[str, Any]]:
        """Every edge as `Edge.describe()` plus its depth, tree order (roots first, depth first)."""
        children: dict[str, list[str]] = {}
        for parent, child in sorted(self.edges):
            children.setdefault(parent, []).append(child)
        roots = sorted(f for f in self.frames if f not in self.parents)
        out: list[dict[str, Any]] = []
        seen: set[tuple[str, str]] = set()

        def walk(frame: str, depth: int):
            for child in children.get(frame, []):
                if (frame, child) in seen:
                    continue
                seen.add((frame, child))
                out.append(dict(self.edges[(frame, child)].describe(), depth=depth))
                walk(child, depth + 1)

        for r in roots:
            walk(r, 0)
        for key in sorted(set(self.edges) - seen):  # edges in cycles
            out.append(dict(self.edges[key].describe(), depth=0))
        return out
