"""Rows in blocks of a few compiled shapes: bucketed row counts, padding by repeating the last
row, the blocks a drive of any length runs in (NumPy in, NumPy out; no tracing)."""

import jax
import numpy as np

# Rows per compiled prediction call: a drive of any length runs in blocks of this size (a
# 10-million-row log asked XLA for one 13.4 GB block before).
PREDICT_CHUNK = 1 << 15


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
