"""Observation history in NumPy only (no JAX): which rows are new detections, the recent windows
the state estimator reads, and the estimator's constants. Shared by `fpe_jax.estimate` (JAX) and
the on-car `fpe_jax.runner` (NumPy), so both see the same rules.
"""

from __future__ import annotations

import numpy as np

from fpe_jax.drive import Drive

MIN_PAIR_DT_S = 0.05  # pairs closer in time than this give slopes dominated by noise
MAX_SPAN_S = 1.0  # older observations describe a different motion
OUTLIER_M = 0.6  # newest observation farther than this from the robust line is an outlier
# A prediction is valid (published by `fpe node`, `valid` = 1 in `fpe predict` / `fpe run`) once
# its history window holds at least MIN_VALID_OBS distinct observations spanning at least
# MIN_VALID_SPAN_S: from fewer the speed and heading are guesses (the first prediction of a drive
# is a stopped car whose heading swings).
MIN_VALID_OBS = 3
MIN_VALID_SPAN_S = 0.2


def history_valid(n_obs, span_s):
    """Whether predictions from windows of `n_obs` distinct observations spanning `span_s` [s]
    are valid (scalars or arrays alike): the one rule of every front end."""
    return (n_obs >= MIN_VALID_OBS) & (span_s >= MIN_VALID_SPAN_S - 1e-9)


def distinct_mask(xy_m: np.ndarray) -> np.ndarray:
    """(N,) True where a row is a new observation, False where it repeats the previous row."""
    same = np.zeros(len(xy_m), dtype=bool)
    same[1:] = np.all(xy_m[1:] == xy_m[:-1], axis=1)
    return ~same


def history_windows(drive: Drive, n_hist: int, rows: slice | None = None) -> dict[str, np.ndarray]:
    """For every observation k (of `rows`, default all), the newest `n_hist` distinct
    observations up to k, right-aligned.

    Returns a dict of arrays: t_s (N, W), xy_m (N, W, 2), yaw_rad (N, W), valid (N, W) bool and
    t_now_s (N,) (the stamp of observation k, the prediction time), N the rows asked for. Slots
    with no observation (the start of a drive, or older than MAX_SPAN_S before the newest) are
    invalid.
    """
    idx_distinct = np.flatnonzero(distinct_mask(drive.xy_m))
    k = np.arange(len(drive.t_s))[rows if rows is not None else slice(None)]
    newest = np.searchsorted(idx_distinct, k, side="right") - 1
    slots = newest[:, None] + np.arange(-n_hist + 1, 1)[None, :]
    valid = slots >= 0
    rows = idx_distinct[np.clip(slots, 0, None)]
    t = drive.t_s[rows]
    valid &= (t[:, -1:] - t) <= MAX_SPAN_S
    return {
        "t_s": t,
        "xy_m": drive.xy_m[rows],
        "yaw_rad": drive.yaw_rad[rows],
        "valid": valid,
        "t_now_s": drive.t_s[k],
    }


def drive_valid(drive: Drive, n_hist: int) -> np.ndarray:
    """(N,) bool: `history_valid` of the prediction from each observation of the drive, with the
    window of `n_hist` distinct observations the estimators read."""
    w = history_windows(drive, n_hist)
    n = w["valid"].sum(axis=1)
    oldest = np.where(w["valid"], w["t_s"], np.inf).min(axis=1)
    return history_valid(n, w["t_s"][:, -1] - oldest)
