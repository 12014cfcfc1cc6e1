"""`Drive`: one recorded or simulated drive of the leading car, as plain NumPy arrays.

Readers in `fpe_jax.io` produce it; `estimate`, `fit` and `metrics` consume it. No file I/O here.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from fpe_jax.path import map_origin as map_origin  # re-exported: drives' local frames


@dataclasses.dataclass(frozen=True)
class Drive:
    """Observations of the leading car, optionally with its ground truth.

    Attributes:
        t_s: (N,) observation stamps [s], strictly increasing.
        xy_m: (N, 2) observed position x [m], y [m] in the map frame.
        yaw_rad: (N,) observed orientation [rad]; NaN where the source has none.
        truth_t_s: (M,) ground-truth stamps [s], strictly increasing, or None.
        truth_xy_m: (M, 2) true position [m], or None.
        truth_yaw_rad: (M,) true yaw [rad] (NaN if unknown), or None.
        truth_v_mps: (M,) true speed [m/s] (NaN if unknown), or None.
        meta: free-form provenance: source path, topics, frames, counts of dropped/reordered rows.
        t_ns, truth_t_ns: (N,) / (M,) int64 stamps [ns] as read from a file, or None (then only
            the float seconds exist). `shifted` subtracts the time origin from these integers, so
            epoch stamps (~1.7e9 s, float64 steps of ~240 ns) lose nothing.
    """

    t_s: np.ndarray
    xy_m: np.ndarray
    yaw_rad: np.ndarray
    truth_t_s: np.ndarray | None = None
    truth_xy_m: np.ndarray | None = None
    truth_yaw_rad: np.ndarray | None = None
    truth_v_mps: np.ndarray | None = None
    meta: dict[str, Any] = dataclasses.field(default_factory=dict)
    t_ns: np.ndarray | None = None
    truth_t_ns: np.ndarray | None = None

    def __post_init__(self):
        n = len(self.t_s)
        if self.xy_m.shape != (n, 2) or self.yaw_rad.shape != (n,):
            raise ValueError(
                f"Drive: shapes t {self.t_s.shape}, xy {self.xy_m.shape}, yaw {self.yaw_rad.shape}"
                " do not agree (expected (N,), (N, 2), (N,))"
            )
        if n and np.any(np.diff(self.t_s) <= 0):
            raise ValueError("Drive: observation stamps must be strictly increasing")
        if self.truth_t_s is not None:
            m = len(self.truth_t_s)
            if self.truth_xy_m is None or self.truth_xy_m.shape != (m, 2):
                raise ValueError("Drive: truth_xy_m must have shape (M, 2) matching truth_t_s")
        for ns, t in ((self.t_ns, self.t_s), (self.truth_t_ns, self.truth_t_s)):
            if ns is not None and (t is None or np.shape(ns) != np.shape(t)):
                raise ValueError("Drive: t_ns / truth_t_ns must match t_s / truth_t_s")

    @property
    def has_truth(self) -> bool:
        return self.truth_t_s is not None and len(self.truth_t_s) > 0

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1] - self.t_s[0]) if len(self.t_s) else 0.0

    def slice_time(self, t0_s: float, t1_s: float) -> Drive:
        """The part of the drive with t0_s <= t < t1_s (observations and truth alike)."""
        keep = (self.t_s >= t0_s) & (self.t_s < t1_s)
        kw: dict[str, Any] = dict(
            t_s=self.t_s[keep], xy_m=self.xy_m[keep], yaw_rad=self.yaw_rad[keep]
        )
        kw["t_ns"] = None if self.t_ns is None else self.t_ns[keep]
        if self.has_truth:
            tk = (self.truth_t_s >= t0_s) & (self.truth_t_s < t1_s)
            kw.update(
                truth_t_ns=None if self.truth_t_ns is None else self.truth_t_ns[tk],
                truth_t_s=self.truth_t_s[tk],
                truth_xy_m=self.truth_xy_m[tk],
                truth_yaw_rad=None if self.truth_yaw_rad is None else self.truth_yaw_rad[tk],
                truth_v_mps=None if self.truth_v_mps is None else self.truth_v_mps[tk],
            )
        return Drive(**kw, meta=dict(self.meta, time_range_s=(t0_s, t1_s)))

    def shifted(self, t0_s: float, origin_xy_m, t0_ns: int | None = None) -> Drive:
        """The same drive with `t0_s` [s] subtracted from every stamp and `origin_xy_m` (2,) [m]
        from every position (in float64), so epoch stamps and UTM-sized coordinates become small
        numbers before anything is cast to float32.

        With `t0_ns` [ns] (the same origin as an integer) the stamps of a drive that has integer
        stamps (t_ns) are shifted as integers first and become seconds after: exact, where
        float64 seconds of epoch stamps are already rounded to ~240 ns."""

        def shift(t_s, ns):
            if ns is not None and t0_ns is not None:
                return seconds_from_ns(np.asarray(ns, dtype=np.int64) - np.int64(t0_ns))
            return np.asarray(t_s, dtype=np.float64) - t0_s

        def minus(ns):
            return None if ns is None or t0_ns is None else np.asarray(ns) - np.int64(t0_ns)

        o = np.asarray(origin_xy_m, dtype=np.float64)
        kw: dict[str, Any] = dict(
            t_s=shift(self.t_s, self.t_ns),
            t_ns=minus(self.t_ns),
            xy_m=np.asarray(self.xy_m, dtype=np.float64) - o,
            yaw_rad=self.yaw_rad,
        )
        if self.truth_t_s is not None:
            kw.update(
                truth_t_s=shift(self.truth_t_s, self.truth_t_ns),
                truth_t_ns=minus(self.truth_t_ns),
                truth_xy_m=np.asarray(self.truth_xy_m, dtype=np.float64) - o,
                truth_yaw_rad=self.truth_yaw_rad,
                truth_v_mps=self.truth_v_mps,
            )
        meta = dict(self.meta, origin_t_s=t0_s, origin_xy_m=o.tolist())
        if t0_ns is not None:
            meta["origin_t_ns"] = int(t0_ns)
        return Drive(**kw, meta=meta)


def seconds_from_ns(ns) -> np.ndarray:
    """(N,) int64 [ns] -> (N,) float64 [s], rounding only once (in the final addition)."""
    ns = np.asarray(ns, dtype=np.int64)
    return (ns // 1_000_000_000).astype(np.float64) + (ns % 1_000_000_000).astype(np.float64) * 1e-9


def local_frame(drive: Drive, waypoints_xy_m) -> tuple[Drive, np.ndarray, float, np.ndarray]:
    """(drive, waypoints (K, 2) [m]) in a local frame: time from the drive's first stamp (as
    integer nanoseconds where the drive has them), positions from `map_origin(waypoints)`.
    Returns (drive, waypoints, t0_s, origin_xy_m (2,))."""
    origin = map_origin(waypoints_xy_m)
    t0 = float(drive.t_s[0]) if len(drive.t_s) else 0.0
    t0_ns = int(drive.t_ns[0]) if drive.t_ns is not None and len(drive.t_ns) else None
    wp = np.asarray(waypoints_xy_m, dtype=np.float64) - origin
    return drive.shifted(t0, origin, t0_ns), wp, t0, origin
