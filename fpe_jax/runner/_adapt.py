"""In-race learning: a runner that learns the opponent's line and speed profile lap by lap.

`AdaptiveRunner` is the NumPy runner (`fpe_jax.runner.Runner`, the line model) whose profile
(offset d(s) [m], speed v(s) [m/s] and coverage along the track, `fpe_jax.model`'s form) is updated
from its own filtered observations as the car drives: every new detection's track-frame estimate
(arc length s, offset d and along-track speed ds/dt, from the Kalman or Theil-Sen estimator the
prediction itself uses) is spread onto the profile's two nearest points with linear weights, as
`fpe_jax.model.line_from_samples` spreads a drive's samples.

- Recent laps weigh more: a point's sums are multiplied by LAP_DECAY for every lap since the point
  last received a sample (lazily, when it next receives one), so the line the car drives now
  replaces the one it drove a lap or two ago (weights 1, 0.25, 0.06, ... for this lap, the last
  and the one before).
- Where the car has not been seen the prior holds: the starting config's profile, or with none
  the line model's uncovered fallback (the car's own offset kept, its speed held).
- Bounded work: an update touches only the points within the smoothing kernel's reach of the
  new offset and speed samples (at most 4 x (2 x 4 sigma + 1) = 68 points with the 0.5 m
  spacing and 1 m kernel), so an update costs the same on any track and any lap.
- Delay, time constants and filter noise stay as the starting config has them (or
  `DEFAULT_PARAMS` without one): they are properties of the ego car's sensor and of the
  opponent's driving that a lap of detections does not identify.

`state_config()` is the learned state as an ordinary line-model config (`fpe predict --config`,
`fpe evaluate`, `fpe export` read it). tests/runner/test_adapt.py computes the same profile from all
samples at once in JAX (a scatter-add, a circular convolution) and compares the two to 1e-6.

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
from fpe_jax.geometry._path import build_path, waypoints_sha256
from fpe_jax.io.config import check_waypoints, read_config
from fpe_jax.runner._runner import Runner, load_waypoints_xy
from fpe_jax.spec import LINE_KEYS, SCHEMA_VERSION, check_config

PROFILE_DS_M = 0.5  # fpe_jax.model's profile spacing [m] (a config's own P is kept)
PROFILE_SMOOTH_M = 1.0  # fpe_jax.model's kernel standard deviation [m]
# kernel-weighted samples for full coverage: fpe_jax.model needs 1 over whole drives; in the race
# half of that, so that one lap at 10 Hz covers the loop (the newest lap weighs most)
MIN_SAMPLES = 0.5
LAP_DECAY = 0.25  # weight of the samples of one lap before the newest, per lap
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
    the car has driven since the start (on a loop).
    """

    def __init__(
        self,
        config: Mapping[str, Any] | None,
        waypoints_xy_m,
        *,
        settings: Mapping[str, Any] | None = None,
        delay_s: float | None = None,
        lap_decay: float = LAP_DECAY,
        min_samples: float = MIN_SAMPLES,
        source: str = "config",
    ):
        """Args:
        config: a config dict (`read_config`'s) to start from, or None (the defaults and an
            empty profile, which keeps the car's own offset and speed until it has been seen).
        waypoints_xy_m: (K, 2) waypoints [m].
        settings, delay_s: without a config, settings to change (e.g. {"horizon": 50}) and
            the ego sensor's detection delay [s] (`start_config`).
        lap_decay: weight of a lap's samples per newer lap, in (0, 1].
        min_samples: kernel-weighted samples at a point for full coverage (> 0).
        """
        if not 0.0 < lap_decay <= 1.0:
            raise InputError("lap_decay", f"{lap_decay!r}", "a number in (0, 1]")
        if not min_samples > 0.0:
            raise InputError("min_samples", f"{min_samples!r}", "a positive number")
        self.min_samples = float(min_samples)
        cfg = start_config(config, waypoints_xy_m, settings, source, delay_s)
        super().__init__(cfg, waypoints_xy_m, source=source)
        self._cfg = cfg
        self._waypoints_sha256 = waypoints_sha256(waypoints_xy_m)
        self.lap_decay = float(lap_decay)
        prior = [np.asarray(v, dtype=np.float64) for v in (cfg["params"][k] for k in LINE_KEYS)]
        self._prior_offset, self._prior_speed, self._prior_coverage = prior
        n = len(self._prior_offset)
        self._n = n
        self._spacing = self.path.length_m / (n if self.path.closed else n - 1)
        self._kernel = kernel(self._spacing, self.path.closed, n)
        # raw sums per point: weight, weight x offset, speed weight, speed weight x speed
        self._sums = np.zeros((4, n))
        self._smoothed = np.zeros((4, n))
        self._lap_of_point = np.zeros(n, dtype=np.int64)
        self._profile = [list(a) for a in prior]
        self._line = self._profile  # the rollout reads the live profile
        self.samples = 0
        self.laps = 0
        self._s_unwrapped: float | None = None
        self._frame = None

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
        """Forget the history and the track position; what was learned stays."""
        super().reset()
        self._s_unwrapped = None

    def _track_frame(self, s_hint_m: float):
        self._frame = super()._track_frame(s_hint_m)
        return self._frame

    def update(self, stamp_s: float, x_m: float, y_m: float, yaw_rad: float | None = None):
        """Predict from the observation (as `Runner.update`), then learn from its filtered
        track-frame estimate (a repeated row, no new detection, teaches nothing)."""
        n_before = self._history[-1] if self._history else None
        self._frame = None
        poses = super().update(stamp_s, x_m, y_m, yaw_rad)
        fresh = self._history and self._history[-1] is not n_before
        if fresh and self._frame is not None:
            s_m, sdot_mps, d_m, age_s = self._frame
            self.learn(s_m, d_m, sdot_mps, age_s)
        return poses

    # ---- learning -----------------------------------------------------------------------------

    def learn(self, s_m: float, d_m: float, v_mps: float, v_age_s: float = 0.0) -> None:
        """Add one sample: the car at arc length s_m [m] (any lap) with offset d_m [m], and its
        along-track speed v_mps [m/s] (not finite or implausible: no speed sample) as it was
        v_age_s [s] before (a window's speed estimate describes its middle: the speed sample
        goes where the car was then, s_m - v_mps v_age_s, as the rollout reads it)."""
        has_v = math.isfinite(v_mps) and abs(v_mps) <= MAX_SAMPLE_SPEED_MPS
        length = self.path.length_m
        if self.path.closed:
            s_mod = s_m % length
            if self._s_unwrapped is None:
                self._s_unwrapped = s_mod
            else:
                step = (s_mod - self._s_unwrapped % length + 0.5 * length) % length - 0.5 * length
                self._s_unwrapped += step
            # never backwards (a car backing up, or jitter at the line): a point's laps only grow
            self.laps = max(self.laps, math.floor(self._s_unwrapped / length))
        touched = set()
        for kind, at_m in ((0, s_m), (1, s_m - v_mps * v_age_s if has_v else None)):
            if at_m is None:
                continue
            if self.path.closed:
                u = (at_m % length) / self._spacing
            else:
                u = min(max(at_m, 0.0), length) / self._spacing
            i = math.floor(u)
            f = u - i
            for idx, w in ((i, 1.0 - f), (i + 1, f)):
                idx = idx % self._n if self.path.closed else min(max(idx, 0), self._n - 1)
                self._deposit(idx, w, kind, d_m if kind == 0 else v_mps)
                touched.add(idx)
        self.samples += 1
        self._refresh(sorted(touched))

    def _deposit(self, idx: int, w: float, kind: int, value: float) -> None:
        """Add weight w of an offset (kind 0) or speed (kind 1) sample at point idx, first
        decaying the point's sums by lap_decay per lap since it was last given one."""
        sums = self._sums
        behind = self.laps - self._lap_of_point[idx]
        if behind > 0:
            sums[:, idx] *= self.lap_decay**behind
            self._lap_of_point[idx] = self.laps
        sums[2 * kind, idx] += w
        sums[2 * kind + 1, idx] += w * value

    def _refresh(self, touched: list[int]) -> None:
        """Re-smooth and re-blend the points within the kernel's reach of the touched ones."""
        half = (len(self._kernel) - 1) // 2
        n, closed = self._n, self.path.closed
        if closed:
            near = sorted({(j + k) % n for j in touched for k in range(-half, half + 1)})
        else:
            near = sorted(
                {j + k for j in touched for k in range(-half, half + 1) if 0 <= j + k < n}
            )
        for j in near:
            if closed:
                cols = [(j + k) % n for k in range(-half, half + 1)]
                self._smoothed[:, j] = self._sums[:, cols] @ self._kernel
            else:  # zero beyond the ends, as np.convolve(mode="same")
                lo, hi = max(j - half, 0), min(j + half, n - 1)
                kk = self._kernel[lo - j + half : hi - j + half + 1]
                self._smoothed[:, j] = self._sums[:, lo : hi + 1] @ kk
            self._blend(j)

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
        cfg["uncertainty"] = None  # the starting config's ellipses describe another profile
        cfg["provenance"] = {
            **dict(provenance or {}),
            "adapted": {
                "samples": self.samples,
                "laps": self.laps,
                "lap_decay": self.lap_decay,
                "at": datetime.now(UTC).isoformat(timespec="seconds"),
            },
        }
        return check_config(cfg, "adapted state")


def predict_drive_adaptive(
    drive, waypoints_xy_m, config: Mapping[str, Any] | None = None, **kw
) -> tuple[AdaptiveRunner, np.ndarray]:
    """Every observation of a drive through a fresh `AdaptiveRunner`, in stream order.

    The drive and waypoints are moved to a local frame first (`fpe_jax.drive.local_frame`), as
    the JAX commands do, and the predictions back to the map frame.

    Args:
        drive: a `fpe_jax.drive.Drive`.
        waypoints_xy_m: (K, 2) waypoints [m] in the drive's frame.
        config: a checked config dict to start from, or None; kw: as `AdaptiveRunner` takes.

    Returns:
        (the runner after the drive, with what it learned (its waypoints in the local frame,
        which `state_config` hashes alike: `waypoints_sha256` is frame-free),
        (N, H, 3) predictions x [m], y [m], yaw [rad] in the drive's frame).
    """
    from fpe_jax.drive import local_frame

    local, wp, _, origin = local_frame(drive, waypoints_xy_m)
    runner = AdaptiveRunner(config, wp, **kw)
    rows = zip(local.t_s.tolist(), local.xy_m.tolist(), local.yaw_rad.tolist())
    poses = np.stack([runner.update(t, x, y, a) for t, (x, y), a in rows])
    poses[..., :2] += origin
    return runner, poses
