"""Host values onto the device without a compiled program per shape."""

import jax
import numpy as np


def device_array(x, dtype=None) -> jax.Array:
    """`jnp.asarray(x, dtype)` for host values (numbers, lists, NumPy arrays), copied with
    `jax.device_put`: jnp.asarray runs a small compiled program for each new shape and dtype
    (jax 0.10.2 on the CPU: 10-30 ms each, most of a warm command's compilations). JAX arrays
    and tracers go through jnp.asarray; a Python number without a dtype stays weakly typed."""
    if isinstance(x, jax.Array):
        return jax.numpy.asarray(x, dtype)
    if dtype is None and isinstance(x, int | float) and not isinstance(x, bool):
        return jax.device_put(x)
    return jax.device_put(np.asarray(x, dtype))
