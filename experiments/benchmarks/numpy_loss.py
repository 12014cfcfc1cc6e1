"""The fitting loss of `fpe_jax.fit` in NumPy, for the SciPy baseline of `make bench`.

The model is the on-car runner's (`fpe_jax.runner.Runner.predict_from_state`, vectorised over
samples: the one NumPy copy of the blend model); the raw -> physical map is `fpe_jax.params`'
own `constrain` (compiled). This file adds only the objective: the same Huber-scaled masked
residuals, smoothness prior on the weights and ridge on the raw values as the JAX fit. No
autodiff: SciPy's L-BFGS-B differentiates it by finite differences. run.py reports how closely
it reproduces the JAX loss (evaluated at the JAX solution). Benchmark code only; blend model only.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np

from fpe_jax.params import Params, constrain


def _huber_scale(e, delta):
    safe = np.maximum(e, delta)
    return np.where(e <= delta, 1.0, np.sqrt(delta * (2.0 * safe - delta)) / safe)


class NumpyLoss:
    """loss(raw_free_vector) = 0.5 * sum(residuals^2), as the JAX fit's objective.

    Args:
        groups: list of (states dict of (N,) float64 arrays x_m, y_m, yaw_rad, v_mps, s_m,
            `fpe_jax.runner.Runner` of the blend model on the drive's track, targets (N, H, 2)
            [m], mask (N, H)).
        raw: the starting point's raw values (`fpe_jax.params.unconstrain`).
        free: the fitted field names (the rest stay at their raw value).
        huber_m, ridge: as in fpe_jax.fit (HUBER_M, RAW_RIDGE).
        weight_smoothing_m2: the smoothness prior on neighbouring weights, per target, as
            fpe_jax.fit.WEIGHT_SMOOTHING_M2 (0: none).
    """

    def __init__(
        self, groups, raw: Params, free, huber_m: float, ridge: float, weight_smoothing_m2=0.0
    ):
        self.groups = groups
        self.huber_m, self.ridge = huber_m, ridge
        n_targets = sum(float(np.sum(mask)) for _, _, _, mask in groups)
        self.smoothing = weight_smoothing_m2 * n_targets
        self.raw = raw
        self.free = [f.name for f in dataclasses.fields(raw) if f.name in set(free)]
        self.n_evals = 0
        # one compiled call and one transfer per evaluation: eager JAX ops would cost more than
        # the NumPy model on a short drive
        self._constrain = jax.jit(lambda vec: constrain(self.unpack(vec)))

    def x0(self) -> np.ndarray:
        return np.concatenate([np.ravel(getattr(self.raw, f)) for f in self.free])

    def unpack(self, vec: np.ndarray) -> Params:
        values, k = {}, 0
        for f in self.free:
            shape = np.shape(getattr(self.raw, f))
            size = int(np.prod(shape))
            values[f] = vec[k : k + size].reshape(shape)
            k += size
        return dataclasses.replace(self.raw, **values)

    def __call__(self, vec: np.ndarray) -> float:
        self.n_evals += 1
        phys = jax.device_get(self._constrain(vec)).physical()
        total = self.smoothing * np.sum(np.diff(phys["weights"]) ** 2)
        for st, runner, target, mask in self.groups:
            model = runner.with_params(phys)
            pred = model.predict_from_state(
                st["x_m"], st["y_m"], st["yaw_rad"], st["v_mps"], st["s_m"]
            )
            d = pred[..., :2] - target
            e = np.sqrt(np.sum(d * d, axis=-1) + 1e-12)
            r = np.where(mask[..., None], d * _huber_scale(e, self.huber_m)[..., None], 0.0)
            total += np.sum(r * r)
        total += self.ridge * np.sum(vec * vec)
        return 0.5 * total
