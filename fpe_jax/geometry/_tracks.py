"""Built-in race tracks and closed-loop polyline helpers.

Every track is a closed loop, counter-clockwise, given as its centerline sampled every ~0.1 m
(the first point is not repeated at the end) plus the track's half-width. `oval` and `hairpin`
are files shipped with the package (fpe_jax/builtin_tracks/, copies of data/tracks/, designed
as straights and arcs by data/make_samples.py); `random:SEED` is generated from its seed.

- ``oval``: a 30 m x 12 m stadium (two 18 m straights, two 6 m radius turns), half-width 1.1 m.
- ``hairpin``: a ~71 m loop with a right-hand 1.5 m radius hairpin between two 2 m turns,
  half-width 0.9 m.
- ``random:SEED``: a smooth random loop, 60-120 m long: a circle whose radius is perturbed by
  Fourier harmonics 2-4, redrawn until its turns are wider than 3 m and distant parts of the
  track do not touch. Star-shaped around its centre, hence never self-intersecting.
  Half-width 1.1 m.
"""

from __future__ import annotations

import math

import numpy as np

from fpe_jax.errors import InputError

SPACING_M = 0.1
BUILTIN_TRACKS = ("oval", "hairpin", "random:SEED")


def is_builtin(name: str) -> bool:
    """Whether `name` names a built-in track (``oval``, ``hairpin`` or ``random:<int>``)."""
    if name in ("oval", "hairpin"):
        return True
    head, _, seed = name.partition(":")
    return head == "random" and seed.lstrip("-").isdigit()


def builtin_track(name: str) -> tuple[np.ndarray, float]:
    """The centerline and half-width of a built-in track.

    Args:
        name: ``oval``, ``hairpin`` or ``random:SEED`` (SEED an integer).

    Returns:
        centerline_xy_m: (K, 2) closed loop x [m], y [m], counter-clockwise, ~0.1 m spacing,
            first point not repeated.
        half_width_m: distance from the centerline to either edge [m].
    """
    if name in ("oval", "hairpin"):
        return _read_builtin(name)
    if is_builtin(name):
        seed = int(name.partition(":")[2])
        if seed < 0:  # SeedSequence needs a non-negative seed
            raise InputError(name, f"seed {seed} is negative", "random:SEED with SEED >= 0")
        return _random_loop(seed, half_width_m=1.1), 1.1
    raise InputError(name, "unknown built-in track", "oval, hairpin or random:SEED")


def _read_builtin(name: str) -> tuple[np.ndarray, float]:
    """A shipped track: fpe_jax/builtin_tracks/NAME.csv, the package's copy of data/tracks/."""
    from importlib.resources import as_file, files

    from fpe_jax.io.tables import read_table  # the one CSV parser (exact: Python's float())

    with as_file(files("fpe_jax") / "builtin_tracks" / f"{name}.csv") as path:
        table = read_table(path)
    xy = np.column_stack([table.column(("x_m",), "x"), table.column(("y_m",), "y")])
    return xy, float(table.column(("w_tr_left_m",), "half-width")[0])


def loop_arclength(xy_m: np.ndarray) -> np.ndarray:
    """(K+1,) arc length [m] at each vertex of a closed loop (K, 2), then the total length."""
    seg = np.linalg.norm(np.diff(xy_m, axis=0, append=xy_m[:1]), axis=1)
    return np.concatenate([[0.0], np.cumsum(seg)])


def resample_loop(
    xy_m: np.ndarray, spacing_m: float, values: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """Resample a closed loop at (nearly) equal arc-length spacing.

    Args:
        xy_m: (K, 2) loop vertices [m]; the closing segment back to the first vertex is implied
            (a repeated last vertex is dropped).
        spacing_m: wanted spacing [m]; the actual one divides the length evenly.
        values: optional (K,) per-vertex values (e.g. speeds), interpolated linearly along the loop.

    Returns:
        (N, 2) resampled loop starting at the first vertex, and the (N,) resampled values or None.
    """
    xy_m = np.asarray(xy_m, dtype=float)
    if np.linalg.norm(xy_m[-1] - xy_m[0]) < 1e-9:
        xy_m = xy_m[:-1]
        values = None if values is None else np.asarray(values, dtype=float)[:-1]
    s = loop_arclength(xy_m)
    n = max(int(round(s[-1] / spacing_m)), 3)
    s_new = np.linspace(0.0, s[-1], n, endpoint=False)
    closed = np.vstack([xy_m, xy_m[:1]])
    out = np.stack([np.interp(s_new, s, closed[:, 0]), np.interp(s_new, s, closed[:, 1])], axis=1)
    if values is None:
        return out, None
    v = np.asarray(values, dtype=float)
    return out, np.interp(s_new, s, np.append(v, v[0]))


def _random_loop(seed: int, half_width_m: float) -> np.ndarray:
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x7AC5]))
    theta = np.linspace(0.0, 2 * math.pi, 2048, endpoint=False)
    for _ in range(1000):
        radius_m = rng.uniform(10.0, 18.0)
        r = np.ones_like(theta)
        for k in (2, 3, 4):
            r += rng.uniform(0.0, 0.5 / k) * np.cos(k * theta + rng.uniform(0.0, 2 * math.pi))
        xy = resample_loop(radius_m * np.stack([r * np.cos(theta), r * np.sin(theta)], 1), 0.1)[0]
        if _looks_like_a_track(xy, half_width_m, min_radius_m=3.0, length_m=(60.0, 120.0)):
            return resample_loop(xy, SPACING_M)[0]
    raise RuntimeError(f"random:{seed}: no valid track found")  # pragma: no cover


def _looks_like_a_track(
    xy_m: np.ndarray, half_width_m: float, min_radius_m: float, length_m: tuple[float, float]
) -> bool:
    """Length in range, no turn tighter than `min_radius_m`, and no two parts of the track whose
    surfaces overlap (points > 6 m apart along the loop stay > 2 half-widths + 1 m apart)."""
    s = loop_arclength(xy_m)
    if not length_m[0] <= s[-1] <= length_m[1]:
        return False
    if np.max(np.abs(loop_curvature(xy_m))) > 1.0 / min_radius_m:
        return False
    coarse = xy_m[::5]
    sc = s[:-1][::5]
    ds = np.abs(sc[:, None] - sc[None, :])
    far_along = np.minimum(ds, s[-1] - ds) > 6.0
    dist = np.linalg.norm(coarse[:, None, :] - coarse[None, :, :], axis=-1)
    return bool(np.all(dist[far_along] > 2 * half_width_m + 1.0))


def loop_curvature(xy_m: np.ndarray, smooth_m: float = 0.0) -> np.ndarray:
    """Signed curvature [1/m] (left turns positive) at each vertex of an evenly spaced closed loop.

    Args:
        xy_m: (K, 2) closed loop, evenly spaced (see `resample_loop`).
        smooth_m: optional moving-average window [m]; noisy surveyed centerlines need ~1-2 m.

    Returns:
        (K,) curvature [1/m].
    """
    d = np.roll(xy_m, -1, axis=0) - np.roll(xy_m, 1, axis=0)
    heading = np.arctan2(d[:, 1], d[:, 0])
    dh = np.angle(np.exp(1j * (np.roll(heading, -1) - np.roll(heading, 1))))
    spacing_m = loop_arclength(xy_m)[-1] / len(xy_m)
    kappa = dh / (2 * spacing_m)
    n = int(round(smooth_m / spacing_m))
    if n > 1:
        pad = np.concatenate([kappa[-n:], kappa, kappa[:n]])
        kappa = np.convolve(pad, np.ones(n) / n, mode="same")[n:-n]
    return kappa
