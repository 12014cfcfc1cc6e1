"""`fpe demo` pipeline and `fpe plot` on very short simulated drives: they run end to end under
the strict test settings and write every figure and file they promise (smoke tests; the numbers
themselves are checked by the demo's own acceptance lines and by experiments/)."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from fpe_jax import cli
from fpe_jax.demo import demo_checks, run_demo
from fpe_jax.sim._sim import simulate, write_simulation
from fpe_jax.spec import SCHEMA_VERSION

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _is_png(path) -> bool:
    return path.is_file() and path.stat().st_size > 10_000 and path.read_bytes()[:8] == PNG_MAGIC


@pytest.fixture(scope="module")
def short_drive(tmp_path_factory):
    """An 8 s simulated oval drive written as drive.mcap + waypoints.csv."""
    out = tmp_path_factory.mktemp("drive")
    write_simulation(simulate("oval", duration_s=8.0, latency_s=0.3, seed=3), out)
    return out


def test_demo_pipeline_on_a_short_drive_writes_everything(tmp_path):
    # `make demo` writes into out/demo, where neither folder exists on a fresh checkout
    res = run_demo(tmp_path / "out" / "demo", fit_s=10.0, test_s=6.0)
    names = {f.name for f in res.files}
    assert names == {
        "waypoints.csv",
        "config.json",
        "params.yaml",
        "trajectory.png",
        "error_vs_horizon.png",
        "line.png",
        "report.md",
    }
    for f in res.files:
        assert f.is_file() and f.parent == tmp_path / "out" / "demo"
    for name in ("trajectory.png", "error_vs_horizon.png", "line.png"):
        assert _is_png(tmp_path / "out" / "demo" / name), name
    cfg = json.loads((tmp_path / "out" / "demo" / "config.json").read_text())
    assert cfg["schema_version"] == SCHEMA_VERSION and len(cfg["params"]["weights"]) == 10
    assert cfg["uncertainty"]["frame"] == "track"
    assert cfg["settings"]["model"] == "line" and cfg["line"]["waypoints"].endswith("waypoints.csv")
    # the written waypoints are the ones the line belongs to
    from fpe_jax.io.config import check_waypoints

    wp = np.loadtxt(tmp_path / "out" / "demo" / "waypoints.csv", delimiter=",", skiprows=1)
    check_waypoints(cfg, "config.json", wp, "waypoints.csv")
    assert set(res.result.report) >= {"fitted", "seed", "seed-measured-speed", "linear"}
    assert [c[0] for c in res.checks] == [c[0] for c in demo_checks(res.result, 0.3)]
    report = (tmp_path / "out" / "demo" / "report.md").read_text()
    assert "| fitted |" in report and ("PASS" in report or "FAIL" in report)


def test_plot_writes_a_figure_and_refuses_to_overwrite(short_drive, tmp_path, capsys):
    fig = tmp_path / "fig.png"
    args = ["plot", str(short_drive / "drive.mcap"), "--waypoints"]
    args += [str(short_drive / "waypoints.csv"), "--preset", "seed-measured-speed"]
    assert cli.main([*args, "--out", str(fig)]) == 0
    assert _is_png(fig)
    assert "ADE" in capsys.readouterr().err
    assert cli.main([*args, "--out", str(fig)]) == 2  # exists, no --force
    assert "exists" in capsys.readouterr().err
    assert cli.main([*args, "--out", str(fig), "--force"]) == 0


def test_plot_rejects_unknown_figure_types_before_any_work(short_drive, tmp_path, capsys):
    args = ["plot", str(short_drive / "drive.mcap"), "--waypoints"]
    args += [str(short_drive / "waypoints.csv"), "--preset", "linear", "--out"]
    assert cli.main([*args, str(tmp_path / "fig.jpg2")]) == 2
    assert "unknown figure type" in capsys.readouterr().err
    assert not (tmp_path / "fig.jpg2").exists()


def test_demo_checks_report_failures():
    """A fit that is worse than the seed and misses the latency fails both checks."""

    fake = SimpleNamespace(
        report={"fitted": {"ade_m": 2.0, "fde_m": 3.0}, "seed": {"ade_m": 1.0, "fde_m": 2.0}},
        params=SimpleNamespace(physical=lambda: {"delay_s": 0.2}),
    )
    checks = demo_checks(fake, 0.3)
    assert [ok for _, ok, _ in checks] == [False, False]
    assert np.isclose(float(checks[1][2].split("error ")[1].split(" s")[0]), -0.1)
