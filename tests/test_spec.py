"""Declared limits (fpe_jax.spec) checked before the work: history, waypoint count and track
length, cars per file and per call, car values, forged or empty `.npy` files, deep recipes."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fpe_jax import cli, spec
from fpe_jax.errors import InputError
from fpe_jax.geometry._path import build_path
from fpe_jax.io.config import params_to_config
from fpe_jax.model._params import presets

SQUARE = "x,y\n0,0\n10,0\n10,10\n0,10\n"


def one_line_error(capsys) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    return err


def test_history_beyond_the_limit_is_refused(tmp_path, capsys):
    cfg = params_to_config(presets["default"])
    cfg["settings"]["history"] = spec.MAX_HISTORY + 1
    path = tmp_path / "c.json"
    path.write_text(json.dumps(cfg))
    assert cli.main(["export", str(path), "--format", "json", "--out", str(tmp_path / "e")]) == 2
    assert "settings.history is 101" in one_line_error(capsys)


@pytest.mark.parametrize(
    "scale, words", [(1e-3, "0.04 m long"), (1e4, "400000 m long")], ids=["km", "mm"]
)
def test_waypoints_in_other_units_than_metres(tmp_path, capsys, scale, words):
    wp = tmp_path / "wp.csv"
    xy = np.array([[0, 0], [10, 0], [10, 10], [0, 10], [0, 0]]) * scale
    np.savetxt(wp, xy, delimiter=",", header="x,y", comments="")
    assert cli.main(["info", "--waypoints", str(wp)]) == 2
    assert words in one_line_error(capsys)


def test_waypoint_count_limit(monkeypatch):
    monkeypatch.setattr(spec, "MAX_WAYPOINTS", 100)
    xy = np.column_stack([np.linspace(0, 50, 101), np.zeros(101)])
    with pytest.raises(InputError, match="101 waypoints"):
        build_path(xy)
    build_path(xy[:100])


def _batch(tmp_path, cars, *flags) -> int:
    (tmp_path / "wp.csv").write_text(SQUARE)
    argv = ["batch", str(cars), "--waypoints", str(tmp_path / "wp.csv"), "--preset", "default"]
    return cli.main([*argv, "--out", str(tmp_path / "out.npy"), "--quiet", *flags])


@pytest.mark.parametrize("chunk", ["0", "-3", str(spec.MAX_CARS_PER_CALL + 1)])
def test_cars_per_call_limit(tmp_path, capsys, chunk):
    assert _batch(tmp_path, tmp_path / "absent.npy", "--chunk", chunk) == 2
    assert "--chunk" in one_line_error(capsys)
    assert not (tmp_path / "out.npy").exists()


@pytest.mark.parametrize(
    "column, value, words",
    [(0, 1e308, "x of car 1 is 1e+308"), (3, -1e9, "v of car 1"), (2, 1e300, "yaw of car 1")],
)
def test_car_values_beyond_the_limits(tmp_path, capsys, column, value, words):
    cars = np.tile([[5.0, 0.0, 0.0, 2.0]], (3, 1))
    cars[1, column] = value
    np.save(tmp_path / "cars.npy", cars)
    assert _batch(tmp_path, tmp_path / "cars.npy") == 2
    assert words in one_line_error(capsys)


def test_cars_per_file_limit_in_a_csv(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(spec, "MAX_CARS", 3)
    (tmp_path / "cars.csv").write_text("x,y,yaw,v\n" + "5,0,0,2\n" * 4)
    assert _batch(tmp_path, tmp_path / "cars.csv") == 2
    assert "4 cars" in one_line_error(capsys)


@pytest.mark.parametrize(
    "content",
    [
        b"",  # an empty file
        b"\x93NUMPY\x01\x00",  # the magic string only
        b"\x93NUMPY\x01\x00\x10\x00{'descr': '<f8',",  # a header cut inside its dict
        b"\x93NUMPY\x01\x00\x10\x00{'descr': 5, 'fortran_order': False, 'shape': (2, 4), }",
    ],
    ids=["empty", "magic", "cut-header", "bad-descr"],
)
def test_empty_or_forged_npy_is_one_line(tmp_path, capsys, content):
    (tmp_path / "cars.npy").write_bytes(content)
    assert _batch(tmp_path, tmp_path / "cars.npy") == 2
    assert "cars.npy" in one_line_error(capsys)


@pytest.mark.parametrize(
    "arr", [np.zeros((0, 4)), np.ones((2, 4), dtype=complex)], ids=["no-rows", "complex"]
)
def test_npy_without_rows_or_of_complex_numbers(tmp_path, capsys, arr):
    np.save(tmp_path / "cars.npy", arr)
    assert _batch(tmp_path, tmp_path / "cars.npy") == 2
    one_line_error(capsys)


@pytest.mark.parametrize(
    "body",
    ["fit = " + "[" * 10_000 + "]" * 10_000, "x = " + "{a = " * 3000 + "1" + "}" * 3000],
    ids=["array", "table"],
)
def test_deep_recipe_is_one_line(tmp_path, capsys, body):
    recipe = tmp_path / "r.toml"
    recipe.write_text(body + "\n")
    assert cli.main(["fit", str(recipe)]) == 2
    assert "nested too deeply" in one_line_error(capsys)


# ---- outputs that cannot be written, found before the work (the tests run as root) -----------


def _refusing_folder() -> str:
    """A folder that refuses new files even to root: /sys (sysfs, or read-only in containers)."""
    import os

    if not os.path.isdir("/sys"):
        pytest.skip("no /sys on this system")
    return "/sys"


@pytest.mark.parametrize("command", ["fit", "predict", "batch", "convert", "plot"])
def test_an_output_folder_refusing_files_is_found_before_the_work(tmp_path, capsys, command):
    out = f"{_refusing_folder()}/fpe-test-out"
    absent = str(tmp_path / "absent.csv")  # the inputs are never read: the output fails first
    argv = {
        "fit": ["fit", absent, "--waypoints", absent, "--out", out + ".json"],
        "predict": ["predict", absent, "--waypoints", absent, "--out", out + ".csv"],
        "batch": ["batch", absent, "--waypoints", absent, "--preset", "default"],
        "convert": ["convert", absent, "--out", out + ".csv"],
        "plot": ["plot", absent, "--waypoints", absent, "--preset", "default"],
    }[command]
    if command == "batch":
        argv += ["--out", out + ".npy"]
    if command == "plot":
        argv += ["--out", out + ".png"]
    assert cli.main(argv) == 2
    err = one_line_error(capsys)
    assert "not writable" in err and "absent" not in err


def test_a_read_only_folder_is_found_before_the_work(tmp_path, capsys, monkeypatch):
    import os

    real_access = os.access
    ro = tmp_path / "ro"
    ro.mkdir()
    # root passes every permission check, so the folder is made read-only to access() itself
    monkeypatch.setattr(os, "access", lambda p, mode: str(p) != str(ro) and real_access(p, mode))
    argv = ["fit", str(tmp_path / "absent.csv"), "--waypoints", "absent.csv"]
    assert cli.main([*argv, "--out", str(ro / "c.json")]) == 2
    assert f"its folder {str(ro)!r} is not writable" in one_line_error(capsys)
    assert not any(ro.iterdir())


def test_a_drive_pose_beyond_the_map_is_refused(tmp_path, capsys):
    log = tmp_path / "d.csv"
    log.write_text("t,x,y\n0,0,0\n0.1,1e308,0\n0.2,0.4,0\n")
    assert cli.main(["convert", str(log), "--out", str(tmp_path / "o.csv")]) == 2
    assert "first: data row 2, x 1e+308" in one_line_error(capsys)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.csv"]
