"""NumPy-only on-car runner: streaming predictions from a tuned config, without JAX.

Cars (Jetson-class computers) often have no JAX, so this module re-implements, in NumPy and plain
`math`, exactly what the JAX path does for a drive (`fpe_jax.predict.predict_drive`):

- the distinct-observation history window and robust state estimate of `fpe_jax.model`
  (repeated rows skipped, Theil-Sen medians, outlier replacement of the newest position);
- the track-frame estimators of the frenet and line models: Theil-Sen lines or the Kalman
  filter of `fpe_jax.model`, step for step;
- the windowed track projection of `fpe_jax.geometry.arclength_along` (global on the first call);
- every model of `fpe_jax.model`: the position and heading blends, linear, pure pursuit, the
  seed's discrete rules, constant velocity and CTRV, with the fractional delay step.

Parity with the JAX predictor is tested to 1e-6 m. The per-step math works on Python floats:
for H = 10 scalar steps that is several times faster than NumPy's per-call overhead; NumPy is
used where a step scans many points (the track window, the seed's waypoint scan).

It imports only `fpe_jax.io.config`, `fpe_jax.errors`, `fpe_jax.geometry._path`,
`fpe_jax.model._history` and (to read waypoint files) `fpe_jax.io`, all JAX-free; a test runs it in
a process where importing JAX fails.

    runner = Runner.from_config("tuned.json", "waypoints.csv")
    poses = runner.update(stamp_s, x_m, y_m, yaw_rad)   # (H, 3) x [m], y [m], yaw [rad]
"""

from __future__ import annotations

import copy
import functools
import json
import math
import time
from collections import deque
from pathlib import Path

import numpy as np

from fpe_jax.errors import InputError
from fpe_jax.geometry._path import (
    BRANCH_COS,
    BRANCH_M,
    LOCAL_PROJECTION_ITERS,
    MIN_HEADING_SPEED_MPS,
    MIN_ON_TRACK_SHARE,
    build_path,
    check_share_near,
    on_track_m,
    window_points,
)
from fpe_jax.io.config import LINE_KEYS, check_waypoints, read_config
from fpe_jax.model._constants import (
    FALLBACK_TAU_S,
    GATE_SHARPNESS,
    INIT_LAT_RATE_SIGMA_MPS,
    INIT_POS_SIGMA_M,
    INIT_SPEED_SIGMA_MPS,
    MAX_SPEED_RATIO,
    MIN_PROFILE_SPEED_MPS,
    SLOPE_DS_M,
    TRACK_FRAME_ITERS,
)
from fpe_jax.model._history import MAX_SPAN_S, MIN_PAIR_DT_S, OUTLIER_M, history_valid
from fpe_jax.spec import BLEND_MODES as BLEND_MODES  # re-exported: the runner's modes
from fpe_jax.spec import FILTER_DEFAULTS, FILTER_KEYS, check_config
from fpe_jax.spec import MODELS as MODELS

# The off-track check (`Runner.check_track`): the first this many observations must pass the
# offline rule (`fpe_jax.geometry.check_share_near`), and a stream reports an off-track car on
# stderr at most once per OFF_TRACK_REPORT_S of stamps.
OFF_TRACK_START_OBS = 10
OFF_TRACK_REPORT_S = 5.0
_MIN_ON_AT_START = math.ceil(round(MIN_ON_TRACK_SHARE * OFF_TRACK_START_OBS, 9))
OFF_TRACK_HINT = (
    "check the waypoints file and that the observations are in its map frame, or pass "
    "--allow-off-track to go on with warnings"
)

_PI = math.pi
_TWO_PI = 2 * math.pi
FloatN = float | np.ndarray  # one car's value, or the (N,) values of N cars (`_Arrays`)


_HALF_INV_PI = 0.5 / math.pi


def _wrap(a: FloatN, floor=math.floor) -> FloatN:
    """Angle [rad] wrapped to [-pi, pi) with the same arithmetic as fpe_jax.geometry.wrap_angle
    (`floor=np.floor` for arrays)."""
    return a - _TWO_PI * floor((a + _PI) * _HALF_INV_PI)


@functools.cache
def _pairs(n: int) -> tuple[tuple[int, int], ...]:
    """The index pairs (i, j), i < j < n, of a window of n observations (Theil-Sen slopes)."""
    return tuple((i, j) for j in range(n) for i in range(j))


class _Floats:
    """The math the rollouts use, on Python floats (one car: several times faster than NumPy)."""

    cos, sin, floor = math.cos, math.sin, math.floor

    @staticmethod
    def clip(a, lo, hi):
        return min(max(a, lo), hi)


class _Arrays:
    """The same math on (N,) arrays: N cars at once (the SciPy baseline of `make bench`)."""

    cos, sin, floor, clip = np.cos, np.sin, np.floor, np.clip


def _ops(x):
    return _Arrays if isinstance(x, np.ndarray) else _Floats


def _median(values: list[float]) -> float:
    """Median as jnp.nanmedian computes it ((lo + hi) * 0.5); 0 for an empty list, like
    fpe_jax.model's masked median."""
    n = len(values)
    if n == 0:
        return 0.0
    v = sorted(values)
    return (v[(n - 1) // 2] + v[n // 2]) * 0.5


GUESS_ITERS = 4
CHAIN_MARGIN = 2  # segments `RunnerPath.project_chain` searches beyond each guessed window


class RunnerPath:
    """The resampled track (same points as fpe_jax.geometry.Track) with its geometry on floats.

    Attributes:
        closed: loop (arc length wraps) or open path (clamps).
        ds_m, length_m: point spacing and total length [m].
        raw_xy_m: (K, 2) the waypoints as given (the seed's goal scan reads them).
    """

    def __init__(self, waypoints_xy_m, *, source: str = "waypoints"):
        p = build_path(waypoints_xy_m, source=source)
        xy = p["xy_m"]
        m = len(xy)
        self.closed: bool = p["closed"]
        self.ds_m: float = float(p["ds_m"])
        self.length_m: float = float(p["length_m"])
        self.raw_xy_m: np.ndarray = np.ascontiguousarray(p["raw_xy_m"], dtype=np.float64)
        self._m = m
        nxt = (np.arange(m) + 1) % m if self.closed else np.minimum(np.arange(m) + 1, m - 1)
        ab = xy[nxt] - xy
        # for the window searches, per segment start i: a_x, a_y, (b - a)_x, (b - a)_y,
        # max(|b - a|^2, 1e-12) as rows (5, M)
        ab2 = np.maximum(ab[:, 0] * ab[:, 0] + ab[:, 1] * ab[:, 1], 1e-12)
        self._seg = np.stack([xy[:, 0], xy[:, 1], ab[:, 0], ab[:, 1], ab2])
        # for the per-step lookups, Track.seg_m as Python tuples: scalar indexing of a list is
        # ~10x faster than of an ndarray
        tangent = np.stack([np.cos(p["heading_rad"]), np.sin(p["heading_rad"])], axis=1)
        rows = np.concatenate([xy, ab, tangent, tangent[nxt]], axis=1)
        self._rows = [tuple(row) for row in rows.tolist()]
        self._table = rows  # the same (M, 8), for `arrays()`
        self._arrays: _ArrayPath | None = None
        self._heading = p["heading_rad"].tolist()
        self.xy_m: np.ndarray = xy  # (M, 2) the resampled points [m] and their headings [rad]
        self.heading_rad: np.ndarray = p["heading_rad"]
        self._all_segments = range(m if self.closed else m - 1)
        n_back, n_ahead = window_points(self.ds_m)
        self._window = np.arange(-n_back, n_ahead + 1)
        self._window_lo, self._window_hi = -n_back, n_ahead  # its first and last offsets
        self._last_window: tuple = (None, 0.0)  # ((x, y, hint's segment), its search's result)
        self._chain_window = np.arange(-n_back - CHAIN_MARGIN, n_ahead + CHAIN_MARGIN + 1)

    def locate(self, s_m: float) -> tuple[int, float]:
        """Segment index i and fraction f in [0, 1] for arc length s [m] (Track._locate)."""
        if self.closed:
            u = s_m / self.ds_m
            u_floor = math.floor(u)
            return u_floor % self._m, u - u_floor
        u = (0.0 if s_m < 0.0 else self.length_m if s_m > self.length_m else s_m) / self.ds_m
        i = int(u)
        if i > self._m - 2:
            i = self._m - 2
        return i, u - i

    def arrays(self) -> RunnerPath:
        """This path with locate, point_at and project_local on (N,) arrays of cars."""
        if self._arrays is None:
            self._arrays = _ArrayPath(self)
        return self._arrays

    def point_at(self, s_m: FloatN) -> tuple[FloatN, FloatN]:
        """Position x [m], y [m] at arc length s [m]."""
        i, f = self.locate(s_m)
        ax, ay, abx, aby = self._rows[i][:4]
        return ax + f * abx, ay + f * aby

    def heading_at(self, s_m: float) -> float:
        """Path heading [rad] at arc length s [m] (Track.heading_at)."""
        i, f = self.locate(s_m)
        j = (i + 1) % self._m if self.closed else i + 1
        h0 = self._heading[i]
        return _wrap(h0 + f * _wrap(self._heading[j] - h0))

    def project_local(
        self, x_m: FloatN, y_m: FloatN, s_hint_m: FloatN, iters: int = LOCAL_PROJECTION_ITERS
    ) -> FloatN:
        """Arc length [m] near s_hint by Newton steps along the interpolated path tangent
        (Track.project_local)."""
        s = s_hint_m
        for _ in range(iters):
            i, f = self.locate(s)
            ax, ay, abx, aby, t0x, t0y, t1x, t1y = self._rows[i]
            g = 1.0 - f
            s = (
                s
                + (x_m - ax - f * abx) * (g * t0x + f * t1x)
                + (y_m - ay - f * aby) * (g * t0y + f * t1y)
            )
        return s

    def _nearest(
        self, x_m: float, y_m: float, idx: np.ndarray | range, contiguous: bool, heading_rad=None
    ) -> float:
        """Arc length [m] of the closest point to (x, y) on the segments starting at idx (n,);
        `contiguous` (idx a range) reads them as a view instead of gathering. With a
        heading [rad], the branch rule of `fpe_jax.geometry.BRANCH_COS`
        (Track._project_segments)."""
        lo = int(idx[0])
        seg = self._seg[:, lo : lo + len(idx)] if contiguous else self._seg.take(idx, axis=1)
        t, d2 = _segment_distances(seg, x_m, y_m)
        k = int(np.argmin(d2))  # the first minimum, as jnp.argmin
        if heading_rad is not None:
            tangent = self._table[idx, 4:6]
            agree = tangent @ np.array([math.cos(heading_rad), math.sin(heading_rad)])
            d2_agree = np.where(agree >= BRANCH_COS, d2, np.inf)
            ka = int(np.argmin(d2_agree))
            if d2_agree[ka] <= BRANCH_M * BRANCH_M:
                k = ka
        return (int(idx[k]) + float(t[k])) * self.ds_m

    def project(self, x_m: float, y_m: float, heading_rad: float | None = None) -> float:
        """Arc length [m] of the closest point of the whole track (global search); given the
        car's heading [rad], of the branch that agrees with it (`fpe_jax.geometry.BRANCH_COS`)."""
        return self._nearest(x_m, y_m, self._all_segments, True, heading_rad)

    def continuous(self, s_m: float, s_ref_m: float) -> float:
        """s [m] moved by whole laps to within half a lap of s_ref [m] on a loop (as is on an
        open path): Track.project_window's seam rule."""
        if not self.closed:
            return s_m
        half = 0.5 * self.length_m
        return s_ref_m + ((s_m - s_ref_m + half) % self.length_m - half)

    def project_window(self, x_m: float, y_m: float, s_hint_m: float) -> float:
        """Arc length [m] of the closest point within [s_hint - 2 m, s_hint + 4 m], continuous
        with the hint across the seam of a loop (it counts laps), as Track.project_window.

        The search's result depends on the hint's segment alone (the window), so the last
        search is kept: a second one of the same point in the same window (the off-track check
        after `Runner.update`) costs nothing."""
        b = math.floor(s_hint_m / self.ds_m)
        key = (x_m, y_m, b)
        last_key, s = self._last_window
        if key != last_key:
            lo, hi = b + self._window_lo, b + self._window_hi
            last = self._m - 1 if self.closed else self._m - 2
            if 0 <= lo and hi <= last:
                s = self._nearest(x_m, y_m, range(lo, hi + 1), True)
            else:  # across the seam (wrap) or past an end (clamp), exactly as the JAX indices do
                idx = self._window + b
                s = self._nearest(
                    x_m, y_m, idx % self._m if self.closed else np.clip(idx, 0, last), False
                )
            self._last_window = (key, s)
        if not self.closed:
            return s
        half = 0.5 * self.length_m
        return s_hint_m + ((s - s_hint_m + half) % self.length_m - half)

    def project_chain(self, xy_m: np.ndarray, s_start_m: float) -> list[float]:
        """Arc lengths [m] of consecutive points (N, 2) [m], each `project_window` of the point
        around the previous one's arc length (the first around s_start_m [m]): the same values
        as that loop, to the last bit, at a fraction of its cost for N = 10.

        The windows are guessed (from `project_local`, a few float operations a point) and the
        points searched at once in their guessed windows widened by CHAIN_MARGIN segments on
        each side; then, point after point, the minimum is taken over the loop's own window
        (the hint's segment is the previous arc length's), which lies inside the widened one
        unless the guess was more than CHAIN_MARGIN segments off (then that point is searched
        alone, as the loop does).
        """
        ds, closed = self.ds_m, self.closed
        xs, ys = xy_m[:, 0].tolist(), xy_m[:, 1].tolist()
        base, s = [], s_start_m
        px, py = self.point_at(s_start_m)
        for x, y in zip(xs, ys):
            base.append(math.floor(s / ds))
            s = self.project_local(x, y, s + math.hypot(x - px, y - py))
            px, py = x, y
        idx = np.array(base)[:, None] + self._chain_window
        idx = idx % self._m if closed else np.clip(idx, 0, self._m - 2)
        rows = self._seg[:, idx]  # (5, N, W + 2 margin)
        t, d2 = _segment_distances(rows, xy_m[:, :1], xy_m[:, 1:2])
        m, w = CHAIN_MARGIN, len(self._window)
        guessed = np.argmin(d2[:, m : m + w], axis=1).tolist()  # the first minimum of each row
        out, s, half, length = [], s_start_m, 0.5 * self.length_m, self.length_m
        for k, (b, j) in enumerate(zip(base, guessed)):
            off = math.floor(s / ds) - b + m  # where the loop's window starts in the row
            if off != m:
                if not 0 <= off <= 2 * m:  # the guess was too far off: the loop's own search
                    s = self.project_window(xs[k], ys[k], s)
                    out.append(s)
                    continue
                j = int(np.argmin(d2[k, off : off + w]))
            c = off + j
            raw = (int(idx[k, c]) + float(t[k, c])) * ds
            s = s + ((raw - s + half) % length - half) if closed else raw
            out.append(s)
        return out


def _segment_distances(seg: np.ndarray, x_m, y_m) -> tuple[np.ndarray, np.ndarray]:
    """(t, squared distance [m^2]) of the closest point a + t (b - a), t in [0, 1], of segments
    to points: seg (5, ...) rows a_x, a_y, (b - a)_x, (b - a)_y, |b - a|^2 as `RunnerPath._seg`;
    x_m, y_m [m] floats or arrays broadcasting against seg's rows. The arithmetic of
    Track._project_segments."""
    ax, ay, abx, aby, ab2 = seg
    t = ((x_m - ax) * abx + (y_m - ay) * aby) / ab2
    np.maximum(t, 0.0, out=t)
    np.minimum(t, 1.0, out=t)
    dx = ax + t * abx - x_m
    dy = ay + t * aby - y_m
    return t, dx * dx + dy * dy


class _ArrayPath(RunnerPath):
    """A RunnerPath whose point_at and project_local take (N,) arrays: the same code, with the
    segment lookup and `locate` on arrays (the scalar path keeps its list-of-tuples speed)."""

    def __init__(self, path: RunnerPath):
        self.__dict__.update(path.__dict__)
        table = path._table

        class Rows:  # rows[i] for (N,) indices i: the (8, N) columns the scalar code unpacks
            def __getitem__(self, i):
                return table[i].T

        self._rows = Rows()

    def locate(self, s_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.closed:
            u = s_m / self.ds_m
            u_floor = np.floor(u)
            return u_floor.astype(np.int64) % self._m, u - u_floor
        u = np.clip(s_m, 0.0, self.length_m) / self.ds_m
        i = np.minimum(u.astype(np.int64), self._m - 2)
        return i, u - i


class Runner:
    """Streaming predictor for one leading car: feed observations, get (H, 3) predictions.

    Keeps its own history of distinct observations and its own arc-length state, so calling
    `update` for every row of a drive gives what `fpe_jax.predict.predict_drive` gives for it.

    Attributes:
        horizon: number of predicted steps H.
        dt_s: step between predicted poses [s].
        model, blend: the config's settings (see fpe_jax.model.Settings).
        calibration: the online calibration of the config's ellipses; None here (the config's
            ellipses as they are), set by `AdaptiveRunner(calibrate=True)`.
    """

    calibration = None

    def __init__(self, config: dict, waypoints_xy_m, *, source: str = "config"):
        """Args:
        config: a config dict as `fpe_jax.io.config.read_config` returns it (schema checked).
        waypoints_xy_m: (K, 2) waypoints x [m], y [m]; resampled exactly as Track does.
        source: names the config in error messages.
        """
        cfg = check_config(config, source)
        p, st = cfg["params"], cfg["settings"]
        self.horizon: int = st["horizon"]
        self.dt_s: float = float(st["dt_s"])
        self.model: str = st["model"]
        self.blend: str = st["blend"]
        # the frenet and line models' track-frame estimator (fpe_jax.model or Theil-Sen)
        self._kalman = st["estimator"] == "kalman" and self.model in ("frenet", "line")
        self._wheelbase_m = float(st["wheelbase_m"])
        self._max_steer_rad = float(st["max_steer_rad"])
        self.path = RunnerPath(waypoints_xy_m, source="waypoints")
        self.on_track_m = on_track_m(self.path.xy_m)  # the offline checks' distance [m]
        self._set_params(p)
        self._history = deque(maxlen=int(st["history"]))  # distinct (t, x, y, yaw), oldest first
        self.waypoints_source = "waypoints"  # names the waypoints in the off-track error
        self.allow_off_track = False  # True: the start check only warns (--allow-off-track)
        self._reset_track_check()
        self.reset()

    def _set_params(self, p: dict) -> None:
        self._lookahead_m = float(p["lookahead_m"])
        self._gain_s = float(p["lookahead_gain_s"])
        self._weights = [float(w) for w in p["weights"]]
        self._delay_s = float(p["delay_s"])
        self._speed_weight = float(p["speed_weight"])
        self._typical_speed_mps = float(p["speed_mps"])
        self._offset_tau_s = float(p.get("offset_tau_s", 1.0))
        self._speed_tau_s = float(p.get("speed_tau_s", 0.5))
        self._pace_return_1ps = float(p.get("pace_return_1ps", 0.0))
        self._smoothing = float(p.get("position_smoothing", 0.0))
        self._filter = tuple(float(p.get(k, FILTER_DEFAULTS[k])) for k in FILTER_KEYS)
        self._line = [[float(v) for v in p[k]] for k in LINE_KEYS] if self.model == "line" else None
        if self.model == "seed":
            self._goal_scan = GoalScan(self.path.raw_xy_m, self._lookahead_m)

    def with_params(self, params: dict) -> Runner:
        """This runner's track and settings with other parameter values, and an empty history.

        Args:
            params: physical values keyed as a config's "params" (`Params.physical()`); not
                schema-checked again (the fitting loss of `make bench`'s SciPy baseline calls
                this once per evaluation).
        """
        new = copy.copy(self)
        new._set_params(params)
        new._history = deque(maxlen=self._history.maxlen)
        new._reset_track_check()
        new.reset()
        return new

    @classmethod
    def from_config(cls, config_path, waypoints_path) -> Runner:
        """Runner from a tuned config JSON and a waypoint file (any form fpe_jax.io reads)."""
        cfg = read_config(config_path)
        xy = load_waypoints_xy(waypoints_path)
        check_waypoints(cfg, config_path, xy, waypoints_path)
        runner = cls(cfg, xy, source=str(config_path))
        runner.waypoints_source = str(waypoints_path)
        return runner

    def reset(self) -> None:
        """Forget the history and the track position (a new drive starts)."""
        self._history.clear()
        self.valid = False  # whether the last prediction had enough history (history_valid)
        self._last_stamp_s: float | None = None
        self._last_xy: tuple[float, float] | None = None
        self._s_m: float | None = None
        self._settled = False  # whether the track position was found with a known heading
        self._motion: tuple[float, ...] | None = None

    def _reset_track_check(self) -> None:
        self._check_s_m: float | None = None  # the off-track check's own track position
        self._start: list[tuple[bool, float, float]] = []  # the first observations: on, x, y

    def track_distance(self, x_m: float, y_m: float) -> float:
        """Distance [m] of a position from the track's line, or from the learned line where
        that is nearer (line model). Its own windowed projection (the whole track again when
        far), so it costs one window search per call and leaves the predictions untouched."""
        path, x, y = self.path, float(x_m), float(y_m)
        s = (
            path.project(x, y)
            if self._check_s_m is None
            else path.project_window(x, y, self._check_s_m)
        )
        dist = self._off_line_m(x, y, s)
        if (
            dist > self.on_track_m and self._check_s_m is not None
        ):  # lost the car: search everywhere
            s = path.project(x, y)
            dist = self._off_line_m(x, y, s)
        self._check_s_m = s
        return dist

    def _off_line_m(self, x: float, y: float, s_m: float) -> float:
        path = self.path
        cx, cy = path.point_at(s_m)
        dist = math.hypot(x - cx, y - cy)
        if self._line is not None:
            h = path.heading_at(s_m)
            d = (y - cy) * math.cos(h) - (x - cx) * math.sin(h)
            dist = min(dist, abs(d - self._profile_at(self._line[0], s_m)))
        return dist

    def check_track(self, x_m: float, y_m: float) -> str | None:
        """The off-track check of one observation (call it for each, alongside `update`).

        Returns None when the position lies within `on_track_m` (`fpe_jax.geometry.on_track_m`: the
        offline checks' distance) of the track's line (or of the learned line), else a one-line
        warning with the distance.

        Raises:
            InputError naming the waypoints when, of the first OFF_TRACK_START_OBS observations,
            fewer than MIN_ON_TRACK_SHARE lie on the track: the offline check's rule
            (`fpe_jax.geometry.check_share_near`), which catches a waypoint file in another map
            frame; not with `allow_off_track` set.
        """
        dist = self.track_distance(x_m, y_m)
        on = dist <= self.on_track_m
        start = self._start
        if len(start) < OFF_TRACK_START_OBS and not self.allow_off_track:
            start.append((on, float(x_m), float(y_m)))
            n_on = sum(o[0] for o in start)
            # as soon as the first OFF_TRACK_START_OBS can no longer meet the rule
            if len(start) - n_on > OFF_TRACK_START_OBS - _MIN_ON_AT_START:
                centre = np.mean([o[1:] for o in start], axis=0) - self.path.xy_m.mean(axis=0)
                check_share_near(
                    n_on / len(start),
                    float(np.hypot(*centre)),
                    source=self.waypoints_source,
                    drive=f"the stream's first {len(start)}",
                    near_m=self.on_track_m,
                    hint=OFF_TRACK_HINT,
                )
        if on:
            return None
        return (
            f"observation {dist:.1f} m from the track (more than {self.on_track_m:.3g} m): its "
            "predictions follow the nearest part of the track"
        )

    def update(self, stamp_s: float, x_m: float, y_m: float, yaw_rad: float | None = None):
        """Add one observation and predict from it.

        Args:
            stamp_s: observation stamp [s], strictly increasing between calls.
            x_m, y_m: observed position [m] in the map frame (a row equal to the previous one is
                a repeat: no new detection, it does not enter the history).
            yaw_rad: observed orientation [rad], or None / NaN when the source has none.

        Returns:
            (H, 3) float64 x [m], y [m], yaw [rad] at stamp + h * dt_s, h = 1..H.

        Raises:
            InputError for a non-finite stamp or position, or a stamp not after the previous one
            (the runner's state is left unchanged).
        """
        t, x, y = float(stamp_s), float(x_m), float(y_m)
        yaw = math.nan if yaw_rad is None else float(yaw_rad)
        if not (math.isfinite(t) and math.isfinite(x) and math.isfinite(y)):
            raise InputError("observation", f"t={t}, x={x}, y={y}", "finite stamp and position")
        if self._last_stamp_s is not None and t <= self._last_stamp_s:
            raise InputError(
                "observation", f"stamp {t} is not after {self._last_stamp_s}", "increasing stamps"
            )
        if self._last_xy != (x, y):
            self._history.append((t, x, y, yaw))
            self._motion = None
            t_new = self._history[-1][0]
            recent = [o[0] for o in self._history if t_new - o[0] <= MAX_SPAN_S]
            self.valid = bool(history_valid(len(recent), t_new - recent[0]))
        self._last_stamp_s, self._last_xy = t, (x, y)
        if self._motion is None:  # a repeated row is predicted from as if fresh: reuse
            self._motion = self._estimate_motion()
        est = self._motion  # x, y, yaw, v, yaw_rate, course
        if self.model == "seed":
            # the original's rules: the current row alone, observed yaw when there is one
            return self._seed(x, y, yaw if math.isfinite(yaw) else est[2], self._speed(est[3]))
        if self.model == "cv":
            return self._linear(est, heading_rad=est[5])
        if self.model == "ctrv":
            return self._ctrv(est)
        path = self.path
        ex, ey = est[0], est[1]
        s_prev = self._s_m
        if not self._settled:  # until the heading is known the branch is searched globally
            known = math.isfinite(self._history[-1][3]) or est[3] >= MIN_HEADING_SPEED_MPS
            s_glob = path.project(ex, ey, est[2] if known else None)
            s_prev = s_glob if s_prev is None else path.continuous(s_glob, s_prev)
            self._settled = known
        self._s_m = path.project_window(ex, ey, s_prev)
        if self.model in ("frenet", "line"):
            return self._frenet(self._track_frame(self._s_m), est)
        return self.predict_from_state(ex, ey, est[2], est[3], self._s_m)

    def predict_from_state(self, x_m, y_m, yaw_rad, v_mps, s_m):
        """The blend model's rollout from an estimated state, as `update` does after estimating.

        Args:
            x_m, y_m, yaw_rad, v_mps: position [m], heading [rad], measured speed [m/s]:
                floats for one car or (N,) float64 arrays for N cars.
            s_m: the arc length [m] near the position (the track projection's start).

        Returns:
            (H, 3) x [m], y [m], yaw [rad] at h * dt_s, h = 1..H; (N, H, 3) for arrays.
        """
        if self.model != "blend":
            raise ValueError(f"predict_from_state: the blend model only, not {self.model!r}")
        est = (x_m, y_m, yaw_rad, v_mps)
        if self.blend == "heading":
            w = self._weights
            out = self._bicycle(est, s_m, [1.0 - wk for wk in [w[0], *w]])
        else:
            out = self._position_blend(est, s_m)
        return np.moveaxis(out, -1, 0) if isinstance(x_m, np.ndarray) else out

    # ---- state estimation (fpe_jax.model.estimate_state on the valid slots) ----------------

    def _estimate_motion(self) -> tuple[float, ...]:
        """(x, y, yaw, v, yaw_rate, course) [m, m, rad, m/s, rad/s, rad] from the distinct
        observations no older than MAX_SPAN_S before the newest (the valid slots of
        fpe_jax.model's window)."""
        t_new = self._history[-1][0]
        obs = [o for o in self._history if t_new - o[0] <= MAX_SPAN_S]
        n = len(obs)
        ts, xs, ys, yaws = zip(*obs)
        pairs = [(i, j, dt) for i, j in _pairs(n) if (dt := ts[j] - ts[i]) >= MIN_PAIR_DT_S]
        vx = _median([(xs[j] - xs[i]) / dt for i, j, dt in pairs])
        vy = _median([(ys[j] - ys[i]) / dt for i, j, dt in pairs])

        # robust line through the window at the newest stamp replaces an outlier newest position
        ahead = [t_new - tk for tk in ts]
        fit_x = _median([xk + vx * a for xk, a in zip(xs, ahead)])
        fit_y = _median([yk + vy * a for yk, a in zip(ys, ahead)])
        use_fit = math.hypot(xs[-1] - fit_x, ys[-1] - fit_y) > OUTLIER_M and n >= 3
        x, y = (fit_x, fit_y) if use_fit else (xs[-1], ys[-1])
        course = math.atan2(vy, vx)

        has_yaw = [math.isfinite(a) for a in yaws]
        ref = yaws[-1] if has_yaw[-1] else course
        if sum(has_yaw) >= 2:
            rate = _median(
                [_wrap(yaws[j] - yaws[i]) / dt for i, j, dt in pairs if has_yaw[i] and has_yaw[j]]
            )
            off = [_wrap(a + rate * h - ref) for a, h, ok in zip(yaws, ahead, has_yaw) if ok]
            yaw = _wrap(ref + _median(off))
        else:
            # without orientation: the turn rate of the courses of consecutive segments
            yaw = ref
            segs = [
                (0.5 * (ts[k + 1] + ts[k]), math.atan2(ys[k + 1] - ys[k], xs[k + 1] - xs[k]))
                for k in range(n - 1)
                if ts[k + 1] - ts[k] >= MIN_PAIR_DT_S
            ]
            rate = _median(
                [
                    _wrap(cb - ca) / (tb - ta)
                    for a, (ta, ca) in enumerate(segs)
                    for tb, cb in segs[a + 1 :]
                    if tb - ta >= MIN_PAIR_DT_S
                ]
            )
        return x, y, yaw, math.hypot(vx, vy), rate, course

    def _track_frame(self, s_hint_m: float) -> tuple[float, float, float, float]:
        """(s, ds/dt, d, age) [m, m/s, m, s]: fpe_jax.model.track_frame_window, then
        track_frame_lines."""
        path = self.path
        t_new = self._history[-1][0]
        obs = [o for o in self._history if t_new - o[0] <= MAX_SPAN_S]
        ss, ds = [0.0] * len(obs), [0.0] * len(obs)
        s = s_hint_m
        for k in range(len(obs) - 1, -1, -1):
            _, x, y, _ = obs[k]
            s = path.project_local(x, y, s, TRACK_FRAME_ITERS)
            cx, cy = path.point_at(s)
            h = path.heading_at(s)
            ss[k], ds[k] = s, (y - cy) * math.cos(h) - (x - cx) * math.sin(h)
        n = len(obs)
        pairs = [(i, j, obs[j][0] - obs[i][0]) for j in range(n) for i in range(j)]
        pairs = [p for p in pairs if p[2] >= MIN_PAIR_DT_S]
        sdot = _median([(ss[j] - ss[i]) / dt for i, j, dt in pairs])
        ddot = _median([(ds[j] - ds[i]) / dt for i, j, dt in pairs])
        ahead = [t_new - o[0] for o in obs]
        s_now = ss[-1] + _median([sk + sdot * a - ss[-1] for sk, a in zip(ss, ahead)])
        d_now = _median([dk + ddot * a for dk, a in zip(ds, ahead)])
        if not self._kalman:
            return s_now, sdot, d_now, _median(ahead)
        prior = (s_now, sdot, d_now, ddot, _median(ahead))
        return self._kalman_window(ahead, ss, ds, prior)

    def _kalman_window(self, ages, ss, ds, prior) -> tuple[float, float, float, float]:
        """(s, ds/dt, d, the speed's age) [m, m/s, m, s] at the newest stamp:
        fpe_jax.model.kalman_window over the valid observations (ages [s], arc lengths ss [m],
        offsets ds [m], oldest first) from the Theil-Sen prior (s, ds/dt, d, dd/dt, age)."""
        accel, lat_accel, obs, gate = self._filter
        q_s, q_d, r2 = accel * accel, lat_accel * lat_accel, obs * obs
        p0 = r2 + INIT_POS_SIGMA_M**2
        age0 = max(ages)  # the oldest observation's
        sx = [prior[0] - prior[1] * age0, prior[1], p0, 0.0, INIT_SPEED_SIGMA_MPS**2]
        dx = [prior[2] - prior[3] * age0, prior[3], p0, 0.0, INIT_LAT_RATE_SIGMA_MPS**2]
        ux = [0.5 * age0 * age0, -prior[4]]  # the unit-acceleration channel
        length = self.path.length_m if self.path.closed else None
        age_prev = age0
        for age, zs, zd in zip(ages, ss, ds):
            dt = age_prev - age
            age_prev = age
            sx, dx = _kf_predict(sx, dt, q_s), _kf_predict(dx, dt, q_d)
            nu_s, nu_d = zs - sx[0], zd - dx[0]
            if length is not None:
                nu_s = (nu_s + 0.5 * length) % length - 0.5 * length
            ss_inn, sd_inn = sx[2] + r2, dx[2] + r2
            m = math.sqrt(nu_s * nu_s / ss_inn + nu_d * nu_d / sd_inn + 1e-12)
            w = _sigmoid(GATE_SHARPNESS * (gate - m))
            kp, kr = w * sx[2] / ss_inn, w * sx[3] / ss_inn
            up = ux[0] + ux[1] * dt
            nu_u = 0.5 * age * age - up
            ux = [up + kp * nu_u, ux[1] + kr * nu_u]
            sx, dx = _kf_update(sx, nu_s, ss_inn, w), _kf_update(dx, nu_d, sd_inn, w)
        return sx[0], sx[1], dx[0], -ux[1]

    # ---- rollouts (fpe_jax.model), each -> (H, 3) ----------------------------------------------

    def _profile_at(self, values: list[float], s_m: float) -> float:
        """fpe_jax.model.profile_at."""
        p, length = len(values), self.path.length_m
        if self.path.closed:
            u = s_m * (p / length)
            u_floor = math.floor(u)
            i = u_floor % p
            j, f = (i + 1) % p, u - u_floor
        else:
            u = min(max(s_m / length, 0.0), 1.0) * (p - 1)
            i = min(max(math.floor(u), 0), p - 2)
            j, f = i + 1, u - i
        return values[i] + f * (values[j] - values[i])

    def _line_at(self, s_m: float) -> tuple[float, float, float]:
        offset, speed, coverage = self._line
        p = self._profile_at
        return p(offset, s_m), p(coverage, s_m), p(speed, s_m)

    def _target_at(self, s_m: float, own_m: float) -> float:
        """fpe_jax.model.rollout_frenet's target offset: the line, where uncovered the car's
        own offset from it (`own_m`) kept."""
        line, c, _ = self._line_at(s_m)
        return line + (1.0 - c) * own_m

    def _frenet(self, frame, est) -> np.ndarray:
        """fpe_jax.model.rollout_frenet from the track-frame estimate and the state."""
        s_fit, v0, d_fit, age = frame
        path = self.path
        # the newest (outlier-free) position's own arc length and offset
        s0 = path.project_local(est[0], est[1], self._s_m)
        cx, cy = path.point_at(s0)
        h = path.heading_at(s0)
        d0 = (est[1] - cy) * math.cos(h) - (est[0] - cx) * math.sin(h)
        w = self._smoothing
        s0, d0 = s0 + w * (s_fit - s0), d0 + w * (d_fit - d0)
        t, s_all, d_all = 0.0, [], []
        l0, tau = 0.0, self._offset_tau_s
        if self._line is not None:
            own = d0 - self._line_at(s0)[0]
            l0 = self._target_at(s0, own)
            rate = est[3] * math.sin(est[5] - h) - v0 * (
                self._target_at(s0 + SLOPE_DS_M, own) - self._target_at(s0 - SLOPE_DS_M, own)
            ) / (2.0 * SLOPE_DS_M)
            _, _, vp0 = self._line_at(s0 - v0 * age)
            ok0 = 1.0 if vp0 > MIN_PROFILE_SPEED_MPS else 0.0
            vp0 = max(vp0, MIN_PROFILE_SPEED_MPS)
        s = s0
        for dt in self._times():
            if self._line is None:
                t += dt
                s = s0 + v0 * t
                line = 0.0
            else:
                _, _, vp = self._line_at(s)
                ratio = min(max(vp / vp0, 0.0), MAX_SPEED_RATIO)
                ratio = 1.0 + ok0 * (1.0 if vp > MIN_PROFILE_SPEED_MPS else 0.0) * (ratio - 1.0)
                own_pace = v0 * ratio
                goal = own_pace
                if vp > MIN_PROFILE_SPEED_MPS:  # the car's pace hands over to the profile's
                    back = -math.expm1(-(t + age) * self._pace_return_1ps)
                    goal += back * (vp - own_pace)
                v = v0 + (goal - v0) * -math.expm1(-(t + age) / self._speed_tau_s)
                s = s + v * dt
                t += dt
                line, c, _ = self._line_at(s)
                line += (1.0 - c) * own * math.exp(-t / FALLBACK_TAU_S)
            s_all.append(s)
            if self._line is None:
                d_all.append(line + (d0 - l0) * math.exp(-t / tau))
            else:
                e0 = d0 - l0
                d_all.append(line + (e0 + (rate + e0 / tau) * t) * math.exp(-t / tau))
        self._step_s_m = s_all[1:]  # each step's arc length [m]: the frame of its ellipse
        rows, s_prev, d_prev = [], s0, d0
        for k, (s, d) in enumerate(zip(s_all, d_all)):
            h = path.heading_at(s)
            cx, cy = path.point_at(s)
            yaw = _wrap(h + math.atan((d - d_prev) / max(s - s_prev, 1e-3)))
            s_prev, d_prev = s, d
            if k:
                rows.append([cx - d * math.sin(h), cy + d * math.cos(h), yaw])
        return np.array(rows)

    def _speed(self, v_mps: FloatN) -> FloatN:
        """Rollout speed [m/s]: the measured one shrunk toward the typical one."""
        w = self._speed_weight
        return w * v_mps + (1.0 - w) * self._typical_speed_mps

    def _times(self) -> list[float]:
        """Durations [s] of the fractional delay step and the H regular steps."""
        return [self._delay_s] + [self.dt_s] * self.horizon

    def _linear_rows(self, est, heading_rad: FloatN) -> list[list[FloatN]]:
        x0, y0, v = est[0], est[1], self._speed(est[3])
        o = _ops(heading_rad)
        c, s = o.cos(heading_rad), o.sin(heading_rad)
        rows, t = [], 0.0
        for k, dt in enumerate(self._times()):
            t += dt
            if k:
                rows.append([x0 + v * t * c, y0 + v * t * s, heading_rad])
        return rows

    def _linear(self, est, heading_rad: float) -> np.ndarray:
        return np.array(self._linear_rows(est, heading_rad))

    def _ctrv(self, est) -> np.ndarray:
        x, y, yaw = est[0], est[1], est[2]
        v, w = self._speed(est[3]), est[4]
        rows = []
        for k, dt in enumerate(self._times()):
            # exact arc as jnp.sinc computes it: chord = v dt sin(pi a) / (pi a), a = w dt / 2 pi
            pi_a = _PI * (w * dt / _TWO_PI)
            chord = v * dt * (math.sin(pi_a) / pi_a if pi_a != 0.0 else 1.0)
            mid = yaw + 0.5 * w * dt
            x, y, yaw = x + chord * math.cos(mid), y + chord * math.sin(mid), yaw + w * dt
            if k:
                rows.append([x, y, _wrap(yaw)])
        return np.array(rows)

    def _bicycle_rows(self, est, s_m: FloatN, turn_scale: list[float]) -> list[list[FloatN]]:
        """Kinematic bicycle steered by pure pursuit; yaw change of step k times turn_scale[k].
        The state's values are floats, or (N,) arrays for N cars."""
        x, y, yaw = est[0], est[1], est[2]
        o = _ops(x)
        path = self.path.arrays() if o is _Arrays else self.path
        cos, sin, clip = o.cos, o.sin, o.clip
        v = self._speed(est[3])
        wb, tan_lim = self._wheelbase_m, math.tan(self._max_steer_rad)
        reach = self._gain_s * v
        s = path.project_local(x, y, s_m)
        cy, sy = cos(yaw), sin(yaw)  # the heading as a unit vector, as the JAX step
        rows = []
        for k, dt in enumerate(self._times()):
            s = path.project_local(x, y, s)
            gx, gy = path.point_at(s + self._lookahead_m + reach)
            dx, dy = gx - x, gy - y
            tan_steer = 2.0 * wb * (cy * dy - sy * dx) / (dx * dx + dy * dy + 1e-12)
            tan_steer = clip(tan_steer, -tan_lim, tan_lim)
            dyaw = turn_scale[k] * v / wb * tan_steer * dt
            ch, sh = cos(0.5 * dyaw), sin(0.5 * dyaw)
            cm, sm = cy * ch - sy * sh, sy * ch + cy * sh  # midpoint heading: the move's direction
            cy, sy = cm * ch - sm * sh, sm * ch + cm * sh
            x, y, yaw = x + v * dt * cm, y + v * dt * sm, yaw + dyaw
            if k:
                rows.append([x, y, _wrap(yaw, o.floor)])
        return rows

    def _bicycle(self, est, s_m: FloatN, turn_scale: list[float]) -> np.ndarray:
        return np.array(self._bicycle_rows(est, s_m, turn_scale))

    def _position_blend(self, est, s_m: FloatN) -> np.ndarray:
        lin = self._linear_rows(est, est[2])
        pp = self._bicycle_rows(est, s_m, [1.0] * (self.horizon + 1))
        floor, out = _ops(est[0]).floor, []
        for w, (lx, ly, lyaw), (px, py, pyaw) in zip(self._weights, lin, pp):
            g = 1.0 - w
            yaw = _wrap(lyaw + g * _wrap(pyaw - lyaw, floor), floor)
            out.append([w * lx + g * px, w * ly + g * py, yaw])
        return np.array(out)

    def _seed(self, x: float, y: float, yaw: float, v: float) -> np.ndarray:
        """The original node's discrete rules (fpe_jax.model.rollout_seed)."""
        st = (self.dt_s, self._wheelbase_m, self._max_steer_rad)
        return np.array(seed_rollout(self._goal_scan.goal, x, y, yaw, v, self._weights, *st))


def _kf_predict(x: list[float], dt: float, q: float) -> list[float]:
    """fpe_jax.model._predict: [position, rate, a, b, c] one constant-velocity step on."""
    p, r, a, b, c = x
    dt2 = dt * dt
    return [
        p + r * dt,
        r,
        a + 2.0 * b * dt + c * dt2 + 0.25 * q * dt2 * dt2,
        b + c * dt + 0.5 * q * dt2 * dt,
        c + q * dt2,
    ]


def _kf_update(x: list[float], nu: float, s_inn: float, w: float) -> list[float]:
    """fpe_jax.model._update: the gate-weighted measurement update of one axis."""
    p, r, a, b, c = x
    kp, kr = w * a / s_inn, w * b / s_inn
    return [p + kp * nu, r + kr * nu, a - kp * a, b - kp * b, c - kr * b]


def _sigmoid(x: float) -> float:
    """1 / (1 + exp(-x)) without overflow for large |x|."""
    if x >= 0.0:
        return 1.0 / (1.0 + math.exp(-x))
    e = math.exp(x)
    return e / (1.0 + e)


def seed_rollout(goal, x_m, y_m, yaw_rad, v_mps, weights, dt_s, wheelbase_m, max_steer_rad):
    """The original 2019 node's prediction for one car, rule by rule (fpe_jax.model.rollout_seed,
    ../shared/data/README.md): per step the goal, a steering of 2 sin(phi - yaw) / d used as an
    angle, the headings blended by weights[k], a move.

    Args:
        goal: (x, y) -> the goal waypoint (x, y) [m] (`GoalScan.goal`, or the original's full
            reverse scan).
        weights: H heading weights; the rest as the config's settings [m, rad, m/s, s].

    Returns:
        H (x [m], y [m], yaw [rad]) lists.
    """
    x, y, yaw, rows = x_m, y_m, yaw_rad, []
    for w in weights:
        gx, gy = goal(x, y)
        d = math.hypot(gx - x, gy - y)
        steer = 2.0 * math.sin(math.atan2(gy - y, gx - x) - yaw) / d if d > 0 else 0.0
        steer = min(max(steer, -max_steer_rad), max_steer_rad)
        yaw_pp = yaw + dt_s * v_mps / wheelbase_m * math.tan(steer)
        yaw = w * yaw + (1.0 - w) * yaw_pp
        x, y = x + v_mps * dt_s * math.cos(yaw), y + v_mps * dt_s * math.sin(yaw)
        rows.append([x, y, yaw])
    return rows


class GoalScan:
    """The seed's goal: the last waypoint of the raw list within `radius_m` of the car, else row 0.

    Scanning all K waypoints (2720 on Levine) ten times per update is most of the seed's cost, so
    the waypoints are bucketed on a grid of cells a little larger than the radius: every waypoint
    within the radius lies in the car's cell or one of its 8 neighbours, and each cell keeps those
    candidates in list order. The distance test is the full scan's, on fewer points.
    """

    def __init__(self, raw_xy_m: np.ndarray, radius_m: float):
        self.xy_m = raw_xy_m
        self.radius_m = radius_m
        self.cell_m = max(radius_m, 1e-3) * 1.001  # margin: |dx| <= r never spans 2 cells
        cells = np.floor(raw_xy_m / self.cell_m).astype(np.int64).tolist()
        buckets: dict[tuple[int, int], list[int]] = {}
        for k, (cx, cy) in enumerate(cells):
            for ox in (-1, 0, 1):
                for oy in (-1, 0, 1):
                    buckets.setdefault((cx + ox, cy + oy), []).append(k)
        self._cells = {
            c: (np.array(ks), raw_xy_m[ks, 0], raw_xy_m[ks, 1]) for c, ks in buckets.items()
        }

    def goal(self, x_m: float, y_m: float) -> tuple[float, float]:
        """Goal position x [m], y [m] for a car at (x, y)."""
        cell = self._cells.get((math.floor(x_m / self.cell_m), math.floor(y_m / self.cell_m)))
        k = 0
        if cell is not None:
            idx, wx, wy = cell
            within = np.flatnonzero(np.hypot(wx - x_m, wy - y_m) <= self.radius_m)
            if len(within):
                k = int(idx[within[-1]])
        return self.xy_m[k, 0].item(), self.xy_m[k, 1].item()


def load_waypoints_xy(path) -> np.ndarray:
    """(K, 2) waypoints x [m], y [m] from any file fpe_jax.io.load_waypoints reads (JAX-free)."""
    from fpe_jax.io.waypoints import load_waypoints

    return np.asarray(load_waypoints(path).xy_m, dtype=np.float64)


# ---- streaming over text lines (`fpe run`) -------------------------------------------------------


def run_stream(runner: Runner, lines, out, err, rate_hz: float | None = None) -> int:
    """Predict for every usable observation line of `lines` (parsed by `fpe_jax.io.stream`),
    writing one JSON line to `out` for each: {"stamp": t, "poses": [[x, y, yaw] x H], "valid":
    bool (`fpe_jax.model.history_valid`: enough history)}, flushed
    at once (a car's process pipes into it). A runner with calibrated ellipses
    (`fpe_jax.runner.AdaptiveRunner(calibrate=True)`) adds "cov_m2": [[[xx, xy], [xy, yy]] x H],
    each step's covariance [m^2] in the frame of the observations (`covariance_map`).

    A bad line is reported on `err` with its line number and skipped (the first
    `spec.STREAM_MESSAGES` in full, then rate-limited, with a closing count: see
    `fpe_jax.io.stream.SkipReport`); where the stamps restart the runner starts a new history.
    The runner gets the stamps since the stream's time origin (exact for epoch stamps); the
    replies carry the stamps as given. An observation far from the track
    (`Runner.check_track`) gets a "warning" field in its reply, and a line on `err` at most once
    per OFF_TRACK_REPORT_S of stamps while the car stays off (and one when it is back). Returns 0
    at the end of the input. Raises InputError for a stream laid out wrongly as a whole, when its
    first observations are off the track, and at the end if lines came but none was usable.
    """
    from fpe_jax.io.stream import SkipReport, read_observations

    warn = SkipReport(err)
    n_written = 0
    off = _OffTrackReports(err)
    for obs in read_observations(lines, warn, rate_hz):
        if obs.restart:
            runner.reset()
            for o in obs.restart:
                runner.update(o.since_s, o.x_m, o.y_m, o.yaw_rad)
        try:
            poses = runner.update(obs.since_s, obs.x_m, obs.y_m, obs.yaw_rad)
            reply = {"stamp": obs.t_s, "poses": poses.tolist(), "valid": runner.valid}
            if runner.calibration is not None:
                reply["cov_m2"] = runner.covariance_map().tolist()
            reply = json.dumps(reply, allow_nan=False)
        except (InputError, ValueError) as e:
            warn(f"line {obs.line}: {e}; skipped")
            continue
        # an InputError here (the first observations off the track) ends the stream
        warning = off.observe(obs, runner.check_track(obs.x_m, obs.y_m))
        if warning is not None:  # only then: an on-track reply is unchanged
            reply = f"{reply[:-1]}, {json.dumps('warning')}: {json.dumps(warning)}}}"
        out.write(reply + "\n")
        out.flush()
        n_written += 1
    if (summary := warn.summary()) is not None:
        print(summary, file=err, flush=True)
    if warn.n_skipped and not n_written:
        raise InputError("stdin", f"none of its observations was usable ({warn.n_skipped} skipped)")
    return 0


class _OffTrackReports:
    """`run_stream`'s stderr lines for a car off the track: at the first off-track observation,
    then at most once per OFF_TRACK_REPORT_S of stamps while it stays off, with the count, and
    once when it is back."""

    def __init__(self, err):
        self.err = err
        self.n_seen = 0
        self.n_off = 0  # of the current stretch off the track
        self.last_report_s: float | None = None

    def observe(self, obs, warning: str | None) -> str | None:
        self.n_seen += 1
        if warning is None:
            if self.n_off:
                self._say(f"line {obs.line}: back on the track after {self.n_off} observation(s)")
            self.n_off, self.last_report_s = 0, None
            return None
        self.n_off += 1
        if self.last_report_s is None or obs.t_s - self.last_report_s >= OFF_TRACK_REPORT_S:
            self._say(f"line {obs.line}: warning: {warning} ({self.n_off} in a row)")
            self.last_report_s = obs.t_s
        return warning

    def _say(self, msg: str) -> None:
        print(f"fpe run: {msg}", file=self.err, flush=True)


# ---- benchmark -----------------------------------------------------------------------------------

BENCH_CONFIG = {
    "schema_version": 1,
    "params": {
        "lookahead_m": 1.2,
        "lookahead_gain_s": 0.25,
        "weights": [0.9 - 0.07 * k for k in range(10)],
        "delay_s": 0.08,
        "speed_weight": 0.9,
        "speed_mps": 2.0,
    },
    "settings": {
        "dt_s": 0.1,
        "horizon": 10,
        "wheelbase_m": 0.325,
        "max_steer_rad": 0.4189,
        "blend": "position",
        "model": "blend",
        "min_lookahead_m": 0.3,
        "history": 10,
    },
}
"""A fitted-looking position blend (the costliest blend: both rollouts) for `benchmark_update`."""


def benchmark_update(waypoints_xy_m, n_updates: int = 2000, config: dict | None = None) -> dict:
    """Time `Runner.update` on a synthetic drive along the given waypoints.

    The drive follows the resampled path at 3 m/s, observed at 10 Hz with 3 cm noise, no yaw,
    and every third row a repeat (as real detectors log): the common case on a car.

    Args:
        waypoints_xy_m: (K, 2) waypoints [m] (e.g. the 2720-point Levine loop).
        n_updates: number of timed updates.
        config: a config dict (default `BENCH_CONFIG`, a position blend).

    Returns:
        dict with median_ms and p99_ms (per update [ms]), n_updates and the model name.
    """
    runner = Runner(config or BENCH_CONFIG, waypoints_xy_m, source="benchmark")
    path = runner.path
    rng = np.random.default_rng(0)
    t = np.arange(n_updates) * 0.1
    xy = np.array([path.point_at(s) for s in 3.0 * t]) + rng.normal(0.0, 0.03, (n_updates, 2))
    for k in range(2, n_updates, 3):
        xy[k] = xy[k - 1]
    rows = [(float(tk), float(xk), float(yk)) for tk, (xk, yk) in zip(t, xy)]
    took_ns = np.empty(n_updates)
    for k, (tk, xk, yk) in enumerate(rows):
        t0 = time.perf_counter_ns()
        runner.update(tk, xk, yk)
        took_ns[k] = time.perf_counter_ns() - t0
    return {
        "median_ms": float(np.median(took_ns) * 1e-6),
        "p99_ms": float(np.percentile(took_ns, 99) * 1e-6),
        "n_updates": n_updates,
        "model": runner.model,
    }


def _main() -> None:  # python -m fpe_jax.runner WAYPOINTS (runner/__main__.py): print the benchmark
    import sys

    print(json.dumps(benchmark_update(load_waypoints_xy(Path(sys.argv[1])))))


if __name__ == "__main__":
    _main()
