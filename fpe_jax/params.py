"""`Params` (fitted physical values, arrays) and `Settings` (static), presets, reparametrisation.

Params holds physical values users read (`lookahead_m`, `weights`, ...). The fitter works on
unconstrained raw values: `unconstrain(params)` and `constrain(raw)` map between the two, so
every fitted value stays in its valid range without clipping (lookahead >= min_lookahead_m,
gain >= 0, weights and speed_weight in [0, 1], delay >= 0, speed_mps >= 0).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from fpe_jax.spec import BLEND_MODES as BLEND_MODES  # re-exported for users of params
from fpe_jax.spec import MODELS as MODELS
from fpe_jax.spec import check_settings


@dataclasses.dataclass(frozen=True)
class Settings:
    """Static settings: never traced, changing one recompiles.

    Attributes:
        dt_s: prediction step [s].
        horizon: number of steps H.
        wheelbase_m: kinematic-bicycle wheelbase [m].
        max_steer_rad: steering limit [rad].
        blend: "position" (blend the linear and pure-pursuit rollouts' positions per step) or
            "heading" (one rollout whose turn is scaled by 1 - w per step, as the original did).
        model: "blend" (linear / pure pursuit / their blend), "seed" (the original node's exact
            discrete rules), "cv" (constant velocity vector from the history), "ctrv"
            (constant turn rate and velocity).
        min_lookahead_m: lower bound of the lookahead distance [m].
        history: number of distinct recent observations the state estimator uses.
    """

    dt_s: float = 0.1
    horizon: int = 10
    wheelbase_m: float = 0.325
    max_steer_rad: float = 0.4189
    blend: str = "position"
    model: str = "blend"
    min_lookahead_m: float = 0.3
    history: int = 10

    def __post_init__(self):
        # the rules of fpe_jax.spec (an InputError, i.e. a ValueError, naming the field)
        check_settings(dataclasses.asdict(self), "Settings")


class Params(eqx.Module):
    """Physical predictor parameters (array fields) plus their static `settings`.

    Attributes:
        lookahead_m: () pure-pursuit lookahead distance at zero speed [m].
        lookahead_gain_s: () lookahead growth with speed [s]: L = lookahead_m + gain * v.
        weights: (H,) per-step blend weight in [0, 1]; 1 = linear, 0 = pure pursuit.
        delay_s: () observation delay offset [s] >= 0: the state is advanced by it first.
        speed_weight: () trust in the measured speed in [0, 1]: the rollouts drive at
            v = speed_weight * v_measured + (1 - speed_weight) * speed_mps (a noisy sensor's
            speed is best shrunk toward a typical speed; 0 is the original's hard-coded speed).
        speed_mps: () the typical speed the measured one is shrunk toward [m/s].
        settings: static `Settings`.
    """

    lookahead_m: Float[Array, ""]
    lookahead_gain_s: Float[Array, ""]
    weights: Float[Array, " H"]
    delay_s: Float[Array, ""]
    speed_weight: Float[Array, ""]
    speed_mps: Float[Array, ""]
    settings: Settings = eqx.field(static=True)

    @classmethod
    def create(
        cls,
        settings: Settings | None = None,
        *,
        lookahead_m=1.5,
        lookahead_gain_s=0.0,
        weights=0.5,
        delay_s=0.0,
        speed_weight=1.0,
        speed_mps=1.0,
    ) -> Params:
        """Params from plain numbers; a scalar `weights` is broadcast to all H steps."""
        settings = settings or Settings()
        w = jnp.broadcast_to(jnp.asarray(weights, dtype=float), (settings.horizon,))
        return cls(
            lookahead_m=jnp.asarray(lookahead_m, dtype=float),
            lookahead_gain_s=jnp.asarray(lookahead_gain_s, dtype=float),
            weights=w,
            delay_s=jnp.asarray(delay_s, dtype=float),
            speed_weight=jnp.asarray(speed_weight, dtype=float),
            speed_mps=jnp.asarray(speed_mps, dtype=float),
            settings=settings,
        )

    def physical(self) -> dict:
        """The values as plain Python numbers / lists (for configs and reports)."""
        return {
            "lookahead_m": float(self.lookahead_m),
            "lookahead_gain_s": float(self.lookahead_gain_s),
            "weights": [float(w) for w in np.asarray(self.weights)],
            "delay_s": float(self.delay_s),
            "speed_weight": float(self.speed_weight),
            "speed_mps": float(self.speed_mps),
        }


# ---- reparametrisation -------------------------------------------------------------------------

_RAW_EPS = 1e-6  # keeps the inverse maps finite at the bounds (w = 0 or 1, delay = 0)


def _inv_softplus(y):
    y = jnp.maximum(y, _RAW_EPS)
    return y + jnp.log(-jnp.expm1(-y))


def _logit(p):
    p = jnp.clip(p, _RAW_EPS, 1 - _RAW_EPS)
    return jnp.log(p) - jnp.log1p(-p)


def unconstrain(params: Params) -> Params:
    """Raw, unconstrained values (same pytree structure) for the fitter."""
    s = params.settings
    return dataclasses.replace(
        params,
        lookahead_m=_inv_softplus(params.lookahead_m - s.min_lookahead_m),
        lookahead_gain_s=_inv_softplus(params.lookahead_gain_s),
        weights=_logit(params.weights),
        delay_s=_inv_softplus(params.delay_s),
        speed_weight=_logit(params.speed_weight),
        speed_mps=_inv_softplus(params.speed_mps),
    )


def constrain(raw: Params) -> Params:
    """Physical values from raw ones: the inverse of `unconstrain`, smooth everywhere."""
    s = raw.settings
    return dataclasses.replace(
        raw,
        lookahead_m=s.min_lookahead_m + jax.nn.softplus(raw.lookahead_m),
        lookahead_gain_s=jax.nn.softplus(raw.lookahead_gain_s),
        weights=jax.nn.sigmoid(raw.weights),
        delay_s=jax.nn.softplus(raw.delay_s),
        speed_weight=jax.nn.sigmoid(raw.speed_weight),
        speed_mps=jax.nn.softplus(raw.speed_mps),
    )


# ---- presets -----------------------------------------------------------------------------------


def _seed(speed_weight: float) -> Params:
    settings = Settings(max_steer_rad=0.5236, blend="heading", model="seed")
    w = 0.7 ** np.arange(settings.horizon)
    return Params.create(settings, lookahead_m=2.0, weights=w, speed_weight=speed_weight)


_PRESET_BUILDERS = {
    "seed": lambda: _seed(0.0),
    "seed-measured-speed": lambda: _seed(1.0),
    "linear": lambda: Params.create(Settings(), weights=1.0),
    "pure-pursuit": lambda: Params.create(Settings(), lookahead_m=2.0, weights=0.0),
    "constant-velocity": lambda: Params.create(Settings(model="cv"), weights=1.0),
    "ctrv": lambda: Params.create(Settings(model="ctrv"), weights=1.0),
    "default": lambda: Params.create(
        Settings(),
        lookahead_m=1.0,
        lookahead_gain_s=0.2,
        weights=0.5,
        delay_s=0.1,
        speed_weight=0.9,
        speed_mps=2.0,
    ),
}

PRESET_DOCS = {
    "seed": "the original 2019 node exactly: 1 m/s, 2 m lookahead, reverse goal scan, 0.7^i",
    "seed-measured-speed": "the original node's rules with the measured speed",
    "linear": "constant speed along the current heading (thesis approach 2)",
    "pure-pursuit": "kinematic bicycle following the path, 2 m lookahead (approach 3)",
    "constant-velocity": "constant velocity vector from the recent history (approach 1)",
    "ctrv": "constant turn rate and velocity",
    "default": "the differentiable position blend; the fitter's starting point",
}


class _Presets(Mapping):
    """Read-only mapping name -> Params, built on access (so arrays get the current dtype)."""

    def __getitem__(self, name: str) -> Params:
        if name not in _PRESET_BUILDERS:
            raise KeyError(f"unknown preset {name!r}; presets: {', '.join(_PRESET_BUILDERS)}")
        return _PRESET_BUILDERS[name]()

    def __iter__(self) -> Iterator[str]:
        return iter(_PRESET_BUILDERS)

    def __len__(self) -> int:
        return len(_PRESET_BUILDERS)


presets: Mapping[str, Params] = _Presets()
