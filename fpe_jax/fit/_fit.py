"""Fit the predictor to recorded drives by robust, gradient-based least squares (optimistix).

Data flow: datasets of targets and states (`fpe_jax.evaluate`) -> residuals of the prediction
(Huber-weighted, masked) -> BFGS or Levenberg-Marquardt on the raw (unconstrained) parameters.
The blend mode is chosen on an inner validation split of the training data; held-out data is
only used for the final report (metrics and uncertainty: `fpe_jax.evaluate`).
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import time
import warnings
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from fpe_jax.compile import _aot as aot
from fpe_jax.compile._arrays import device_array
from fpe_jax.compile._rows import bucket, pad_rows
from fpe_jax.drive import Drive
from fpe_jax.errors import InputError
from fpe_jax.evaluate._evaluate import (
    Dataset,
    cross_fold_lines,
    evaluate,
    fit_uncertainty,
    make_datasets,
    predict_targets,
    split_drive,
    targets_before,
)
from fpe_jax.evaluate._metrics import errors_m
from fpe_jax.geometry._track import Track
from fpe_jax.model._params import (
    USER_SETTINGS,
    Params,
    Settings,
    constrain,
    presets,
    unconstrain,
    with_settings,
)
from fpe_jax.model._rollout import rollout
from fpe_jax.model._state import Poses, State
from fpe_jax.predict._predict import WINDOW_FIELDS, filtered, predict_poses, uses_filter
from fpe_jax.spec import BLEND_MODES, ESTIMATORS, FILTER_DEFAULTS, LINE_ESTIMATOR, LINE_KEYS
from fpe_jax.spec import DEFAULT_FIT as DEFAULT_FIT
from fpe_jax.spec import DEFAULT_SOLVER as DEFAULT_SOLVER
from fpe_jax.spec import FIT_GROUPS as FIT_GROUPS
from fpe_jax.spec import SOLVERS as SOLVERS

# the groups each fitted model reads, and its default: the line model has no memorised speed
MODEL_FIT = {
    "blend": (("lookahead", "lookahead_m", "gain", "weights", "delay", "speed"), DEFAULT_FIT),
    "line": (("delay", "tau", "pace", "smoothing", "filter"), ("delay", "tau", "smoothing")),
}
# Not "pace" by default: the pace's return to the profile assumes the car keeps the pace of the
# fit drives. Fitted on slow laps of the oval it went to ~15 /s, and on fast laps the prediction
# slowed to the slow profile at once (tests/fit/test_speed_shift.py: FDE 3.25 m against 0.15 m for
# a fit on fast laps). Where the opponent's pace is known to hold (a planner's 3-5 s on the
# drives the profile was learned from, experiments/horizon), `--fit` names it.
# the groups only one estimator has (the line model's defaults add its estimator's own)
ESTIMATOR_GROUPS = {"kalman": ("filter",), "theil-sen": ()}
# The filter's noise values and gate are fitted under a prior: a residual sqrt(FILTER_PRIOR_M2)
# log(value / FILTER_DEFAULTS) each, so a factor e away from the default costs as much as
# FILTER_PRIOR_M2 / 2 [m^2] of squared prediction error. The prediction error says little about
# them on one short drive: fitted freely on the first 60 % of the Levine lap they went to a stiff
# filter gated at 1 sigma that predicted the held-out 40 % worse (docs/model.md); a long drive
# moves them (its squared errors outweigh the prior).
FILTER_PRIOR_M2 = 100.0
FIT_MODELS = ("auto", *MODEL_FIT)  # spec.FIT_MODELS, which the CLI offers without JAX
# The line model predicts every study best: on the approaches study's eight drives (Levine
# included, where it holds the car's own offset beyond the fit part) no preset beats it at any
# step, while "auto"'s inner split chose the blend on Catalunya and Monza, and (with the blend's
# memorised speed) on a slow oval fit drive that missed the fast test laps (FDE 1.61 m)
DEFAULT_MODEL = "line"
BLEND_CHOICES = BLEND_MODES
BASELINES = ("seed", "seed-measured-speed", "linear", "pure-pursuit", "constant-velocity", "ctrv")
BASELINES += ("frenet",)
HUBER_M = 0.3  # residuals beyond this grow linearly: AprilTag jumps must not dominate
MIN_STEP_ERROR_M = 0.01  # `lead_time_scale`: a step's typical error counts as at least this
RAW_RIDGE = 1e-3  # light pull of raw values toward 0: stops saturated weights from drifting
# Consecutive weights are nearly interchangeable (a turn at step h or h+1 ends in about the same
# place), so without a prior the fit can alternate 0/1 between steps. The penalty costs a jump of
# 1 between neighbours as much as 1 % of the data's squared error budget at 1 m^2 per target.
WEIGHT_SMOOTHING_M2 = 0.01
# Both solvers are optimistix's. BFGS is the default: in experiments/results/solvers.md it ends
# at an equal (to 2e-10 relative) or lower loss on every drive (LM up to 3e-6 relative higher)
# in comparable time. An LM step needs the full Jacobian (~18 forward passes), a BFGS step one
# gradient.
# the default step limits of a minimiser (BFGS, which counts line-search trials too) and of a
# least-squares solver (Levenberg-Marquardt)
MAX_STEPS = {"minimise": 1000, "least_squares": 200}
# the names `info["solver"]` (and a config's provenance) give the two solvers the CLI offers
SOLVER_NAMES = {"BFGS": "bfgs", "LevenbergMarquardt": "lm"}
# BFGS minimises loss / (target points x BFGS_LOSS_UNIT_M2). Its first inverse Hessian is the
# identity, so this unit sets the first steps' length: on the raw sum (~1e4 on a 10-minute
# drive) most line-search trials were rejected. Of the units tried (1e-3 to 3e-2 m^2), 1/300
# took the fewest steps over the solver study's drives (experiments/results/solvers.md).
BFGS_LOSS_UNIT_M2 = 1.0 / 300
# On a long drive BFGS first minimises the loss of every k-th target row, k = rows //
# PRESOLVE_ROWS (at least 2), to a looser stop (PRESOLVE_DECREASE_RTOL), then goes on over all
# rows from that solution and that solve's inverse Hessian estimate. Most steps of a solve find
# the basin and the curvature, which a subsample of these 10 Hz rows shows nearly as well as the
# whole drive; the steps over all rows then only refine, with the curvature already known.
# experiments/results/presolve.md compares it with solving over all rows from the start on
# 5-minute drives (the same loss, fewer steps over all rows). It costs compilation: the loss is
# compiled for both row counts. A subsample of a few dozen rows can lead to another
# local minimum.
PRESOLVE_ROWS = 1024
PRESOLVE_DECREASE_RTOL = 1e-8
# A minimiser's loss is summed over blocks of this many target rows of each dataset, each block
# (and each shorter dataset) a `jax.checkpoint`, a long dataset's blocks in a scan
# (`_data_loss`): the solver's working memory is then that of one block, whatever the length
# of the logs, where it grew by ~0.5 GB per hour of 10 Hz logs. The price is one more forward
# rollout per gradient, so data of fewer than two blocks in all stay one piece: the
# benchmark's 10-minute drive (6144 padded rows) runs exactly as before.
FIT_BLOCK_ROWS = 8192
# A fit with "pace" free starts the pace's return to the profile at a 5 s time constant (when
# its start has none), within the horizons planners read: from 0 (the car's own pace kept, where
# the softplus is flat) the solver could not move it
PACE_RETURN_INIT_1PS = 0.2


def _huber_scale(err_m, delta_m):
    """Factor that turns a squared residual into a Huber one: 1/2 (scale e)^2 = huber(e)."""
    safe = jnp.maximum(err_m, delta_m)
    return jnp.where(err_m <= delta_m, 1.0, jnp.sqrt(delta_m * (2.0 * safe - delta_m)) / safe)


def robust_residuals(weights, preds, targets, masks, raw_values, huber_m, step_scales=None):
    """The fit's residual vector from its predictions: the smoothness prior on neighbouring
    weights, the Huber-scaled masked position errors, the ridge on the raw values.

    Any predictor's output can be scored with it (the benchmarks' SciPy baseline scores the
    on-car runner's NumPy predictions); `_residuals` feeds it the JAX rollout's.

    Args:
        weights: (H,) the blend weights of the physical params.
        preds, targets, masks: per dataset the predicted and target positions (N, H, 2) [m] and
            which targets exist (N, H). `preds` may be an iterator: each prediction is taken
            after the previous dataset's residuals, the order the JAX fit is compiled in.
        raw_values: the fitted raw values (arrays of any shape).
        huber_m: residuals beyond this grow linearly [m].
        step_scales: per dataset None or (H,) factors on each step's residuals
            (`lead_time_scale`); None: all 1.
    """
    n_targets = sum(jnp.sum(mask) for mask in masks).astype(weights.dtype)
    out = [jnp.sqrt(WEIGHT_SMOOTHING_M2 * n_targets) * jnp.diff(weights)]
    scales = [None] * len(masks) if step_scales is None else step_scales
    for pred, target, mask, scale in zip(preds, targets, masks, scales):
        out.append(_data_residuals(pred, target, mask, huber_m, scale).reshape(-1))
    ridge = [jnp.sqrt(RAW_RIDGE) * jnp.ravel(x) for x in raw_values]
    return jnp.concatenate(out + ridge)


def _data_residuals(pred, target, mask, huber_m, step_scale=None):
    """(..., H, 2) Huber-scaled position errors [m] of predictions (..., H, 2) at their targets,
    each step's times step_scale (H,) (None: 1), 0 where the mask (..., H) has no target."""
    d = pred - target
    e = jnp.sqrt(jnp.sum(d * d, axis=-1) + 1e-12)
    factor = _huber_scale(e, huber_m)
    if step_scale is not None:
        factor = factor * jnp.reshape(step_scale, (1,) * (factor.ndim - 1) + (-1,))
    return jnp.where(mask[..., None], d * factor[..., None], 0.0)


def _filter_prior(params: Params, raw_free) -> list:
    """The prior's residuals on the filter's values that are free (FILTER_PRIOR_M2); [] when
    none is."""
    free_filter = [k for k in FILTER_DEFAULTS if getattr(raw_free, k) is not None]
    prior = [jnp.log(getattr(params, k) / FILTER_DEFAULTS[k]) for k in free_filter]
    return [np.sqrt(FILTER_PRIOR_M2) * jnp.stack(prior)] if prior else []


def _residuals(raw_free, args):
    """Residual vector of the raw free values: `robust_residuals` of the JAX rollout, and the
    prior on the filter's values where they are free (`FILTER_PRIOR_M2`)."""
    raw_fixed, groups, huber_m = args
    params = constrain(eqx.combine(raw_free, raw_fixed))
    preds = (_group_poses(params, g[0], g[1], g[4], g[5]).xy_m for g in groups)
    targets, masks = [g[2] for g in groups], [g[3] for g in groups]
    raw = jax.tree.leaves(raw_free)
    scales = [g[6] for g in groups]
    out = robust_residuals(params.weights, preds, targets, masks, raw, huber_m, scales)
    prior = _filter_prior(params, raw_free)
    return jnp.concatenate([out, *prior]) if prior else out


def _group_poses(params: Params, states: State, track: Track, fold, lines) -> Poses:
    """`predict_poses` of N states (leading axis N); with cross-fitted lines (`_cross_lines`:
    fold (N,) int, lines a dict of the profile's arrays (F, P)) each row's prediction uses its
    fold's line instead of params' own."""
    if lines is None:
        return predict_poses(params, states, track)

    def one(state, f):
        p = dataclasses.replace(params, **{k: jnp.asarray(v)[f] for k, v in lines.items()})
        return rollout(p, filtered(p, state, track), track)

    return jax.vmap(one)(states, fold)


def _cross_lines(datasets: Sequence[Dataset]):
    """The line model's cross-fitted lines for datasets fitted as one group: (fold (N,) int over
    all their rows, in order; lines: dict of (F, P) arrays, every dataset's folds in turn)."""
    folds, lines = [], []
    for d in datasets:
        fold, per_fold = cross_fold_lines(d)
        folds.append(fold + len(lines))
        lines += per_fold
    stacked = {k: np.stack([line[k] for line in lines]) for k in LINE_KEYS}
    return np.concatenate(folds).astype(np.int32), stacked


def lead_time_scale(params: Params, datasets: Sequence[Dataset]) -> np.ndarray:
    """(H,) factors on each step's residuals in the fit: mean(e) / e_h, e_h the mean error [m]
    of params' predictions (the fit's start) at step h over datasets.

    A prediction's error grows with its lead time (on the Levine lap from 0.12 m at 0.1 s to
    1.6 m at 5 s): summed as they are, the last steps' metres outweigh the first second's
    centimetres, and the values that set the near term (delay, filter) are fitted to serve the
    tail. Scaled by the typical error at its lead time, every step counts alike.
    """
    err = np.asarray(evaluate(params, list(datasets))["per_step_m"], dtype=np.float64)
    err = np.where(np.isfinite(err), err, np.nanmean(err) if np.isfinite(err).any() else 1.0)
    scale = 1.0 / np.maximum(err, MIN_STEP_ERROR_M)
    # normalised to a mean square of 1 over the targets: the data weigh as much in all against
    # the priors (FILTER_PRIOR_M2, the ridge) as unscaled
    count = sum(np.asarray(d.targets.mask).sum(axis=0) for d in datasets)
    return scale / np.sqrt(np.sum(count * scale**2) / max(np.sum(count), 1))


def _free_mask(params: Params, free: Sequence[str]) -> Params:
    """A Params-shaped filter: True for the fields of the groups `free` (mapped over the leaves:
    a Params of bools is no valid Params to construct)."""
    names = {f for group in free for f in FIT_GROUPS[group]}
    return jax.tree_util.tree_map_with_path(lambda path, _: path[0].name in names, params)


def _loss(raw_free, args, block_rows: int | None = None, devices: int = 1):
    """The scalar robust loss 1/2 |residuals|^2 (what BFGS minimises), in row blocks.

    BFGS linearizes it at each trial point and transposes the linearization (reverse mode: the
    gradient) only where its line search accepts the point, so a rejected trial costs one
    forward rollout. A hand-written value-and-gradient derivative would compute the gradient at
    every trial (16-22 % more solve time over seven 10-minute drives, at the same losses).

    With block_rows, each dataset's loss is summed block by block (`_data_loss`; a dataset of
    fewer than two blocks is one): the linearization then keeps O(block_rows) intermediates
    instead of O(rows of all datasets). None, or fewer than two blocks of rows in all: the sum
    of the squares of `_residuals`, in one piece. devices: over how many of `jax.devices()` the
    blocks are spread (`_data_loss`).
    """
    raw_fixed, groups, huber_m = args
    if block_rows is None or sum(g[2].shape[0] for g in groups) < 2 * block_rows:
        r = _residuals(raw_free, args)
        return 0.5 * jnp.sum(r * r)
    params = constrain(eqx.combine(raw_free, raw_fixed))
    masks = [g[3] for g in groups]
    rest = robust_residuals(params.weights, (), (), masks, jax.tree.leaves(raw_free), huber_m)
    rest = jnp.concatenate([rest, *_filter_prior(params, raw_free)])
    data = [_data_loss(params, *g, huber_m, block_rows, devices) for g in groups]
    return 0.5 * jnp.sum(rest * rest) + sum(data)


def _block_loss(
    params: Params, states: State, track: Track, xy_m, mask, fold, lines, scale, huber_m
):
    """1/2 the sum of the squared `_data_residuals` of the predictions from states (leading
    axis N) at their targets xy_m (N, H, 2) [m], mask (N, H), steps scaled by scale (H,);
    fold, lines: `_group_poses`."""
    pred = _group_poses(params, states, track, fold, lines).xy_m
    r = _data_residuals(pred, xy_m, mask, huber_m, scale)
    return 0.5 * jnp.sum(r * r)


def _data_loss(
    params,
    states,
    track,
    xy_m,
    mask,
    fold,
    lines,
    scale,
    huber_m,
    block_rows: int,
    devices: int = 1,
):
    """`_block_loss` of N rows summed over blocks of block_rows rows (a scan; the rows past the
    last whole block as one more, shorter block; fewer than two blocks' rows as one block).

    Each block is a `jax.checkpoint`: the loss's linearization keeps only the block's inputs
    (the data, already held) and recomputes its rollout when transposed, so the solver's
    memory is O(block_rows) in the data, not O(N), at the cost of one more forward rollout
    per gradient (`FIT_BLOCK_ROWS` says when this applies). With devices > 1 and whole blocks
    that divide evenly among them, the blocks are spread over the first `devices` of
    `jax.devices()` (`_sharded_sum`)."""
    n = xy_m.shape[0]
    whole = n // block_rows * block_rows
    one = jax.checkpoint(_block_loss)
    if whole <= block_rows:  # at most one whole block: no scan
        return one(params, states, track, xy_m, mask, fold, lines, scale, huber_m)
    data = (states, xy_m, mask, fold)
    blocks = jax.tree.map(lambda x: x[:whole].reshape(-1, block_rows, *x.shape[1:]), data)
    huber_m = jnp.asarray(huber_m, xy_m.dtype)
    if devices > 1 and whole == n and (n // block_rows) % devices == 0:
        return _sharded_sum(params, track, huber_m, blocks, (lines, scale), devices)
    total = _scan_blocks(params, track, huber_m, blocks, (lines, scale))
    if whole < n:
        tail = jax.tree.map(lambda x: x[whole:], data)
        total = total + one(params, tail[0], track, *tail[1:], lines, scale, huber_m)
    return total


def _scan_blocks(params, track, huber_m, blocks, shared):
    """The sum of `_block_loss` over blocks (states, xy_m, mask, fold) with a leading block
    axis, one checkpointed block at a time; shared: every block's (lines, scale)."""
    one = jax.checkpoint(_block_loss)

    def block_loss(carry, block):
        return carry, one(params, block[0], track, *block[1:], *shared, huber_m)

    _, per_block = jax.lax.scan(block_loss, None, blocks)
    return jnp.sum(per_block)


def _sharded_sum(params, track, huber_m, blocks, shared, devices: int):
    """`_scan_blocks` with the blocks split evenly over a mesh of the first `devices` JAX
    devices (`jax.shard_map`): each device scans its own blocks, the partial sums are added
    (`psum`, whose transpose hands every device the same cotangent), params and track are
    copied to every device.

    The copies enter each device's computation as values that vary by device (`pcast`): the
    line model's filter and rollout scan carries that start from params and take in the
    device's own rows, and a scan's carry must keep one such type. Its transpose adds the
    devices' cotangents, the gradient of params."""
    from jax.sharding import Mesh
    from jax.sharding import PartitionSpec as P

    mesh = Mesh(np.array(jax.devices()[:devices]), ("blocks",))

    def local(params, track, huber_m, blocks, shared):
        params, track, huber_m, shared = jax.lax.pcast(
            (params, track, huber_m, shared), ("blocks",), to="varying"
        )
        return jax.lax.psum(_scan_blocks(params, track, huber_m, blocks, shared), "blocks")

    specs = (P(), P(), P(), P("blocks"), P())
    return jax.shard_map(local, mesh=mesh, in_specs=specs, out_specs=P())(
        params, track, huber_m, blocks, shared
    )


def default_solver():
    """BFGS on the scalar robust loss, the default solver (see the solver notes above MAX_STEPS):
    optimistix's, stopping also once its next step is predicted to lower the loss by at most
    1e-10 of it (`fpe_jax.fit.BFGS` says why).

    rms_norm in the stopping test: with the default max_norm a solver stops only once every one of
    the ~1e5 residuals and every raw value has settled, which a saturating weight or a gain
    creeping toward its bound never does (LM ran to max_steps on every drive measured)."""
    # imported here: predict, evaluate and plot use this module but not the solver, and
    # optimistix adds ~0.3 s to their start
    from fpe_jax.fit._bfgs import BFGS

    return BFGS(rtol=1e-6, atol=1e-8, decrease_rtol=1e-10)


class _Static:
    """A solver as one static argument of the compiled solve. The compiled solve is keyed by the
    printed form of its static arguments; a solver's pytree leaves include functions (its norm)
    whose printed form holds a memory address, so the key would change with every process.
    `eqx.tree_pformat` prints the solver's type and settings with functions by name.

    None stands for `default_solver()`, built only when the solve is traced: a warm fit (its
    solve loaded from the cache, `fpe_jax.compile`) then never imports optimistix (~0.3 s). The
    package's source is part of every key, so a changed default compiles anew."""

    def __init__(self, solver=None):
        self._solver = solver
        self._key = (
            "default_solver()" if solver is None else eqx.tree_pformat(solver, short_arrays=False)
        )

    @property
    def solver(self):
        return default_solver() if self._solver is None else self._solver

    def __repr__(self) -> str:
        return self._key


def _is_least_squares(solver) -> bool:
    """Whether solver is a least-squares one; None (the default, BFGS) is not, and asking
    imports no optimistix."""
    if solver is None:
        return False
    import optimistix as optx

    return isinstance(solver, optx.AbstractLeastSquaresSolver)


def _solver_object(solver):
    """`solver` checked to be an optimistix solver; None (the default solver) stays None, so
    that a warm fit need not import optimistix (`_Static`)."""
    if solver is None:
        return None
    import optimistix as optx

    if not isinstance(solver, optx.AbstractMinimiser | optx.AbstractLeastSquaresSolver):
        what = repr(solver) if isinstance(solver, str) else type(solver).__name__
        raise InputError(
            "solver",
            f"{what} is not an optimistix solver",
            "an optimistix minimiser or least-squares solver such as optx.BFGS(rtol, atol); "
            "fpe_jax.fit.solver_named turns the CLI's names (bfgs, lm) into them",
        )
    return solver


def _per_unit(unravel, groups, block_rows: int | None, devices: int = 1):
    """The BFGS objective over `groups`: the loss of the flat raw values (in row blocks of
    block_rows over `devices`, `_loss`) in units of BFGS_LOSS_UNIT_M2 per target point (at
    least one), and that unit [m^2], computed once here rather than at every evaluation."""
    n_points = sum(jnp.sum(g[3]) for g in groups)
    unit = BFGS_LOSS_UNIT_M2 * jnp.maximum(n_points, 1).astype(groups[0][2].dtype)
    return (lambda y, a: _loss(unravel(y), a, block_rows, devices) / unit), unit


def _presolve_groups(groups, presolve_rows: int):
    """Every k-th row of each group (states, track, targets (N, H, 2), mask (N, H)), k = all
    groups' rows // presolve_rows: the data of BFGS's pre-solve (PRESOLVE_ROWS). None where k
    < 2 (or presolve_rows <= 0): too short a drive for a pre-solve to save steps."""
    stride = sum(g[2].shape[0] for g in groups) // presolve_rows if presolve_rows > 0 else 0
    if stride < 2:
        return None
    cut = functools.partial(jax.tree.map, lambda x: x[::stride])
    return [
        (cut(states), track, cut(xy), cut(mask), cut(fold), lines, scale)
        for states, track, xy, mask, fold, lines, scale in groups
    ]


@aot.fusion_emitters
def _solve(
    raw_free,
    raw_fixed,
    groups,
    huber_m,
    max_steps: int,
    solver: _Static,
    presolve_rows: int,
    block_rows: int | None = None,
    devices: int = 1,
):
    """Run the optimistix solver; returns (raw values, steps, pre-solve steps, converged, loss).

    The solver works on the free raw values as one flat vector (13 for the blend's default
    groups) rather than on the Params pytree: a BFGS step then updates one small matrix instead
    of a Params of Params, and the 10-minute oval fit's steps took 8.0 instead of 10.5 ms
    (a third less under load), at the same losses on the solver study's drives. The package's
    BFGS (`fpe_jax.fit.BFGS`, the default) first solves on a subsample of a long drive's rows
    (`_presolve_groups`, PRESOLVE_ROWS); max_steps applies to each of the two solves. A
    minimiser's loss runs in row blocks of block_rows (`_loss`, FIT_BLOCK_ROWS), spread over
    `devices`; a least-squares solver needs the whole residual vector.
    """
    import optimistix as optx
    from jax.flatten_util import ravel_pytree

    from fpe_jax.fit._bfgs import BFGS

    args = (raw_fixed, groups, huber_m)
    y0, unravel = ravel_pytree(raw_free)
    method = solver.solver
    least_squares = _is_least_squares(method)
    options, presolve_steps = {}, 0
    if least_squares:
        run, fn = optx.least_squares, lambda y, a: _residuals(unravel(y), a)
    else:
        run, (fn, unit) = optx.minimise, _per_unit(unravel, groups, block_rows, devices)
        sub = _presolve_groups(groups, presolve_rows) if isinstance(method, BFGS) else None
        if sub is not None:
            loose = eqx.tree_at(lambda m: m.decrease_rtol, method, PRESOLVE_DECREASE_RTOL)
            first = optx.minimise(
                _per_unit(unravel, sub, block_rows, devices)[0],
                loose,
                y0,
                args=(raw_fixed, sub, huber_m),
                max_steps=max_steps,
                throw=False,
            )
            y0, presolve_steps = first.value, first.stats["num_steps"]
            options["hessian_inv"] = first.state.f_info.hessian_inv.pytree
    sol = run(fn, method, y0, args=args, max_steps=max_steps, throw=False, options=options)
    ok = sol.result == optx.RESULTS.successful
    value = unravel(sol.value)
    # the solver's own evaluation at its last accepted point (sol.value): no further rollout
    # to trace and compile (the first step is always accepted, so this is never its zero init);
    # a solver that keeps no such evaluation costs one more
    info = getattr(sol.state, "f_info", None)
    if least_squares and hasattr(info, "residual"):
        loss = 0.5 * jnp.sum(info.residual * info.residual)
    elif not least_squares and hasattr(info, "f"):
        loss = info.f * unit
    else:
        loss = _loss(value, args, None if least_squares else block_rows)
    return value, sol.stats["num_steps"], presolve_steps, ok, loss


def _by_track(datasets: Sequence[Dataset]) -> list[list[Dataset]]:
    """The datasets grouped by their track (equal arrays and settings), in first-seen order."""
    parts: dict[str, list[Dataset]] = {}
    for d in datasets:
        h = hashlib.sha256(str(jax.tree.structure(d.track)).encode())
        for leaf in jax.tree.leaves(d.track):
            h.update(np.ascontiguousarray(leaf).tobytes())
        parts.setdefault(h.hexdigest(), []).append(d)
    return list(parts.values())


def _joined(trees: list):
    """Pytrees of equal structure, their leaves (N_i, ...) concatenated as NumPy (sum N_i, ...)."""
    if len(trees) == 1:
        return trees[0]
    return jax.tree.map(lambda *xs: np.concatenate([np.asarray(x) for x in xs]), *trees)


def _free_groups(free, fit, caller: str):
    """The free groups given as `free=`, or as the deprecated `fit=` (one of them)."""
    if fit is None:
        return free
    if free is not None:
        raise TypeError(f"{caller}: pass free= only (fit= is its deprecated name)")
    warnings.warn(
        f"{caller}(fit=...) is deprecated: the free parameter groups are now free=",
        DeprecationWarning,
        stacklevel=3,
    )
    return fit


def _require_float64(caller: str) -> None:
    """Refuse to fit in float32: the loss's gradients are too small for it and the solver stalls.

    The dtype is the program's choice (set once at start-up, as the fpe CLI does), so a library
    call neither flips the global flag under its caller nor casts: without x64 JAX has no float64
    to cast to.
    """
    if not jax.config.jax_enable_x64:
        raise InputError(
            "jax_enable_x64",
            f"{caller} needs float64 but JAX runs in float32",
            'jax.config.update("jax_enable_x64", True) at start-up, before any JAX array is made',
        )


def fit_params(
    datasets: Sequence[Dataset],
    init: Params,
    *,
    free: Sequence[str] | None = None,
    huber_m: float = HUBER_M,
    solver=None,
    max_steps: int | None = None,
    fit: Sequence[str] | None = None,
    presolve_rows: int = PRESOLVE_ROWS,
    block_rows: int | None = None,
    devices: int = 1,
) -> tuple[Params, dict]:
    """Fit the free raw parameters of `init` over all datasets jointly (optimistix, float64).

    Args:
        free: the parameter groups to fit (names of FIT_GROUPS; default: the model's,
            `default_groups`; the line model's "filter" needs settings.estimator "kalman",
            "smoothing" the Theil-Sen one). `fit=` is its deprecated name.
        solver: an optimistix solver. A minimiser (default `default_solver()`: BFGS) minimises
            the scalar robust loss with reverse-mode gradients: a step costs about one forward
            and one backward pass. A least-squares solver (optx.LevenbergMarquardt) works on the
            residual vector, forward-mode Jacobians (one pass per fitted value, ~15) per step.
            experiments/results/solvers.md compares the two.
        max_steps: solver steps before giving up (default per kind of solver, MAX_STEPS).
        presolve_rows: with the package's BFGS (the default solver), data of at least twice
            this many target rows are first fitted on every k-th row, k = rows //
            presolve_rows, and the solve over all rows starts from there (PRESOLVE_ROWS says
            why); 0 solves over all rows from the start.
        block_rows: a minimiser's loss and gradient are accumulated over blocks of this many
            target rows of each dataset, so that its memory does not grow with the data
            (default FIT_BLOCK_ROWS, which says why; a dataset of fewer than twice as many
            rows is one block). The fitted values depend on it only through the order of the
            sum.
        devices: spread a minimiser's row blocks over the first this many of `jax.devices()`
            (a mesh, `jax.shard_map`); each dataset's rows are then padded to a multiple of
            block_rows x devices. On the CPU, XLA_FLAGS=--xla_force_host_platform_device_count=N
            (set before JAX starts) makes N devices of the host's cores.

    Returns the fitted Params and solver info: solver (its name: "bfgs", "lm" or the class
    name), steps (over all rows), presolve_steps (over the subsample; 0 without), converged,
    loss, devices (that shared the row blocks), processes (JAX's processes), seconds (all of
    this call) and of those trace_s (tracing the solver), compile_s (XLA) or load_s (its stored
    executable, `aot`), all on a second thread while the states are estimated and all 0 when an
    earlier call made it, and solve_s.

    Raises InputError naming the argument (free, solver, presolve_rows) for a value it cannot
    use, and naming jax_enable_x64 when JAX runs in float32 (`_require_float64`).
    """
    _require_float64("fit_params")
    free = _free_groups(free, fit, "fit_params")
    if init.settings.model not in MODEL_FIT:
        raise ValueError(f"fit_params: only the models {tuple(MODEL_FIT)} are fitted, not presets'")
    names = tuple(free) if free else default_groups(init.settings)
    unknown = [f for f in names if f not in FIT_GROUPS]
    if unknown:
        raise InputError("free", f"unknown name(s) {', '.join(unknown)}", ", ".join(FIT_GROUPS))
    solver = _solver_object(solver)
    allowed = allowed_groups(init.settings)
    if any(f not in allowed for f in names):
        wrong = ", ".join(f for f in names if f not in allowed)
        msg = f"{wrong} do(es) not apply to model {init.settings.model}"
        if init.settings.model == "line":
            msg += f" with the {init.settings.estimator} estimator"
        raise InputError("free", msg, ", ".join(allowed))
    whole = isinstance(presolve_rows, int | np.integer) and not isinstance(presolve_rows, bool)
    if not whole or presolve_rows < 0:
        raise InputError("presolve_rows", repr(presolve_rows), "a whole number >= 0 (0: none)")
    block_rows = FIT_BLOCK_ROWS if block_rows is None else block_rows
    whole = isinstance(block_rows, int | np.integer) and not isinstance(block_rows, bool)
    if not whole or block_rows < 1:
        raise InputError("block_rows", repr(block_rows), "a whole number >= 1")
    n_devices = len(jax.devices())
    whole = isinstance(devices, int | np.integer) and not isinstance(devices, bool)
    if not whole or not 1 <= devices <= n_devices:
        raise InputError("devices", repr(devices), f"a whole number from 1 to {n_devices}")
    if "pace" in names and float(init.pace_return_1ps) <= 0.0:
        init = dataclasses.replace(init, pace_return_1ps=jnp.asarray(PACE_RETURN_INIT_1PS))
    raw = unconstrain(init)
    free, fixed = eqx.partition(raw, _free_mask(raw, names))
    # targets and states padded to a bucketed row count (padded targets masked out): drives of
    # similar length share one compiled solver. Data of two or more blocks are solved in row
    # blocks; then the drives on one track are joined into one row set, so that the program
    # (and its compilation) does not grow with the number of drives either
    parts = [[d] for d in datasets]
    if not _is_least_squares(solver) and sum(len(d.targets.rows) for d in datasets) >= (
        2 * block_rows
    ):
        parts = _by_track(datasets)
    rows = [sum(len(d.targets.rows) for d in part) for part in parts]
    sizes = [bucket(n) for n in rows]
    if devices > 1:  # whole blocks, as many on every device
        per = block_rows * devices
        sizes = [-(-n // per) * per if n > block_rows else n for n in sizes]
    targets = [
        (
            pad_rows(np.concatenate([d.targets.xy_m for d in part]), n),
            pad_rows(np.concatenate([d.targets.mask for d in part]), n)
            & (np.arange(n) < m)[:, None],
        )
        for part, n, m in zip(parts, sizes, rows)
    ]

    kalman = uses_filter(init.settings)

    def shape_of(xy):  # every State field is (N,) in the default float dtype, a window (N, W)
        leaf = jax.ShapeDtypeStruct(xy.shape[:1], xy.dtype)
        fields = {f.name: leaf for f in dataclasses.fields(State)}
        for f in WINDOW_FIELDS:
            width = 5 if f == "window_prior" else init.settings.history
            window = jax.ShapeDtypeStruct((xy.shape[0], width), xy.dtype)
            fields[f] = window if kalman else None
        cov = jax.ShapeDtypeStruct((xy.shape[0], 4, 4), xy.dtype)
        return State(**fields | {"filter_cov": cov if kalman else None})

    t0 = time.perf_counter()
    kind = "least_squares" if _is_least_squares(solver) else "minimise"
    steps_limit = MAX_STEPS[kind] if max_steps is None else max_steps
    static = dict(
        max_steps=steps_limit,
        solver=_Static(solver),
        presolve_rows=int(presolve_rows),
        block_rows=int(block_rows),
        devices=int(devices),
    )
    # With the pace's return free (the long-horizon fit), the line model is fitted on
    # predictions from lines that did not see the rows they predict (`cross_fold_lines`), as a
    # drive the fit never saw is predicted: from its own line the fit drive's pace looks like
    # the profile's (fitted so on the first 60 % of the Levine lap, the return went to 15 /s,
    # where the held-out 40 % asked for 0.3-0.5 /s); and every step counts alike
    # (`lead_time_scale`, one for all the data however grouped). The default groups keep the
    # in-sample line and plain residuals: on the approaches study's simulated drives, whose
    # test drives the final line covers everywhere, the cross-fitted lines (which leave
    # stretches of a one-lap drive uncovered) made the 1 s FDE up to 5 % worse.
    long_horizon = "pace" in names and init.settings.model == "line"
    cross = [(None, None)] * len(parts)
    scales = [None] * len(parts)
    if long_horizon:
        cross = [_cross_lines(part) for part in parts]
        cross = [(pad_rows(fold, n), lines) for (fold, lines), n in zip(cross, sizes)]
        scales = [lead_time_scale(init, datasets)] * len(parts)
    abstract = [
        (shape_of(xy), part[0].track, xy, m, *c, sc)
        for part, (xy, m), c, sc in zip(parts, targets, cross, scales)
    ]
    huber = np.float64(huber_m)
    # the solver's executable (from memory, from disk, or traced and compiled: seconds) is made
    # on a second thread from shapes alone while this one estimates the states
    pool = ThreadPoolExecutor(1)
    try:
        pending = pool.submit(aot.executable, _solve, free, fixed, abstract, huber, **static)
        groups = [
            (pad_rows(_joined([d.states(init) for d in part]), n), part[0].track, *tm, *c, sc)
            for part, n, tm, c, sc in zip(parts, sizes, targets, cross, scales)
        ]
        compiled = pending.result()
    finally:  # an error or a Ctrl-C is reported without waiting for the compile to finish
        pool.shutdown(wait=False, cancel_futures=True)
    took = dict(compiled.seconds)
    t = time.perf_counter()
    out = jax.block_until_ready(compiled(free, fixed, groups, huber, **static))
    if devices > 1:  # replicated over the mesh: this process's copy, where the rest runs
        out = jax.tree.map(lambda x: x.addressable_data(0), out)
    value, steps, presolve_steps, ok, loss = out
    took["solve_s"] = time.perf_counter() - t
    fitted = constrain(eqx.combine(value, fixed))
    name = type(solver).__name__
    info = {
        "solver": "bfgs" if solver is None else SOLVER_NAMES.get(name, name),
        "steps": int(steps),
        "presolve_steps": int(presolve_steps),
        "converged": bool(ok),
        "loss": float(loss),
        "seconds": time.perf_counter() - t0,
        "devices": int(devices),
        "processes": jax.process_count(),
        **took,
    }
    return fitted, info


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
    free: Sequence[str] | None = None,
    model: str = DEFAULT_MODEL,
    blend: str = "auto",
    holdout: float = 0.3,
    test_drives: Sequence[Drive] | None = None,
    test_tracks: Sequence[Track] | None = None,
    init: Params | None = None,
    solver=None,
    progress: Callable[[str], None] = lambda msg: None,
    fit: Sequence[str] | None = None,
    estimator: str = LINE_ESTIMATOR,
    devices: int = 1,
    block_rows: int | None = None,
) -> FitResult:
    """Fit on the training data, report on held-out data.

    Args:
        drives, tracks: the drives to fit and the track each was driven on.
        free: the parameter groups to fit (names of FIT_GROUPS; default: the model's,
            `default_groups`). `fit=` is its deprecated name.
        model: "line" (the opponent's line and speed profile, learned from the training
            drives, `fpe_jax.model`; every training and test drive must share one set of
            waypoints; the default), "blend" (linear / pure-pursuit blend) or "auto" (each
            candidate, the line model and the blend in each mode of `blend`, is fitted on the
            first 75 % of the training data, the line learned from that part only, and the one
            with the lowest validation ADE on the rest, reweighted to the final line's coverage
            (`_expected_ade`), is fitted on all of it; `info["model"]` says which and why). The
            winner is then fitted exactly as when named.
        blend: for the blend model: "position", "heading", or "auto" (each mode is a candidate
            on the inner split, as above).
        holdout: fraction of each drive (its end) held out, unless test_drives are given.
        test_drives, test_tracks: separate held-out drives (then all of `drives` is training).
        init: starting point (default: the "default" preset). For the line model a Params of
            another model only lends its car and prediction grid (`USER_SETTINGS`).
        solver: an optimistix solver (default `default_solver()`; see `fit_params`).
        progress: called with a short message at each phase.
        estimator: the line model's track-frame state estimator, "kalman" (the default; its
            noise values are the "filter" group) or "theil-sen" (ignored when `init` is a
            line-model Params: its own applies).
        devices: how many of `jax.devices()` share each solve's row blocks (`fit_params`;
            after `jax.distributed` has started, the devices of every process: `_processes`).
        block_rows: target rows per block of the loss (`fit_params`; default FIT_BLOCK_ROWS).

    Raises InputError naming the argument (free, model, solver, estimator) for a value it
    cannot use, and
    naming jax_enable_x64 when JAX runs in float32 (`_require_float64`).
    """
    _require_float64("fit")
    free = _free_groups(free, fit, "fit")
    solver = _solver_object(solver)
    if test_drives is None:
        pairs = [split_drive(d, holdout) for d in drives]
        train_d, test_d = [p[0] for p in pairs], [p[1] for p in pairs]
        test_tracks = tracks
        split = {"kind": "temporal", "holdout": holdout}
    else:
        train_d, test_d = list(drives), list(test_drives)
        test_tracks = test_tracks or tracks
        split = {"kind": "drives", "n_test": len(test_d)}
    if model not in FIT_MODELS:
        raise InputError("model", f"unknown model {model!r}", ", ".join(FIT_MODELS))
    if estimator not in ESTIMATORS:
        raise InputError("estimator", f"unknown estimator {estimator!r}", ", ".join(ESTIMATORS))
    free = tuple(free) if free else None
    candidates, line_info = _candidates(
        model, blend, init, free, train_d, tracks, test_tracks, progress, estimator
    )
    settings = next(iter(candidates.values()))[0].settings  # every candidate's targets
    # the first states estimate of every dataset also runs the Kalman filter (`Dataset.kalman`)
    # when a candidate or a baseline uses it: one compiled states program then serves the
    # training, validation and held-out data, a blend's own states included
    scored = [p.settings for p, _ in candidates.values()] + [presets[n].settings for n in BASELINES]
    kalman = any(uses_filter(s) for s in scored)
    train = make_datasets(train_d, tracks, settings, "training", kalman=kalman)
    test = make_datasets(test_d, test_tracks, settings, "held-out", kalman=kalman)
    for label, (p0, groups) in candidates.items():
        if "speed" in groups:  # start the typical speed where the data is
            v = np.concatenate([np.asarray(d.states(p0).v_mps) for d in train])
            p0 = dataclasses.replace(p0, speed_mps=jnp.asarray(max(float(np.median(v)), 0.1)))
            candidates[label] = (p0, groups)

    selection = {}
    if len(candidates) > 1:
        inner = [split_drive(d, 0.25) for d in train_d]
        # the inner fit masks the training targets after the inner split instead of slicing the
        # drives: the same shapes as the final fit, so the chosen candidate's solver compiles once
        inner_val = make_datasets(
            [p[1] for p in inner], tracks, settings, "validation", kalman=kalman
        )
        inner_fit = [
            targets_before(d, v.drive.t_s[0], settings.dt_s) for d, v in zip(train, inner_val)
        ]
        score = lambda p: evaluate(p, inner_val)["ade_m"]  # noqa: E731
        if "line" in candidates:
            from fpe_jax.model._line import learn_line

            # learned from the inner fit part only: the validation part must be as new to the
            # line as held-out data is (on Levine it lies mostly where the fit never went)
            line = learn_line([p[0] for p in inner], tracks[0])
            inner_line = {k: device_array(v) for k, v in line.items()}
            p_line = candidates["line"][0]
            final_cover = float(np.mean(np.asarray(p_line.line_coverage)))
            covered = [_row_coverage(line["line_coverage"], d, p_line) > 0 for d in inner_val]
            score = functools.partial(
                _expected_ade, datasets=inner_val, covered=covered, cover=final_cover
            )
        for label, (p0, groups) in candidates.items():
            if p0.settings.model == "line":
                p0 = dataclasses.replace(p0, **inner_line)
            progress(f"choosing the model: fitting {_label(p0)} on the inner split")
            p, _ = fit_params(
                inner_fit, p0, free=groups, solver=solver, block_rows=block_rows, devices=devices
            )
            selection[label] = score(p)
        best = min(selection, key=selection.get)
    else:
        best = next(iter(candidates))
    p0, free = candidates[best]
    progress(f"fitting {_label(p0)} on {sum(len(d.targets.rows) for d in train)} predictions")

    def independent_of_the_fit():
        """The presets' held-out scores and the line model's cross-fitted lines (for its
        uncertainty, `cross_fold_lines`, kept by each dataset)."""
        scores = {name: evaluate(baseline(name, settings), test) for name in BASELINES}
        if p0.settings.model == "line":
            for d in train:
                cross_fold_lines(d)
        return scores

    # a second thread does what does not depend on the fit while this one waits for the
    # solver's executable and its steps (XLA's threads)
    pool = ThreadPoolExecutor(1)
    meanwhile = pool.submit(independent_of_the_fit)
    try:
        params, info = fit_params(
            train, p0, free=free, solver=solver, block_rows=block_rows, devices=devices
        )
        scores = meanwhile.result()
    finally:  # an error or a Ctrl-C is reported without waiting for the second thread
        pool.shutdown(wait=False, cancel_futures=True)
    progress(f"estimating uncertainty on {len(train)} training drive(s)")
    uncertainty = fit_uncertainty(params, train)
    progress(f"evaluating the fit on {len(test)} held-out drive(s)")
    report = {"fitted": evaluate(params, test, uncertainty=uncertainty)} | scores
    chosen = params.settings.model
    info.update(
        blend=params.settings.blend,
        validation_ade_m={k: v for k, v in selection.items() if k in BLEND_CHOICES},
        model={"requested": model, "chosen": chosen, "validation_ade_m": selection},
        split=split,
        fit=list(free),
        **(line_info if chosen == "line" else {}),
    )
    return FitResult(params, uncertainty, report, info)


def baseline(name: str, settings: Settings) -> Params:
    """Preset `name` on the fit's prediction grid (step, horizon) and, where the fit's car is not
    the F1TENTH default, with its wheelbase and steering limit."""
    default = Settings()
    changes = dict(dt_s=settings.dt_s, horizon=settings.horizon)
    for k in ("wheelbase_m", "max_steer_rad"):
        if getattr(settings, k) != getattr(default, k):
            changes[k] = getattr(settings, k)
    return with_settings(presets[name], **changes)


def _row_coverage(coverage, d: Dataset, params: Params) -> np.ndarray:
    """(N,) a line profile's coverage at the arc length of each of d's prediction rows (the
    states of `params`)."""
    from fpe_jax.model._rollout import profile_at

    s_m = d.states(params).s_m
    at = jax.vmap(profile_at, in_axes=(None, 0, None))
    return np.asarray(at(jnp.asarray(coverage), jnp.asarray(s_m), d.track))


def _expected_ade(params: Params, datasets, covered, cover: float) -> float:
    """Validation ADE [m] of params reweighted to the share of the track the final line covers.

    The inner validation part lies where the inner line went less often than a new drive will
    lie where the final line went (on a long track the last quarter of a drive is mostly new to
    its first three quarters): ADE on the rows the inner line covers, weighted by `cover` (the
    final line's mean coverage), plus ADE on the rest weighted by 1 - cover. Either part falls
    back to the overall ADE when it has no rows. Every candidate is scored this way.
    """
    errs = [
        errors_m(predict_targets(params, d).xy_m, d.targets.xy_m, d.targets.mask) for d in datasets
    ]
    err, cov = np.concatenate(errs), np.concatenate(covered)
    overall = float(np.nanmean(err))

    def part(rows):
        e = err[rows]
        return float(np.nanmean(e)) if np.isfinite(e).any() else overall

    return cover * part(cov) + (1.0 - cover) * part(~cov)


def _label(p0: Params) -> str:
    return f"the '{p0.settings.blend}' blend" if p0.settings.model == "blend" else "the line model"


def _candidates(
    model, blend, init, free, train_d, tracks, test_tracks, progress, estimator
) -> tuple[dict, dict]:
    """The starting points `fit` chooses among: label ("line" or a blend mode) -> (Params, fit
    groups), and the line's provenance (`waypoints_sha256`).

    "auto" offers the line model (unless the drives use different waypoints or `free` names a
    group it lacks) and the blend model in each mode of `blend`, each with its own default
    groups. Without `speed` among them the blend starts (and stays) at the measured speed,
    speed_weight 1: no memorised speed. (Such a blend scored better on the inner split of Austin
    and Catalunya but predicted their test drives worse, FDE 0.975 and 0.868 m against the line's
    0.491 and 0.514 m: the line model is the default.)
    """
    from fpe_jax.geometry._path import waypoints_sha256

    names = ("line", "blend") if model == "auto" else (model,)
    every_track = list(tracks) + list(test_tracks)
    hashes = {waypoints_sha256(np.asarray(t.raw_xy_m)) for t in every_track}
    if model == "auto":
        names = tuple(n for n in names if not free or set(free) <= set(MODEL_FIT[n][0]))
        names = tuple(n for n in names if n != "line" or len(hashes) == 1)
        if not names:
            allowed = ", ".join(sorted(set(MODEL_FIT["line"][0]) | set(MODEL_FIT["blend"][0])))
            raise InputError("free", "no model fits all of these groups", allowed)
    out, line_info = {}, {}
    for name in names:
        if name == "line":
            if init is not None and init.settings.model == "line":
                p0 = init
            else:
                car = init.settings if init is not None else Settings()
                progress("learning the line and speed profile from the training drives")
                p0 = _line_init(train_d, every_track, car, estimator)
                line_info = {"waypoints_sha256": next(iter(hashes))}
            out["line"] = (p0, free or default_groups(p0.settings))
            continue
        p0 = init if init is not None else presets["default"]
        if p0.settings.model != "blend":  # a line config lends only its car and grid
            car = {k: getattr(p0.settings, k) for k in USER_SETTINGS}
            p0 = with_settings(presets["default"], **car)
        if (p0 is not init or _preset_speed(p0)) and "speed" not in (free or MODEL_FIT["blend"][1]):
            # the preset's shrinkage toward 2 m/s would stay: drive at the measured speed (also
            # from an `init` that only set the car and grid on the preset, as `fpe fit` passes)
            p0 = dataclasses.replace(p0, speed_weight=jnp.ones_like(p0.speed_weight))
        for mode in BLEND_CHOICES if blend == "auto" else (blend,):
            p = dataclasses.replace(p0, settings=dataclasses.replace(p0.settings, blend=mode))
            out[mode] = (p, free or MODEL_FIT["blend"][1])
    return out, line_info


def _preset_speed(params: Params) -> bool:
    """Whether params shrink the speed exactly as the "default" preset does (speed_weight and
    speed_mps its values): a start nobody fitted, whose memorised 2 m/s is no one's choice."""
    d = presets["default"]
    return all(
        np.array_equal(np.asarray(getattr(params, k)), np.asarray(getattr(d, k)))
        for k in ("speed_weight", "speed_mps")
    )


def allowed_groups(settings: Settings) -> tuple[str, ...]:
    """The fit groups that apply to a fitted model with these settings (its estimator's)."""
    groups = MODEL_FIT[settings.model][0]
    if settings.model != "line":
        return groups
    other = [g for e, gs in ESTIMATOR_GROUPS.items() if e != settings.estimator for g in gs]
    return tuple(g for g in groups if g not in other)


def default_groups(settings: Settings) -> tuple[str, ...]:
    """The groups `fit_params` frees when told none: the model's defaults, for the line model
    with its estimator's own (ESTIMATOR_GROUPS)."""
    groups = MODEL_FIT[settings.model][1]
    if settings.model == "line":
        groups += ESTIMATOR_GROUPS[settings.estimator]
    return groups


def _line_init(
    drives: Sequence[Drive], tracks: Sequence[Track], car: Settings, estimator: str
) -> Params:
    """The line model's starting point: the profile learned from `drives` on the one track
    every drive (fit and test) uses, good unfitted time constants and delay, on the car and
    prediction grid of `car` (its `USER_SETTINGS`)."""
    from fpe_jax.geometry._path import waypoints_sha256
    from fpe_jax.model._line import learn_line

    hashes = {waypoints_sha256(np.asarray(t.raw_xy_m)) for t in tracks}
    if len(hashes) != 1:
        raise InputError(
            "model", "line: the drives use different waypoints", "one track, or model blend"
        )
    profile = learn_line(drives, tracks[0])
    init = Params.create(
        Settings(model="line", estimator=estimator, **{k: getattr(car, k) for k in USER_SETTINGS}),
        weights=1.0,
        delay_s=0.1,
        offset_tau_s=1.0,
        speed_tau_s=0.5,
        **profile,
    )
    return init
