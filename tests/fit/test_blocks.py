"""The fit's loss in row blocks: equal to the loss in one piece, the same fit, memory bounded."""

import functools
import json
import os
import pickle
import subprocess
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

from fpe_jax.compile._rows import pad_rows
from fpe_jax.errors import InputError
from fpe_jax.evaluate import _evaluate as E
from fpe_jax.fit import _fit as F
from fpe_jax.geometry._track import Track
from fpe_jax.model._params import Settings, presets, unconstrain
from fpe_jax.sim._sim import simulate

BLOCK = 64  # rows per block in these tests: a 40 s drive's ~370 rows are several blocks


@pytest.fixture(scope="module")
def drive():
    res = simulate("oval", duration_s=40, latency_s=0.3, seed=11)
    return res.drive, Track.from_waypoints(res.centerline_xy_m)


@pytest.fixture(scope="module")
def objective(drive):
    """`_objective` of the drive by model, made once per model (the tests only read it)."""
    return functools.cache(lambda model: _objective(drive, model))


def _objective(drive, model: str):
    """(flat raw free values, args, unravel, dataset, init, free raw values) of the fit of
    `model` on the drive: the blend's default one; the line model's with the pace free, the
    fit that predicts each row from its fold's cross-fitted line (`fit_params`)."""
    d, track = drive
    if model == "line":
        init = F._line_init([d], [track], Settings(), "kalman")
        names = (*F.default_groups(init.settings), "pace")
    else:
        init = presets["default"]
        names = F.default_groups(init.settings)
    # the first states estimate runs the Kalman filter for either model, as a fit that scores
    # both kinds makes it: the blend's states come from the line model's compiled program
    data = E.make_datasets([d], [track], init.settings, "training", kalman=True)[0]
    raw = unconstrain(init)
    free, fixed = eqx.partition(raw, F._free_mask(raw, names))
    # the line model's rows predicted from their folds' lines, every model's steps scaled
    fold, lines = F._cross_lines([data]) if model == "line" else (None, None)
    scale = F.lead_time_scale(init, [data])
    xy = jnp.asarray(data.targets.xy_m)
    groups = [(data.states(init), track, xy, data.targets.mask, fold, lines, scale)]
    y0, unravel = ravel_pytree(free)
    return y0, (fixed, groups, F.HUBER_M), unravel, data, init, free


@pytest.fixture(scope="module")
def one_device(objective):
    """`_one_device` by model, made once per model (its programs run in this process, on one
    device; the two-device tests compare theirs with its values)."""
    return functools.cache(lambda model: _one_device(objective, model))


def _one_device(objective, model: str):
    """(args, unravel, ys, whole, blocked) of `model`'s loss over two datasets, the drive's rows
    and its first 100 (shorter than two blocks): whole and blocked are the loss and gradient in
    one piece and in blocks of BLOCK, jitted, at each of three points ys near the fit's start."""
    y0, (fixed, groups, huber), unravel, *_ = objective(model)
    states, track, xy, mask, fold, lines, scale = groups[0]
    cut = jax.tree.map(lambda x: x[:100], (states, xy, mask, fold))
    short = (cut[0], track, cut[1], cut[2], cut[3], lines, scale)
    args = (fixed, [groups[0], short], huber)
    whole = jax.jit(jax.value_and_grad(lambda y: F._loss(unravel(y), args)))
    blocked = jax.jit(jax.value_and_grad(lambda y: F._loss(unravel(y), args, BLOCK)))
    ys = y0[None, :] + 0.05 * jnp.sin(jnp.arange(1.0, 3 * y0.size + 1)).reshape(3, -1)
    return args, unravel, ys, [whole(y) for y in ys], [blocked(y) for y in ys]


@pytest.mark.parametrize("model", ["line", "blend"])
def test_blocked_loss_and_gradient_equal_the_loss_in_one_piece(objective, one_device, model):
    """Several whole blocks and a shorter last one (370 rows in blocks of 64), next to a
    dataset shorter than two blocks, sum to the one-piece loss to 1e-12 relative, and so does
    the gradient, under jit and grad (and vmap for the blend model)."""
    data = objective(model)[3]
    n = len(data.targets.rows)
    assert n > 2 * BLOCK and n % BLOCK, n  # several blocks and a partial one
    args, unravel, ys, whole, blocked = one_device(model)
    for (f1, g1), (f2, g2) in zip(whole, blocked, strict=True):
        assert abs(float(f2) - float(f1)) <= 1e-12 * abs(float(f1))
        scale = float(jnp.max(jnp.abs(g1)))
        np.testing.assert_allclose(np.asarray(g2), np.asarray(g1), rtol=1e-12, atol=1e-12 * scale)
    if model == "blend":  # vmap over parameter sets (once: the line model's is the same code)
        many = jax.jit(jax.vmap(lambda y: F._loss(unravel(y), args, BLOCK)))(ys)
        np.testing.assert_allclose(np.asarray(many), [float(f) for f, _ in whole], rtol=1e-12)


@pytest.fixture(scope="module")
def fits(objective):
    """The blend's fit of two datasets on one track (the drive, and the drive with only its
    targets due 10 s before its end) in one piece and in blocks of BLOCK rows on one device:
    ((datasets, init), (params, info) in one piece, (params, info) in blocks)."""
    _, _, _, data, init, _ = objective("blend")
    later = E.targets_before(data, data.drive.t_s[-1] - 10.0, init.settings.dt_s)
    one = F.fit_params([data, later], init, block_rows=10**6)
    many = F.fit_params([data, later], init, block_rows=BLOCK)
    return ([data, later], init), one, many


def test_a_fit_over_several_blocks_equals_the_fit_in_one_piece(fits):
    """The blocked fit (two datasets on one track, joined into one row set in blocks) changes
    only the order of the loss's sum: the loss to 1e-10 relative, the fitted values to 1e-6."""
    (datasets, init), (one, one_info), (many, many_info) = fits
    assert one_info["converged"] and many_info["converged"]
    assert many_info["loss"] == pytest.approx(one_info["loss"], rel=1e-10)
    a, b = ravel_pytree(unconstrain(one))[0], ravel_pytree(unconstrain(many))[0]
    np.testing.assert_allclose(np.asarray(b), np.asarray(a), atol=1e-6)
    for bad in (0, -3, True):
        with pytest.raises(InputError, match="^block_rows: .*a whole number >= 1"):
            F.fit_params(datasets[:1], init, block_rows=bad)


def _temp_bytes(objective, n_rows: int, block_rows: int | None, datasets: int = 1) -> int:
    """XLA's temporary buffer size [bytes] of the compiled loss and gradient (what BFGS
    evaluates) of the line model on `datasets` datasets of n_rows target rows each (the
    drive's rows, padded by repeating its last row)."""
    y0, (fixed, groups, huber), unravel, *_ = objective("line")
    states, track, xy, mask, fold, lines, scale = groups[0]
    big = pad_rows((states, xy, mask, fold), n_rows)
    big = (big[0], track, big[1], big[2], big[3], lines, scale)
    shapes = [jax.tree.map(lambda x: jax.ShapeDtypeStruct(np.shape(x), x.dtype), big)] * datasets

    def value_and_grad(y, g):
        return jax.value_and_grad(lambda v: F._loss(unravel(v), (fixed, g, huber), block_rows))(y)

    compiled = jax.jit(value_and_grad).lower(y0, shapes).compile()
    return compiled.memory_analysis().temp_size_in_bytes


def test_the_blocked_loss_needs_the_same_memory_for_four_times_the_rows(objective):
    """The compiled loss and gradient's temporary buffers (XLA's memory analysis) stay the
    same size from 8 to 32 blocks of rows, while those of the loss in one piece grow with the
    rows: the fit's memory beyond its data does not grow with the logs."""
    small, large = 8 * 512, 32 * 512
    blocked = [_temp_bytes(objective, n, 512) for n in (small, large)]
    whole = [_temp_bytes(objective, n, None) for n in (small, large)]
    assert blocked[1] <= 1.05 * blocked[0], blocked
    assert whole[1] >= 3.0 * whole[0], whole
    assert blocked[1] < whole[1] / 8, (blocked, whole)


# run with two forced CPU devices: given (pickled by `two_devices`) the loss's arguments and a
# point of each model and the datasets of `fits`, the loss and gradient with the row blocks
# split over both devices, and the blocked fit over both
TWO_DEVICES = r"""
import json
import pickle
import sys

import jax

jax.config.update("jax_enable_x64", True)
import numpy as np
from jax.flatten_util import ravel_pytree

from fpe_jax.fit import _fit as F
from fpe_jax.model._params import unconstrain

with open(sys.argv[1], "rb") as f:
    given = pickle.load(f)
out = {"devices": len(jax.devices())}
for model in ("blend", "line"):
    free, fixed, groups, huber, y = given[model]
    unravel = ravel_pytree(free)[1]
    loss = jax.value_and_grad(lambda y: F._loss(unravel(y), (fixed, groups, huber), 64, 2))
    lowered = jax.jit(loss).lower(y)
    value, grad = lowered.compile()(y)
    out[model] = {
        "all_reduce": "all_reduce" in lowered.as_text(),
        "loss": float(value),
        "grad": np.asarray(grad).tolist(),
    }
datasets, init = given["fit"]
p, info = F.fit_params(datasets, init, block_rows=64, devices=2)
out["fit"] = np.asarray(ravel_pytree(unconstrain(p))[0]).tolist()
out["fit_loss"], out["fit_devices"] = info["loss"], info["devices"]
print(json.dumps(out))
"""


@pytest.fixture(scope="module")
def two_devices(tmp_path_factory, objective, one_device, fits) -> dict:
    """What TWO_DEVICES prints as JSON, run in a process with two forced CPU devices (the
    suite's XLA flags kept) and a cache folder of its own. Given for each model the rows of
    `one_device`'s two datasets joined into one (the loss sums over rows: the same loss)
    and padded to whole blocks, as many on each device (padded targets masked out), and its
    first point; and the datasets of `fits`."""
    given = {}
    for model in ("blend", "line"):
        *_, free = objective(model)
        (fixed, groups, huber), _, ys, _, _ = one_device(model)
        _, track, _, _, _, lines, scale = groups[0]  # the short dataset shares them
        rows = jax.tree.map(lambda *x: np.concatenate(x), *[(g[0], *g[2:5]) for g in groups])
        m = len(rows[1])
        n = -(-m // (2 * BLOCK)) * 2 * BLOCK
        states, xy, mask, fold = pad_rows(rows, n)
        mask = mask & (np.arange(n) < m)[:, None]
        joined = (states, track, xy, mask, fold, lines, scale)
        given[model] = (free, fixed, [joined], huber, np.asarray(ys[0]))
    given["fit"] = fits[0]
    path = tmp_path_factory.mktemp("two_devices") / "given.pickle"
    path.write_bytes(pickle.dumps(given))
    env = {
        **os.environ,
        "XLA_FLAGS": os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2",
        "FPE_CACHE_DIR": str(tmp_path_factory.mktemp("cache")),
    }
    proc = subprocess.run(
        [sys.executable, "-c", TWO_DEVICES, str(path)], capture_output=True, text=True, env=env
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _same_as_one_device(two: dict, one: tuple) -> None:
    """The two devices' loss and gradient `two` equal one device's blocked ones at the same
    point (`_one_device`) to 1e-12 relative (the order of the sum)."""
    f1, g1 = one[4][0]
    assert two["loss"] == pytest.approx(float(f1), rel=1e-12)
    g1, g2 = np.asarray(g1), np.array(two["grad"])
    np.testing.assert_allclose(g2, g1, rtol=1e-12, atol=1e-12 * np.max(np.abs(g1)))


def test_a_fit_over_two_forced_cpu_devices_equals_the_one_device_fit(two_devices, one_device, fits):
    """In a process with two forced host devices, the row blocks split over both (the program
    adds the devices' partial sums: an all-reduce) give the loss and gradient of one device
    (this process's, on the same rows) to 1e-12 relative and the same fit as one device's in
    blocks (`fits`: loss to 1e-10 relative, values to 1e-6)."""
    out = two_devices
    assert out["devices"] == 2 and out["blend"]["all_reduce"]
    _same_as_one_device(out["blend"], one_device("blend"))
    _, _, (many, info) = fits
    assert out["fit_devices"] == 2
    assert out["fit_loss"] == pytest.approx(info["loss"], rel=1e-10)
    np.testing.assert_allclose(
        out["fit"], np.asarray(ravel_pytree(unconstrain(many))[0]), atol=1e-6
    )


def test_more_devices_than_jax_has_are_refused(objective):
    data, init = objective("blend")[3:5]
    for bad in (0, len(jax.devices()) + 1):
        with pytest.raises(InputError, match="^devices: .*a whole number from 1 to"):
            F.fit_params([data], init, devices=bad)


def test_the_line_models_loss_over_two_forced_cpu_devices_equals_one_devices(
    two_devices, one_device
):
    """The line model (Kalman filter, cross-fitted lines, the pace free) over two devices: its
    scans' carries start from constants and take in each device's own rows, which
    `jax.shard_map` accepts only when the constants vary by device as the rows do. Loss and
    gradient equal one device's to 1e-12 relative (the order of the sum)."""
    out = two_devices
    assert out["devices"] == 2 and out["line"]["all_reduce"]
    _same_as_one_device(out["line"], one_device("line"))
