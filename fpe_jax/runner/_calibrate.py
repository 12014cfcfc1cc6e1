"""Online calibration of the prediction ellipses from the runner's own realised errors.

A config's ellipses (`uncertainty.cov_m2`, per step, in the along-/cross-track frame) are fitted
on the fit drive's residuals; on the road the errors can be larger or smaller (a driver whose
circle wanders, a line learned on other laps). `EllipseCalibration` keeps each step's ellipse at
the size the car's own errors show: the runner records its predictions, and when a later
filtered observation shows where the car was at a predicted time, that prediction's error at
that lead time is realised. Per step h and axis a (along, cross) the calibration keeps a
running mean of the squared error normalised by the config's variance there,
z = r_a^2 / cov_m2[h][a][a], and scales the variance on that axis by it (the correlation kept):

    S_h <- decay S_h + z,  W_h <- decay W_h + 1          (per realised error of step h)
    scale_h = (S_h + n0 scale_{h-1}) / (W_h + n0),  scale_0 = 1

so that a step with few realised errors leans on the step before it (n0 = `prior_samples`
pseudo-errors: long lead times realise last), and old errors fade by `decay` per newer one.
The mean of z is what a variance states (as the offline ellipses are second moments of the
residuals), per axis because the along- and cross-track errors change apart (on a wandering
circle the cross-track error grew 4-fold where the along-track error did not).

What a calibrated ellipse means: `covariance()` is, per step, the second moment of the recent
realised errors at that step (against the filtered estimate of where the car was), along and
across the track, with the config's correlation. Its 1- and 2-sigma ellipses hold 39.3 % and
86.5 % of the errors only where these are Gaussian; heavier-tailed errors (most small, a few
large) put more inside 1 sigma and fewer inside 2 sigma, and one scale per step and axis then
matches both barely if at all. On the real 1:10 drives the pooled coverage is 60.1 % / 82.2 %;
the other online rules measured there (a clipped mean, matching the coverage itself, a local
level of the recent errors, a variance growing with the car's speed deviation from its learned
profile) miss 2 sigma by more when the runner starts at the held-out part; started at the
recording's start the last one holds 43.7 % / 81.8 %, the mean 54.1 % / 84.2 %
(experiments/results/real_drives_calibration.md).

- Which time an observation shows: a detection stamped t shows the car at t - delay (the
  prediction's own delay step), so it realises each recorded prediction's step h = round(u),
  u = (t - delay - t0) / dt, once (the first observation that falls there), against the
  prediction interpolated at u.
- Bounded work: a prediction is recorded at most every dt / 2 and dropped once its last step
  has passed, so at most 2 (H + delay / dt) + 4 are held, each realised in O(1) per
  observation, and the scales cost O(H) per observation.

Imports no JAX (the car's computer may have none).
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from fpe_jax.errors import InputError

CALIBRATION_DECAY = 0.98  # weight of a realised error per newer one of its step (~50 errors)
PRIOR_SAMPLES = 5.0  # pseudo-errors at the previous step's scale


class EllipseCalibration:
    """Per-step, per-axis scales of a config's track-frame ellipses, from realised errors.

    Attributes:
        scale: (H, 2) the variance scale along and across the track per step.
        weights: (H,) the decayed number of realised errors per step (W_h).
        errors: the number of errors realised so far.
    """

    def __init__(
        self,
        cov_track_m2,
        dt_s: float,
        delay_s: float,
        *,
        decay: float = CALIBRATION_DECAY,
        prior_samples: float = PRIOR_SAMPLES,
        source: str = "config",
    ):
        """Args:
        cov_track_m2: (H, 2, 2) the ellipses to calibrate, along-/cross-track [m^2] per step
            (a config's `uncertainty.cov_m2`); both variances positive.
        dt_s: the prediction step [s]; delay_s: the detection delay [s] (the config's).
        decay: weight of a realised error per newer one of its step, in (0, 1].
        prior_samples: n0 > 0, the weight of the step before's scale.
        source: names the config in errors.
        """
        base = np.asarray(cov_track_m2, dtype=np.float64)
        if base.ndim != 3 or base.shape[1:] != (2, 2) or len(base) == 0:
            raise InputError(source, f"uncertainty.cov_m2 has shape {base.shape}", "(H, 2, 2)")
        var = np.stack([base[:, 0, 0], base[:, 1, 1]], axis=-1)
        if not np.all(np.isfinite(var) & (var > 0.0)):
            raise InputError(
                source,
                "uncertainty.cov_m2 has a zero variance",
                "positive along- and cross-track variances at every step, to calibrate",
            )
        if not 0.0 < decay <= 1.0:
            raise InputError("calibration decay", f"{decay!r}", "a number in (0, 1]")
        if not prior_samples > 0.0:
            raise InputError("calibration prior_samples", f"{prior_samples!r}", "a positive number")
        self.base = base
        self.horizon = len(base)
        self.dt_s, self.delay_s = float(dt_s), float(delay_s)
        self.decay, self.prior_samples = float(decay), float(prior_samples)
        self._var = var.tolist()
        self._sums = [[0.0, 0.0] for _ in range(self.horizon)]
        self.weights = np.zeros(self.horizon)
        self.scale = np.ones((self.horizon, 2))
        self.errors = 0
        cap = 2 * (self.horizon + math.ceil(max(self.delay_s, 0.0) / self.dt_s)) + 4
        # recorded predictions: [stamp, xs, ys, cos, sin of the path heading per step, the
        # last step realised]
        self._pending: deque = deque(maxlen=cap)
        self._last_recorded = -math.inf

    def reset(self) -> None:
        """Forget the predictions not yet realised (a new drive, or a restarted clock); the
        scales stay."""
        self._pending.clear()
        self._last_recorded = -math.inf

    def record(self, stamp_s: float, xy_m, heading_rad) -> bool:
        """Hold a prediction made at stamp_s [s]: xy_m (H, 2) [m] at stamp + h dt, and the path
        heading (H,) [rad] at each step (the ellipses' frame). Not within dt / 2 of the
        previous one (returns False then)."""
        t = float(stamp_s)
        if t - self._last_recorded < 0.5 * self.dt_s:
            return False
        xy = np.asarray(xy_m, dtype=np.float64)
        h = np.asarray(heading_rad, dtype=np.float64)
        row = [t, xy[:, 0].tolist(), xy[:, 1].tolist(), np.cos(h).tolist(), np.sin(h).tolist(), 0]
        self._pending.append(row)
        self._last_recorded = t
        return True

    def observe(self, stamp_s: float, x_m: float, y_m: float) -> int:
        """Realise the recorded predictions' errors against where a filtered observation stamped
        stamp_s [s] shows the car (x_m, y_m [m], at stamp - delay); returns how many."""
        when = float(stamp_s) - self.delay_s
        n_steps, dt = self.horizon, self.dt_s
        kept, done = deque(maxlen=self._pending.maxlen), 0
        for row in self._pending:
            t0, xs, ys, cs, sn, last = row
            u = (when - t0) / dt
            h = math.floor(u + 0.5)
            if h > n_steps:  # every step has passed
                continue
            kept.append(row)
            if h < 1 or h <= last:
                continue
            row[5] = h
            lo = math.floor(u)
            if lo < 1:
                px, py = xs[0], ys[0]
            elif lo >= n_steps:
                px, py = xs[-1], ys[-1]
            else:  # between steps lo and lo + 1
                f = u - lo
                px = xs[lo - 1] + f * (xs[lo] - xs[lo - 1])
                py = ys[lo - 1] + f * (ys[lo] - ys[lo - 1])
            rx, ry = float(x_m) - px, float(y_m) - py
            c, s = cs[h - 1], sn[h - 1]
            along, cross = c * rx + s * ry, -s * rx + c * ry
            var, sums = self._var[h - 1], self._sums[h - 1]
            sums[0] = self.decay * sums[0] + along * along / var[0]
            sums[1] = self.decay * sums[1] + cross * cross / var[1]
            self.weights[h - 1] = self.decay * self.weights[h - 1] + 1.0
            done += 1
        self._pending = kept
        if done:
            self.errors += done
            self._refresh()
        return done

    def _refresh(self) -> None:
        n0 = self.prior_samples
        prev = (1.0, 1.0)
        for h in range(self.horizon):
            w, (sa, sc) = self.weights[h], self._sums[h]
            prev = ((sa + n0 * prev[0]) / (w + n0), (sc + n0 * prev[1]) / (w + n0))
            self.scale[h] = prev

    def covariance(self) -> np.ndarray:
        """(H, 2, 2) the calibrated track-frame covariance [m^2]: each step's variances scaled,
        their correlation kept."""
        root = np.sqrt(self.scale)
        return self.base * root[:, :, None] * root[:, None, :]

    def state(self) -> dict:
        """What the calibration has learned, for a saved state's provenance."""
        return {
            "scale": self.scale.tolist(),
            "weights": self.weights.tolist(),
            "errors": self.errors,
            "decay": self.decay,
            "prior_samples": self.prior_samples,
        }
