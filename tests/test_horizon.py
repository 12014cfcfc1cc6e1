"""Planning horizons: 5 s (50 steps of 0.1 s) in every command, the runner and the exports."""

import json
from pathlib import Path

import numpy as np
import pytest
from helpers import cli_runner, track_drive

from fpe_jax import Params, Settings, Track, cli, predict_drive, presets
from fpe_jax.errors import InputError
from fpe_jax.geometry._path import waypoints_sha256
from fpe_jax.io.config import params_to_config, read_config
from fpe_jax.model._params import with_settings
from fpe_jax.runner._runner import Runner
from fpe_jax.sim._sim import simulate, write_simulation
from fpe_jax.spec import MAX_HORIZON, check_config

H = 50  # 5 s of 0.1 s steps: what planners read
TOL_M = 1e-6


def _run(r: Runner, drive) -> np.ndarray:
    rows = zip(drive.t_s, drive.xy_m, drive.yaw_rad)
    return np.stack([r.update(t, x, y, yaw) for t, (x, y), yaw in rows])


def _assert_parity(a: np.ndarray, b: np.ndarray) -> None:
    assert a.shape == b.shape and a.shape[1] == H
    assert np.max(np.abs(a[..., :2] - b[..., :2])) <= TOL_M
    assert np.max(np.abs(np.angle(np.exp(1j * (a[..., 2] - b[..., 2]))))) <= TOL_M


@pytest.mark.parametrize("name", ["default", "frenet", "ctrv", "seed"])
def test_runner_matches_jax_at_horizon_50(name):
    wp, drive = track_drive("oval")
    p = with_settings(presets[name], horizon=H)
    _, pred_jax = predict_drive(p, drive, Track.from_waypoints(wp))
    _assert_parity(_run(Runner(params_to_config(p), wp), drive), np.asarray(pred_jax))


@pytest.mark.parametrize("estimator", ["theil-sen", "kalman"])
def test_runner_matches_jax_at_horizon_50_with_the_line_model(estimator):
    from fpe_jax.model._line import learn_line

    wp, drive = track_drive("oval")
    track = Track.from_waypoints(wp)
    profile = learn_line([drive.slice_time(-np.inf, 8.0)], track)  # part uncovered
    p = Params.create(
        Settings(model="line", estimator=estimator, horizon=H),
        delay_s=0.12,
        offset_tau_s=0.8,
        speed_tau_s=0.3,
        pace_return_1ps=0.7,
        position_smoothing=0.6,
        **profile,
    )
    _, pred_jax = predict_drive(p, drive, track)
    cfg = params_to_config(p, line={"waypoints_sha256": waypoints_sha256(wp)})
    _assert_parity(_run(Runner(cfg, wp), drive), np.asarray(pred_jax))


def test_the_horizon_limit_is_one_rule():
    cfg = params_to_config(with_settings(presets["default"], horizon=H))
    assert check_config(cfg, "c")["settings"]["horizon"] == H
    cfg["settings"]["horizon"] = MAX_HORIZON + 1
    cfg["params"]["weights"] = [0.5] * (MAX_HORIZON + 1)
    with pytest.raises(InputError, match="horizon"):
        check_config(cfg, "c")
    with pytest.raises(InputError, match=f"1 to {MAX_HORIZON}"):
        from fpe_jax.io.config import apply_settings

        apply_settings(presets["default"], {"--horizon": ("horizon", MAX_HORIZON + 1)})


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    """A 25 s simulated oval drive (drive.mcap, waypoints.csv): fitted, then predicted,
    evaluated and streamed (every assertion is on the horizon's length, not on held-out data)."""
    root = tmp_path_factory.mktemp("h50")
    write_simulation(simulate("oval", duration_s=25.0, seed=1), root)
    return root


def test_every_command_takes_horizon_50(drive, tmp_path, capsys, monkeypatch):
    wp = str(drive / "waypoints.csv")
    log = str(drive / "drive.mcap")
    cfg = tmp_path / "c.json"
    argv = ["fit", log, "--waypoints", wp, "--horizon", str(H)]
    assert cli.main([*argv, "--out", str(cfg), "--quiet"]) == 0
    assert read_config(cfg)["settings"]["horizon"] == H
    assert len(read_config(cfg)["params"]["weights"]) == H

    pred = tmp_path / "p.csv"
    argv = ["predict", log, "--waypoints", wp, "--config", str(cfg), "--out", str(pred)]
    assert cli.main([*argv, "--quiet"]) == 0
    rows = np.genfromtxt(pred, delimiter=",", names=True)
    assert rows["step"].max() == H and np.isclose(rows["horizon_s"].max(), 5.0)
    # with a preset, the flag sets it
    pre = tmp_path / "pre.csv"
    argv = ["predict", log, "--waypoints", wp, "--preset", "frenet", "--horizon", str(H)]
    assert cli.main([*argv, "--out", str(pre), "--quiet"]) == 0
    assert np.genfromtxt(pre, delimiter=",", names=True)["step"].max() == H

    capsys.readouterr()
    argv = ["evaluate", log, "--waypoints", wp, "--config", str(cfg)]
    assert cli.main([*argv, "--quiet"]) == 0
    assert f"err@{H} m" in capsys.readouterr().out

    cars = tmp_path / "cars.csv"
    cars.write_text("x,y,yaw,v\n18.3,0.0,1.57,3.0\n10.0,5.0,3.1,2.5\n")
    out = tmp_path / "b.npy"
    argv = ["batch", str(cars), "--waypoints", wp, "--config", str(cfg), "--out", str(out)]
    assert cli.main([*argv, "--quiet"]) == 0
    assert np.load(out).shape == (2, H, 3)

    ex = tmp_path / "ex"
    assert (
        cli.main(["export", str(cfg), "--format", "all", "--waypoints", wp, "--out", str(ex)]) == 0
    )
    assert json.loads((ex / "config.json").read_text())["settings"]["horizon"] == H
    assert f"horizon: {H}" in (ex / "params.yaml").read_text()
    from fpe_jax.io.export import load

    f = load(ex / "predictor.stablehlo")
    assert f.horizon == H

    # fpe run (the NumPy runner) streams 50 poses per observation
    lines = ["t,x,y"] + [
        f"{float(t)!r},{float(x)!r},{float(y)!r}" for t, (x, y) in zip(*_first(drive, 15))
    ]
    argv = ["run", "--config", cfg, "--waypoints", wp]
    _, out, _ = cli_runner(capsys, argv, "\n".join(lines) + "\n", monkeypatch, expect=0)
    out_rows = [json.loads(ln) for ln in out.splitlines() if ln.startswith("{")]
    assert out_rows and all(len(r["poses"]) == H for r in out_rows)


def _first(folder: Path, n: int):
    from fpe_jax import io

    d = io.load_drive(folder / "drive.mcap")
    return d.t_s[:n], d.xy_m[:n]
