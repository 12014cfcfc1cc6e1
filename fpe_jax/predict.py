"""Predict one car, a batch of cars (optionally under P parameter sets), or a whole drive."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from fpe_jax import aot
from fpe_jax.drive import Drive
from fpe_jax.estimate import estimate_state, track_frame_lines, track_frame_window
from fpe_jax.history import history_windows
from fpe_jax.kalman import kalman_params, kalman_window
from fpe_jax.params import Params, Settings
from fpe_jax.path import MIN_HEADING_SPEED_MPS
from fpe_jax.rollout import estimate_variance, rollout
from fpe_jax.state import Poses, State
from fpe_jax.track import Track, arclength_along_heading

# Rows per compiled prediction call: a drive of any length runs in blocks of this size (a
# 10-million-row log asked XLA for one 13.4 GB block before).
PREDICT_CHUNK = 1 << 15


WINDOW_FIELDS = ("window_age_s", "window_s_m", "window_d_m", "window_valid", "window_prior")


def uses_filter(settings: Settings) -> bool:
    """Whether a model's rollout starts from the track-frame Kalman filter."""
    return settings.estimator == "kalman" and settings.model in ("frenet", "line")


def filtered(params: Params, state: State, track: Track) -> State:
    """One car's state with its track-frame estimate from the Kalman filter over the state's
    window (`fpe_jax.kalman`) under params' noise values: s_fit_m, sdot_mps, offset_m at the
    newest stamp, sdot_age_s, the age of the filter's speed, and filter_cov, the estimate's
    covariance. Unchanged where the model does not use the filter or the state carries no
    window."""
    if not uses_filter(params.settings) or state.window_s_m is None:
        return state
    return _filter_state(kalman_params(params), state, track)


def _filter_state(values: tuple, state: State, track: Track) -> State:
    mean, cov, speed_age = kalman_window(
        state.window_age_s,
        state.window_s_m,
        state.window_d_m,
        state.window_valid > 0.5,
        state.window_prior,
        *values,
        length_m=track.length_m if track.closed else None,
    )
    new = dict(s_fit_m=mean[0], sdot_mps=mean[1], offset_m=mean[2], sdot_age_s=speed_age)
    if state.s_fit_m is not None:  # an empty window (an export's default): the state's own
        has = jnp.any(state.window_valid > 0.5)
        new = {k: jnp.where(has, v, getattr(state, k)) for k, v in new.items()}
        cov = jnp.where(has, cov, 0.0)  # of an estimate given as it is: unknown
    return dataclasses.replace(state, **new, filter_cov=cov)


def _poses(params: Params, state: State, track: Track) -> Poses:
    return rollout(params, filtered(params, state, track), track)


def predict(params: Params, state: State, track: Track) -> Float[Array, "H 3"]:
    """Poses (H, 3) x [m], y [m], yaw [rad] at t + h * dt_s, h = 1..H, for one car (its
    window filtered first, `filtered`)."""
    return _poses(params, state, track).packed()


def predict_poses(params: Params, states: State, track: Track) -> Poses:
    """`Poses` of N cars (states with a leading axis N), fields (N, H); (P, N, H) under P stacked
    parameter sets (`stack_params`; weights of shape (P, H)): every car under every hypothesis."""
    over_cars = jax.vmap(_poses, in_axes=(None, 0, None))
    if params.weights.ndim == 2:
        return jax.vmap(over_cars, in_axes=(0, None, None))(params, states, track)
    return over_cars(params, states, track)


@eqx.filter_jit
def predict_batch(params: Params, states: State, track: Track) -> Float[Array, "... N H 3"]:
    """`predict_poses` in one compiled call, packed: (N, H, 3), or (P, N, H, 3)."""
    return predict_poses(params, states, track).packed()


def predict_variance(params: Params, states: State, track: Track) -> Float[Array, "N H 2"]:
    """(N, H, 2) variance [m^2] along and across the track of N cars' predicted points from
    their state estimates' uncertainty (`fpe_jax.rollout.estimate_variance`, each car's window
    filtered first); zeros without the Kalman filter."""

    def one(state):
        return estimate_variance(params, filtered(params, state, track))

    return jax.vmap(one)(states)


# the commands' path: executables kept on disk (`aot`), so a warm run traces nothing; the public
# predict_batch stays a plain jit (it also runs on sharded arrays and inside other traces)
_predict_rows_block = aot.jit(predict_poses)
_variance_rows_block = aot.jit(predict_variance)


def stack_params(params_list: list[Params]) -> Params:
    """Stack P parameter sets that share their settings into one Params with a leading axis."""
    settings = {p.settings for p in params_list}
    if len(settings) != 1:
        raise ValueError("stack_params: all parameter sets must share the same Settings")
    return jax.tree.map(lambda *xs: jnp.stack(xs), *params_list)


MIN_BUCKET = 64


def bucket(n: int) -> int:
    """Padded row count for n rows: the smallest of 64, 80, 96, 112, 128, 160, ... (four sizes per
    doubling, 2^k times 1, 5/4, 6/4 or 7/4) that is >= n.

    Executables are compiled per shape: the fit's solver takes each drive's targets whole, and
    padding them to one of these sizes lets drives of similar length and the inner and final
    fits share one, in one process and from the persistent cache. A padded row costs a real
    one's time in every solver step, so the sizes are close: at most a quarter more rows.
    """
    if n <= MIN_BUCKET:
        return MIN_BUCKET
    octave = 1 << (n - 1).bit_length() - 1  # the largest power of two below n
    return octave + -(-(n - octave) // (octave // 4)) * (octave // 4)


def pad_rows(tree, n: int):
    """Every leaf (numpy or JAX, leading axis N <= n) as numpy padded to n rows by repeating its
    last row: padded rows hold real, finite values (no NaN in a masked-out gradient)."""

    def pad(x):
        x = np.asarray(x)
        if len(x) == n:
            return x
        if len(x) == 0:
            return np.zeros((n, *x.shape[1:]), x.dtype)
        return np.concatenate([x, np.repeat(x[-1:], n - len(x), axis=0)])

    return jax.tree.map(pad, tree)


# Rows of the commands' other blocks: every drive, split and fold runs in blocks of this one
# size, so predict, evaluate, plot and fit share one executable per function and model (a warm
# 10-minute fit loaded 19 executables, 3 of them the state estimator's for three sizes, and
# compiled each cold); padding a short drive to it costs less than one more shape.
BLOCK_ROWS = 1024


def row_blocks(n: int):
    """Slices covering 0..n, each with its padded row count: PREDICT_CHUNK rows while that many
    are left, then blocks of BLOCK_ROWS. Memory stays O(chunk x H) for any n, and drives of
    every length run one or two compiled shapes."""
    small = min(BLOCK_ROWS, PREDICT_CHUNK)
    a = 0
    while a < n:
        size = PREDICT_CHUNK if n - a >= PREDICT_CHUNK else small
        yield slice(a, min(n, a + size)), size
        a += size


def no_arclength() -> np.ndarray:
    """The start arc length of a drive's first block: NaN, projected globally
    (`arclength_along_heading`)."""
    return np.full((), np.nan, jax.dtypes.canonicalize_dtype(np.float64))


def _over_rows(block_fn, params: Params, states: State, track: Track, empty):
    """block_fn(params, states, track) over the padded blocks of `row_blocks` of N states
    (leading axis N), its outputs' leaves as NumPy (N, ...); `empty` for N = 0. Intermediates
    stay O(chunk x H) for any N, and every drive reuses the same compiled shapes."""
    out = []
    for rows, size in row_blocks(len(states.x_m)):
        part = pad_rows(jax.tree.map(lambda x, r=rows: x[r], states), size)
        res = block_fn(params, part, track)
        out.append(jax.tree.map(lambda x, n=rows.stop - rows.start: np.asarray(x)[:n], res))
    return jax.tree.map(lambda *xs: np.concatenate(xs), *out) if out else empty


def predict_rows(params: Params, states: State, track: Track) -> Poses:
    """`Poses` (NumPy fields (N, H)) of N states (leading axis N): `predict_poses` in blocks."""
    empty = Poses(*[np.zeros((0, params.settings.horizon))] * 3)
    return _over_rows(_predict_rows_block, params, states, track, empty)


def variance_rows(params: Params, states: State, track: Track) -> np.ndarray:
    """(N, H, 2) `predict_variance` of N states (leading axis N) in blocks."""
    empty = np.zeros((0, params.settings.horizon, 2))
    return _over_rows(_variance_rows_block, params, states, track, empty)


@aot.jit
def _states_from_windows(windows: dict, track: Track, s_before_m, filter_values: tuple | None):
    """States of a block of windows under both track-frame estimators: (Theil-Sen's, the Kalman
    filter's under filter_values (`kalman_params`), carrying its windows); with filter_values
    None, (Theil-Sen's, None).

    One program for both: they share all but the filter (whose prior is the Theil-Sen lines),
    and a fit scores both (the line model and the presets), so every model shares one
    executable, compiled once. Without the filter the program is smaller and faster to compile,
    load and run: the blend and seed models never need it.
    """
    states = jax.vmap(estimate_state)(
        windows["t_s"], windows["xy_m"], windows["yaw_rad"], windows["valid"], windows["t_now_s"]
    )
    # the heading is known where the newest observation has a yaw or the car moves
    known = jnp.isfinite(windows["yaw_rad"][:, -1]) | (states.v_mps >= MIN_HEADING_SPEED_MPS)
    heading = jnp.where(known, states.yaw_rad, jnp.nan)
    xy = jnp.stack([states.x_m, states.y_m], axis=1)
    s_m = arclength_along_heading(track, xy, heading, s_before_m)
    states = dataclasses.replace(states, s_m=s_m)
    s_win, d_win = jax.vmap(track_frame_window, in_axes=(0, 0, 0, None))(
        windows["xy_m"], windows["valid"], s_m, track
    )
    s_ts, sdot_ts, d_ts, ddot_ts, age_ts = jax.vmap(track_frame_lines)(
        windows["t_s"], s_win, d_win, windows["valid"]
    )
    theil_sen = dataclasses.replace(
        states, s_fit_m=s_ts, sdot_mps=sdot_ts, offset_m=d_ts, sdot_age_s=age_ts
    )
    window = dict(
        window_age_s=windows["t_s"][:, -1:] - windows["t_s"],
        window_s_m=s_win,
        window_d_m=d_win,
        window_valid=windows["valid"].astype(s_win.dtype),
        window_prior=jnp.stack([s_ts, sdot_ts, d_ts, ddot_ts, age_ts], axis=1),
    )
    if filter_values is None:
        return theil_sen, None
    kalman = jax.vmap(_filter_state, in_axes=(None, 0, None))(
        filter_values, dataclasses.replace(states, **window), track
    )
    return theil_sen, kalman


def states_both(
    params: Params, drive: Drive, track: Track, *, kalman: bool = True
) -> tuple[State, State | None]:
    """The state at every observation of a drive (numpy leaves, leading axis N) under both
    track-frame estimators: (Theil-Sen's, the Kalman filter's under params' noise values,
    carrying its windows `State.window_s_m`, ... so that `predict` filters them again under
    other values; None unless `kalman`). A model's are `model_states` of them."""
    # in blocks of PREDICT_CHUNK rows, each block's projection window continuing from the last
    # arc length of the one before: memory stays O(block) for a log of any length
    parts, s_before = [], no_arclength()
    dtype = jax.dtypes.canonicalize_dtype(np.float64)
    values = tuple(np.asarray(v, dtype) for v in kalman_params(params)) if kalman else None
    for rows, size in list(row_blocks(len(drive.t_s))) or [(slice(0, 0), BLOCK_ROWS)]:
        windows = history_windows(drive, params.settings.history, rows)
        part = _states_from_windows(pad_rows(windows, size), track, s_before, values)
        part = jax.tree.map(lambda x, n=rows.stop - rows.start: np.asarray(x)[:n], part)
        s_before = np.asarray(part[0].s_m[-1]) if len(part[0].s_m) else no_arclength()
        parts.append(part)
    return jax.tree.map(lambda *xs: np.concatenate(xs), *parts) if len(parts) > 1 else parts[0]


def model_states(
    params: Params, theil_sen: State, kalman: State | None, drive: Drive, rows=slice(None)
) -> State:
    """A model's states from both estimators' (`states_both`) at a drive's `rows` (numpy leaves,
    leading axis N): the Kalman filter's where the model uses it, else Theil-Sen's; the seed
    model's by the original's rules: the current row alone, its position and observed yaw as
    recorded (the direction of motion where the log has no yaw)."""
    if params.settings.model == "seed":
        yaw_obs = np.asarray(drive.yaw_rad[rows])
        return dataclasses.replace(
            theil_sen,
            x_m=np.asarray(drive.xy_m[rows, 0]),
            y_m=np.asarray(drive.xy_m[rows, 1]),
            yaw_rad=np.where(np.isfinite(yaw_obs), yaw_obs, theil_sen.yaw_rad),
        )
    return kalman if uses_filter(params.settings) else theil_sen


def states_from_drive(
    params: Params, drive: Drive, track: Track, *, keep_window: bool = False
) -> State:
    """The state at every observation of a drive (numpy leaves, leading axis N), under params'
    estimator (`model_states`); keep_window: the Kalman filter's states also carry their windows.
    """
    both = states_both(params, drive, track, kalman=uses_filter(params.settings))
    states = model_states(params, *both, drive)
    return states if keep_window else dataclasses.replace(states, **dict.fromkeys(WINDOW_FIELDS))


def predict_drive(params: Params, drive: Drive, track: Track) -> tuple[np.ndarray, np.ndarray]:
    """Predict from every observation of a drive.

    Returns:
        stamps_s: (N,) observation stamps [s] (the prediction times).
        poses: (N, H, 3) x [m], y [m], yaw [rad] at stamp + h * dt_s.
    """
    states = states_from_drive(params, drive, track)
    return drive.t_s.copy(), predict_rows(params, states, track).packed()
