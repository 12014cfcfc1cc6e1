"""Split batch prediction and fitting losses across devices with `jax.sharding`.

The data-parallel axis is the leading one: cars for batch prediction, samples (prediction
times) for a fitting loss. Arrays are laid out over a 1-D `Mesh` with
`NamedSharding(mesh, PartitionSpec(axis))`; parameters and the track are replicated. `jax.jit`
then partitions the computation (GSPMD): each device rolls out its own cars, and a sum over
samples becomes per-device partial sums plus one all-reduce. Results equal the single-device
ones up to float rounding of the reduction order (<= 1e-6 here).

One host, several devices (GPUs, or CPU "devices" for testing):

    from fpe_jax.predict import car_mesh, predict_sharded
    mesh = car_mesh()                       # all local devices, axis "cars"
    poses = predict_sharded(params, states, track, mesh)   # (N, H, 3), N padded internally

    # a loss over samples: shard the per-sample data, replicate the rest, jit as usual
    data = shard_along_axis0(pad_axis0(samples, mesh.devices.size)[0], mesh)
    value = jax.jit(loss)(params, data)

    # big batches, chunked: fpe_jax.predict.predict_chunked(..., mesh=mesh)

To try several devices on a CPU, set `XLA_FLAGS=--xla_force_host_platform_device_count=2`
before JAX initialises (i.e. in the environment of a fresh process).

Several processes (hosts, or CPU sockets): `fpe fit --num-processes N --process-id I
--coordinator HOST:PORT` runs a fit as N processes (`fpe_jax.pipeline.fit_logs`); its module
`fpe_jax.fit._processes` meets the processes, calls `jax.distributed.initialize` before anything
asks for a device, and checks that every process ends with the same fit. `jax.devices()` then
lists the devices of every process, so `car_mesh()` spans them all, and a jitted program over
that mesh runs in every process at once (each must call it, with equal shapes). Arrays whose
every process holds the same values (the fit's data, params, the track) can be passed as they
are; an array of which each process holds only its own rows is assembled with
`jax.make_array_from_process_local_data(NamedSharding(mesh, PartitionSpec("cars")), x_local)`,
and a replicated result is read with `x.addressable_data(0)`. The per-process row count times
the number of processes must divide evenly by the device count (use `pad_axis0` and mask padded
samples out of losses). docs/fitting-at-scale.md says how to run it and what it costs.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from fpe_jax.geometry._track import Track
from fpe_jax.model._params import Params
from fpe_jax.model._state import State
from fpe_jax.predict._predict import predict_batch

AXIS = "cars"


def car_mesh(devices=None, axis_name: str = AXIS) -> Mesh:
    """A 1-D mesh over `devices` (default: every device JAX sees, on every host)."""
    devs = np.asarray(jax.devices() if devices is None else devices)
    return Mesh(devs.reshape(-1), (axis_name,))


def _is_array(x) -> bool:
    return isinstance(x, (np.ndarray, np.generic, jax.Array))


def _array_leaves(tree):
    return [x for x in jax.tree.leaves(tree) if _is_array(x)]


def leading_size(tree) -> int:
    """The common leading-axis size N of every non-scalar array leaf; raises if they differ."""
    sizes = {x.shape[0] for x in _array_leaves(tree) if x.ndim >= 1}
    if len(sizes) != 1:
        raise ValueError(f"leading axes differ or are missing: sizes {sorted(sizes)}")
    return sizes.pop()


def pad_axis0(tree, multiple: int):
    """Pad every non-scalar array leaf along axis 0 to a multiple of `multiple`.

    Padding repeats the first row, so padded entries are finite, valid-looking data; use the
    returned mask to drop them from sums.

    Returns:
        (padded tree, valid) with valid a (N_padded,) bool NumPy array, True for real rows.
    """
    n = leading_size(tree)
    n_pad = int(math.ceil(n / multiple) * multiple)

    def pad(x):
        if not _is_array(x) or x.ndim == 0 or n_pad == n:
            return x
        xp = jnp if isinstance(x, jax.Array) else np
        rep = xp.repeat(x[:1], n_pad - n, axis=0)
        return xp.concatenate([x, rep], axis=0)

    valid = np.arange(n_pad) < n
    return jax.tree.map(pad, tree), valid


def shard_along_axis0(tree, mesh: Mesh, axis_name: str | None = None):
    """Place a pytree on `mesh`: non-scalar arrays split along axis 0, scalars replicated.

    Every non-scalar leaf must share the leading size N, divisible by the mesh size (pad with
    `pad_axis0` first). Non-array leaves (static fields) are left alone.
    """
    axis = axis_name or mesh.axis_names[0]
    n_dev = mesh.devices.size
    n = leading_size(tree)
    if n % n_dev:
        raise ValueError(f"leading size {n} is not a multiple of the {n_dev} devices; pad_axis0")
    split = NamedSharding(mesh, PartitionSpec(axis))
    whole = NamedSharding(mesh, PartitionSpec())

    def place(x):
        if not _is_array(x):
            return x
        return jax.device_put(x, split if x.ndim >= 1 else whole)

    return jax.tree.map(place, tree)


def replicate(tree, mesh: Mesh):
    """Place every array leaf of a pytree on all devices of `mesh` (params, track, grid)."""
    whole = NamedSharding(mesh, PartitionSpec())
    return jax.tree.map(lambda x: jax.device_put(x, whole) if _is_array(x) else x, tree)


def predict_sharded(
    params: Params, states: State, track: Track, mesh: Mesh | None = None
) -> jax.Array:
    """`predict_batch` with the N cars split across the mesh's devices.

    Args:
        params: one parameter set (or P stacked: the result is then (P, N, H, 3)).
        states: State with leading axis N (give `s_m`, or the rollout projects globally).
        track: the track (replicated).
        mesh: a 1-D mesh; default `car_mesh()`.

    Returns:
        (N, H, 3) poses x [m], y [m], yaw [rad] (a global array sharded along the car axis).
    """
    mesh = car_mesh() if mesh is None else mesh
    states = jax.tree.map(jnp.asarray, states)
    n = leading_size(states)
    padded, _ = pad_axis0(states, mesh.devices.size)
    out = predict_batch(
        replicate(params, mesh), shard_along_axis0(padded, mesh), replicate(track, mesh)
    )
    return out[:, :n] if params.weights.ndim == 2 else out[:n]
