"""The fitting loss of `fpe_jax.fit` ported to NumPy, for the SciPy baseline of `make bench`.

Same model (position blend of a linear and a pure-pursuit kinematic-bicycle rollout, delay
step, speed shrinkage), same Huber-scaled masked residuals and the same ridge on the raw values,
vectorised over samples with NumPy. No autodiff: SciPy's L-BFGS-B differentiates it by finite
differences. run.py reports how closely it reproduces the JAX loss (evaluated at the JAX
solution). Benchmark code only; the position blend only.
"""

from __future__ import annotations

import numpy as np


def _softplus(x):
    return np.logaddexp(0.0, x)


def _sigmoid(x):
    return 0.5 * (1.0 + np.tanh(0.5 * x))


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def constrain(raw: dict, min_lookahead_m: float) -> dict:
    """Physical values from raw ones, as `fpe_jax.params.constrain`."""
    return {
        "lookahead_m": min_lookahead_m + _softplus(raw["lookahead_m"]),
        "lookahead_gain_s": _softplus(raw["lookahead_gain_s"]),
        "weights": _sigmoid(raw["weights"]),
        "delay_s": _softplus(raw["delay_s"]),
        "speed_weight": _sigmoid(raw["speed_weight"]),
        "speed_mps": _softplus(raw["speed_mps"]),
    }


class NumpyTrack:
    """`fpe_jax.track.Track`'s arc-length queries on NumPy arrays (vectorised over cars)."""

    def __init__(self, track):
        self.seg = np.asarray(track.seg_m, dtype=np.float64)  # (M, 8), see Track.seg_m
        self.ds = float(track.ds_m)
        self.length = float(track.length_m)
        self.closed = bool(track.closed)
        self.m = len(self.seg)

    def locate(self, s):
        if self.closed:
            u = s / self.ds
            u_floor = np.floor(u)
            return u_floor.astype(np.int64) % self.m, u - u_floor
        u = np.clip(s, 0.0, self.length) / self.ds
        i = np.clip(np.floor(u).astype(np.int64), 0, self.m - 2)
        return i, u - i

    def point_at(self, s):
        i, f = self.locate(s)
        row = self.seg[i]
        return row[:, :2] + f[:, None] * row[:, 2:4]

    def project_local(self, x, y, s, iters=2):
        for _ in range(iters):
            i, f = self.locate(s)
            r = self.seg[i].T
            g = 1.0 - f
            s = (
                s
                + (x - r[0] - f * r[2]) * (g * r[4] + f * r[6])
                + (y - r[1] - f * r[3]) * (g * r[5] + f * r[7])
            )
        return s


def predict_blend(phys: dict, states: dict, track: NumpyTrack, settings) -> np.ndarray:
    """(N, H, 3) poses of the position blend for N states (dict of (N,) arrays)."""
    h, dt, wb = settings.horizon, settings.dt_s, settings.wheelbase_m
    w_v = phys["speed_weight"]
    v = w_v * states["v_mps"] + (1.0 - w_v) * phys["speed_mps"]
    times = np.concatenate([[phys["delay_s"]], np.full(h, dt)])
    x, y, yaw = states["x_m"].copy(), states["y_m"].copy(), states["yaw_rad"].copy()
    s = track.project_local(x, y, states["s_m"])
    ahead = phys["lookahead_m"] + phys["lookahead_gain_s"] * v
    out = np.empty((len(x), h + 1, 3))
    for k, step in enumerate(times):
        s = track.project_local(x, y, s)
        goal = track.point_at(s + ahead)
        dx, dy = goal[:, 0] - x, goal[:, 1] - y
        tan_steer = 2.0 * wb * (np.cos(yaw) * dy - np.sin(yaw) * dx) / (dx * dx + dy * dy + 1e-12)
        lim = np.tan(settings.max_steer_rad)
        dyaw = v / wb * np.clip(tan_steer, -lim, lim) * step
        mid = yaw + 0.5 * dyaw
        x = x + v * step * np.cos(mid)
        y = y + v * step * np.sin(mid)
        yaw = yaw + dyaw
        out[:, k] = np.stack([x, y, yaw], axis=1)
    pp = out[:, 1:]
    pp[..., 2] = _wrap(pp[..., 2])
    t = np.cumsum(times)[1:]
    y0 = states["yaw_rad"]
    lin_x = states["x_m"][:, None] + v[:, None] * t * np.cos(y0)[:, None]
    lin_y = states["y_m"][:, None] + v[:, None] * t * np.sin(y0)[:, None]
    w = phys["weights"]
    px = w * lin_x + (1.0 - w) * pp[..., 0]
    py = w * lin_y + (1.0 - w) * pp[..., 1]
    pyaw = _wrap(y0[:, None] + (1.0 - w) * _wrap(pp[..., 2] - y0[:, None]))
    return np.stack([px, py, pyaw], axis=-1)


def _huber_scale(e, delta):
    safe = np.maximum(e, delta)
    return np.where(e <= delta, 1.0, np.sqrt(delta * (2.0 * safe - delta)) / safe)


class NumpyLoss:
    """loss(raw_free_vector) = 0.5 * sum(residuals^2), as the JAX fit's objective.

    Args:
        groups: list of (states dict of (N,) arrays, NumpyTrack, targets (N, H, 2), mask (N, H)).
        raw: dict field -> raw value (NumPy) for every Params field (the starting point).
        free: the fitted field names (the rest stay at their raw value).
        settings: the Params' static Settings; huber_m, ridge: as in fpe_jax.fit.
        weight_smoothing_m2: the smoothness prior on neighbouring weights, per target, as
            fpe_jax.fit.WEIGHT_SMOOTHING_M2 (0: none).
    """

    def __init__(
        self,
        groups,
        raw: dict,
        free,
        settings,
        huber_m: float,
        ridge: float,
        weight_smoothing_m2=0.0,
    ):
        self.groups, self.settings = groups, settings
        self.huber_m, self.ridge = huber_m, ridge
        n_targets = sum(float(np.sum(mask)) for _, _, _, mask in groups)
        self.smoothing = weight_smoothing_m2 * n_targets
        self.raw = {k: np.asarray(v, dtype=np.float64) for k, v in raw.items()}
        self.free = [f for f in raw if f in set(free)]
        self.n_evals = 0

    def x0(self) -> np.ndarray:
        return np.concatenate([np.ravel(self.raw[f]) for f in self.free])

    def unpack(self, vec: np.ndarray) -> dict:
        raw, k = dict(self.raw), 0
        for f in self.free:
            size = self.raw[f].size
            raw[f] = vec[k : k + size].reshape(self.raw[f].shape)
            k += size
        return raw

    def __call__(self, vec: np.ndarray) -> float:
        self.n_evals += 1
        phys = constrain(self.unpack(vec), self.settings.min_lookahead_m)
        total = self.smoothing * np.sum(np.diff(phys["weights"]) ** 2)
        for states, track, target, mask in self.groups:
            pred = predict_blend(phys, states, track, self.settings)[..., :2]
            d = pred - target
            e = np.sqrt(np.sum(d * d, axis=-1) + 1e-12)
            r = np.where(mask[..., None], d * _huber_scale(e, self.huber_m)[..., None], 0.0)
            total += np.sum(r * r)
        total += self.ridge * np.sum(vec * vec)
        return 0.5 * total
