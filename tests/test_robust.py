"""Real-log numerics and hostile input: epoch stamps and UTM-sized coordinates give the zero-origin
results; bad configs, recipes and flags are one line with exit 2 and change no file."""

from __future__ import annotations

import json
from pathlib import Path

import jax
import numpy as np
import pytest

from fpe_jax import cli
from fpe_jax.config import params_to_config, read_config
from fpe_jax.params import presets
from fpe_jax.runner import Runner

T_EPOCH_S = 1.7e9  # a ROS time stamp in epoch seconds
UTM_M = (5e5, 5e6)  # easting, northing of a UTM-like map frame
Q_S, Q_M = 2.0**-16, 2.0**-8  # stamps and positions on grids that survive the offsets exactly


@pytest.fixture(scope="module")
def drive_rows():
    """(t, x, y, yaw) rows of a short simulated oval drive, and its centerline (K, 2) [m]."""
    from fpe_jax.sim import simulate

    res = simulate("oval", duration_s=8.0, seed=3)
    d = res.drive
    t = np.round(d.t_s / Q_S) * Q_S
    xy = np.round(d.xy_m / Q_M) * Q_M
    wp = np.round(res.centerline_xy_m / Q_M) * Q_M
    return np.column_stack([t, xy, d.yaw_rad]), wp


def _write(folder: Path, rows, wp, dt_s: float, dxy) -> tuple[Path, Path]:
    folder.mkdir()
    log, wpf = folder / "drive.csv", folder / "wp.csv"
    r = rows + np.array([dt_s, dxy[0], dxy[1], 0.0])
    log.write_text("t,x,y,yaw\n" + "".join(",".join(map(repr, map(float, x))) + "\n" for x in r))
    w = wp + np.asarray(dxy)
    wpf.write_text("x,y\n" + "".join(f"{float(a)!r},{float(b)!r}\n" for a, b in w))
    return log, wpf


def _pair(tmp_path, drive_rows):
    rows, wp = drive_rows
    zero = _write(tmp_path / "zero", rows, wp, 0.0, (0.0, 0.0))
    far = _write(tmp_path / "far", rows, wp, T_EPOCH_S, UTM_M)
    return zero, far


def _pred(path: Path) -> np.ndarray:
    return np.loadtxt(path, delimiter=",", skiprows=1)


@pytest.mark.parametrize("x64", [False, True], ids=["float32", "float64"])
def test_predict_epoch_stamps_and_utm_offsets(tmp_path, drive_rows, x64):
    (zlog, zwp), (flog, fwp) = _pair(tmp_path, drive_rows)
    with jax.enable_x64(x64):
        for log, wp in ((zlog, zwp), (flog, fwp)):
            out = log.with_name("pred.csv")
            assert cli.main([*f"predict {log} --waypoints {wp} --out {out}".split()]) == 0
    z, f = _pred(zlog.with_name("pred.csv")), _pred(flog.with_name("pred.csv"))
    np.testing.assert_allclose(f[:, 0] - T_EPOCH_S, z[:, 0], atol=1e-6)
    np.testing.assert_allclose(f[:, 3] - UTM_M[0], z[:, 3], atol=1e-6)
    np.testing.assert_allclose(f[:, 4] - UTM_M[1], z[:, 4], atol=1e-6)
    np.testing.assert_allclose(f[:, 5], z[:, 5], atol=1e-6)


def test_evaluate_epoch_stamps_and_utm_offsets(tmp_path, drive_rows, capsys):
    (zlog, zwp), (flog, fwp) = _pair(tmp_path, drive_rows)
    metrics = []
    for log, wp in ((zlog, zwp), (flog, fwp)):
        capsys.readouterr()
        argv = f"evaluate {log} --waypoints {wp} --preset default --json".split()
        assert cli.main(argv) == 0
        metrics.append(json.loads(capsys.readouterr().out))
    for k, v in metrics[0].items():
        if isinstance(v, float):
            assert metrics[1][k] == pytest.approx(v, abs=1e-6), k


def test_batch_epoch_utm_offsets(tmp_path, drive_rows):
    rows, wp = drive_rows
    cars = np.column_stack([rows[::7, 1:3], rows[::7, 3], np.full(len(rows[::7]), 2.0)])
    outs = {}
    for name, dxy in (("zero", (0.0, 0.0)), ("far", UTM_M)):
        folder = tmp_path / name
        folder.mkdir()
        np.savetxt(folder / "wp.csv", wp + dxy, delimiter=",", header="x,y", comments="")
        c = cars.copy()
        c[:, :2] += dxy
        np.save(folder / "cars.npy", c)
        for dtype in ("float32", "float64"):
            out = folder / f"{dtype}.npy"
            argv = [str(folder / "cars.npy"), "--waypoints", str(folder / "wp.csv")]
            argv += ["--preset", "default", "--out", str(out), "--dtype", dtype]
            assert cli.main(["batch", *argv]) == 0
            outs[name, dtype] = np.load(out).astype(np.float64)
    assert np.load(tmp_path / "far" / "float32.npy").dtype == np.float64  # UTM needs float64
    for dtype in ("float32", "float64"):
        far = outs["far", dtype] - np.array([*UTM_M, 0.0])
        np.testing.assert_allclose(far, outs["zero", dtype], atol=1e-6)


def test_fit_epoch_stamps_and_utm_offsets(tmp_path, drive_rows, capsys):
    (zlog, zwp), (flog, fwp) = _pair(tmp_path, drive_rows)
    cfgs = []
    for log, wp in ((zlog, zwp), (flog, fwp)):
        out = log.with_name("cfg.json")
        argv = f"fit {log} --waypoints {wp} --out {out} --fit delay,speed --holdout 0.4".split()
        assert cli.main(argv) == 0
        cfgs.append(read_config(out)["params"])
    for k, v in cfgs[0].items():
        np.testing.assert_allclose(cfgs[1][k], v, atol=1e-6, err_msg=k)


def test_runner_epoch_stamps_and_utm_offsets(drive_rows):
    rows, wp = drive_rows
    cfg = params_to_config(presets["default"])
    zero, far = Runner(cfg, wp), Runner(cfg, wp + np.asarray(UTM_M))
    shift = np.array([*UTM_M, 0.0])
    for t, x, y, yaw in rows:
        a = zero.update(t, x, y, yaw)
        b = far.update(t + T_EPOCH_S, x + UTM_M[0], y + UTM_M[1], yaw)
        np.testing.assert_allclose(np.asarray(b) - shift, a, atol=1e-6)
