"""Real-log numerics and hostile input: epoch stamps and UTM-sized coordinates give the zero-origin
results; bad configs, recipes and flags are one line with exit 2 and change no file."""

from __future__ import annotations

import json
from pathlib import Path

import jax
import numpy as np
import pytest

from fpe_jax import cli
from fpe_jax.io.config import params_to_config, read_config
from fpe_jax.model._params import presets
from fpe_jax.runner._runner import Runner

T_EPOCH_S = 1.7e9  # a ROS time stamp in epoch seconds
UTM_M = (5e5, 5e6)  # easting, northing of a UTM-like map frame
Q_S, Q_M = 2.0**-16, 2.0**-8  # stamps and positions on grids that survive the offsets exactly


@pytest.fixture(scope="module")
def drive_rows():
    """(t, x, y, yaw) rows of a short simulated oval drive, and its centerline (K, 2) [m]."""
    from fpe_jax.sim._sim import simulate

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
    # stamps as their exact decimals (a stamp on the 2^-16 s grid has 16 decimal places): the
    # readers take a stamp's text exactly, and repr's shortest form of 1.7e9 + t is not exact
    log.write_text(
        "t,x,y,yaw\n"
        + "".join(f"{x[0]:.16f}," + ",".join(map(repr, map(float, x[1:]))) + "\n" for x in r)
    )
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
        argv = f"fit {log} --waypoints {wp} --out {out} --fit delay,tau --holdout 0.4".split()
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


# ---- hostile input: one line, exit 2, nothing written ------------------------------------------

from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

_BAD_VALUES = st.one_of(
    st.none(),
    st.booleans(),
    st.text(max_size=5),
    st.just(float("nan")),
    st.just(float("inf")),
    st.just(-1.0),
    st.just(1e9),
    st.lists(st.floats(allow_nan=True), max_size=3),
    st.just([[[[1.0]]]]),
)
_FIELDS = [
    ("params", "lookahead_m"),
    ("params", "weights"),
    ("params", "delay_s"),
    ("params", "speed_weight"),
    ("params", "speed_mps"),
    ("settings", "dt_s"),
    ("settings", "horizon"),
    ("settings", "max_steer_rad"),
    ("settings", "model"),
    ("settings", "history"),
]


def _one_line_error(capsys) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err and 1 <= len(err.strip().splitlines()) <= 3, err
    return err


@settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(field=st.sampled_from(_FIELDS), value=_BAD_VALUES)
def test_tampered_config_is_one_line_everywhere(tmp_path, capsys, field, value):
    from fpe_jax.spec import SECTIONS

    rule = next(r for r in SECTIONS[field[0]] if r.key == field[1])
    cfg = params_to_config(presets["default"])
    cfg[field[0]][field[1]] = value
    try:
        from fpe_jax.spec import check_value

        check_value(rule, value, cfg, "x", "y")
        return  # a valid value drawn by chance
    except ValueError:
        pass
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(cfg))
    wp = tmp_path / "wp.csv"
    wp.write_text("x,y\n0,0\n10,0\n10,10\n0,10\n")
    out = tmp_path / "pred.csv"
    for argv in (
        ["predict", "d.csv", "--waypoints", str(wp), "--config", str(path), "--out", str(out)],
        ["evaluate", "d.csv", "--waypoints", str(wp), "--config", str(path), "--json"],
        ["batch", "c.npy", "--waypoints", str(wp), "--config", str(path), "--out", str(out)],
        ["export", str(path), "--format", "json", "--out", str(tmp_path / "e.json")],
    ):
        capsys.readouterr()
        assert cli.main(argv) == 2
        assert str(path) in _one_line_error(capsys)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.json", "wp.csv"]


def test_config_cross_field_rules(tmp_path, capsys):
    cfg = params_to_config(presets["default"])
    for mutate, words in (
        (lambda c: c["settings"].update(max_steer_rad=1.6), "settings.max_steer_rad"),
        (lambda c: c.update(uncertainty={"frame": "track", "cov_m2": [[[1, 0], [0, 1]]]}), "steps"),
        (lambda c: c["params"].update(weights=0.5), "params.weights"),
        (lambda c: c["params"].update(lookahead_m=0.1), "params.lookahead_m"),
        (lambda c: c["settings"].update(extra=1), "unknown key settings.extra"),
    ):
        bad = json.loads(json.dumps(cfg))
        mutate(bad)
        p = tmp_path / "c.json"
        p.write_text(json.dumps(bad))
        capsys.readouterr()
        assert cli.main(["export", str(p), "--format", "json", "--out", str(tmp_path / "o")]) == 2
        assert words in _one_line_error(capsys)
    deep = tmp_path / "deep.json"
    deep.write_text("[" * 10_000 + "]" * 10_000)
    assert cli.main(["export", str(deep), "--format", "json", "--out", str(tmp_path / "o")]) == 2
    assert "nested too deeply" in _one_line_error(capsys)


@pytest.mark.parametrize(
    "flags, words",
    [
        (["--holdout", "0"], "--holdout"),
        (["--holdout", "1.5"], "--holdout"),
        (["--fit", ""], "--fit"),
        (["--fit", "delay,nonsense"], "nonsense"),
    ],
)
def test_fit_flags_are_checked_before_any_work(tmp_path, capsys, flags, words):
    argv = ["fit", "absent.csv", "--waypoints", "absent.csv", "--out", str(tmp_path / "c.json")]
    assert cli.main([*argv, *flags]) == 2
    assert words in _one_line_error(capsys)
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize(
    "body, words",
    [
        ('out = "../../x.json"\n[[drives]]\npath = "a.csv"', "leaves the recipe's folder"),
        ('out = 5\n[[drives]]\npath = "a.csv"', "out is 5"),
        ('holdout = "abc"\n[[drives]]\npath = "a.csv"', "holdout is 'abc'"),
        ("drives = [1, 2]", "drives[0] is 1"),
        ('[[drives]]\nsimulate = "oval"', "drives[0].simulate"),
        ("[[drives]]\nsimulate = { track = 'oval', speed = 3 }", "unknown drives[0].simulate"),
        ("[[drives]]\nsimulate = { duration_s = 1e12 }", "duration_s"),
        ('solver = "adam"\n[[drives]]\npath = "a.csv"', "solver is 'adam'"),
    ],
)
def test_bad_recipes_are_one_line(tmp_path, capsys, body, words):
    sub = tmp_path / "r"
    sub.mkdir()
    recipe = sub / "r.toml"
    recipe.write_text(body + "\n")
    assert cli.main(["fit", str(recipe)]) == 2
    assert words in _one_line_error(capsys)
    assert [p.name for p in sub.iterdir()] == ["r.toml"]


def test_non_utf8_recipe(tmp_path, capsys):
    recipe = tmp_path / "r.toml"
    recipe.write_bytes(b"out = '\xff\xfe'\n")
    assert cli.main(["fit", str(recipe)]) == 2
    assert "not UTF-8" in _one_line_error(capsys)


def test_outputs_checked_before_work_and_never_replaced(tmp_path, capsys):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        import os

        if not os.access(ro, os.W_OK):  # root can write anywhere: nothing to check then
            argv = ["fit", "absent.csv", "--waypoints", "absent.csv", "--out", str(ro / "c.json")]
            assert cli.main(argv) == 2
            assert "not writable" in _one_line_error(capsys)
    finally:
        ro.chmod(0o755)
    cfg = tmp_path / "c.json"
    cfg.write_text(json.dumps(params_to_config(presets["default"])))
    for out in (tmp_path / "missing" / "o.json", tmp_path):
        assert cli.main(["export", str(cfg), "--format", "json", "--out", str(out)]) == 2
        _one_line_error(capsys)
    demo = tmp_path / "demo"
    demo.mkdir()
    (demo / "report.md").write_text("mine")
    assert cli.main(["demo", "--out", str(demo)]) == 2
    assert "report.md" in _one_line_error(capsys)
    assert (demo / "report.md").read_text() == "mine"


def test_simulate_values_are_one_line(tmp_path, capsys):
    for flags in (
        ["--seed", "-1"],
        ["--track", "random:-1"],
        ["--stops-per-min", "nan"],
        ["--duration", "1e12"],
        ["--latency", "5", "--duration", "3"],
    ):
        assert cli.main(["simulate", "--out", str(tmp_path / "s"), *flags]) == 2
        _one_line_error(capsys)
    assert not (tmp_path / "s").exists()


def test_atomic_writer_leaves_nothing_on_failure(tmp_path):
    from fpe_jax.io import atomic_output

    target = tmp_path / "x.json"
    (tmp_path / "x.json.tmp").write_text("a user's file")
    with pytest.raises(KeyboardInterrupt), atomic_output(target, False) as tmp:
        tmp.write_text("half")
        raise KeyboardInterrupt
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.json.tmp"]
