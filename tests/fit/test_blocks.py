"""The fit's loss in row blocks: equal to the loss in one piece, the same fit, memory bounded."""

import functools
import json
import os
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
    """(flat raw free values, args, unravel, dataset, init) of the default fit of `model` on
    the drive."""
    d, track = drive
    if model == "line":
        init = F._line_init([d], [track], Settings(), "kalman")
    else:
        init = presets["default"]
    data = E.make_datasets([d], [track], init.settings, "training", kalman=model == "line")[0]
    raw = unconstrain(init)
    free, fixed = eqx.partition(raw, F._free_mask(raw, F.default_groups(init.settings)))
    # the line model's rows predicted from their folds' lines, every model's steps scaled
    fold, lines = F._cross_lines([data]) if model == "line" else (None, None)
    scale = F.lead_time_scale(init, [data])
    xy = jnp.asarray(data.targets.xy_m)
    groups = [(data.states(init), track, xy, data.targets.mask, fold, lines, scale)]
    y0, unravel = ravel_pytree(free)
    return y0, (fixed, groups, F.HUBER_M), unravel, data, init


@pytest.mark.parametrize("model", ["line", "blend"])
def test_blocked_loss_and_gradient_equal_the_loss_in_one_piece(objective, model):
    """Several whole blocks and a shorter last one (370 rows in blocks of 64), next to a
    dataset shorter than two blocks, sum to the one-piece loss to 1e-12 relative, and so does
    the gradient, under jit and grad (and vmap for the blend model)."""
    y0, (fixed, groups, huber), unravel, data, _ = objective(model)
    n = len(data.targets.rows)
    assert n > 2 * BLOCK and n % BLOCK, n  # several blocks and a partial one
    states, track, xy, mask, fold, lines, scale = groups[0]
    cut = jax.tree.map(lambda x: x[:100], (states, xy, mask, fold))
    short = (cut[0], track, cut[1], cut[2], cut[3], lines, scale)
    args = (fixed, [groups[0], short], huber)
    whole = jax.jit(jax.value_and_grad(lambda y: F._loss(unravel(y), args)))
    blocked = jax.jit(jax.value_and_grad(lambda y: F._loss(unravel(y), args, BLOCK)))
    ys = y0[None, :] + 0.05 * jnp.sin(jnp.arange(1.0, 3 * y0.size + 1)).reshape(3, -1)
    for y in ys:
        (f1, g1), (f2, g2) = whole(y), blocked(y)
        assert abs(float(f2) - float(f1)) <= 1e-12 * abs(float(f1))
        scale = float(jnp.max(jnp.abs(g1)))
        np.testing.assert_allclose(np.asarray(g2), np.asarray(g1), rtol=1e-12, atol=1e-12 * scale)
    if model == "blend":  # vmap over parameter sets (once: the line model's is the same code)
        many = jax.vmap(lambda y: F._loss(unravel(y), args, BLOCK))(ys)
        np.testing.assert_allclose(np.asarray(many), [float(whole(y)[0]) for y in ys], rtol=1e-12)


def test_a_fit_over_several_blocks_equals_the_fit_in_one_piece(objective):
    """The blocked fit (two datasets on one track, joined into one row set in blocks) changes
    only the order of the loss's sum: the loss to 1e-10 relative, the fitted values to 1e-6."""
    _, _, _, data, init = objective("blend")
    later = E.targets_before(data, data.drive.t_s[-1] - 10.0, init.settings.dt_s)
    one, one_info = F.fit_params([data, later], init, block_rows=10**6)
    many, many_info = F.fit_params([data, later], init, block_rows=BLOCK)
    assert one_info["converged"] and many_info["converged"]
    assert many_info["loss"] == pytest.approx(one_info["loss"], rel=1e-10)
    a, b = ravel_pytree(unconstrain(one))[0], ravel_pytree(unconstrain(many))[0]
    np.testing.assert_allclose(np.asarray(b), np.asarray(a), atol=1e-6)
    for bad in (0, -3, True):
        with pytest.raises(InputError, match="^block_rows: .*a whole number >= 1"):
            F.fit_params([data], init, block_rows=bad)


def _temp_bytes(objective, n_rows: int, block_rows: int | None, datasets: int = 1) -> int:
    """XLA's temporary buffer size [bytes] of the compiled loss and gradient (what BFGS
    evaluates) of the line model on `datasets` datasets of n_rows target rows each (the
    drive's rows repeated)."""
    y0, (fixed, groups, huber), unravel, data, _ = objective("line")
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


TWO_DEVICES = r"""
import functools
import json
import jax
jax.config.update("jax_enable_x64", True)
import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree
from fpe_jax.evaluate import _evaluate as E
from fpe_jax.fit import _fit as F
from fpe_jax.model._params import Settings, presets, unconstrain
from fpe_jax.sim import simulate
from fpe_jax.geometry._track import Track

res = simulate("oval", duration_s=40, latency_s=0.3, seed=11)
track = Track.from_waypoints(res.centerline_xy_m)
init = presets["default"]
data = E.make_datasets([res.drive], [track], init.settings, "training")
raw = unconstrain(init)
free, fixed = eqx.partition(raw, F._free_mask(raw, F.default_groups(init.settings)))
d = data[0]
n = -(-len(d.targets.rows) // 128) * 128  # whole blocks of 64, as many on each device
g = [(E.pad_rows(d.states(init), n), track, E.pad_rows(d.targets.xy_m, n),
      E.pad_rows(d.targets.mask, n) & (np.arange(n) < len(d.targets.rows))[:, None],
      None, None, F.lead_time_scale(init, data))]
y0, unravel = ravel_pytree(free)
args = (fixed, g, F.HUBER_M)
losses = {k: jax.jit(jax.value_and_grad(lambda y, k=k: F._loss(unravel(y), args, 64, k)))
          for k in (1, 2)}
hlo = jax.jit(lambda y: F._loss(unravel(y), args, 64, 2)).lower(y0).as_text()
out = {"devices": len(jax.devices()), "all_reduce": "all_reduce" in hlo}
for k, f in losses.items():
    v, grad = f(y0)
    out[f"loss_{k}"], out[f"grad_{k}"] = float(v), np.asarray(grad).tolist()
for k in (1, 2):
    p, info = F.fit_params(data, init, block_rows=64, devices=k)
    out[f"fit_{k}"] = np.asarray(ravel_pytree(unconstrain(p))[0]).tolist()
    out[f"fit_loss_{k}"], out[f"steps_{k}"] = info["loss"], info["steps"]
print(json.dumps(out))
"""


def test_a_fit_over_two_forced_cpu_devices_equals_the_one_device_fit(two_devices):
    """In a process with two forced host devices, the row blocks split over both (the program
    adds the devices' partial sums: an all-reduce) give the loss and gradient of one device to
    1e-12 relative and the same fit (loss to 1e-10 relative, values to 1e-6)."""
    out = two_devices["blend"]
    assert out["devices"] == 2 and out["all_reduce"]
    assert out["loss_2"] == pytest.approx(out["loss_1"], rel=1e-12)
    g1, g2 = np.array(out["grad_1"]), np.array(out["grad_2"])
    np.testing.assert_allclose(g2, g1, rtol=1e-12, atol=1e-12 * np.max(np.abs(g1)))
    assert out["fit_loss_2"] == pytest.approx(out["fit_loss_1"], rel=1e-10)
    np.testing.assert_allclose(out["fit_2"], out["fit_1"], atol=1e-6)


def test_more_devices_than_jax_has_are_refused(objective):
    _, _, _, data, init = objective("blend")
    for bad in (0, len(jax.devices()) + 1):
        with pytest.raises(InputError, match="^devices: .*a whole number from 1 to"):
            F.fit_params([data], init, devices=bad)


# run after TWO_DEVICES in its process: the same drive and track
LINE_TWO_DEVICES = r"""
init = F._line_init([res.drive], [track], Settings(), "kalman")
data = E.make_datasets([res.drive], [track], init.settings, "training", kalman=True)
raw = unconstrain(init)
free, fixed = eqx.partition(raw, F._free_mask(raw, (*F.default_groups(init.settings), "pace")))
d = data[0]
n = -(-len(d.targets.rows) // 128) * 128  # whole blocks of 64, as many on each device
fold, lines = F._cross_lines(data)
g = [(E.pad_rows(d.states(init), n), track, E.pad_rows(d.targets.xy_m, n),
      E.pad_rows(d.targets.mask, n) & (np.arange(n) < len(d.targets.rows))[:, None],
      E.pad_rows(fold, n), lines, F.lead_time_scale(init, data))]
y0, unravel = ravel_pytree(free)
args = (fixed, g, F.HUBER_M)
out = {"devices": len(jax.devices())}
for k in (1, 2):
    v, grad = jax.jit(jax.value_and_grad(lambda y: F._loss(unravel(y), args, 64, k)))(y0)
    out[f"loss_{k}"], out[f"grad_{k}"] = float(v), np.asarray(grad).tolist()
print(json.dumps(out))
"""


@pytest.fixture(scope="module")
def two_devices(tmp_path_factory) -> dict:
    """What TWO_DEVICES ("blend") and then LINE_TWO_DEVICES ("line") print as JSON, run in one
    process with two forced CPU devices (the suite's XLA flags kept) and a cache folder of its
    own."""
    env = {
        **os.environ,
        "XLA_FLAGS": os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2",
        "FPE_CACHE_DIR": str(tmp_path_factory.mktemp("cache")),
    }
    script = TWO_DEVICES + LINE_TWO_DEVICES
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    blend, line = proc.stdout.strip().splitlines()[-2:]
    return {"blend": json.loads(blend), "line": json.loads(line)}


def test_the_line_models_loss_over_two_forced_cpu_devices_equals_one_devices(two_devices):
    """The line model (Kalman filter, cross-fitted lines, the pace free) over two devices: its
    scans' carries start from constants and take in each device's own rows, which
    `jax.shard_map` accepts only when the constants vary by device as the rows do. Loss and
    gradient equal one device's to 1e-12 relative (the order of the sum)."""
    out = two_devices["line"]
    assert out["devices"] == 2
    assert out["loss_2"] == pytest.approx(out["loss_1"], rel=1e-12)
    g1, g2 = np.array(out["grad_1"]), np.array(out["grad_2"])
    np.testing.assert_allclose(g2, g1, rtol=1e-12, atol=1e-12 * np.max(np.abs(g1)))
