"""In-race learning: a runner that learns the opponent's line and speed profile lap by lap.

`AdaptiveRunner` is the NumPy runner (`fpe_jax.runner.Runner`, the line model) whose profile
(offset d(s) [m], speed v(s) [m/s] and coverage along the track, `fpe_jax.model`'s form) is updated
from its own filtered observations as the car drives: every new detection's track-frame estimate
(arc length s, offset d and along-track speed ds/dt, from the Kalman or Theil-Sen estimator the
prediction itself uses) is spread onto the profile's two nearest points with linear weights, as
`fpe_jax.model.line_from_samples` spreads a drive's samples.

- Recent passes weigh more: each point keeps the sums of the car's current pass over it apart
  from those of the passes before; a sample arriving more than PASS_GAP_S after the point's
  previous one (or the first after a reset) starts a new pass there, and the passes before then
  weigh LAP_DECAY (weights 1, 0.25, 0.06, ... for this pass, the last and the one before). A
  pass is the car's own return to the point, so no lap counter or clock has to run on across a
  car out of sight, a jump in the stream or a restarted clock.
- A change detector keeps an unchanged driver's averaging and drops it when the driver changes:
  every sample's offset and log speed are compared with what the previous passes learned where
  it is (the smoothed profile of those passes alone), and the residuals averaged over the last
  CHANGE_WINDOW_M of track. While either window mean is beyond its threshold (CHANGE_OFFSET_M,
  CHANGE_LOG_SPEED: above what a driver keeping its line and pace shows lap to lap), the
  previous passes weigh CHANGE_DECAY instead at every point the car passes, and, as the change
  is found, at the points of the window behind it: one pass on the new line and pace replaces
  the old profile there, where a fixed decay would still mix in a quarter of it. Offset and
  speed share the rule and the detector (a change of line, cornering or pace changes both).
- Where the car has not been seen the prior holds: the starting config's profile, or with none
  the line model's uncovered fallback (the car's own offset kept, its speed held).
- Bounded work: an update touches only the points within the smoothing kernel's reach of the
  new offset and speed samples (at most 4 x (2 x 4 sigma + 1) = 68 points with the 0.5 m
  spacing and 1 m kernel), reads the previous passes there for the detector and, when a change
  is found, the window behind (CHANGE_WINDOW_M / 0.5 m + 3 points), so an update costs the same
  on any track and any lap.
- Delay, time constants and filter noise stay as the starting config has them (or
  `DEFAULT_PARAMS` without one): they are properties of the ego car's sensor and of the
  opponent's driving that a lap of detections does not identify.
- With `calibrate=True` the starting config's ellipses follow the drive
  (`fpe_jax.runner._calibrate.EllipseCalibration`): each recorded prediction's error is
  realised against the runner's later filtered estimate of where the car was, and each step's
  along- and cross-track variance scaled by the running mean of its normalised squared error.
  Off by default: it adds the calibrated ellipses to the saved state (`uncertainty`, which is
  null without it) and its own work to each update (experiments/benchmarks/adapt_calibration.md).

`state_config()` is the learned state as an ordinary line-model config (`fpe predict --config`,
`fpe evaluate`, `fpe export` read it). tests/runner/test_adapt.py computes the same profile in
JAX (the rule written over whole arrays, scanned over the samples, then a circular convolution)
and compares the two to 1e-6.

Imports no JAX (the car's computer may have none).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping
from datetime import UTC, datetime
from typing import Any

import numpy as np

from fpe_jax.errors import InputError
from fpe_jax.geometry._path import build_path, covariance_map, waypoints_sha256
from fpe_jax.io.config import check_waypoints, read_config
from fpe_jax.runner._calibrate import CALIBRATION_DECAY, PRIOR_SAMPLES, EllipseCalibration
from fpe_jax.runner._runner import Runner, load_waypoints_xy
from fpe_jax.spec import LINE_KEYS, SCHEMA_VERSION, check_config

PROFILE_DS_M = 0.5  # fpe_jax.model's profile spacing [m] (a config's own P is kept)
PROFILE_SMOOTH_M = 1.0  # fpe_jax.model's kernel standard deviation [m]
# kernel-weighted samples for full coverage: fpe_jax.model needs 1 over whole drives; in the race
# half of that, so that one lap at 10 Hz covers the loop (the newest lap weighs most)
MIN_SAMPLES = 0.5
LAP_DECAY = 0.25  # weight of a point's samples from one pass before the newest, per pass
# a point's next sample more than this after its previous one (or after a reset) starts a new
# pass there: longer than any stay at a point of a car that is moving or seen standing, shorter
# than any lap
PASS_GAP_S = 2.0
# the change detector: the car's offset and log speed against what the previous passes learned
# where it is, averaged over the last CHANGE_WINDOW_M of track (about a second of driving, the
# span the rollout reads the profile over); beyond CHANGE_OFFSET_M or CHANGE_LOG_SPEED there,
# the previous passes' weight at the points the car passes drops to CHANGE_DECAY. The
# thresholds sit above what an unchanged driver shows: on the simulated races (a line wandering
# +-0.3 m, sensor noise, 0.3 s latency) the window means stay within 0.36 m and 0.09 (95 % within
# 0.28 m and 0.07), so a driver who keeps its line and pace keeps its averaging over laps
CHANGE_WINDOW_M = 5.0
CHANGE_OFFSET_M = 0.45
CHANGE_LOG_SPEED = 0.15
CHANGE_DECAY = 0.0
MIN_RESIDUAL_SPEED_MPS = 0.5  # speeds are compared above this (a standing car: no ratio)
MAX_SAMPLE_SPEED_MPS = 100.0  # a track-frame speed above this is a filter transient: no sample

# Without a config: the line model with the Kalman estimator, no detection delay (give the ego
# sensor's own), and the time constants and filter noise `fpe fit` typically finds on the
# simulated 1:10 tracks (experiments/results/approaches.md: offset decay 0.1-0.4 s, speed-profile
# blend 0.05-0.4 s, position smoothing 0.7-0.8, filter 1 / 1 m/s^2, 0.25 m, gate 3-4 sigma): a
# learned line is trusted within a fraction of a second.
DEFAULT_PARAMS = {
    "lookahead_m": 1.0,
    "lookahead_gain_s": 0.2,
    "delay_s": 0.0,
    "speed_weight": 1.0,
    "speed_mps": 2.0,
    "offset_tau_s": 0.2,
    "speed_tau_s": 0.1,
    "position_smoothing": 0.7,
    "filter_accel_mps2": 1.0,
    "filter_lat_accel_mps2": 1.0,
    "filter_obs_m": 0.25,
    "filter_gate_sigma": 3.5,
}
DEFAULT_SETTINGS = {
    "dt_s": 0.1,
    "horizon": 10,
    "wheelbase_m": 0.325,
    "max_steer_rad": 0.4189,
    "blend": "position",
    "model": "line",
    "min_lookahead_m": 0.3,
    "history": 10,
    "estimator": "kalman",
}


def profile_points(length_m: float, ds_m: float = PROFILE_DS_M) -> int:
    """fpe_jax.model's number of profile points P on a track of `length_m` [m]."""
    return max(int(round(length_m / ds_m)), 8)


def kernel(spacing_m: float, closed: bool, n: int, smooth_m: float = PROFILE_SMOOTH_M):
    """fpe_jax.model._smooth's Gaussian kernel over points: (2 half + 1,) weights summing to 1."""
    sigma = smooth_m / spacing_m
    half = min(int(np.ceil(4 * sigma)), n // 2 if closed else (n - 1) // 2)
    k = np.exp(-0.5 * (np.arange(-half, half + 1) / max(sigma, 1e-9)) ** 2)
    return k / k.sum()


def start_config(
    config: Mapping[str, Any] | None,
    waypoints_xy_m,
    settings: Mapping[str, Any] | None = None,
    source: str = "config",
    delay_s: float | None = None,
) -> dict[str, Any]:
    """The line-model config an adaptive runner starts from.

    Args:
        config: a checked config dict, or None (DEFAULT_PARAMS / DEFAULT_SETTINGS). A line-model
            config keeps its profile (the prior where the car has not been seen); another
            model's config lends its delay, time constants, filter noise and prediction grid,
            and the profile starts empty.
        waypoints_xy_m: (K, 2) the waypoints the runner runs on [m].
        settings: settings to change (e.g. {"horizon": 50}); only without a config.
        source: names the config in errors.
        delay_s: the detection delay [s] of the ego car's own sensor (known without any drive
            of the opponent); only without a config (default 0).
    """
    if config is None:
        cfg = {
            "schema_version": SCHEMA_VERSION,
            "params": dict(DEFAULT_PARAMS),
            "settings": {**DEFAULT_SETTINGS, **(settings or {})},
        }
        if delay_s is not None:
            cfg["params"]["delay_s"] = delay_s
        h = cfg["settings"]["horizon"]
        cfg["params"]["weights"] = [1.0] * h if isinstance(h, int) else []
    else:
        if settings or delay_s is not None:
            what = ", ".join([*(settings or {}), *(["delay"] if delay_s is not None else [])])
            raise InputError(what, "given with a config", "the config's own values")
        cfg = copy.deepcopy(dict(config))
        if cfg["settings"]["model"] != "line":
            cfg["settings"] = {**cfg["settings"], "model": "line", "estimator": "kalman"}
            for k in LINE_KEYS:
                cfg["params"].pop(k, None)
    cfg.setdefault("uncertainty", None)
    cfg.setdefault("provenance", {})
    if not all(k in cfg["params"] for k in LINE_KEYS):
        n = profile_points(float(build_path(waypoints_xy_m)["length_m"]))
        cfg["params"].update(
            line_offset_m=[0.0] * n, line_speed_mps=[0.0] * n, line_coverage=[0.0] * n
        )
        cfg["line"] = {"waypoints_sha256": waypoints_sha256(waypoints_xy_m)}
    return check_config(cfg, source)


class AdaptiveRunner(Runner):
    """`Runner` (line model) whose profile is learned from the car's own observations as laps
    go by; `update` has the same interface and returns (H, 3) x [m], y [m], yaw [rad].

    Attributes (besides Runner's): samples: the number of samples learned from; laps: the laps
    the car has driven since the start (on a loop); changes: how often the change detector has
    found the car driving unlike its previous passes; changed: whether it does now;
    calibration: the `EllipseCalibration` of the config's ellipses (None unless calibrate).
    """

    def __init__(
        self,
        config: Mapping[str, Any] | None,
        waypoints_xy_m,
        *,
        settings: Mapping[str, Any] | None = None,
        delay_s: float | None = None,
        lap_decay: float = LAP_DECAY,
        change_decay: float = CHANGE_DECAY,
        detect_changes: bool = True,
        min_samples: float = MIN_SAMPLES,
        calibrate: bool = False,
        calibration_decay: float = CALIBRATION_DECAY,
        calibration_prior_samples: float = PRIOR_SAMPLES,
        source: str = "config",
    ):
        """Args:
        config: a config dict (`read_config`'s) to start from, or None (the defaults and an
            empty profile, which keeps the car's own offset and speed until it has been seen).
        waypoints_xy_m: (K, 2) waypoints [m].
        settings, delay_s: without a config, settings to change (e.g. {"horizon": 50}) and
            the ego sensor's detection delay [s] (`start_config`).
        lap_decay: weight of a point's previous passes, per newer pass, in (0, 1].
        change_decay: their weight where the change detector finds the car driving unlike
            them, in [0, lap_decay].
        detect_changes: False: no change detector (the previous passes always weigh
            lap_decay, the road ahead is read as learned).
        min_samples: kernel-weighted samples at a point for full coverage (> 0).
        calibrate: calibrate the config's ellipses (`uncertainty.cov_m2`, which it must
            have) on the runner's own realised errors (`EllipseCalibration`, with
            calibration_decay and calibration_prior_samples as its decay and prior_samples).
        """
        if not 0.0 < lap_decay <= 1.0:
            raise InputError("lap_decay", f"{lap_decay!r}", "a number in (0, 1]")
        if not 0.0 <= change_decay <= lap_decay:
            raise InputError("change_decay", f"{change_decay!r}", "a number in [0, lap_decay]")
        if not min_samples > 0.0:
            raise InputError("min_samples", f"{min_samples!r}", "a positive number")
        self.min_samples = float(min_samples)
        cfg = start_config(config, waypoints_xy_m, settings, source, delay_s)
        super().__init__(cfg, waypoints_xy_m, source=source)
        self._cfg = cfg
        self._waypoints_sha256 = waypoints_sha256(waypoints_xy_m)
        self.lap_decay = float(lap_decay)
        self.change_decay = float(change_decay)
        self.detect_changes = bool(detect_changes)
        prior = [np.asarray(v, dtype=np.float64) for v in (cfg["params"][k] for k in LINE_KEYS)]
        self._prior_offset, self._prior_speed, self._prior_coverage = prior
        n = len(self._prior_offset)
        self._n = n
        self._spacing = self.path.length_m / (n if self.path.closed else n - 1)
        self._kernel = kernel(self._spacing, self.path.closed, n)
        # raw sums per point (weight, weight x offset, speed weight, speed weight x speed) of
        # the current pass there and of the passes before it; the profile's are
        # current + keep x before
        self._current = np.zeros((4, n))
        self._before = np.zeros((4, n))
        self._keep = np.zeros(n)
        self._last_s = np.full(n, -math.inf)  # stamp of each point's newest sample [s]
        self._sums = np.zeros((4, n))
        self._smoothed = np.zeros((4, n))
        self._profile = [list(a) for a in prior]
        self._line = self._profile  # the rollout reads the live profile
        self.samples = 0
        self.laps = 0
        self.changes = 0
        self.changed = False
        self._residual = [0.0, 0.0]  # the detector's window means: offset [m], log speed
        self._residual_at: float | None = None  # arc length [m] of its newest sample
        self._changed_s = -math.inf  # stamp [s] at which the change now found was found
        self._s_unwrapped: float | None = None
        self._frame = None
        self.calibration: EllipseCalibration | None = None
        if calibrate:
            unc = cfg.get("uncertainty")
            if unc is None:
                raise InputError(
                    source,
                    "has no uncertainty to calibrate",
                    "a config with ellipses (`fpe fit` writes them)",
                )
            self.calibration = EllipseCalibration(
                unc["cov_m2"],
                self.dt_s,
                self._delay_s,
                decay=calibration_decay,
                prior_samples=calibration_prior_samples,
                source=source,
            )

    @classmethod
    def from_files(cls, config_path, waypoints_path, **kw) -> AdaptiveRunner:
        """From a config file (or None) and a waypoint file (any form fpe_jax.io reads)."""
        xy = load_waypoints_xy(waypoints_path)
        cfg = None
        if config_path is not None:
            cfg = read_config(config_path)
            check_waypoints(cfg, config_path, xy, waypoints_path)
        return cls(cfg, xy, source=str(config_path or "defaults"), **kw)

    def reset(self) -> None:
        """Forget the history, the track position and the change detector's window (and the
        clock: the next sample at any point starts a new pass there); what was learned stays."""
        super().reset()
        if hasattr(self, "_last_s"):  # Runner.__init__ resets before the state exists
            self._last_s[:] = -math.inf
            self._residual, self._residual_at, self.changed = [0.0, 0.0], None, False
        if self.calibration is not None:
            self.calibration.reset()

    def _track_frame(self, s_hint_m: float):
        self._frame = super()._track_frame(s_hint_m)
        return self._frame

    def update(self, stamp_s: float, x_m: float, y_m: float, yaw_rad: float | None = None):
        """Predict from the observation (as `Runner.update`), then learn from its filtered
        track-frame estimate (a repeated row, no new detection, teaches nothing). With the
        calibration, that estimate also realises the errors of earlier predictions, and the
        new prediction is recorded (when the history is valid)."""
        n_before = self._history[-1] if self._history else None
        self._frame = None
        poses = super().update(stamp_s, x_m, y_m, yaw_rad)
        fresh = self._history and self._history[-1] is not n_before
        if fresh and self._frame is not None:
            s_m, sdot_mps, d_m, age_s = self._frame
            self.learn(float(stamp_s), s_m, d_m, sdot_mps, age_s)
            if self.calibration is not None:
                self._calibrate(float(stamp_s), s_m, d_m, poses)
        return poses

    def _calibrate(self, stamp_s: float, s_m: float, d_m: float, poses: np.ndarray) -> None:
        """Realise earlier predictions' errors against the filtered position (arc length s_m,
        offset d_m [m]), then record this prediction with the path heading at each step (at
        the rollout's own arc length there, which a projection of the predicted position finds
        again)."""
        path = self.path
        cx, cy = path.point_at(s_m)
        h = path.heading_at(s_m)
        self.calibration.observe(stamp_s, cx - d_m * math.sin(h), cy + d_m * math.cos(h))
        if self.valid:  # the path heading at each step's arc length in the rollout
            heading = [path.heading_at(s) for s in self._step_s_m]
            self.calibration.record(stamp_s, poses[:, :2], heading)

    def covariance(self) -> np.ndarray | None:
        """(H, 2, 2) the calibrated along-/cross-track covariance [m^2] of the predictions
        now (None without the calibration)."""
        return None if self.calibration is None else self.calibration.covariance()

    def covariance_map(self) -> np.ndarray | None:
        """(H, 2, 2) the calibrated covariance [m^2] of the last prediction in the frame of the
        observations: `covariance` turned by the path heading at each step's arc length in
        the rollout (None without the calibration)."""
        if self.calibration is None:
            return None
        heading = np.array([[self.path.heading_at(s) for s in self._step_s_m]])
        return covariance_map(self.covariance()[None], heading)[0]

    # ---- learning -----------------------------------------------------------------------------

    def learn(
        self, stamp_s: float, s_m: float, d_m: float, v_mps: float, v_age_s: float = 0.0
    ) -> None:
        """Add one sample, taken at stamp_s [s]: the car at arc length s_m [m] (any lap) with
        offset d_m [m], and its along-track speed v_mps [m/s] (not finite or implausible: no
        speed sample) as it was v_age_s [s] before (a window's speed estimate describes its
        middle: the speed sample goes where the car was then, s_m - v_mps v_age_s, as the
        rollout reads it).

        A point's sample more than PASS_GAP_S after its previous one starts a new pass there:
        the passes before weigh lap_decay less. The change detector compares the sample with
        what the previous passes learned where it was; while the window mean of that residual
        is beyond CHANGE_OFFSET_M or CHANGE_LOG_SPEED, the previous passes weigh change_decay
        at the points the car passes, from CHANGE_WINDOW_M behind the sample on."""
        has_v = math.isfinite(v_mps) and abs(v_mps) <= MAX_SAMPLE_SPEED_MPS
        length = self.path.length_m
        if self.path.closed:
            s_mod = s_m % length
            if self._s_unwrapped is None:
                self._s_unwrapped = s_mod
            else:
                self._s_unwrapped += self._arc_step(s_mod, self._s_unwrapped)
            # never backwards (a car backing up, or jitter at the line): laps only grow
            self.laps = max(self.laps, math.floor(self._s_unwrapped / length))
        places = [(0, s_m, d_m)] + ([(1, s_m - v_mps * v_age_s, v_mps)] if has_v else [])
        spread = [(kind, value, self._spread(at_m)) for kind, at_m, value in places]
        touched = set(self._detect(stamp_s, s_m, spread) if self.detect_changes else [])
        for kind, value, pairs in spread:
            for idx, w in pairs:
                self._deposit(stamp_s, idx, w, kind, value)
                touched.add(idx)
        self.samples += 1
        self._refresh(sorted(touched))

    def _arc_step(self, to_m: float, from_m: float) -> float:
        """The arc length [m] from from_m to to_m: the shorter way round on a loop."""
        if not self.path.closed:
            return to_m - from_m
        length = self.path.length_m
        return (to_m - from_m + 0.5 * length) % length - 0.5 * length

    def _spread(self, at_m: float) -> list[tuple[int, float]]:
        """The two profile points around arc length at_m [m] and their linear weights."""
        length = self.path.length_m
        if self.path.closed:
            u = (at_m % length) / self._spacing
        else:
            u = min(max(at_m, 0.0), length) / self._spacing
        i = math.floor(u)
        f = u - i
        out = []
        for idx, w in ((i, 1.0 - f), (i + 1, f)):
            out.append((idx % self._n if self.path.closed else min(max(idx, 0), self._n - 1), w))
        return out

    def _in_pass(self, stamp_s: float, idx: int) -> bool:
        return bool(0.0 <= stamp_s - self._last_s[idx] <= PASS_GAP_S)

    def _detect(self, stamp_s: float, s_m: float, spread) -> list[int]:
        """Update the change detector with one sample's residuals against the previous passes
        (spread: as `learn` places it); returns the points whose previous passes it drops."""
        if self._residual_at is None:
            a = 1.0
        else:  # an exponential window in distance driven
            a = -math.expm1(-abs(self._arc_step(s_m, self._residual_at)) / CHANGE_WINDOW_M)
        self._residual_at = s_m
        residual = [0.0, 0.0]  # no previous passes there: no evidence of a change
        for kind, value, pairs in spread:
            before = self._previous(stamp_s, kind, pairs)
            if before is None:
                continue
            if kind == 0:
                residual[0] = value - before
            else:
                low = MIN_RESIDUAL_SPEED_MPS
                residual[1] = math.log(max(value, low) / max(before, low))
        self._residual = [m + a * (r - m) for m, r in zip(self._residual, residual)]
        was = self.changed
        self.changed = (
            abs(self._residual[0]) > CHANGE_OFFSET_M or abs(self._residual[1]) > CHANGE_LOG_SPEED
        )
        if not self.changed or was:
            return []
        self.changes += 1
        self._changed_s = stamp_s
        # the window that showed the change: the points of this pass up to CHANGE_WINDOW_M back
        out = []
        back = math.ceil(CHANGE_WINDOW_M / self._spacing) + 1
        first = math.floor(s_m / self._spacing)
        for i in range(first - back, first + 2):
            idx = i % self._n if self.path.closed else i
            if not 0 <= idx < self._n or not self._in_pass(stamp_s, idx):
                continue
            if 0.0 <= self._arc_step(s_m, idx * self._spacing) <= CHANGE_WINDOW_M:
                self._keep[idx] = self.change_decay
                self._sums[:, idx] = self._current[:, idx] + self._keep[idx] * self._before[:, idx]
                out.append(idx)
        return out

    def _previous(self, stamp_s: float, kind: int, pairs) -> float | None:
        """The offset (kind 0) [m] or speed (kind 1) [m/s] the previous passes learned at a
        sample's two points (pairs: point, linear weight), or None where they saw too little
        (less than min_samples kernel-weighted samples)."""
        w_sum, x_sum = 0.0, 0.0
        for j, w in pairs:
            cols = self._columns(j)
            k = self._kernel if self.path.closed else self._open_kernel(j)
            for c, kk in zip(cols, k):
                # a point already in its new pass holds its previous passes apart
                prev = self._before[:, c] if self._in_pass(stamp_s, c) else self._sums[:, c]
                w_sum += w * kk * prev[2 * kind]
                x_sum += w * kk * prev[2 * kind + 1]
        return x_sum / w_sum if w_sum >= self.min_samples else None

    def _columns(self, j: int) -> list[int]:
        """The points the kernel centred on point j reads (wrapped on a loop, cut at the ends of
        an open path)."""
        half = (len(self._kernel) - 1) // 2
        if self.path.closed:
            return [(j + k) % self._n for k in range(-half, half + 1)]
        return list(range(max(j - half, 0), min(j + half, self._n - 1) + 1))

    def _open_kernel(self, j: int) -> np.ndarray:
        half = (len(self._kernel) - 1) // 2
        lo, hi = max(j - half, 0), min(j + half, self._n - 1)
        return self._kernel[lo - j + half : hi - j + half + 1]

    def _deposit(self, stamp_s: float, idx: int, w: float, kind: int, value: float) -> None:
        """Add weight w of an offset (kind 0) or speed (kind 1) sample at point idx, first
        starting a new pass there if its previous sample is more than PASS_GAP_S old."""
        cur, before = self._current[:, idx], self._before[:, idx]
        if not self._in_pass(stamp_s, idx):
            before[:] = cur + self._keep[idx] * before
            cur[:] = 0.0
            self._keep[idx] = self.lap_decay
        if self.changed:
            self._keep[idx] = self.change_decay
        self._last_s[idx] = stamp_s
        cur[2 * kind] += w
        cur[2 * kind + 1] += w * value
        self._sums[:, idx] = cur + self._keep[idx] * before

    def _refresh(self, touched: list[int]) -> None:
        """Re-smooth and re-blend the points within the kernel's reach of the touched ones."""
        near = sorted({c for j in touched for c in self._columns(j)})
        for j in near:
            cols = self._columns(j)
            k = self._kernel if self.path.closed else self._open_kernel(j)
            self._smoothed[:, j] = self._sums[:, cols] @ k  # zero beyond an open path's ends
            self._blend(j)

    def _line_at(self, s_m: float) -> tuple[float, float, float]:
        """The profile the rollout reads at arc length s_m [m]: offset [m], coverage, speed
        [m/s]. While the detector finds the car driving unlike its previous passes, the points
        it has not passed since hold the old behaviour: there the change seen so far carries
        on (its window mean offset added, its speed ratio applied), so that the road ahead
        agrees with the line and pace the car now shows behind."""
        offset, coverage, speed = super()._line_at(s_m)
        if not self.changed:
            return offset, coverage, speed
        old = sum(w for idx, w in self._spread(s_m) if self._last_s[idx] < self._changed_s)
        return (
            offset + old * self._residual[0],
            coverage,
            speed * math.exp(old * self._residual[1]),
        )

    def _blend(self, j: int) -> None:
        sw, sd, svw, sv = self._smoothed[:, j]
        c = min(max(min(sw, svw) / self.min_samples, 0.0), 1.0)
        offset = sd / max(sw, 1e-9) if sw > 1e-9 else 0.0
        speed = sv / max(svw, 1e-9) if svw > 1e-9 else 0.0
        if c <= 0.0:
            offset, speed = 0.0, 0.0
        po, ps, pc = self._prior_offset[j], self._prior_speed[j], self._prior_coverage[j]
        known = c + (1.0 - c) * pc
        self._profile[0][j] = c * offset + (1.0 - c) * po
        # the speed is read without its coverage (fpe_jax.model's ratio to the speed where the
        # car is): weighted by what is known, so that where the prior knows nothing a partly
        # seen point holds the speed seen there, not a mix with the prior's zero
        if known > 0.0:
            self._profile[1][j] = (c * speed + (1.0 - c) * pc * ps) / known
        else:
            self._profile[1][j] = ps
        self._profile[2][j] = known

    # ---- state --------------------------------------------------------------------------------

    def profile(self) -> dict[str, np.ndarray]:
        """The current line_offset_m, line_speed_mps, line_coverage, each (P,)."""
        return {k: np.array(v) for k, v in zip(LINE_KEYS, self._profile)}

    def state_config(self, provenance: Mapping[str, Any] | None = None) -> dict[str, Any]:
        """What the runner has learned as a line-model config (schema-checked), the prior's
        delay, time constants and settings included."""
        cfg = copy.deepcopy(self._cfg)
        cfg["params"].update({k: [float(x) for x in v] for k, v in zip(LINE_KEYS, self._profile)})
        cfg["line"] = {**cfg.get("line", {}), "waypoints_sha256": self._waypoints_sha256}
        # the starting config's ellipses describe another profile; calibrated ones this one
        cfg["uncertainty"] = None
        extra = {}
        if self.calibration is not None:
            cov = self.calibration.covariance()
            cfg["uncertainty"] = {"frame": "track", "axes": ["along_m", "cross_m"]}
            cfg["uncertainty"]["cov_m2"] = cov.tolist()
            extra["calibration"] = self.calibration.state()
        cfg["provenance"] = {
            **dict(provenance or {}),
            "adapted": {
                "samples": self.samples,
                "laps": self.laps,
                "lap_decay": self.lap_decay,
                "change_decay": self.change_decay,
                "changes": self.changes,
                "at": datetime.now(UTC).isoformat(timespec="seconds"),
                **extra,
            },
        }
        return check_config(cfg, "adapted state")


def predict_drive_adaptive(
    drive,
    waypoints_xy_m,
    config: Mapping[str, Any] | None = None,
    *,
    with_covariance: bool = False,
    **kw,
) -> tuple:
    """Every observation of a drive through a fresh `AdaptiveRunner`, in stream order.

    The drive and waypoints are moved to a local frame first (`fpe_jax.drive.local_frame`), as
    the JAX commands do, and the predictions back to the map frame.

    Args:
        drive: a `fpe_jax.drive.Drive`.
        waypoints_xy_m: (K, 2) waypoints [m] in the drive's frame.
        config: a checked config dict to start from, or None; kw: as `AdaptiveRunner` takes.
        with_covariance: also return each prediction's covariance as calibrated then (needs
            calibrate=True).

    Returns:
        (the runner after the drive, with what it learned (its waypoints in the local frame,
        which `state_config` hashes alike: `waypoints_sha256` is frame-free),
        (N, H, 3) predictions x [m], y [m], yaw [rad] in the drive's frame), and with
        with_covariance (N, H, 2, 2) their map-frame covariance [m^2]: the calibrated
        along-/cross-track one turned by the path heading at each step.
    """
    from fpe_jax.drive import local_frame

    local, wp, _, origin = local_frame(drive, waypoints_xy_m)
    runner = AdaptiveRunner(config, wp, **kw)
    if with_covariance and runner.calibration is None:
        raise ValueError("predict_drive_adaptive: with_covariance needs calibrate=True")
    rows = zip(local.t_s.tolist(), local.xy_m.tolist(), local.yaw_rad.tolist())
    poses, cov = [], []
    for t, (x, y), a in rows:
        poses.append(runner.update(t, x, y, a))
        if with_covariance:
            cov.append(runner.covariance_map())
    poses = np.stack(poses)
    poses[..., :2] += origin
    if not with_covariance:
        return runner, poses
    return runner, poses, np.stack(cov)
