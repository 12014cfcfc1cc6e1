"""CSV quirks every table reader must survive: a UTF-8 byte-order mark (BOM) before the header.

Spreadsheet programs on Windows save "CSV UTF-8" with a BOM (bytes EF BB BF). Read naively, the
first header cell becomes "\\ufefft", the time column disappears, and a drive would be re-stamped
with --rate. Every reader that goes through `fpe_jax.io.tables` (drives, waypoints, cars for
batch) and the stdin stream of `fpe run` must see the same values with and without the BOM.
"""

from __future__ import annotations

import io as stdio
import json

import numpy as np
import pytest

from fpe_jax import io
from fpe_jax.io.config import params_to_config
from fpe_jax.io.tables import read_table
from fpe_jax.model._params import presets
from fpe_jax.runner._runner import Runner, run_stream

BOM = "\ufeff"


def _write(path, text: str, bom: bool):
    path.write_text((BOM if bom else "") + text, encoding="utf-8")
    return path


DRIVE = "t,x,y,yaw\n0.0,10,0,1.5\n0.1,10,0.1,1.5\n0.25,10,0.2,1.5\n"
WAYPOINTS = "x_m,y_m\n" + "".join(
    f"{10 * np.cos(a):.17g},{10 * np.sin(a):.17g}\n" for a in np.linspace(0, 6, 40)
)
CARS = "x,y,yaw,v\n1,2,0.1,3\n4,5,0.2,6\n"


@pytest.mark.parametrize(
    "text",
    [DRIVE, WAYPOINTS, CARS, "# x_m, y_m\n1,2\n3,4\n5,6\n", "1,2,0\n3,4,0\n"],
    ids=["header", "waypoints", "cars", "comment-header", "no-header"],
)
def test_read_table_ignores_a_bom(tmp_path, text):
    plain = read_table(_write(tmp_path / "plain.csv", text, bom=False))
    marked = read_table(_write(tmp_path / "bom.csv", text, bom=True))
    assert marked.header == plain.header
    np.testing.assert_array_equal(marked.data, plain.data)


def test_drive_with_a_bom_keeps_its_time_column(tmp_path):
    d = io.load_drive(_write(tmp_path / "bom.csv", DRIVE, bom=True))
    np.testing.assert_array_equal(d.t_s, [0.0, 0.1, 0.25])
    assert d.meta["columns"] == ["t", "x", "y", "yaw"]
    np.testing.assert_array_equal(d.yaw_rad, [1.5, 1.5, 1.5])


def test_header_less_drive_with_a_bom(tmp_path):
    d = io.load_drive(_write(tmp_path / "xyz.csv", "1,2,0\n3,4,0\n5,6,0\n", bom=True), rate_hz=10)
    np.testing.assert_array_equal(d.xy_m, [[1, 2], [3, 4], [5, 6]])


def test_waypoints_and_cars_with_a_bom(tmp_path):
    wp = io.load_waypoints(_write(tmp_path / "wp.csv", WAYPOINTS, bom=True))
    ref = io.load_waypoints(_write(tmp_path / "wp0.csv", WAYPOINTS, bom=False))
    np.testing.assert_array_equal(wp.xy_m, ref.xy_m)
    cars = io.read_cars(_write(tmp_path / "cars.csv", CARS, bom=True))
    np.testing.assert_array_equal(cars, [[1, 2, 0.1, 3], [4, 5, 0.2, 6]])


def test_run_stream_header_after_a_bom():
    """A BOM before a header that reorders the columns: the header must still be honoured."""
    a = np.linspace(0, 2 * np.pi, 60, endpoint=False)
    runner = Runner(
        params_to_config(presets["constant-velocity"]), np.c_[10 * np.cos(a), np.sin(a)]
    )
    lines = [BOM + "x,y,t\n", "1.0,0.0,0.0\n", "1.2,0.0,0.1\n", "1.4,0.0,0.2\n"]
    out, err = stdio.StringIO(), stdio.StringIO()
    assert run_stream(runner, lines, out, err) == 0
    assert err.getvalue() == ""
    assert [json.loads(line)["stamp"] for line in out.getvalue().splitlines()] == [0.0, 0.1, 0.2]
