"""`Params` (fitted physical values, arrays) and `Settings` (static), presets, reparametrisation.

Params holds physical values users read (`lookahead_m`, `weights`, ...). The fitter works on
unconstrained raw values: `unconstrain(params)` and `constrain(raw)` map between the two, so
every fitted value stays in its valid range without clipping (lookahead >= min_lookahead_m,
gain >= 0, weights and speed_weight in [0, 1], delay, speed_mps and pace_return_1ps >= 0, time
constants >= MIN_TAU_S, the filter's noise values >= MIN_FILTER_NOISE and its gate >=
MIN_GATE_SIGMA).
The learned line's profile arrays are never fitted by the solver (they are learned from the fit
drives first, `fpe_jax.model`) and pass through both maps unchanged.
"""

from __future__ import annotations

import dataclasses
import typing
from collections.abc import Iterator, Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from fpe_jax.compile import _aot as aot
from fpe_jax.compile._arrays import device_array
from fpe_jax.spec import BLEND_MODES as BLEND_MODES  # re-exported for users of params
from fpe_jax.spec import (
    DEFAULT_ESTIMATOR,
    FILTER_DEFAULTS,
    MIN_FILTER_NOISE,
    MIN_GATE_SIGMA,
    check_settings,
)
from fpe_jax.spec import ESTIMATORS as ESTIMATORS
from fpe_jax.spec import LINE_KEYS as LINE_KEYS
from fpe_jax.spec import MIN_TAU_S as MIN_TAU_S
from fpe_jax.spec import MODELS as MODELS
from fpe_jax.spec import USER_SETTINGS as USER_SETTINGS


# the spec's rules check the values (accepting any real number for a float field, NumPy scalars
# included) and name the field: a runtime type checker must not pre-empt them with its own
@typing.no_type_check
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
            (constant turn rate and velocity), "frenet" (along-track speed held, lateral offset
            from the path decaying with `offset_tau_s`), "line" (the Frenet rollout on the
            opponent's learned line with its speed profile; the fitted default).
        min_lookahead_m: lower bound of the lookahead distance [m].
        history: number of distinct recent observations the state estimator uses.
        estimator: the frenet and line models' track-frame state: "kalman" (a Kalman filter
            over the history window, `fpe_jax.model`; its noise values are fitted) or
            "theil-sen" (robust lines through the window, `estimate.track_frame_lines`).
    """

    dt_s: float = 0.1
    horizon: int = 10
    wheelbase_m: float = 0.325
    max_steer_rad: float = 0.4189
    blend: str = "position"
    model: str = "blend"
    min_lookahead_m: float = 0.3
    history: int = 10
    estimator: str = DEFAULT_ESTIMATOR

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
        offset_tau_s: () frenet / line models: time constant [s] of the lateral offset's decay
            from the car's current offset to the line (the centerline for "frenet").
        speed_tau_s: () line model: time constant [s] with which the speed profile's shape
            v(s') / v(s_now) is blended into the car's current along-track speed.
        pace_return_1ps: () line model: rate [1/s] at which the car's own pace (its speed
            relative to the speed profile's at the same place) returns to the profile's: the
            share of its own pace left after t seconds is exp(-rate t). 0 keeps its pace over
            the whole horizon (configs written before this value read 0).
        position_smoothing: () frenet / line models, in [0, 1]: where the rollout starts
            along and across the track: 0 = the newest observation's projection, 1 = the
            track-frame estimate at the newest stamp (the Kalman filter's, or the Theil-Sen
            lines' `estimate.track_frame_lines`), linear between. The speed is the estimate's
            either way. (On the real Levine lap, whose targets are later detections with the
            same tag's errors, the fit chose 0; on simulated drives scored against the truth
            0.6-0.9.)
        filter_accel_mps2: () Kalman estimator: along-track acceleration noise [m/s^2] (the
            rms acceleration, constant over each interval between observations).
        filter_lat_accel_mps2: () Kalman estimator: lateral acceleration noise [m/s^2].
        filter_obs_m: () Kalman estimator: observation noise [m] (one sigma, along and across).
        filter_gate_sigma: () Kalman estimator: innovation gate [sigma] (>= 1): an observation
            farther than this (Mahalanobis distance) from the prediction has its gain faded
            out smoothly (an outlier does not move the state).
        line_offset_m: (P,) line model: the learned line's lateral offset from the centerline
            [m] on P points spread evenly over the track's arc length (left positive); (0,)
            for every other model.
        line_speed_mps: (P,) line model: along-track speed profile [m/s] on the same points.
        line_coverage: (P,) line model: in [0, 1], how well the fit drives covered each point;
            where 0 the profile is a prior from the track's curvature (`fpe_jax.model`) and the
            rollout keeps the car's own offset from it (slowly decaying), following only its
            change.
        settings: static `Settings`.
    """

    lookahead_m: Float[Array, "*sets"]
    lookahead_gain_s: Float[Array, "*sets"]
    weights: Float[Array, "*sets H"]
    delay_s: Float[Array, "*sets"]
    speed_weight: Float[Array, "*sets"]
    speed_mps: Float[Array, "*sets"]
    offset_tau_s: Float[Array, "*sets"]
    speed_tau_s: Float[Array, "*sets"]
    pace_return_1ps: Float[Array, "*sets"]
    position_smoothing: Float[Array, "*sets"]
    filter_accel_mps2: Float[Array, "*sets"]
    filter_lat_accel_mps2: Float[Array, "*sets"]
    filter_obs_m: Float[Array, "*sets"]
    filter_gate_sigma: Float[Array, "*sets"]
    line_offset_m: Float[Array, "*sets P"]
    line_speed_mps: Float[Array, "*sets P"]
    line_coverage: Float[Array, "*sets P"]
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
        offset_tau_s=1.0,
        speed_tau_s=0.5,
        pace_return_1ps=0.0,
        position_smoothing=0.0,
        filter_accel_mps2=FILTER_DEFAULTS["filter_accel_mps2"],
        filter_lat_accel_mps2=FILTER_DEFAULTS["filter_lat_accel_mps2"],
        filter_obs_m=FILTER_DEFAULTS["filter_obs_m"],
        filter_gate_sigma=FILTER_DEFAULTS["filter_gate_sigma"],
        line_offset_m=(),
        line_speed_mps=(),
        line_coverage=(),
    ) -> Params:
        """Params from plain numbers; a scalar `weights` is broadcast to all H steps."""
        settings = settings or Settings()
        if isinstance(weights, jax.Array):
            w = jnp.broadcast_to(jnp.asarray(weights, dtype=float), (settings.horizon,))
        else:
            w = device_array(np.broadcast_to(np.asarray(weights, float), (settings.horizon,)))
        profiles = (line_offset_m, line_speed_mps, line_coverage)
        line = [device_array(a, dtype=float).reshape(-1) for a in profiles]
        if len({a.shape for a in line}) != 1:
            raise ValueError("Params: line_offset_m, line_speed_mps, line_coverage differ in size")
        if (settings.model == "line") != (line[0].shape[0] > 0):
            raise ValueError("Params: the line model needs a line profile, other models none")
        return cls(
            lookahead_m=device_array(lookahead_m, dtype=float),
            lookahead_gain_s=device_array(lookahead_gain_s, dtype=float),
            weights=w,
            delay_s=device_array(delay_s, dtype=float),
            speed_weight=device_array(speed_weight, dtype=float),
            speed_mps=device_array(speed_mps, dtype=float),
            offset_tau_s=device_array(offset_tau_s, dtype=float),
            speed_tau_s=device_array(speed_tau_s, dtype=float),
            pace_return_1ps=device_array(pace_return_1ps, dtype=float),
            position_smoothing=device_array(position_smoothing, dtype=float),
            filter_accel_mps2=device_array(filter_accel_mps2, dtype=float),
            filter_lat_accel_mps2=device_array(filter_lat_accel_mps2, dtype=float),
            filter_obs_m=device_array(filter_obs_m, dtype=float),
            filter_gate_sigma=device_array(filter_gate_sigma, dtype=float),
            line_offset_m=line[0],
            line_speed_mps=line[1],
            line_coverage=line[2],
            settings=settings,
        )

    def physical(self) -> dict:
        """The values as plain Python numbers / lists (for configs and reports); the line
        profile only for the line model."""
        out = {
            "lookahead_m": float(self.lookahead_m),
            "lookahead_gain_s": float(self.lookahead_gain_s),
            "weights": [float(w) for w in np.asarray(self.weights)],
            "delay_s": float(self.delay_s),
            "speed_weight": float(self.speed_weight),
            "speed_mps": float(self.speed_mps),
            "offset_tau_s": float(self.offset_tau_s),
            "speed_tau_s": float(self.speed_tau_s),
            "pace_return_1ps": float(self.pace_return_1ps),
            "position_smoothing": float(self.position_smoothing),
            "filter_accel_mps2": float(self.filter_accel_mps2),
            "filter_lat_accel_mps2": float(self.filter_lat_accel_mps2),
            "filter_obs_m": float(self.filter_obs_m),
            "filter_gate_sigma": float(self.filter_gate_sigma),
        }
        if self.settings.model == "line":
            for key in LINE_KEYS:
                out[key] = [float(v) for v in np.asarray(getattr(self, key))]
        return out


def with_settings(params: Params, **changes) -> Params:
    """params with some `USER_SETTINGS` changed (Settings checks them: ValueError).

    On a new step or horizon the per-step weights are read off as a function of lead time
    (linear interpolation of the old weights at h * dt_s, held beyond the old horizon), so a
    preset's blend means the same at the same time ahead.
    """
    unknown = set(changes) - set(USER_SETTINGS)
    if unknown:
        raise ValueError(f"Settings: unknown {sorted(unknown)}; expected {USER_SETTINGS}")
    old = params.settings
    new = dataclasses.replace(old, **changes)
    weights = params.weights
    if (new.horizon, new.dt_s) != (old.horizon, old.dt_s):
        t_old = np.arange(1, old.horizon + 1) * old.dt_s
        t_new = np.arange(1, new.horizon + 1) * new.dt_s
        w = np.interp(t_new, t_old, np.asarray(weights))
        weights = jnp.asarray(w, dtype=weights.dtype)
    return dataclasses.replace(params, weights=weights, settings=new)


# ---- reparametrisation -------------------------------------------------------------------------

_RAW_EPS = 1e-6  # keeps the inverse maps finite at the bounds (w = 0 or 1, delay = 0)


def _inv_softplus(y):
    y = jnp.maximum(y, _RAW_EPS)
    return y + jnp.log(-jnp.expm1(-y))


def _logit(p):
    p = jnp.clip(p, _RAW_EPS, 1 - _RAW_EPS)
    return jnp.log(p) - jnp.log1p(-p)


@aot.jit  # eagerly, nine small XLA programs: one executable instead
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
        offset_tau_s=_inv_softplus(params.offset_tau_s - MIN_TAU_S),
        speed_tau_s=_inv_softplus(params.speed_tau_s - MIN_TAU_S),
        pace_return_1ps=_inv_softplus(params.pace_return_1ps),
        position_smoothing=_logit(params.position_smoothing),
        filter_accel_mps2=_inv_softplus(params.filter_accel_mps2 - MIN_FILTER_NOISE),
        filter_lat_accel_mps2=_inv_softplus(params.filter_lat_accel_mps2 - MIN_FILTER_NOISE),
        filter_obs_m=_inv_softplus(params.filter_obs_m - MIN_FILTER_NOISE),
        filter_gate_sigma=_inv_softplus(params.filter_gate_sigma - MIN_GATE_SIGMA),
    )


@aot.jit
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
        offset_tau_s=MIN_TAU_S + jax.nn.softplus(raw.offset_tau_s),
        speed_tau_s=MIN_TAU_S + jax.nn.softplus(raw.speed_tau_s),
        pace_return_1ps=jax.nn.softplus(raw.pace_return_1ps),
        position_smoothing=jax.nn.sigmoid(raw.position_smoothing),
        filter_accel_mps2=MIN_FILTER_NOISE + jax.nn.softplus(raw.filter_accel_mps2),
        filter_lat_accel_mps2=MIN_FILTER_NOISE + jax.nn.softplus(raw.filter_lat_accel_mps2),
        filter_obs_m=MIN_FILTER_NOISE + jax.nn.softplus(raw.filter_obs_m),
        filter_gate_sigma=MIN_GATE_SIGMA + jax.nn.softplus(raw.filter_gate_sigma),
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
    "frenet": lambda: Params.create(
        Settings(model="frenet", estimator="kalman"),
        weights=1.0,
        offset_tau_s=1.0,
        position_smoothing=1.0,
    ),
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
