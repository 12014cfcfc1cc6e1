"""Predict one car, a batch of cars (optionally under P parameter sets), or a whole drive."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from fpe_jax.drive import Drive
from fpe_jax.estimate import estimate_state, estimate_track_frame
from fpe_jax.history import history_windows
from fpe_jax.params import Params
from fpe_jax.rollout import State, rollout
from fpe_jax.track import Track, arclength_along


def predict(params: Params, state: State, track: Track) -> Float[Array, "H 3"]:
    """Poses (H, 3) x [m], y [m], yaw [rad] at t + h * dt_s, h = 1..H, for one car."""
    return rollout(params, state, track)


@eqx.filter_jit
def predict_batch(params: Params, states: State, track: Track) -> Float[Array, "... N H 3"]:
    """Predict N cars (states with a leading axis N) -> (N, H, 3).

    With P stacked parameter sets (`stack_params`; weights of shape (P, H)) -> (P, N, H, 3): every
    car under every hypothesis, in one compiled call.
    """
    over_cars = jax.vmap(predict, in_axes=(None, 0, None))
    if params.weights.ndim == 2:
        return jax.vmap(over_cars, in_axes=(0, None, None))(params, states, track)
    return over_cars(params, states, track)


def stack_params(params_list: list[Params]) -> Params:
    """Stack P parameter sets that share their settings into one Params with a leading axis."""
    settings = {p.settings for p in params_list}
    if len(settings) != 1:
        raise ValueError("stack_params: all parameter sets must share the same Settings")
    return jax.tree.map(lambda *xs: jnp.stack(xs), *params_list)


@eqx.filter_jit
def _states_from_windows(windows: dict, track: Track) -> State:
    states = jax.vmap(estimate_state)(
        windows["t_s"], windows["xy_m"], windows["yaw_rad"], windows["valid"], windows["t_now_s"]
    )
    p = jnp.stack([states.x_m, states.y_m], axis=1)
    s_m = arclength_along(track, p)
    s_fit, sdot, offset, age = jax.vmap(estimate_track_frame, in_axes=(0, 0, 0, 0, None))(
        windows["t_s"], windows["xy_m"], windows["valid"], s_m, track
    )
    return dataclasses.replace(
        states, s_m=s_m, s_fit_m=s_fit, sdot_mps=sdot, offset_m=offset, sdot_age_s=age
    )


def states_from_drive(params: Params, drive: Drive, track: Track) -> State:
    """The state at every observation of a drive (leading axis N).

    For the seed model the original's rules apply: the current row is used alone (position and
    observed yaw as recorded; the direction of motion stands in when the log has no yaw).
    """
    windows = history_windows(drive, params.settings.history)
    states = _states_from_windows(jax.tree.map(jnp.asarray, windows), track)
    if params.settings.model == "seed":
        yaw_obs = jnp.asarray(drive.yaw_rad)
        states = dataclasses.replace(
            states,
            x_m=jnp.asarray(drive.xy_m[:, 0]),
            y_m=jnp.asarray(drive.xy_m[:, 1]),
            yaw_rad=jnp.where(jnp.isfinite(yaw_obs), yaw_obs, states.yaw_rad),
        )
    return states


def predict_drive(params: Params, drive: Drive, track: Track) -> tuple[np.ndarray, np.ndarray]:
    """Predict from every observation of a drive.

    Returns:
        stamps_s: (N,) observation stamps [s] (the prediction times).
        poses: (N, H, 3) x [m], y [m], yaw [rad] at stamp + h * dt_s.
    """
    states = states_from_drive(params, drive, track)
    return drive.t_s.copy(), np.asarray(predict_batch(params, states, track))
