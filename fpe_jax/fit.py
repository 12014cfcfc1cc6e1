"""Fit the predictor to recorded drives by robust, gradient-based least squares (optimistix).

Data flow: each drive -> prediction times with enough history and their future targets
(`make_targets`) -> states (`predict.states_from_drive`) -> residuals of the position blend
(Huber-weighted, masked) -> Levenberg-Marquardt on the raw (unconstrained) parameters. The blend
mode is chosen on an inner validation split of the training data; held-out data is only used for
the final report. Uncertainty: per-step residual covariance in the track frame.
"""

from __future__ import annotations

import dataclasses
import datetime
import functools
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from fpe_jax.drive import Drive
from fpe_jax.errors import InputError
from fpe_jax.history import distinct_mask, history_windows
from fpe_jax.metrics import coverage, errors_m, fit_covariance, summarize, track_frame_residuals
from fpe_jax.params import Params, Settings, constrain, presets, unconstrain
from fpe_jax.predict import predict, predict_batch, states_from_drive
from fpe_jax.rollout import State
from fpe_jax.spec import DEFAULT_FIT as DEFAULT_FIT
from fpe_jax.spec import DEFAULT_SOLVER as DEFAULT_SOLVER
from fpe_jax.spec import FIT_GROUPS as FIT_GROUPS
from fpe_jax.spec import SOLVERS as SOLVERS
from fpe_jax.track import Track

PARAM_FIELDS = (
    "lookahead_m",
    "lookahead_gain_s",
    "weights",
    "delay_s",
    "speed_weight",
    "speed_mps",
)
BLEND_CHOICES = ("position", "heading")
BASELINES = ("seed", "seed-measured-speed", "linear", "pure-pursuit", "constant-velocity", "ctrv")
MIN_HISTORY = 3  # distinct observations needed before a prediction counts
HUBER_M = 0.3  # residuals beyond this grow linearly: AprilTag jumps must not dominate
RAW_RIDGE = 1e-3  # light pull of raw values toward 0: stops saturated weights from drifting
# Consecutive weights are nearly interchangeable (a turn at step h or h+1 ends in about the same
# place), so without a prior the fit can alternate 0/1 between steps. The penalty costs a jump of
# 1 between neighbours as much as 1 % of the data's squared error budget at 1 m^2 per target.
WEIGHT_SMOOTHING_M2 = 0.01
# Both solvers are optimistix's. BFGS is the default: in experiments/results/solvers.md it ends
# at an equal or lower loss on every drive (LM up to 2e-5 relative higher) in comparable
# time. An LM step needs the full Jacobian (~18 forward passes), a BFGS step one gradient.
MAX_STEPS = {"bfgs": 1000, "lm": 200}  # BFGS counts line-search trials too
# BFGS minimises loss / (target points x BFGS_LOSS_UNIT_M2). Its first inverse Hessian is the
# identity, so this unit sets the first steps' length: on the raw sum (~1e4 on a 10-minute
# drive) most line-search trials were rejected. Measured over the solver study's drives plus a
# 60-minute one (units 1e-3, 1/300, 1e-2, 3e-2 m^2): 1/300 took the fewest steps overall, at the
# same loss to 1e-8 but on Monza (another local minimum, 5e-6 apart). Steps against the raw sum:
# 10-minute oval 234 -> 85, Levine 124 -> 93 (experiments/results/solvers.md).
BFGS_LOSS_UNIT_M2 = 1.0 / 300


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
    _states: dict = dataclasses.field(default_factory=dict, repr=False, compare=False)

    def states(self, params: Params) -> State:
        """The model's states at the target rows (the seed model uses raw rows).

        Cached: states depend only on the estimator window and on whether the model is the
        seed's, and a fit asks for them once per solve, for the uncertainty and per preset.
        """
        key = (params.settings.history, params.settings.model == "seed")
        if key not in self._states:
            all_states = states_from_drive(params, self.drive, self.track)
            self._states[key] = jax.tree.map(lambda x: x[self.targets.rows], all_states)
        return self._states[key]


def _huber_scale(err_m, delta_m):
    """Factor that turns a squared residual into a Huber one: 1/2 (scale e)^2 = huber(e)."""
    safe = jnp.maximum(err_m, delta_m)
    return jnp.where(err_m <= delta_m, 1.0, jnp.sqrt(delta_m * (2.0 * safe - delta_m)) / safe)


def _residuals(raw_free, args):
    """Residual vector: weight smoothness, Huber-scaled masked position errors, the ridge."""
    raw_fixed, groups, huber_m = args
    params = constrain(eqx.combine(raw_free, raw_fixed))
    out = []
    n_targets = sum(jnp.sum(mask) for _, _, _, mask in groups)
    out.append(jnp.sqrt(WEIGHT_SMOOTHING_M2 * n_targets) * jnp.diff(params.weights))
    for states, track, target, mask in groups:
        pred = jax.vmap(predict, in_axes=(None, 0, None))(params, states, track)[..., :2]
        d = pred - target
        e = jnp.sqrt(jnp.sum(d * d, axis=-1) + 1e-12)
        r = jnp.where(mask[..., None], d * _huber_scale(e, huber_m)[..., None], 0.0)
        out.append(r.reshape(-1))
    ridge = [jnp.sqrt(RAW_RIDGE) * jnp.ravel(x) for x in jax.tree.leaves(raw_free)]
    return jnp.concatenate(out + ridge)


def _free_mask(params: Params, fit: Sequence[str]) -> Params:
    """A Params-shaped filter: True for the fields being fitted."""
    names = {f for group in fit for f in FIT_GROUPS[group]}
    return dataclasses.replace(params, **{f: f in names for f in PARAM_FIELDS})


def _loss(raw_free, args):
    """The scalar robust loss 1/2 |residuals|^2 (what BFGS minimises)."""
    r = _residuals(raw_free, args)
    return 0.5 * jnp.sum(r * r)


@jax.custom_jvp
def _objective(raw_free, args):
    """`_loss` with a hand-written derivative for the BFGS solver (which asks for it via
    jax.linearize): one value-and-gradient pass, the directional derivative <grad, tangent>.
    Only the raw values are differentiated (the solver holds args fixed). Linearizing the
    rollout's scan instead took most of the solver's tracing and compile time."""
    return _loss(raw_free, args)


@_objective.defjvp
def _objective_jvp(primals, tangents):
    raw_free, args = primals
    value, grad = jax.value_and_grad(_loss)(raw_free, args)
    pairs = zip(jax.tree.leaves(grad), jax.tree.leaves(tangents[0]))
    return value, sum(jnp.vdot(g, t) for g, t in pairs)


# plain jax.jit (every argument is a pytree of arrays): it can be compiled ahead of the call from
# shapes alone, while the states are still being estimated (see fit_params). Compiled solvers
# are kept by argument structure, shapes and static settings (as jit's own cache would).
_COMPILED: dict = {}


@functools.partial(jax.jit, static_argnames=("max_steps", "solver"))
def _solve(raw_free, raw_fixed, groups, huber_m, max_steps: int, solver: str):
    """Run the optimistix solver; returns (raw values, steps, converged, loss)."""
    args = (raw_fixed, groups, huber_m)
    # rms_norm in the stopping test: with the default max_norm, LM stops only once every one of
    # the ~1e5 residuals and every raw value has settled, which a saturating weight or a gain
    # creeping toward its bound never does (it ran to max_steps on every drive measured)
    if solver == "lm":
        run, fn = optx.least_squares, _residuals
        method = optx.LevenbergMarquardt(rtol=1e-3, atol=1e-5, norm=optx.rms_norm)
    else:
        n_points = sum(jnp.sum(mask) for _, _, _, mask in groups)
        scale = BFGS_LOSS_UNIT_M2 * jnp.maximum(n_points, 1)
        run, fn = optx.minimise, lambda y, a: _objective(y, a) / scale  # see BFGS_LOSS_UNIT_M2
        method = optx.BFGS(rtol=1e-6, atol=1e-8, norm=optx.rms_norm)
    sol = run(fn, method, raw_free, args=args, max_steps=max_steps, throw=False)
    ok = sol.result == optx.RESULTS.successful
    # the solver's own evaluation at its last accepted point (sol.value): no further rollout
    # to trace and compile (the first step is always accepted, so this is never its zero init)
    info = sol.state.f_info
    loss = info.f * scale if solver == "bfgs" else 0.5 * jnp.sum(info.residual * info.residual)
    return sol.value, sol.stats["num_steps"], ok, loss


def fit_params(
    datasets: Sequence[Dataset],
    init: Params,
    *,
    fit: Sequence[str] = DEFAULT_FIT,
    huber_m: float = HUBER_M,
    solver: str = DEFAULT_SOLVER,
    max_steps: int | None = None,
) -> tuple[Params, dict]:
    """Fit the free raw parameters of `init` over all datasets jointly (optimistix, float64).

    Args:
        solver: "bfgs" (default): BFGS on the scalar robust loss, reverse-mode gradients: a
            step costs about one forward and one backward pass. "lm": Levenberg-Marquardt on
            the residual vector, forward-mode Jacobians (one pass per fitted value, ~15) per
            step. See SOLVERS for what was measured.
        max_steps: solver steps before giving up (default per solver, MAX_STEPS).

    Returns the fitted Params and solver info: solver, steps, converged, loss, seconds (all of
    this call) and of those trace_s (tracing the solver), compile_s (XLA, on a second thread
    while the states are estimated; both 0 when compiled by an earlier call) and solve_s.
    """
    unknown = [f for f in fit if f not in FIT_GROUPS]
    if unknown:
        raise InputError("--fit", f"unknown name(s) {', '.join(unknown)}", ", ".join(FIT_GROUPS))
    if solver not in SOLVERS:
        raise InputError("--solver", f"unknown solver {solver!r}", ", ".join(SOLVERS))
    if init.settings.model != "blend":
        raise ValueError("fit_params: only the blend model is fitted (presets are baselines)")
    raw = unconstrain(init)
    free, fixed = eqx.partition(raw, _free_mask(raw, fit))
    targets = [(jnp.asarray(d.targets.xy_m), jnp.asarray(d.targets.mask)) for d in datasets]

    def shape_of(xy):  # every State field is (N,) in the default float dtype
        leaf = jax.ShapeDtypeStruct(xy.shape[:1], xy.dtype)
        return State(**{f.name: leaf for f in dataclasses.fields(State)})

    t0 = time.perf_counter()
    static = dict(max_steps=MAX_STEPS[solver] if max_steps is None else max_steps, solver=solver)
    abstract = [(shape_of(xy), d.track, xy, m) for d, (xy, m) in zip(datasets, targets)]
    leaves, treedef = jax.tree.flatten((free, fixed, abstract, huber_m))
    key = (treedef, tuple((jnp.shape(x), jnp.result_type(x)) for x in leaves), str(static))
    # XLA compiles the solver (seconds) on a second thread while this one estimates the states
    # (measured against estimating them on the second thread while this one traces, and against
    # no thread: 6.2 s vs 6.4 s and 6.7 s, medians of 6 fits of a 10-minute drive)
    took = {"trace_s": 0.0, "compile_s": 0.0}  # stay 0 when the solver was compiled before

    def compile_timed(lowered):
        t = time.perf_counter()
        compiled = lowered.compile()
        took["compile_s"] = time.perf_counter() - t
        return compiled

    with ThreadPoolExecutor(1) as pool:
        if key not in _COMPILED:
            lowered = _solve.lower(free, fixed, abstract, huber_m, **static)
            took["trace_s"] = time.perf_counter() - t0
            _COMPILED[key] = pool.submit(compile_timed, lowered)
        groups = [(d.states(init), d.track, *tm) for d, tm in zip(datasets, targets)]
        compiled = _COMPILED[key].result()
    t = time.perf_counter()
    value, steps, ok, loss = jax.block_until_ready(compiled(free, fixed, groups, huber_m))
    took["solve_s"] = time.perf_counter() - t
    fitted = constrain(eqx.combine(value, fixed))
    info = {
        "solver": solver,
        "steps": int(steps),
        "converged": bool(ok),
        "loss": float(loss),
        "seconds": time.perf_counter() - t0,
        **took,
    }
    return fitted, info


def predict_targets(params: Params, dataset: Dataset) -> np.ndarray:
    """(N, H, 3) predictions at a dataset's target rows."""
    return np.asarray(predict_batch(params, dataset.states(params), dataset.track))


def evaluate(params: Params, datasets: Sequence[Dataset], cov_m2=None) -> dict:
    """Metrics (see `metrics.summarize`) of params over datasets, plus coverage when cov given."""
    errs, res, masks = [], [], []
    for d in datasets:
        pred = predict_targets(params, d)
        errs.append(errors_m(pred[..., :2], d.targets.xy_m, d.targets.mask))
        if cov_m2 is not None:
            res.append(_track_residuals(pred, d))
            masks.append(d.targets.mask)
    out = summarize(np.concatenate(errs))
    if cov_m2 is not None:
        out.update(coverage(np.concatenate(res), np.concatenate(masks), np.asarray(cov_m2)))
    return out


def path_heading(track: Track, xy_m: np.ndarray) -> np.ndarray:
    """Path heading [rad] (N, H) at predicted positions (N, H, 2): the frame of the uncertainty."""
    along = jax.vmap(jax.vmap(track.project))(jnp.asarray(xy_m))
    return np.asarray(jax.vmap(jax.vmap(track.heading_at))(along))


def covariance_map(cov_track_m2, heading_rad: np.ndarray) -> np.ndarray:
    """(N, H, 2, 2) map-frame covariance [m^2] from the per-step track-frame one (H, 2, 2)."""
    c, s = np.cos(heading_rad), np.sin(heading_rad)
    rot = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)  # (N, H, 2, 2)
    return rot @ np.asarray(cov_track_m2)[None] @ np.swapaxes(rot, -1, -2)


def _track_residuals(pred: np.ndarray, d: Dataset) -> np.ndarray:
    heading = path_heading(d.track, pred[..., :2])
    return track_frame_residuals(pred[..., :2], d.targets.xy_m, heading)


def fit_uncertainty(params: Params, datasets: Sequence[Dataset]) -> dict:
    """Per-step residual covariance (H, 2, 2) in the (along-track, cross-track) frame."""
    res = np.concatenate([_track_residuals(predict_targets(params, d), d) for d in datasets])
    mask = np.concatenate([d.targets.mask for d in datasets])
    return {
        "frame": "track",
        "axes": ["along_m", "cross_m"],
        "cov_m2": fit_covariance(res, mask).tolist(),
    }


def split_drive(drive: Drive, holdout: float) -> tuple[Drive, Drive]:
    """Temporal split: the first (1 - holdout) of the drive's duration, and the rest."""
    if not 0.0 < holdout < 1.0:
        raise InputError("--holdout", f"{holdout} is outside (0, 1)", "a fraction such as 0.3")
    t_split = drive.t_s[0] + (1.0 - holdout) * drive.duration_s
    return drive.slice_time(-np.inf, t_split), drive.slice_time(t_split, np.inf)


def _datasets(drives: Sequence[Drive], tracks: Sequence[Track], settings: Settings, what: str):
    out = []
    for drv, trk in zip(drives, tracks, strict=True):
        targets = make_targets(drv, settings)
        if len(targets.rows) == 0:
            src = drv.meta.get("source", "drive")
            raise InputError(src, f"no usable predictions in the {what} part", "a longer drive")
        out.append(Dataset(drv, trk, targets))
    return out


def _before(d: Dataset, t_cut_s: float, dt_s: float) -> Dataset:
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


@dataclasses.dataclass
class FitResult:
    """What `fit` returns: the fitted params, their uncertainty and the held-out report."""

    params: Params
    uncertainty: dict
    report: dict  # name -> metrics on the held-out data (fitted + every preset)
    info: dict  # solver and selection details


def fit(
    drives: Sequence[Drive],
    tracks: Sequence[Track],
    *,
    fit: Sequence[str] = DEFAULT_FIT,
    blend: str = "auto",
    holdout: float = 0.3,
    test_drives: Sequence[Drive] | None = None,
    test_tracks: Sequence[Track] | None = None,
    init: Params | None = None,
    solver: str = DEFAULT_SOLVER,
    progress: Callable[[str], None] = lambda msg: None,
) -> FitResult:
    """Fit on the training data, report on held-out data.

    Args:
        drives, tracks: the drives to fit and the track each was driven on.
        fit: which values to fit (names of FIT_GROUPS).
        blend: "position", "heading", or "auto" (each is fitted on the first 75 % of the
            training data and the one with the lower validation loss on the rest is kept).
        holdout: fraction of each drive (its end) held out, unless test_drives are given.
        test_drives, test_tracks: separate held-out drives (then all of `drives` is training).
        init: starting point (default: the "default" preset).
        solver: "bfgs" or "lm" (see `fit_params`).
        progress: called with a short message at each phase.
    """
    jax.config.update("jax_enable_x64", True)  # fitting needs float64 (tiny gradients)
    init = init or presets["default"]
    settings = init.settings
    if test_drives is None:
        pairs = [split_drive(d, holdout) for d in drives]
        train_d, test_d = [p[0] for p in pairs], [p[1] for p in pairs]
        test_tracks = tracks
        split = {"kind": "temporal", "holdout": holdout}
    else:
        train_d, test_d = list(drives), list(test_drives)
        test_tracks = test_tracks or tracks
        split = {"kind": "drives", "n_test": len(test_d)}
    train = _datasets(train_d, tracks, settings, "training")
    test = _datasets(test_d, test_tracks, settings, "held-out")
    if "speed" in fit:  # start the typical speed where the data is
        v = np.concatenate([np.asarray(d.states(init).v_mps) for d in train])
        init = dataclasses.replace(init, speed_mps=jnp.asarray(max(float(np.median(v)), 0.1)))

    modes = BLEND_CHOICES if blend == "auto" else (blend,)
    selection = {}
    if len(modes) > 1:
        inner = [split_drive(d, 0.25) for d in train_d]
        # the inner fit masks the training targets after the inner split instead of slicing the
        # drives: the same shapes as the final fit, so the chosen mode's solver compiles once
        inner_val = _datasets([p[1] for p in inner], tracks, settings, "validation")
        inner_fit = [_before(d, v.drive.t_s[0], settings.dt_s) for d, v in zip(train, inner_val)]
        for mode in modes:
            progress(f"choosing the blend mode: fitting '{mode}' on the inner split")
            p0 = dataclasses.replace(init, settings=dataclasses.replace(settings, blend=mode))
            p, _ = fit_params(inner_fit, p0, fit=fit, solver=solver)
            selection[mode] = evaluate(p, inner_val)["ade_m"]
        best = min(selection, key=selection.get)
    else:
        best = modes[0]
    progress(f"fitting '{best}' blend on {sum(len(d.targets.rows) for d in train)} predictions")
    p0 = dataclasses.replace(init, settings=dataclasses.replace(settings, blend=best))
    params, info = fit_params(train, p0, fit=fit, solver=solver)
    progress("estimating uncertainty and evaluating on held-out data")
    uncertainty = fit_uncertainty(params, train)
    report = {"fitted": evaluate(params, test, uncertainty["cov_m2"])}
    for name in BASELINES:
        report[name] = evaluate(presets[name], test)
    info.update(blend=best, validation_ade_m=selection, split=split, fit=list(fit))
    return FitResult(params, uncertainty, report, info)


def provenance(result: FitResult, sources: Sequence[str], topics: dict) -> dict:
    """The provenance block of a tuned config."""
    from fpe_jax import __version__

    return {
        "drives": list(sources),
        "topics": topics,
        "split": result.info["split"],
        "fit": result.info["fit"],
        "blend_selection_ade_m": result.info["validation_ade_m"],
        "solver": {k: result.info[k] for k in ("solver", "steps", "converged", "loss", "seconds")},
        "heldout": result.report,
        "fitted_at": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "fpe_jax_version": __version__,
    }


def format_fitted(result: FitResult) -> str:
    """Two lines: the fitted values, and the per-step weights."""
    p, info = result.params.physical(), result.info
    return (
        f"fitted ({info['blend']} blend, {info['steps']} {info['solver']} steps): "
        f"lookahead {p['lookahead_m']:.3f} m + {p['lookahead_gain_s']:.3f} s * v, "
        f"delay {p['delay_s']:.3f} s, speed {p['speed_weight']:.2f} * measured + "
        f"{1 - p['speed_weight']:.2f} * {p['speed_mps']:.2f} m/s\n"
        "weights " + " ".join(f"{w:.3f}" for w in p["weights"])
    )


def format_table(report: dict) -> str:
    """A Markdown table of held-out metrics, one row per predictor."""
    h = len(next(iter(report.values()))["per_step_m"])
    steps = [0, h // 2 - 1, h - 1] if h >= 3 else list(range(h))
    head = "| predictor | ADE m | FDE m | FDE p90 m | miss rate | " + " | ".join(
        f"err@{k + 1} m" for k in steps
    )
    lines = [head + " | n |", "|" + "---|" * (6 + len(steps))]
    for name, m in report.items():
        cells = [m["ade_m"], m["fde_m"], m["fde_p90_m"], m["miss_rate"]]
        cells += [m["per_step_m"][k] for k in steps]
        lines.append(
            f"| {name} | " + " | ".join(f"{c:.3f}" for c in cells) + f" | {m['n_predictions']} |"
        )
    return "\n".join(lines)
