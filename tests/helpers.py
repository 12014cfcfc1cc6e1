"""What several test files share: the in-process CLI runner, tree closeness, finite-difference
checks, and the catalogue of tracks x predictors that parity tests run over."""

from __future__ import annotations

import functools
import io
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from fpe_jax import Drive, Params, Settings, presets
from fpe_jax.sim import simulate

LEVINE = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "levine"


# ---- the CLI ----------------------------------------------------------------------------------


def cli_runner(
    capsys, argv, *, stdin: str | None = None, monkeypatch=None, expect=(0, 2)
) -> tuple[int, str, str]:
    """In-process `fpe ARGV` (items turned into str): (exit status, stdout, stderr). The status
    must be one of `expect` (an int for exactly one) and stderr must hold no traceback; `stdin`
    (with monkeypatch) is what the command reads."""
    from fpe_jax import cli

    if stdin is not None:
        monkeypatch.setattr(sys, "stdin", io.StringIO(stdin))
    capsys.readouterr()
    rc = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    assert "Traceback" not in err, err
    expect = (expect,) if isinstance(expect, int) else tuple(expect)
    assert rc in expect, (rc, expect, err)
    return rc, out, err


# ---- trees -------------------------------------------------------------------------------------


def assert_trees_close(a, b, *, rtol: float = 0.0, atol: float = 0.0, err_msg: str = "") -> None:
    """a and b have one pytree structure (static fields such as Settings included) and every
    leaf of a is within atol + rtol |b| of b's."""
    leaves_a, tree_a = jax.tree.flatten(a)
    leaves_b, tree_b = jax.tree.flatten(b)
    assert tree_a == tree_b, f"{err_msg}: {tree_a} != {tree_b}"
    for x, y in zip(leaves_a, leaves_b):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol, atol, err_msg=err_msg)


# ---- finite differences ------------------------------------------------------------------------


def fd_jvp(f, x, tangent, eps: float):
    """Central difference (f(x + eps t) - f(x - eps t)) / (2 eps) of f at the pytree x along the
    pytree tangent t, leaf by leaf of f's output (NumPy)."""
    up = f(jax.tree.map(lambda a, t: a + eps * t, x, tangent))
    down = f(jax.tree.map(lambda a, t: a - eps * t, x, tangent))
    return jax.tree.map(lambda u, d: (np.asarray(u) - np.asarray(d)) / (2 * eps), up, down)


def assert_jvp_matches_fd(f, x, tangent, eps: float, *, rtol: float, atol: float) -> None:
    """jax.jvp of f at x along tangent equals its central difference."""
    _, auto = jax.jvp(f, (x,), (tangent,))
    assert_trees_close(auto, fd_jvp(f, x, tangent, eps), rtol=rtol, atol=atol)


def fd_gradient(f, x, eps: float) -> np.ndarray:
    """Central-difference gradient of a scalar f at the array x, one basis direction (a JVP) at a
    time: same shape as x."""
    x = np.asarray(x, dtype=float)
    out = np.zeros(x.size)
    for i in range(x.size):
        e = np.zeros(x.size)
        e[i] = 1.0
        out[i] = float(fd_jvp(f, x, e.reshape(x.shape), eps))
    return out.reshape(x.shape)


# ---- the catalogue: tracks x predictors --------------------------------------------------------

CUSTOM = {  # non-trivial weights, delay, gain and speed shrinkage; both blend modes
    "heading-blend": lambda: Params.create(
        Settings(blend="heading"),
        lookahead_m=1.3,
        lookahead_gain_s=0.3,
        weights=np.linspace(0.95, 0.1, 10),
        delay_s=0.15,
    ),
    "shrunk-speed": lambda: Params.create(
        Settings(),
        lookahead_m=0.8,
        lookahead_gain_s=0.1,
        weights=np.linspace(0.2, 0.9, 10),
        delay_s=0.05,
        speed_weight=0.3,
        speed_mps=2.5,
    ),
}
# every preset and the two fitted-looking blends
PREDICTORS = (*presets, *CUSTOM)


def predictor(name: str) -> Params:
    """A preset by name, or one of CUSTOM's."""
    return CUSTOM[name]() if name in CUSTOM else presets[name]


@functools.cache
def _oval() -> tuple[np.ndarray, Drive]:
    res = simulate("oval", duration_s=20.0, seed=3)
    return res.centerline_xy_m, res.drive


@functools.cache
def _levine() -> tuple[np.ndarray, Drive]:
    wp = np.loadtxt(LEVINE / "levine-waypoints.csv", delimiter=",")[:, :2]
    poses = np.loadtxt(LEVINE / "actual-poses.csv", delimiter=",")
    n = len(poses)
    drive = Drive(t_s=np.arange(n) * 0.1, xy_m=poses[:, :2], yaw_rad=np.full(n, np.nan))
    return wp, drive


TRACKS = {
    # a 20 s simulated drive on the oval: noisy detections with yaw, outliers, repeats-free
    "oval": _oval,
    # the real 2019 drive: 10 Hz, no yaw, ~48 % repeated rows, stops and outlier jumps
    "levine": _levine,
}
# (track, predictor) pairs: every predictor on the oval; the 2720-point real lap (slow to run
# through the JAX predictor) with the seed and one of each blend mode
CASES = [("oval", p) for p in PREDICTORS] + [
    ("levine", p) for p in ("seed", "default", "heading-blend")
]


def track_drive(name: str) -> tuple[np.ndarray, Drive]:
    """(K, 2) waypoints [m] and a drive on them; skips when the real data is absent."""
    if name == "levine" and not LEVINE.is_dir():
        pytest.skip(f"real data not found at {LEVINE} (../shared/data beside the checkout)")
    return TRACKS[name]()
