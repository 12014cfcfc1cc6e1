"""Batch prediction at scale: many cars, chunked, float32 by default, optionally sharded.

A planner weighing overtakes asks "where will each of these 10^5 candidate cars be?" every
cycle; build a predictor once and call it:

    from fpe_jax import Track, presets
    from fpe_jax.predict import BatchPredictor, predict_chunked
    track = Track.from_waypoints(waypoints_xy_m)
    predict = BatchPredictor(presets["default"], track)      # casts, places, splits once
    poses = predict(cars)                                     # cars: (N, 4|5) -> (N, H, 3)
    poses = predict_chunked(presets["default"], cars, track)  # the same, one-shot

`cars` rows are `x [m], y [m], yaw [rad], v [m/s][, yaw_rate [rad/s]]` (or a `State` with a
leading axis N). With P stacked parameter sets (`fpe_jax.stack_params`) the result is
(P, N, H, 3).

How it stays fast and bounded:

- **Fixed chunk shape.** Cars are cut into chunks of `chunk` rows (the last one padded by
  repeating a real car), so the predictor compiles once per (chunk, dtype, settings) and memory
  holds a few chunks' intermediates plus the output. Chunks run on a few threads at once (XLA
  runs one chunk's step loop on one core), results are copied into place as they finish.
- **No global search per car.** A car without an arc-length hint is projected onto the track by a
  `ProjectionGrid`: a uniform grid over a band along the track whose cells list the only
  segments that can be nearest to any point in the cell. The result equals `Track.project` (the
  exhaustive search) while costing O(K) segments instead of O(M), inside the same compiled call.
  The rare cars the grid cannot answer (farther than its margin from the track) get the
  exhaustive search afterwards, in small batches, and are predicted again. Inside the rollout,
  every step projects locally from the previous step's arc length (`Track.project_local`).
- **Streamed.** `BatchPredictor.chunks` yields each chunk's poses as it finishes, in car order
  (the rare off-grid cars' final rows after the last chunk), and reads `CarBlocks` (a file in
  pieces) on the worker threads: `fpe batch` writes each chunk while later ones run, with
  neither all cars nor all poses in memory.
- **float32 by default** (float64 on request): every float array of the parameters, the track
  and the cars is cast, and the computation runs under `jax.enable_x64(dtype == float64)`, so
  constants created inside the predictor take the same precision whatever the global flag says.

Several devices: pass `mesh=fpe_jax.predict.car_mesh()`; each chunk is split along the car axis
across the mesh (see `fpe_jax.predict` for GPUs and several hosts).
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import itertools
import math
import os
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from fpe_jax import spec
from fpe_jax.compile._rows import pad_rows
from fpe_jax.errors import InputError
from fpe_jax.geometry._path import BRANCH_COS, BRANCH_M, ON_TRACK_M
from fpe_jax.geometry._path import off_track_judge as geometry_off_track_judge
from fpe_jax.geometry._track import Track
from fpe_jax.model._params import Params
from fpe_jax.model._state import State
from fpe_jax.predict._predict import predict_batch

DTYPES = {"float32": np.float32, "float64": np.float64}
DEFAULT_CHUNK = 1 << 14  # 16384 cars: working set stays in cache (1.3x the rate of 65536 here)
_SLOW_BATCH = 256  # cars per exhaustive projection in the off-grid fallback: bounds its memory


def _dtype(dtype) -> type:
    name = np.dtype(dtype).name
    if name not in DTYPES:
        raise InputError("dtype", f"unsupported dtype {name!r}", "float32 or float64")
    return DTYPES[name]


def cast_floats(tree, dtype):
    """Cast every floating array leaf of a pytree (Params, State, Track, ...) to `dtype`.

    Returns NumPy leaves (cast on the host, exactly); integer, bool and static fields are kept.
    Call `jnp.asarray` on the result inside the precision context you compute in.
    """
    dt = _dtype(dtype)

    def cast(leaf):
        if isinstance(leaf, (np.ndarray, jax.Array)) and jnp.issubdtype(leaf.dtype, jnp.floating):
            return np.asarray(leaf).astype(dt)
        return leaf

    return jax.tree.map(cast, tree)


def _to_device(tree):
    return jax.tree.map(lambda a: jnp.asarray(a) if isinstance(a, np.ndarray) else a, tree)


# ---- fast initial projection -------------------------------------------------------------------


class ProjectionGrid(eqx.Module):
    """A lookup grid answering "arc length of the nearest track point" in O(K), exactly.

    Each cell of a uniform grid lists the segments that can be nearest to *some* point of the
    cell, found by two exact tests. Coarse: segment j qualifies when dist(centre, j) - r <= U,
    where r is the cell's half diagonal and U = min over segments of the largest corner distance
    (no point of the cell is farther than U from its nearest segment, and no point is closer
    than dist(centre, j) - r to segment j). Fine: of those, j stays when on a lattice of points
    spanning the cell it comes within a Lipschitz bound of the nearest one (`_lattice_test`).
    A cell is complete when every segment within reach was examined while building and its list
    fits in K; the candidates of a complete cell include the global nearest segment of every
    point in it, so the nearest of them is `Track.project`'s answer (same formula; ties broken
    toward the lowest index as there). A query costs O(K): K is the longest list stored.

    Only the complete cells (a band along the track) are stored, as sorted keys: memory and
    build time grow with the track's length, not with the area of its bounding box. A query
    finds its cell's row by binary search, then gathers its K candidates' geometry.

    Attributes:
        origin_m: (2,) lower-left corner of the grid x [m], y [m].
        cell_m: () cell side [m].
        keys: (R + 1,) int32 sorted keys i * ny + j of the R complete cells, then a sentinel
            (2^31 - 1) no cell has.
        candidates: (R + 1, K) int32 candidate segments of each complete cell (lists padded by
            repeating their first candidate; the sentinel's row is zeros).
        geometry: (7, S) rows a_x, a_y, ab_x, ab_y, ab_x / |ab|^2, ab_y / |ab|^2, s_a for each
            segment a -> b, with s_a the arc length [m] at a. One row per quantity: a query
            gathers K scalars from each (XLA on CPU fuses scalar gathers into the arithmetic;
            gathering K rows of all quantities took 1.3x as long).
        ds_m: () the track's nominal spacing [m], the arc length of every segment.
        shape: static (nx, ny).
        n_complete: static R.
    """

    origin_m: Float[Array, "2"]
    cell_m: Float[Array, ""]
    keys: Int[Array, " R1"]
    candidates: Int[Array, "R1 K"]
    geometry: Float[Array, "7 S"]
    ds_m: Float[Array, ""]
    shape: tuple[int, int] = eqx.field(static=True)
    n_complete: int = eqx.field(static=True)

    @classmethod
    def build(
        cls, track: Track, *, cell_m: float = 0.2, margin_m: float = 1.5, max_candidates: int = 16
    ) -> ProjectionGrid:
        """Build the grid for a track (NumPy, float64, once per track: ~0.2 s for Levine).

        Args:
            track: the track whose `xy_m` polyline is searched.
            cell_m: cell side [m]; smaller cells give shorter candidate lists, more cells. A
                track spanning more than 2^31 cells gets cells just large enough.
            margin_m: how far from the track cells are complete [m]; cars farther away use the
                exhaustive fallback.
            max_candidates: K at most; cells needing more are incomplete (their cars use the
                fallback). K is the longest list of a complete cell. With the default 0.2 m
                cells, 16 answers every point within 0.5 m of Levine's centre line
                (tests/predict/test_batch.py); cells needing more lie farther out or at the
                centre of a tight bend.
        """
        xy = np.asarray(track.xy_m, dtype=np.float64)
        ds = float(track.ds_m)
        m = xy.shape[0]
        n_seg = m if track.closed else m - 1
        a = xy[:n_seg]
        b = xy[(np.arange(n_seg) + 1) % m]
        span = np.ptp(xy, axis=0) + 2 * (margin_m + 3.0 * cell_m) + 2 * cell_m
        cell_m = max(float(cell_m), math.sqrt(span[0] * span[1] / 2.0**30))  # keys fit int32
        half_diag = cell_m * math.sqrt(0.5)
        # Candidate search radius around each segment: reach = margin + enough for the cell test.
        reach = margin_m + 3.0 * half_diag + 1e-3
        origin = xy.min(axis=0) - reach
        nx, ny = (np.ceil((xy.max(axis=0) + reach - origin) / cell_m).astype(int) + 1).tolist()
        seg_len = np.hypot(*(b - a).T)
        w = int(np.ceil((reach + seg_len.max()) / cell_m)) + 1
        off = np.arange(-w, w + 1)
        ox, oy = (o.ravel() for o in np.meshgrid(off, off, indexing="ij"))
        # a disk, not the square: farther cells cannot come within reach of the segment
        disk = np.hypot(ox, oy) * cell_m <= reach + half_diag + 0.5 * seg_len.max() + 1e-9
        ox, oy = ox[disk], oy[disk]
        mid_cell = np.floor(((a + b) / 2 - origin) / cell_m).astype(np.int64)
        corners = np.array([[-1, -1], [-1, 1], [1, -1], [1, 1]]) * (0.5 * cell_m)
        chunk = max(1, (1 << 20) // ox.size)  # segments per pass: bounded memory on any track

        def pairs(lo: int):
            """(cell key, segment, distance from the cell centre [m], centre) of every pair of
            segments lo..lo+chunk and cells within `reach` of them."""
            mc, sl = mid_cell[lo : lo + chunk], slice(lo, min(lo + chunk, n_seg))
            cx, cy = (mc[:, 0, None] + ox[None]).ravel(), (mc[:, 1, None] + oy[None]).ravel()
            seg = np.repeat(np.arange(sl.start, sl.stop), ox.size)
            keep = (cx >= 0) & (cx < nx) & (cy >= 0) & (cy < ny)
            cx, cy, seg = cx[keep], cy[keep], seg[keep]
            centre = origin + (np.stack([cx, cy], axis=1) + 0.5) * cell_m
            d = _seg_dist(centre, a[seg], b[seg])
            near = d <= reach
            key = (cx * ny + cy)[near].astype(np.int32)  # < 2^30: cell_m saw to it
            return key, seg[near].astype(np.int32), d[near], centre[near]

        # pass 1: U per cell, the least over segments of the largest corner distance
        keys, upper = [], []
        for lo in range(0, n_seg, chunk):
            cell, seg, _, centre = pairs(lo)
            d_far = np.max([_seg_dist(centre + c, a[seg], b[seg]) for c in corners], axis=0)
            cell, d_far = _min_by_key(cell, d_far)
            keys.append(cell)
            upper.append(d_far)
        cells, upper = _min_by_key(np.concatenate(keys), np.concatenate(upper))
        # pass 2: each cell's candidates
        slack = 1e-6 + 1e-6 * cell_m  # float32 queries near a cell border stay covered
        cand_cell, cand_seg = [], []
        for lo in range(0, n_seg, chunk):
            cell, seg, d_centre, _ = pairs(lo)
            keep = d_centre - half_diag <= upper[np.searchsorted(cells, cell)] + slack
            cand_cell.append(cell[keep])
            cand_seg.append(seg[keep])
        cell, seg = np.concatenate(cand_cell), np.concatenate(cand_seg)
        order = np.lexsort((seg, cell))  # by cell, then segment index (ties as in Track.project)
        cell, seg = cell[order], seg[order]
        keep = _lattice_test(cell, seg, a, b, origin, ny, cell_m, slack)
        cell, seg = cell[keep], seg[keep]
        key, first, counts = np.unique(cell, return_index=True, return_counts=True)
        # a cell is complete when every segment that could qualify lay within `reach`
        u = upper[np.searchsorted(cells, key)]
        complete = (counts <= max_candidates) & (u + half_diag <= reach)
        k = int(counts[complete].max()) if complete.any() else 1
        rows = np.flatnonzero(complete)
        rank = np.arange(k)[None, :]
        pick = first[rows, None] + np.where(rank < counts[rows, None], rank, 0)
        table = np.vstack([seg[pick], np.zeros((1, k), np.int64)]).astype(np.int32)
        ab = b - a
        inv = ab / np.maximum(np.sum(ab * ab, axis=1, keepdims=True), 1e-12)
        geo = np.concatenate([a.T, ab.T, inv.T, (np.arange(n_seg) * ds)[None]], axis=0)
        return cls(
            origin_m=jnp.asarray(origin),
            cell_m=jnp.asarray(float(cell_m)),
            keys=jnp.asarray(np.append(key[rows], 2**31 - 1).astype(np.int32)),
            candidates=jnp.asarray(table),
            geometry=jnp.asarray(geo),
            ds_m=jnp.asarray(ds),
            shape=(int(nx), int(ny)),
            n_complete=int(len(rows)),
        )

    def locate(self, p_m: Float[Array, "2"]) -> tuple[Int[Array, ""], Bool[Array, ""]]:
        """Row of `candidates` for p (2,) [m], and whether p lies in a complete cell."""
        nx, ny = self.shape
        ij = jnp.floor((p_m - self.origin_m) / self.cell_m).astype(jnp.int32)
        inside = jnp.all((ij >= 0) & (ij < jnp.array([nx, ny], dtype=jnp.int32)))
        key = jnp.clip(ij[0], 0, nx - 1) * ny + jnp.clip(ij[1], 0, ny - 1)
        row = jnp.searchsorted(self.keys, key).astype(jnp.int32)  # <= R: the sentinel's row
        return row, inside & (self.keys[row] == key)

    def project(
        self, p_m: Float[Array, "2"], heading_rad=None
    ) -> tuple[Float[Array, ""], Bool[Array, ""]]:
        """Arc length [m] of the nearest track point to p (2,) [m], and whether it is exact;
        given the car's heading [rad], of the nearest branch that agrees with it where the track
        crosses itself (`Track.project`'s rule, judged by the segments' chords).

        Equal to `track.project(p)` where the second value is True (up to float rounding; where
        two segments are equally near within rounding either may win); where it is False (p off
        the grid or in an incomplete cell) the value is meaningless.
        """
        row, ok = self.locate(p_m)
        cand = self.candidates[row]  # (K,)
        ax, ay, abx, aby, ix, iy, s_a = (self.geometry[q][cand] for q in range(7))
        dx, dy = p_m[0] - ax, p_m[1] - ay
        t = jnp.clip(dx * ix + dy * iy, 0.0, 1.0)
        ex, ey = dx - t * abx, dy - t * aby
        d2 = ex * ex + ey * ey
        s = s_a + t * self.ds_m
        d2_min = _chained_min(d2)
        if heading_rad is not None:
            agree = abx * jnp.cos(heading_rad) + aby * jnp.sin(heading_rad)
            d2_agree = jnp.where(agree >= BRANCH_COS * self.ds_m, d2, jnp.inf)
            d2_agree_min = _chained_min(d2_agree)
            use = d2_agree_min <= BRANCH_M * BRANCH_M
            d2, d2_min = jnp.where(use, d2_agree, d2), jnp.where(use, d2_agree_min, d2_min)
        # The nearest distance, then the least s at it: among equal distances the smallest s is
        # the lowest index, as argmin picks in Track.project. Not argmin (XLA CPU runs it as a
        # slow variadic reduce, 2.4x slower here), and the minima as chains of K elementwise
        # minimums rather than reductions over a trailing axis of K (1.2x faster vmapped).
        return _chained_min(jnp.where(d2 <= d2_min, s, jnp.inf)), ok


LATTICE_SIDE = 9  # lattice points per cell side in the build's fine candidate test


def _lattice_test(cell, seg, a, b, origin, ny, cell_m, slack, pairs_per_pass=1 << 10):
    """Which (cell, segment) pairs pass the fine test: the segment can be the nearest for some
    point of the cell, judged on an n x n lattice of points spanning the cell (n LATTICE_SIDE).

    f(p) = dist(p, j) - min_i dist(p, i) is 2-Lipschitz (a difference of two 1-Lipschitz
    functions) and every point of the cell lies within rho = h / sqrt(2) of a lattice point
    (h the lattice spacing), so min over the lattice of f > 2 rho proves segment j nearer to
    no point of the cell: dropping it is exact. The minimum runs over the cell's coarse
    candidates, which hold every point's nearest segment where the cell is complete (elsewhere
    it overestimates the nearest distance and keeps more). Far from the track, where the coarse
    test's bound is loosest, it shortens the lists most (a cell 1.2 m beside a straight path:
    from 17 segments to 9, tests/predict/test_batch.py).

    Args:
        cell, seg: (P,) int pairs sorted by cell (each cell's pairs contiguous).
        a, b: (S, 2) segment ends [m]; origin: (2,) grid corner [m]; ny: cells along y.
        cell_m: cell side [m]; slack: added to the threshold [m] (float32 queries near a border).
        pairs_per_pass: pairs per vectorised pass (whole cells). Its (pairs, n^2) arrays stay
            in cache: on a 500 m loop 1024 built the grid in 1.8 s, 16384 in 2.4 s.

    Returns (P,) bool.
    """
    n = LATTICE_SIDE
    u = np.linspace(-0.5, 0.5, n) * cell_m
    lattice = np.stack(np.meshgrid(u, u, indexing="ij"), axis=-1).reshape(-1, 2)
    threshold = 2.0 * (cell_m / (n - 1)) / math.sqrt(2.0) + slack
    # each cell's first pair, then the end (just [0] for no pairs): passes cut between cells
    bounds = np.r_[np.flatnonzero(np.diff(cell, prepend=cell[:1] - 1)), len(cell)]
    keep = np.ones(len(cell), dtype=bool)
    k = 0  # bounds[k]: where this pass starts
    while k < len(bounds) - 1:
        # whole cells: up to the first cell boundary at or past this start + pairs_per_pass
        k_end = int(np.searchsorted(bounds, min(bounds[k] + pairs_per_pass, len(cell))))
        lo, hi = bounds[k], bounds[k_end]
        c, j = cell[lo:hi].astype(np.int64), seg[lo:hi, None]
        centre = origin + (np.stack([c // ny, c % ny], axis=1) + 0.5) * cell_m
        # in each cell's frame (origin at its centre), so no (pairs, n^2, 2) points are made
        d = _seg_dist(lattice, a[j] - centre[:, None], b[j] - centre[:, None])  # (pairs, n^2)
        nearest = np.minimum.reduceat(d, bounds[k:k_end] - lo, axis=0)  # (cells, n^2)
        nearest = np.repeat(nearest, np.diff(bounds[k : k_end + 1]), axis=0)
        keep[lo:hi] = np.min(d - nearest, axis=1) <= threshold
        k = k_end
    return keep


def _chained_min(x: Float[Array, " K"]) -> Float[Array, ""]:
    """min(x) as a chain of K elementwise minimums (K is static and small)."""
    return functools.reduce(jnp.minimum, [x[k] for k in range(x.shape[0])])


def _min_by_key(keys: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sorted unique keys (U,) and the least value of each (U,)."""
    order = np.argsort(keys, kind="stable")
    k, v = keys[order], values[order]
    start = np.flatnonzero(np.r_[True, k[1:] != k[:-1]]) if len(k) else np.zeros(0, np.int64)
    return k[start], np.minimum.reduceat(v, start) if len(k) else v


def _seg_dist(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance [m] from points p (..., 2) to segments a-b (..., 2), broadcast over the leading
    axes (e.g. p (L, 2) against a, b (n, 1, 2): the same L points for each segment) -> (...)."""
    # by components: sums over a trailing axis of 2 made the grid build 1.7x as long
    abx, aby = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    apx, apy = p[..., 0] - a[..., 0], p[..., 1] - a[..., 1]
    t = np.clip((apx * abx + apy * aby) / np.maximum(abx * abx + aby * aby, 1e-12), 0.0, 1.0)
    ex, ey = apx - t * abx, apy - t * aby
    return np.sqrt(ex * ex + ey * ey)


# ---- cars in, poses out ------------------------------------------------------------------------


def _check_cars(cars) -> np.ndarray:
    """The (N, 4|5) car rows as a float NumPy array; InputError for any other shape."""
    arr = np.asarray(cars)
    if arr.ndim != 2 or arr.shape[1] not in (4, 5):
        raise InputError("cars", f"array of shape {arr.shape}", "(N, 4|5) x, y, yaw, v[, yaw_rate]")
    return arr if np.issubdtype(arr.dtype, np.floating) else arr.astype(np.float64)


def states_from_array(cars) -> State:
    """A `State` (leading axis N) from rows x [m], y [m], yaw [rad], v [m/s][, yaw_rate [rad/s]].

    Args:
        cars: (N, 4) or (N, 5) array; a missing yaw rate is 0. Fields stay NumPy arrays.
    """
    arr = _check_cars(cars)
    rate = arr[:, 4] if arr.shape[1] == 5 else np.zeros_like(arr[:, 0])
    # fields not named here (direction of motion, ...) take State's own defaults
    return State(
        x_m=arr[:, 0], y_m=arr[:, 1], yaw_rad=arr[:, 2], v_mps=arr[:, 3], yaw_rate_rps=rate
    )


def _state_columns(states: State) -> dict[str, np.ndarray]:
    """Host arrays (N,) of every array field of the State (whatever fields State has); s_m is
    NaN where unknown, other unset optional fields are left out (State fills them)."""
    n = np.shape(states.x_m)[0] if np.ndim(states.x_m) == 1 else -1
    cols = {}
    for field in dataclasses.fields(State):
        value = getattr(states, field.name)
        if field.name == "s_m" and value is None:
            value = np.full(n, np.nan)
        if value is None:
            continue
        col = np.asarray(value)
        if col.shape != (n,):
            raise InputError("states", f"field {field.name} has shape {col.shape}", "(N,) like x_m")
        cols[field.name] = col
    return cols


_CAR_NAMES = ("x_m", "y_m", "yaw_rad", "v_mps", "yaw_rate_rps", "s_m")  # an array's table


@dataclasses.dataclass(frozen=True)
class CarBlocks:
    """N cars handed out a block at a time (a file read in pieces): read(start, stop) returns
    the cars start..stop as (k, 4|5) rows x [m], y [m], yaw [rad], v [m/s][, yaw_rate [rad/s]].
    `BatchPredictor` calls it from its worker threads, for disjoint ranges."""

    n_cars: int
    read: Callable[[int, int], np.ndarray]


def _n_cars(cars) -> int:
    """N of an (N, 4|5) array or a State (InputError for any other shape)."""
    if isinstance(cars, State):
        return _state_columns(cars)["x_m"].shape[0]
    return _check_cars(cars).shape[0]


def _car_table(cars, dtype) -> tuple[tuple[str, ...], np.ndarray]:
    """(State field names, (N, F) table in dtype) from an (N, 4|5) array or a State."""
    if isinstance(cars, State):
        cols = _state_columns(cars)
        names = tuple(cols)
        return names, np.column_stack([cols[k] for k in names]).astype(dtype)
    # an array: straight into the table (no State on the host: cheaper for small batches);
    # fields not given here take State's defaults inside the compiled call
    arr = _check_cars(cars)
    table = np.empty((arr.shape[0], len(_CAR_NAMES)), dtype=dtype)
    table[:, :4] = arr[:, :4]
    table[:, 4] = arr[:, 4] if arr.shape[1] == 5 else 0.0
    table[:, 5] = np.nan
    return _CAR_NAMES, table


@eqx.filter_jit
def _project_exhaustive(track: Track, xy_m, heading_rad):
    """Exhaustive projection of a small batch (B, 2), headings (B,) [rad] -> (B,) [m] (the
    off-grid fallback)."""
    return jax.vmap(track.project)(xy_m, heading_rad)


@functools.partial(jax.jit, static_argnums=(0, 1))
def _predict_block(names: tuple[str, ...], static, dynamic, block):
    """One compiled call for a chunk of cars.

    Args:
        names: static; the State field of each column of `block`.
        static, dynamic: (params, track, grid) split by `eqx.partition` once per predictor, so a
            call only hashes the small static part (cheaper dispatch than `eqx.filter_jit`).
        block: (C, F) one row per car, columns as `names`; s_m NaN where unknown.

    Returns:
        poses (C, H, 3) or (P, C, H, 3), and ok (C,) bool: False where the car needed a grid
        projection the grid could not give exactly (off the grid or in an incomplete cell).
    """
    params, track, grid = eqx.combine(dynamic, static)
    cols = {name: block[:, k] for k, name in enumerate(names)}
    p = jnp.stack([cols["x_m"], cols["y_m"]], axis=1)
    known = ~jnp.isnan(cols["s_m"])
    # a chunk whose cars all carry hints skips the grid (a third of the chunk's time)
    s_grid, exact = jax.lax.cond(
        jnp.all(known),
        lambda: (cols["s_m"], known),
        lambda: jax.vmap(grid.project)(p, cols["yaw_rad"]),
    )
    cols["s_m"] = jnp.where(known, cols["s_m"], s_grid)
    return predict_batch(params, State(**cols), track), known | exact


@dataclasses.dataclass
class ChunkPlan:
    """How `predict_chunked` cut the work (returned through `info`, for reports and tests)."""

    n_cars: int
    chunk: int
    n_chunks: int
    dtype: str
    n_off_grid: int = 0
    tail_chunk: int = 0  # shape of a smaller last chunk (0: none, every chunk has `chunk` rows)


def chunk_size(n_cars: int, chunk: int = DEFAULT_CHUNK, multiple: int = 1) -> int:
    """The fixed chunk shape for N cars: `chunk`, or the next power of two >= N when N is
    smaller (a single car does not pay for a full chunk), rounded up to a multiple of the device
    count."""
    spec.check_chunk(chunk)
    c = min(chunk, 1 << max(n_cars - 1, 0).bit_length())
    return int(math.ceil(c / multiple) * multiple)


class BatchPredictor:
    """Predict many cars under fixed parameters and track, repeatedly (a planner's per-cycle
    call): casting, device placement and the split into static and traced parts happen once
    here; each call then costs one compiled call per chunk.

    Args:
        params: one parameter set, or P stacked ones (`stack_params`: weights (P, H)).
        track: the track.
        dtype: "float32" (default) or "float64" for the whole computation.
        chunk: cars per compiled call. A last, partial chunk is padded to the next power of two
            instead (at most log2(chunk) further shapes ever compile; N = 1e5 in chunks of 16384
            would otherwise run 13 % padding).
        grid: a prebuilt `ProjectionGrid` for the track (built here when None).
        mesh: a 1-D `jax.sharding.Mesh` (`fpe_jax.predict.car_mesh()`) to split each chunk's cars
            across its devices; None runs on the default device.
        workers: chunks in flight at once (threads); default: the CPU count, at most 4.
    """

    def __init__(
        self,
        params: Params,
        track: Track,
        *,
        dtype="float32",
        chunk: int = DEFAULT_CHUNK,
        grid: ProjectionGrid | None = None,
        mesh=None,
        workers: int | None = None,
    ):
        from fpe_jax.predict import (
            _shard as shard,  # sharding helpers; imported here to keep this import light
        )

        self.dtype = _dtype(dtype)
        chunk_size(1, chunk)  # validates it; the size used depends on each call's N
        self.max_chunk = chunk
        self.mesh = mesh
        self._n_devices = 1 if mesh is None else mesh.devices.size
        self._compiled: set = set()  # (column names, chunk rows) already run once
        self.workers = max(1, workers if workers is not None else min(os.cpu_count() or 1, 4))
        self.horizon = params.settings.horizon
        self.n_sets = params.weights.shape[0] if params.weights.ndim == 2 else None
        grid = ProjectionGrid.build(track) if grid is None else grid
        with self._precision():
            tree = _to_device(cast_floats((params, track, grid), self.dtype))
            self._dynamic, self._static = eqx.partition(tree, eqx.is_array)
            self._track = tree[1]
            if mesh is not None:
                self._dynamic = shard.replicate(self._dynamic, mesh)

    def _precision(self):
        # constants made inside the predictor follow the global x64 flag: pin it to the dtype
        return jax.enable_x64(self.dtype == np.float64)

    def __call__(
        self,
        cars,
        *,
        out: np.ndarray | None = None,
        progress: Callable[[int, int], None] | None = None,
        info: dict | None = None,
    ) -> np.ndarray:
        """Poses (N, H, 3) or (P, N, H, 3) x [m], y [m], yaw [rad] at t + h * dt_s, h = 1..H.

        Args:
            cars: (N, 4|5) rows x [m], y [m], yaw [rad], v [m/s][, yaw_rate [rad/s]], a
                `State` with leading axis N (its `s_m`, if given, is the arc-length hint; NaN
                entries are projected), or `CarBlocks`.
            out: optional preallocated result array (e.g. `np.lib.format.open_memmap`), so host
                memory stays bounded too.
            progress: called as progress(done_cars, n_cars) after each chunk.
            info: if a dict, filled with the `ChunkPlan` fields.
        """
        n = cars.n_cars if isinstance(cars, CarBlocks) else _n_cars(cars)
        h = self.horizon
        out_shape = (n, h, 3) if self.n_sets is None else (self.n_sets, n, h, 3)
        if out is None:
            out = np.empty(out_shape, dtype=self.dtype)
        elif out.shape != out_shape:
            raise InputError("out", f"array of shape {out.shape}", f"shape {out_shape}")
        for rows, poses in self.chunks(cars, progress=progress, info=info):
            if self.n_sets is None:
                out[rows] = poses
            else:
                out[:, rows] = poses
        return out

    def chunks(
        self,
        cars,
        *,
        progress: Callable[[int, int], None] | None = None,
        info: dict | None = None,
    ) -> Iterator[tuple[slice | np.ndarray, np.ndarray]]:
        """Yield (rows, poses): first each chunk in car order, rows = slice(start, stop) and
        poses (k, H, 3) or (P, k, H, 3); then, for the rare cars off the projection grid,
        their final poses, rows an ascending index array. Writing each item's poses at its
        rows gives `__call__`'s result exactly (a chunk's off-grid rows are provisional until
        then). Cars as for `__call__`; with `CarBlocks` each chunk's cars are read on the worker
        thread that predicts them, so neither the cars nor the poses of all N need be in memory
        at once. `info` is filled when the last item has been yielded."""
        if isinstance(cars, CarBlocks):
            names, n = _CAR_NAMES, cars.n_cars
            rows = lambda a, b: _car_table(cars.read(a, b), self.dtype)[1]  # noqa: E731
        else:
            names, table = _car_table(cars, self.dtype)
            n = table.shape[0]
            rows = lambda a, b: table[a:b]  # noqa: E731
        c = chunk_size(n, self.max_chunk, self._n_devices)
        plan = ChunkPlan(n, c, math.ceil(n / c), np.dtype(self.dtype).name)
        tail = chunk_size(n % c or c, c, self._n_devices)
        plan.tail_chunk = tail if tail < c else 0
        redo, redo_cars = [], []
        for start, stop, block, poses, ok in self._run(names, rows, n, c, progress):
            bad = np.flatnonzero(~ok)
            if bad.size:
                redo.append(start + bad)
                redo_cars.append(block[bad])
            yield slice(start, stop), poses
        if redo:  # rare: exact arc lengths by exhaustive search, then predict again
            redo, sub = np.concatenate(redo), np.concatenate(redo_cars)
            plan.n_off_grid = int(redo.size)
            with self._precision():
                sub[:, names.index("s_m")] = self._exhaustive(sub, names)
            for start, stop, _, poses, _ in self._run(
                names, lambda a, b: sub[a:b], len(sub), c, None
            ):
                yield redo[start:stop], poses
        if info is not None:
            info.update(dataclasses.asdict(plan))

    def compile_seconds(self, cars, chunk: int) -> float:
        """Seconds to compile, ahead of time, the chunk function for `chunk` cars (`cars` as for
        `__call__`): compile time apart from running, for benchmarks."""
        import time

        names, table = _car_table(cars[:chunk], self.dtype)
        with self._precision():
            block = jnp.asarray(pad_rows(table, chunk))
            t0 = time.perf_counter()
            _predict_block.lower(names, self._static, self._dynamic, block).compile()
            return time.perf_counter() - t0

    def _predict_table(self, names, table, c) -> tuple[np.ndarray, np.ndarray]:
        """Poses (k, H, 3) or (P, k, H, 3) and ok (k,) of the k <= c cars of `table` (k, F) in
        one compiled call, padded to `chunk_size(k, c)` rows."""
        from fpe_jax.predict import _shard as shard

        k = table.shape[0]
        with self._precision():  # config contexts are per thread
            block = pad_rows(table, chunk_size(k, c, self._n_devices))
            if self.mesh is not None:
                block = shard.shard_along_axis0(block, self.mesh)
            poses, ok = _predict_block(names, self._static, self._dynamic, jnp.asarray(block))
            poses, ok = np.asarray(poses), np.asarray(ok)[:k]
        return (poses[:k] if self.n_sets is None else poses[:, :k]), ok

    def _run(self, names, rows, n, c, progress):
        """Yield (start, stop, table, poses, ok) per chunk, as NumPy, in order; rows(start, stop)
        gives a chunk's (k, F) table.

        Chunks run on `workers` threads: XLA runs one chunk's step loop on one core, so two
        chunks in flight use two (1.4x the rate on this 2-core machine). The first chunk of a
        shape not yet compiled runs alone, so that it compiles once, and a single chunk runs on
        the calling thread (a pool costs ~0.4 ms). At most 2 x workers results wait to be
        consumed, keeping memory bounded.
        """

        def work(start):
            stop = min(start + c, n)
            table = rows(start, stop)
            return (start, stop, table, *self._predict_table(names, table, c))

        starts = iter(range(0, n, c))
        if n <= c or (names, c) not in self._compiled:  # one chunk needs no thread
            first = next(starts, None)
            if first is None:
                return
            done = work(first)
            self._compiled.add((names, c))
            yield done
            if progress is not None:
                progress(done[1], n)
        with ThreadPoolExecutor(max_workers=self.workers) as pool:
            window = collections.deque(
                pool.submit(work, s) for s in itertools.islice(starts, 2 * self.workers)
            )
            try:
                while window:
                    done = window.popleft().result()
                    nxt = next(starts, None)
                    if nxt is not None:
                        window.append(pool.submit(work, nxt))
                    yield done
                    if progress is not None:
                        progress(done[1], n)
            finally:  # a consumer that stops early (an error, Ctrl-C) waits for no more chunks
                for f in window:
                    f.cancel()

    def _exhaustive(self, table, names) -> np.ndarray:
        """Arc lengths (k,) of the cars of `table` (k, F) by exhaustive search."""
        xy = table[:, [names.index("x_m"), names.index("y_m")]]
        yaw = table[:, names.index("yaw_rad")]
        k = table.shape[0]
        s = np.empty(k, dtype=self.dtype)
        for start in range(0, k, _SLOW_BATCH):
            pts = pad_rows(xy[start : start + _SLOW_BATCH], _SLOW_BATCH)
            h = pad_rows(yaw[start : start + _SLOW_BATCH], _SLOW_BATCH)
            res = np.asarray(_project_exhaustive(self._track, jnp.asarray(pts), jnp.asarray(h)))
            s[start : start + _SLOW_BATCH] = res[: min(_SLOW_BATCH, k - start)]
        return s


def predict_chunked(
    params: Params,
    cars,
    track: Track,
    *,
    dtype="float32",
    chunk: int = DEFAULT_CHUNK,
    grid: ProjectionGrid | None = None,
    mesh=None,
    out: np.ndarray | None = None,
    progress: Callable[[int, int], None] | None = None,
    info: dict | None = None,
) -> np.ndarray:
    """Predict N cars in fixed-size chunks, one compiled vmapped call per chunk.

    A one-shot `BatchPredictor(params, track, dtype=, chunk=, grid=, mesh=)(cars, out=,
    progress=, info=)`; see there for the arguments. Build a `BatchPredictor` yourself when
    predicting repeatedly with the same parameters and track.

    Returns:
        poses: (N, H, 3), or (P, N, H, 3) for P stacked parameter sets: x [m], y [m], yaw [rad]
        at t + h * dt_s, h = 1..H, as NumPy in `dtype`.
    """
    predictor = BatchPredictor(params, track, dtype=dtype, chunk=chunk, grid=grid, mesh=mesh)
    return predictor(cars, out=out, progress=progress, info=info)


def off_track_cars(params: Params, cars_xy_m, track: Track) -> np.ndarray:
    """(N,) bool: the cars (N, 2) [m] (in the track's frame) that lie farther than
    `fpe_jax.geometry.on_track_m` of the track from its line and, for the line model, from the
    learned line: the rule of the on-track checks (`fpe_jax.geometry.off_track`). Their
    predictions follow the nearest part of the track, which for a car in another map frame
    means nothing."""
    return off_track_judge(params, track)(np.asarray(cars_xy_m, dtype=np.float64))


def off_track_judge(params: Params, track: Track):
    """`off_track_cars` for one predictor and track, made once for many blocks of cars:
    judge(cars_xy_m (k, 2) [m], n_points=None) -> (k,) bool, n_points the cars of all blocks
    together (`fpe_jax.geometry.NearPath`)."""
    path = dict(
        xy_m=np.asarray(track.xy_m, dtype=np.float64),
        heading_rad=np.asarray(track.heading_rad, dtype=np.float64),
        ds_m=float(track.ds_m),
        length_m=float(track.length_m),
        closed=track.closed,
    )
    line = np.asarray(params.line_offset_m) if params.settings.model == "line" else None
    return geometry_off_track_judge(path, line)


def off_track_summary(
    off: np.ndarray, source: str, near_m: float = ON_TRACK_M, shown: int = 10
) -> str | None:
    """One line on the cars `off_track_cars` flagged (N,) (farther than near_m [m]: the track's
    `fpe_jax.geometry.on_track_m`), None when there are none."""
    rows = np.flatnonzero(off)
    if not len(rows):
        return None
    listed = ", ".join(str(r) for r in rows[:shown]) + (", ..." if len(rows) > shown else "")
    return (
        f"warning: {len(rows)} of {len(off)} cars of {source} lie off the track, more than "
        f"{near_m:.3g} m from its waypoints (rows {listed}): likely another map frame; "
        "their predictions follow the nearest part of the track"
    )


ORIGIN_MAX_FLOAT32_M = 1000.0  # beyond a kilometre float32 cannot hold a position to the mm


def origin_dtype(dtype, origin_m) -> np.dtype:
    """The dtype of poses in `dtype` once moved by the map origin (2,) [m]: float64 where
    float32 cannot hold map coordinates to the mm (|origin| > ORIGIN_MAX_FLOAT32_M)."""
    far = np.abs(np.asarray(origin_m, dtype=np.float64)).max() > ORIGIN_MAX_FLOAT32_M
    return np.dtype(np.float64) if far else np.dtype(dtype)


def with_origin(
    poses: np.ndarray, origin_m, block: int = 1 << 16, *, out: np.ndarray | None = None
) -> np.ndarray:
    """Poses (..., 3) in the track's local frame moved back by the map origin (2,) [m]: x, y
    plus the origin, each sum the float64 sum rounded to the result's dtype, block by block
    along the first axis (no full float64 copy), into `out` if given, else in place when the
    poses' dtype can hold map coordinates (`origin_dtype`), else into a new float64 array."""
    origin = np.asarray(origin_m, dtype=np.float64)
    if out is None:
        same = origin_dtype(poses.dtype, origin) == poses.dtype
        out = poses if same else np.empty(poses.shape, dtype=np.float64)
    # -0.0 leaves every yaw as it is (-0.0 included); the whole rows are added at once
    shift = np.array([origin[0], origin[1], -0.0])
    if poses.dtype == out.dtype == np.float32 and np.all(shift.astype(np.float32) == shift):
        # a float32 sum of float32 numbers is their float64 sum rounded to float32 (double
        # rounding is harmless for a sum when 53 >= 2 * 24 + 2 bits), at a third of the cost
        shift = shift.astype(np.float32)
    width = poses[:1].size  # one car's values, added as one row (4x the rate of rows of 3)
    flat = width % 3 == 0 and poses.flags.c_contiguous and out.flags.c_contiguous
    rows = (lambda x: x.reshape(-1, width)) if flat else (lambda x: x)  # noqa: E731
    shift = np.tile(shift, width // 3) if flat else shift
    for a in range(0, len(poses), block):
        np.add(rows(poses[a : a + block]), shift, out=rows(out[a : a + block]))
    return out
