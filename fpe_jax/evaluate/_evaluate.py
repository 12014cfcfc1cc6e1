"""Evaluation of a predictor on recorded drives: targets, datasets, held-out split and metrics,
uncertainty and its frames.

Data flow: each drive -> prediction times with enough history and their future targets
(`make_targets`) -> a `Dataset` (drive, track, targets, cached states) -> predictions at the
targets (`predict_targets`) -> metrics (`evaluate`), held-out predictions for plots
(`heldout_predictions`) and the per-step residual covariance in the track frame
(`fit_uncertainty`, mapped back to the map frame along the path by `covariance_map`). `fit`
builds on this module; it imports nothing from `fit`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import jax
import numpy as np

from fpe_jax.compile import _aot as aot
from fpe_jax.compile._arrays import device_array
from fpe_jax.compile._rows import pad_rows, row_blocks
from fpe_jax.drive import Drive
from fpe_jax.errors import InputError
from fpe_jax.evaluate._metrics import (
    coverage,
    errors_m,
    fit_covariance,
    fit_variance_model,
    row_covariance,
    summarize,
    track_frame_residuals,
)
from fpe_jax.geometry._path import covariance_map as covariance_map  # re-exported
from fpe_jax.geometry._track import Track, project_rollout
from fpe_jax.model._history import distinct_mask, history_windows
from fpe_jax.model._params import Params, Settings
from fpe_jax.model._state import Poses, State
from fpe_jax.predict._predict import (
    model_states,
    predict_rows,
    states_both,
    uses_filter,
    variance_rows,
)

MIN_HISTORY = 3  # distinct observations needed before a prediction counts


@dataclasses.dataclass(frozen=True)
class Targets:
    """Prediction times of one drive and what the car did after each.

    Attributes:
        rows: (N,) indices into the drive's observations (the prediction times).
        xy_m: (N, H, 2) target positions [m] at stamp + h * dt_s.
        mask: (N, H) True where the target exists.
    """

    rows: np.ndarray
    xy_m: np.ndarray
    mask: np.ndarray


def make_targets(drive: Drive, settings: Settings) -> Targets:
    """Targets for every observation with enough history.

    From the ground-truth stream when the drive has one (linear interpolation, masked where the
    stream has a gap > 0.1 s or ends); otherwise from the observations themselves: the nearest
    new (non-repeated) observation within half a sample period, masked when none is.
    """
    h = np.arange(1, settings.horizon + 1) * settings.dt_s
    windows = history_windows(drive, settings.history)
    rows = np.flatnonzero(windows["valid"].sum(axis=1) >= MIN_HISTORY)
    when = drive.t_s[rows, None] + h[None, :]  # (N, H)
    if drive.has_truth:
        tt, txy = drive.truth_t_s, drive.truth_xy_m
        xy = np.stack([np.interp(when, tt, txy[:, 0]), np.interp(when, tt, txy[:, 1])], axis=-1)
        k = np.clip(np.searchsorted(tt, when), 1, len(tt) - 1)
        mask = (when >= tt[0]) & (when <= tt[-1]) & ((tt[k] - tt[k - 1]) <= 0.1)
    else:
        new = np.flatnonzero(distinct_mask(drive.xy_m))
        tn = drive.t_s[new]
        half_period = 0.5 * np.median(np.diff(drive.t_s)) if len(drive.t_s) > 1 else 0.0
        k = np.clip(np.searchsorted(tn, when), 1, len(tn) - 1)
        nearest = np.where(np.abs(tn[k - 1] - when) <= np.abs(tn[k] - when), k - 1, k)
        xy = drive.xy_m[new[nearest]]
        mask = np.abs(tn[nearest] - when) <= half_period + 1e-9
    keep = mask.any(axis=1)
    return Targets(rows=rows[keep], xy_m=xy[keep], mask=mask[keep])


@dataclasses.dataclass(frozen=True)
class Dataset:
    """One drive ready for fitting: its track, targets and (for the blend model) states."""

    drive: Drive
    track: Track
    targets: Targets
    kalman: bool = False  # the first estimate also runs the Kalman filter, whatever the model
    _states: dict = dataclasses.field(default_factory=dict, repr=False, compare=False)
    _folds: list = dataclasses.field(default_factory=list, repr=False, compare=False)

    def states(self, params: Params) -> State:
        """The model's states at the target rows (`model_states`).

        Cached: states depend only on the estimator window (`states_both` gives both
        estimators' at once; the Kalman filter's carry their windows: `predict` filters them
        under the params at hand), and a fit asks for them once per solve, for the uncertainty
        and per preset. The Kalman filter runs only for a model that uses it, or with the first
        estimate when the dataset was made with kalman=True (a fit scores both kinds of model
        on it: one program then gives both); a Kalman model after a Theil-Sen one without it
        estimates both again.
        """
        key = params.settings.history
        need = uses_filter(params.settings)
        if key not in self._states or (need and self._states[key][1] is None):
            both = states_both(params, self.drive, self.track, kalman=need or self.kalman)
            self._states[key] = [jax.tree.map(lambda x: x[self.targets.rows], s) for s in both]
        return model_states(params, *self._states[key], self.drive, self.targets.rows)


def predict_targets(params: Params, dataset: Dataset) -> Poses:
    """Predictions (NumPy fields (N, H)) at a dataset's target rows."""
    return predict_rows(params, dataset.states(params), dataset.track)


@dataclasses.dataclass(frozen=True)
class Heldout:
    """Predictions on a case's test drive, aligned with their targets.

    Attributes:
        rows: (N,) indices of the prediction times in the test drive.
        origin_xy_m: (N, 2) the observation each prediction starts from [m].
        target_xy_m: (N, H, 2) where the car was at stamp + h * dt [m] (truth when the drive
            has it, else later observations).
        mask: (N, H) True where the target exists.
        pred_xy_m: name -> (N, H, 2) predicted positions [m].
    """

    rows: np.ndarray
    origin_xy_m: np.ndarray
    target_xy_m: np.ndarray
    mask: np.ndarray
    pred_xy_m: dict[str, np.ndarray]


def heldout_predictions(drive: Drive, track, params_by_name: dict) -> Heldout:
    """Predict from every observation of `drive` that has targets, for each named Params.

    Uses the same targets (and, for equal shapes, the same compiled code) as `evaluate`.
    """
    settings = next(iter(params_by_name.values())).settings
    kalman = any(uses_filter(p.settings) for p in params_by_name.values())
    data = Dataset(drive, track, make_targets(drive, settings), kalman)
    preds = {n: predict_targets(p, data).xy_m for n, p in params_by_name.items()}
    return Heldout(
        rows=data.targets.rows,
        origin_xy_m=drive.xy_m[data.targets.rows],
        target_xy_m=data.targets.xy_m,
        mask=data.targets.mask,
        pred_xy_m=preds,
    )


def evaluate(
    params: Params, datasets: Sequence[Dataset], cov_m2=None, *, uncertainty: dict | None = None
) -> dict:
    """Metrics (see `metrics.summarize`) of params over datasets, plus the coverage of the
    uncertainty's ellipses when given: a fit's `uncertainty` (per prediction where it has the
    filter's terms, `prediction_covariance`), or a per-step track-frame cov_m2 (H, 2, 2)."""
    if cov_m2 is not None:
        uncertainty = {"cov_m2": cov_m2}
    errs, res, masks, covs = [], [], [], []
    for d in datasets:
        xy = predict_targets(params, d).xy_m
        errs.append(errors_m(xy, d.targets.xy_m, d.targets.mask))
        if uncertainty is not None:
            res.append(_track_residuals(xy, d, params))
            masks.append(d.targets.mask)
            covs.append(prediction_covariance(params, d.states(params), d.track, uncertainty))
    out = summarize(np.concatenate(errs))
    if uncertainty is not None:
        out.update(coverage(np.concatenate(res), np.concatenate(masks), np.concatenate(covs)))
    return out


def prediction_covariance(
    params: Params, states: State, track: Track, uncertainty: dict
) -> np.ndarray:
    """(N, H, 2, 2) track-frame covariance [m^2] of the predictions from N states (leading axis
    N): from each one's state estimate (`metrics.row_covariance`) where the uncertainty has the
    filter's terms (`fit_uncertainty`), else its per-step cov_m2 for every prediction."""
    if "state_scale" not in uncertainty:
        cov = np.asarray(uncertainty["cov_m2"], dtype=np.float64)
        return np.broadcast_to(cov, (len(states.x_m), *cov.shape))
    var = variance_rows(params, states, track)
    return row_covariance(
        var, uncertainty["state_scale"], uncertainty["model_var_m2"], uncertainty["correlation"]
    )


def path_heading(track: Track, xy_m: np.ndarray, states: State) -> np.ndarray:
    """Path heading [rad] (N, H) at predicted positions (N, H, 2): the frame of the uncertainty.

    Each prediction is projected near its own car's arc length (`states`, leading axis N, with
    `s_m`), in the padded blocks of `row_blocks`: memory O(block x H + track points), not
    (N, H, track points).
    """
    out = []
    for rows, size in row_blocks(len(xy_m)):
        st = pad_rows(jax.tree.map(lambda x, r=rows: x[r], states), size)
        start = np.stack([st.x_m, st.y_m], axis=-1)
        xy = pad_rows(np.asarray(xy_m[rows]), size)
        out.append(np.asarray(_heading_chunk(track, xy, start, st.s_m))[: rows.stop - rows.start])
    return np.concatenate(out) if out else np.zeros(np.shape(xy_m)[:2])


@aot.jit
def _heading_chunk(track: Track, xy_m, start_xy_m, s_start_m):
    along = jax.vmap(project_rollout, in_axes=(None, 0, 0, 0))(track, xy_m, start_xy_m, s_start_m)
    return jax.vmap(jax.vmap(track.heading_at))(along)


def _track_residuals(xy_m: np.ndarray, d: Dataset, params: Params) -> np.ndarray:
    heading = path_heading(d.track, xy_m, d.states(params))
    return track_frame_residuals(xy_m, d.targets.xy_m, heading)


# Folds of the cross-fitted residuals (contiguous in time). Two halves made the residuals'
# core wider than on a separate drive (the test's line is learned on all of the fit drive, not
# half of it): hairpin 1-sigma coverage 53 % on the test drive. With five folds each line sees 80 %.
CROSS_FOLDS = 5
MIN_FOLD_S = 12.0


def cross_fold_lines(d: Dataset) -> tuple[np.ndarray, list[dict[str, np.ndarray]]]:
    """The folds of d's prediction rows for cross-fitting the line model, and each fold's line.

    The drive is cut into CROSS_FOLDS contiguous folds in time (fewer on a short drive, at
    least MIN_FOLD_S each, at least 2); each fold's line is learned on the rest of the drive
    (`fpe_jax.model.line_from_samples`). The line fits its own drive's truth, so predictions
    from it at the rows it was learned on are better than on a drive it was not learned on.

    Returns (fold (N,) int, the fold of each of d's prediction rows; lines, per fold the
    profile as `learn_line` gives it). Made once per dataset (they depend on its drive alone;
    the long-horizon fit and the uncertainty both ask); treat them as read-only.
    """
    from fpe_jax.model._line import line_from_samples, line_samples

    if d._folds:
        return d._folds[0]
    # at least MIN_FOLD_S per fold: on a 40 s drive five folds' lines were too good (the oval
    # test's 2-sigma coverage 74.7 %)
    folds = int(np.clip(d.drive.duration_s // MIN_FOLD_S, 2, CROSS_FOLDS))
    edges = np.linspace(d.drive.t_s[0], d.drive.t_s[-1], folds + 1)
    edges[-1] = np.inf
    t_rows = d.drive.t_s[d.targets.rows]
    fold = np.clip(np.searchsorted(edges, t_rows, side="right") - 1, 0, folds - 1)
    whole = line_samples(d.drive, d.track)  # projected once; each fold leaves out its part
    lines = [
        line_from_samples([whole.outside(lo, hi)], d.track) for lo, hi in zip(edges[:-1], edges[1:])
    ]
    d._folds.append((fold, lines))
    return fold, lines


def _cross_fitted(params: Params, d: Dataset) -> np.ndarray:
    """(N, H, 2) positions [m] of the line model at d's targets, each from a line learned on the
    rest of d's drive (`cross_fold_lines`): in-sample residuals would understate the error on
    drives the line was not learned on."""
    fold, lines = cross_fold_lines(d)
    out = np.zeros((len(fold), params.settings.horizon, 2))
    states = d.states(params)
    for i, line in enumerate(lines):
        rows = fold == i
        if not rows.any():
            continue
        fold_params = dataclasses.replace(params, **{k: device_array(v) for k, v in line.items()})
        fold_states = jax.tree.map(lambda x, f=rows: x[f], states)
        out[rows] = predict_rows(fold_params, fold_states, d.track).xy_m
    return out


def fit_uncertainty(params: Params, datasets: Sequence[Dataset]) -> dict:
    """The predictions' uncertainty in the (along-track, cross-track) frame, fitted on the
    residuals of the datasets' predictions (for the line model cross-fitted, `_cross_fitted`).

    Returns {"frame": "track", "axes", "cov_m2": (H, 2, 2) [m^2]}: per step the residuals'
    covariance. With the Kalman filter also the per-prediction terms of
    `metrics.fit_variance_model`, state_scale (H, 2), model_var_m2 (H, 2) [m^2] and correlation
    (H,): a prediction's covariance is then its own state estimate's variance
    (`fpe_jax.model.estimate_variance`) scaled, plus the model's error
    (`prediction_covariance`); cov_m2 is their mean over the datasets' predictions.
    """
    line = params.settings.model == "line"
    xy = [_cross_fitted(params, d) if line else predict_targets(params, d).xy_m for d in datasets]
    res = np.concatenate([_track_residuals(p, d, params) for p, d in zip(xy, datasets)])
    mask = np.concatenate([d.targets.mask for d in datasets])
    out = {"frame": "track", "axes": ["along_m", "cross_m"]}
    if not uses_filter(params.settings):
        return out | {"cov_m2": fit_covariance(res, mask).tolist()}
    var = np.concatenate([variance_rows(params, d.states(params), d.track) for d in datasets])
    terms = fit_variance_model(res, var, mask)
    cov = row_covariance(var, **terms)
    mean = np.sum(cov * mask[..., None, None], axis=0) / np.maximum(mask.sum(0), 1)[:, None, None]
    return out | {"cov_m2": mean.tolist()} | {k: v.tolist() for k, v in terms.items()}


def split_drive(drive: Drive, holdout: float) -> tuple[Drive, Drive]:
    """Temporal split: the first (1 - holdout) of the drive's duration, and the rest."""
    if not 0.0 < holdout < 1.0:
        raise InputError("holdout", f"{holdout} is outside (0, 1)", "a fraction such as 0.3")
    t_split = drive.t_s[0] + (1.0 - holdout) * drive.duration_s
    return drive.slice_time(-np.inf, t_split), drive.slice_time(t_split, np.inf)


def make_datasets(
    drives: Sequence[Drive],
    tracks: Sequence[Track],
    settings: Settings,
    what: str,
    *,
    kalman: bool = False,
) -> list[Dataset]:
    """One `Dataset` per (drive, track) pair; `what` names the part in the error raised when a
    drive has no usable prediction ("training", "held-out"); kalman: `Dataset.kalman`."""
    out = []
    for drv, trk in zip(drives, tracks, strict=True):
        targets = make_targets(drv, settings)
        if len(targets.rows) == 0:
            src = drv.meta.get("source", "drive")
            raise InputError(src, f"no usable predictions in the {what} part", "a longer drive")
        out.append(Dataset(drv, trk, targets, kalman))
    return out


def targets_before(d: Dataset, t_cut_s: float, dt_s: float) -> Dataset:
    """d with only the targets due before t_cut_s [s]; rows, shapes and cached states unchanged.

    Half a step of margin: a target near the cut may be made from data after it.
    """
    steps = np.arange(1, d.targets.mask.shape[1] + 1) * dt_s
    due = d.drive.t_s[d.targets.rows, None] + steps[None, :]
    mask = d.targets.mask & (due + 0.5 * dt_s < t_cut_s)
    if not mask.any():
        src = d.drive.meta.get("source", "drive")
        raise InputError(src, "no usable predictions before the inner split", "a longer drive")
    targets = dataclasses.replace(d.targets, mask=mask)
    return dataclasses.replace(d, targets=targets, _states=d._states)
