"""Built-in race tracks, generated procedurally (no data files), and closed-loop polyline helpers.

Every track is a closed loop, counter-clockwise, given as its centerline sampled every ~0.1 m
(the first point is not repeated at the end) plus the track's half-width.

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
    if name == "oval":
        return _oval(), 1.1
    if name == "hairpin":
        return _hairpin(), 0.9
    if is_builtin(name):
        return _random_loop(int(name.partition(":")[2]), half_width_m=1.1), 1.1
    raise InputError(name, "unknown built-in track", "oval, hairpin or random:SEED")


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


def _turtle(segments: list[tuple[float, float]], step_m: float = 0.01) -> np.ndarray:
    """Trace straight/arc segments (length [m], curvature [1/m]) from the origin heading +x.

    Positions are exact per arc (no integration drift), so a closed design closes exactly.
    Returns (N, 2) points every `step_m`, closing point dropped.
    """
    x = y = th = 0.0
    pts = []
    for length_m, kappa in segments:
        n = max(int(round(length_m / step_m)), 1)
        s = np.arange(n) * (length_m / n)
        if kappa == 0.0:
            px, py = x + s * math.cos(th), y + s * math.sin(th)
        else:
            px = x + (np.sin(th + kappa * s) - math.sin(th)) / kappa
            py = y - (np.cos(th + kappa * s) - math.cos(th)) / kappa
        pts.append(np.stack([px, py], axis=1))
        if kappa == 0.0:
            x, y = x + length_m * math.cos(th), y + length_m * math.sin(th)
        else:
            x += (math.sin(th + kappa * length_m) - math.sin(th)) / kappa
            y -= (math.cos(th + kappa * length_m) - math.cos(th)) / kappa
        th += kappa * length_m
    assert math.hypot(x, y) < 1e-9, "track design does not close"
    return np.concatenate(pts)


def _arc(radius_m: float, angle_rad: float) -> tuple[float, float]:
    """A turn as a turtle segment: positive angle turns left, negative turns right."""
    return radius_m * abs(angle_rad), math.copysign(1.0 / radius_m, angle_rad)


def _oval() -> np.ndarray:
    pi = math.pi
    dense = _turtle([(18.0, 0.0), _arc(6.0, pi), (18.0, 0.0), _arc(6.0, pi)])
    return resample_loop(_smooth_loop(dense, 2.0), SPACING_M)[0]


def _hairpin() -> np.ndarray:
    # East 20 m, wide left turn, then a left-right-left "S" whose middle is a 1.5 m radius
    # hairpin (its two legs 3 m apart: 1.2 m of wall between the track edges), back west, and
    # a wide left turn home. The x-displacements sum to zero, so the loop closes exactly.
    pi = math.pi
    design = [
        (20.0, 0.0),
        _arc(4.0, pi),
        (5.0, 0.0),
        _arc(2.0, pi / 2),
        (1.0, 0.0),
        _arc(1.5, -pi),
        (1.0, 0.0),
        _arc(2.0, pi / 2),
        (8.0, 0.0),
        _arc(4.0, pi),
    ]
    return resample_loop(_smooth_loop(_turtle(design), 1.0), SPACING_M)[0]


def _smooth_loop(xy_m: np.ndarray, window_m: float, step_m: float = 0.01) -> np.ndarray:
    """Moving average over `window_m` of a closed loop sampled every `step_m`: turns in and out
    of arcs get gradual curvature (as on real tracks) instead of a jump."""
    n = int(round(window_m / step_m))
    pad = np.concatenate([xy_m[-n:], xy_m, xy_m[:n]])
    kernel = np.ones(n) / n
    smooth = [np.convolve(pad[:, c], kernel, mode="same")[n:-n] for c in (0, 1)]
    return np.stack(smooth, axis=1)


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
