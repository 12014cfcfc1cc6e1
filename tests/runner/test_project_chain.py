"""`RunnerPath.project_chain`: the window searches of a predicted path's points all at once
give exactly the values of `project_window` point after point."""

from __future__ import annotations

import numpy as np
import pytest

from fpe_jax.io.config import params_to_config
from fpe_jax.model._params import presets
from fpe_jax.runner._runner import Runner, RunnerPath
from fpe_jax.sim._sim import simulate


def loop(path: RunnerPath, xy_m: np.ndarray, s_m: float) -> list[float]:
    out = []
    for x, y in xy_m.tolist():
        s_m = path.project_window(x, y, s_m)
        out.append(s_m)
    return out


@pytest.mark.parametrize("track", ["oval", "hairpin", "random:3"])
def test_project_chain_equals_the_loop_of_window_searches(track):
    """Every prediction of a drive (the hairpin's cut the bend, far from the line), from the
    car's arc length and from hints 5 cm, 3 m and 30 m off: equal values, to the last bit."""
    res = simulate(track, duration_s=20.0, seed=2)
    runner = Runner(params_to_config(presets["default"]), res.centerline_xy_m)
    path = runner.path
    n = 0
    for ts, (x, y) in zip(res.drive.t_s, res.drive.xy_m):
        poses = runner.update(float(ts), float(x), float(y))
        for s_m in (runner._s_m, runner._s_m + 0.05, runner._s_m - 3.0, runner._s_m + 30.0):
            assert path.project_chain(poses[:, :2], s_m) == loop(path, poses[:, :2], s_m)
            n += 1
    assert n > 500


def test_project_chain_on_an_open_path_past_its_ends():
    """An open path: points before its start and after its end clamp as the loop's do."""
    xy = np.column_stack([np.linspace(0.0, 20.0, 41), 0.1 * np.sin(np.linspace(0.0, 3.0, 41))])
    path = RunnerPath(xy)
    assert not path.closed
    pts = np.column_stack([np.linspace(-3.0, 24.0, 12), np.full(12, 0.4)])
    for s_m in (0.0, 1.0, 19.5):
        assert path.project_chain(pts, s_m) == loop(path, pts, s_m)
