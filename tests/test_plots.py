"""`fpe_jax.plots` draws without pyplot and lays a figure out once, with the same pixels as
pyplot's figures laid out by `Figure.tight_layout`."""

from __future__ import annotations

import io
import subprocess
import sys
from types import SimpleNamespace

import matplotlib.pyplot as plt
import numpy as np
import pytest

from fpe_jax import plots


def _drive_and_heldout(n: int = 120, horizon: int = 10):
    """A car going round a 20 m circle at 5 m/s (10 Hz) and predictions 0.3 m outside its path."""
    t_s = 0.1 * np.arange(n + horizon)
    a = 0.25 * t_s
    xy = 20.0 * np.stack([np.cos(a), np.sin(a)], 1)
    rows = np.arange(n)
    target = np.stack([xy[rows + h] for h in range(1, horizon + 1)], 1)
    drive = SimpleNamespace(t_s=t_s, has_truth=True, truth_xy_m=xy, xy_m=xy)
    held = SimpleNamespace(
        rows=rows,
        origin_xy_m=xy[rows],
        target_xy_m=target,
        mask=np.ones((n, horizon), bool),
        pred_xy_m={"fitted": target * (20.3 / 20.0)},
    )
    a_track = np.linspace(0.0, 2 * np.pi, 90, endpoint=False)
    waypoints = 20.0 * np.stack([np.cos(a_track), np.sin(a_track)], 1)
    return waypoints, drive, held


def _png(fig) -> bytes:
    out = io.BytesIO()
    fig.savefig(out, dpi=60, format="png")
    return out.getvalue()


def _pyplot_figures(monkeypatch):
    """Make `plots` draw as it did with pyplot: `plt.subplots` and `Figure.tight_layout`."""
    monkeypatch.setattr(
        plots, "subplots", lambda *a, figsize, **kw: plt.subplots(*a, figsize=figsize, **kw)
    )
    monkeypatch.setattr(plots, "tight_layout", lambda fig, rect=None: fig.tight_layout(rect=rect))


def _figures():
    """name -> a function drawing one of `plots`' figures on made-up data (every layout path)."""
    waypoints, drive, held = _drive_and_heldout()
    held.pred_xy_m["seed"] = held.target_xy_m * (19.8 / 20.0)
    kw = dict(title="circle", half_width_m=1.5)
    per_step = {
        "fitted": {"per_step_m": 0.1 * np.arange(1, 11)},
        "seed": {"per_step_m": [1.0] * 10},
    }
    n = 30
    line = SimpleNamespace(
        physical=lambda: {
            "line_offset_m": np.sin(np.arange(n)),
            "line_speed_mps": 5 + np.cos(np.arange(n)),
            "line_coverage": (np.arange(n) % 7 > 1).astype(float),
        }
    )
    return {
        "trajectory, one predictor": lambda: plots.trajectory_figure(
            waypoints, drive, held, names=("fitted",), **kw
        ),
        "trajectory, two predictors": lambda: plots.trajectory_figure(
            waypoints, drive, held, names=("fitted", "seed"), **kw
        ),
        "error vs horizon, one case": lambda: plots.error_vs_horizon_figure(
            {"a": per_step}, dt_s=0.1, title="one"
        ),
        "error vs horizon, three cases": lambda: plots.error_vs_horizon_figure(
            {"a": per_step, "b": per_step, "c": per_step}, dt_s=0.1, title="three", ncols=2
        ),
        "line": lambda: plots.line_figure(line, 120.0, True, title="line"),
    }


@pytest.mark.parametrize("name", list(_figures()))
def test_a_figure_has_the_pixels_of_the_pyplot_figure(monkeypatch, name):
    ours = _figures()[name]()
    assert ours.canvas.manager is None and ours.get_layout_engine() is None
    png = _png(ours)
    with monkeypatch.context() as m:
        _pyplot_figures(m)
        theirs = _figures()[name]()
        assert theirs.canvas.manager is not None  # the reference is pyplot's
        assert _png(theirs) == png
        plt.close(theirs)


def test_tight_layout_places_the_axes_as_the_figure_method_and_leaves_no_engine():
    figs = []
    for _ in range(2):
        fig, axes = plots.subplots(2, 2, figsize=(6, 5))
        for ax in axes.flat:
            ax.plot([0, 1000], [0, 1e5], label="line")
            ax.set(xlabel="x [m]", ylabel="y [m]", title="a title")
        fig.legend(loc="lower center")
        figs.append(fig)
    figs[0].tight_layout(rect=(0, 0.1, 1, 1))
    plots.tight_layout(figs[1], rect=(0, 0.1, 1, 1))
    params = [vars(f.subplotpars) for f in figs]
    assert params[1] == params[0]
    # the method leaves an engine behind, for which savefig lays the figure out again
    assert figs[0].get_layout_engine() is not None and figs[1].get_layout_engine() is None


def test_save_lets_pyplot_forget_its_figure_and_makes_none(tmp_path):
    fig, ax = plt.subplots(figsize=(3, 2))  # as the experiments make theirs
    ax.plot([0, 1], [0, 1])
    assert plt.fignum_exists(fig.number)
    plots.save(fig, tmp_path / "pyplot.png")
    assert not plt.fignum_exists(fig.number)
    before = plt.get_fignums()
    fig, ax = plots.subplots(figsize=(3, 2))
    ax.plot([0, 1], [0, 1])
    plots.save(fig, tmp_path / "agg.png")
    assert plt.get_fignums() == before
    assert (tmp_path / "agg.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_importing_plots_imports_no_pyplot():
    code = "import sys, fpe_jax.plots; print('matplotlib.pyplot' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
