"""A car far from the track (and from the learned line) is reported by the on-car runner and by
`fpe batch`, with the offline check's rule (`fpe_jax.geometry.ON_TRACK_M`); an on-track stream's
output stays exactly what the runner predicts, with nothing on stderr."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from helpers import csv_lines, expected, fpe_run, oval_stream, stream_files

from fpe_jax.cli import main
from fpe_jax.errors import InputError
from fpe_jax.geometry._path import ON_TRACK_M, build_path, waypoints_sha256
from fpe_jax.runner._runner import OFF_TRACK_START_OBS, Runner


@pytest.fixture(scope="module")
def oval():
    """(config, centerline (K, 2) [m], rows (N, 4) t [s], x, y [m], yaw [rad]): 15 s on the oval."""
    return oval_stream(15.0, seed=5)


@pytest.fixture()
def files(tmp_path, oval):
    return stream_files(tmp_path, *oval[:2])


def test_an_on_track_stream_is_unchanged_bit_for_bit(monkeypatch, capsys, files, oval):
    cfg, wp, rows = oval
    rc, replies, err = fpe_run(monkeypatch, capsys, files, csv_lines(rows))
    assert rc == 0 and err == []
    assert replies == expected(cfg, wp, rows)  # exact floats, and no other field
    runner = Runner(cfg, wp)
    assert all(runner.check_track(x, y) is None for _, x, y, _ in rows)


def test_a_car_leaving_the_track_is_warned_per_observation(monkeypatch, capsys, files, oval):
    cfg, wp, rows = oval
    rows = rows.copy()
    k = 40  # on the track for the first 40 observations, then 100 m off (another map frame)
    rows[k:, 1] += 100.0
    rc, replies, err = fpe_run(monkeypatch, capsys, files, csv_lines(rows))
    assert rc == 0
    assert [r.get("warning") is not None for r in replies] == [i >= k for i in range(len(rows))]
    assert re.match(r"observation \d+\.\d m from the track", replies[k]["warning"])
    # the poses are still the runner's own
    want = expected(cfg, wp, rows)
    assert [r["poses"] for r in replies] == [w["poses"] for w in want]
    # stderr: rate-limited, not one line per observation
    warned = [line for line in err if "from the track" in line]
    assert 1 <= len(warned) <= 1 + (rows[-1, 0] - rows[k, 0]) / 5.0
    assert f"line {k + 2}" in warned[0]


def test_a_stream_starting_off_the_track_is_an_error(monkeypatch, capsys, files, oval):
    _, _, rows = oval
    rows = rows.copy()
    rows[:, 1] += 100.0
    rc, replies, err = fpe_run(monkeypatch, capsys, files, csv_lines(rows))
    assert rc == 2
    assert len(replies) < OFF_TRACK_START_OBS
    assert any("wp.csv" in line and f"{ON_TRACK_M:g} m" in line for line in err), err


def test_check_track_measures_from_the_learned_line_too(oval):
    """A line config whose learned line runs 5 m beside the centre line: a car on that line is on
    the track, a car 5 m on the other side is not."""
    from fpe_jax.spec import LINE_KEYS

    cfg, wp, _ = oval
    line_cfg = dict(cfg)
    line_cfg["settings"] = dict(cfg["settings"], model="line", estimator="kalman")
    p = 64
    offset, speed, coverage = [5.0] * p, [3.0] * p, [1.0] * p
    line_cfg["params"] = dict(cfg["params"]) | dict(
        zip(LINE_KEYS, (offset, speed, coverage), strict=True)
    )
    line_cfg["line"] = {"waypoints_sha256": waypoints_sha256(wp)}
    runner = Runner(line_cfg, wp)
    path = build_path(wp)
    i = len(path["xy_m"]) // 3
    (x, y), h = path["xy_m"][i], path["heading_rad"][i]
    nx, ny = -math.sin(h), math.cos(h)  # left normal: positive offsets
    assert runner.check_track(x + 5.0 * nx, y + 5.0 * ny) is None
    assert runner.check_track(x - 5.0 * nx, y - 5.0 * ny) is not None


def test_batch_reports_off_track_cars_once(tmp_path, capsys, oval):
    _, wp, rows = oval
    np.savetxt(tmp_path / "wp.csv", wp, delimiter=",", fmt="%.17g")
    cars = np.column_stack([rows[:50, 1:4], np.full(50, 3.0)])
    off = [3, 17, 40]
    cars[off, 0] += 100.0
    np.savetxt(tmp_path / "cars.csv", cars, delimiter=",", header="x,y,yaw,v", comments="")
    argv = ["batch", tmp_path / "cars.csv", "--waypoints", tmp_path / "wp.csv"]
    argv += ["--preset", "linear", "--out", tmp_path / "out.csv", "--quiet"]
    assert main([str(a) for a in argv]) == 0
    err = capsys.readouterr().err
    summary = [line for line in err.splitlines() if "off the track" in line]
    assert len(summary) == 1 and "3 of 50 cars" in summary[0] and "3, 17, 40" in summary[0]
    table = np.genfromtxt(tmp_path / "out.csv", delimiter=",", names=True)
    flagged = np.unique(table["car"][table["off_track"] == 1]).astype(int)
    assert flagged.tolist() == off
    # all on the track: no summary, the column all 0
    cars[off, 0] -= 100.0
    np.savetxt(tmp_path / "cars.csv", cars, delimiter=",", header="x,y,yaw,v", comments="")
    assert main([str(a) for a in argv] + ["--force"]) == 0
    assert "off the track" not in capsys.readouterr().err
    assert not np.genfromtxt(tmp_path / "out.csv", delimiter=",", names=True)["off_track"].any()


def test_runner_start_check_is_the_offline_rule(oval):
    """The start check raises the offline check's InputError (share of observations within
    ON_TRACK_M below MIN_ON_TRACK_SHARE, 80 %, of the first OFF_TRACK_START_OBS = 10) as soon
    as the rule can no longer be met: at the third off-track observation, not before."""
    cfg, wp, rows = oval
    runner = Runner(cfg, wp)
    for _, x, y, _ in rows[:2]:
        assert runner.check_track(x + 100.0, y) is not None
    with pytest.raises(InputError, match="only 0% of the observations of the stream's first 3"):
        runner.check_track(rows[2, 1] + 100.0, rows[2, 2])
    # two off, eight on: the rule is met, the stream goes on
    runner = Runner(cfg, wp)
    for k, (_, x, y, _) in enumerate(rows[:30]):
        runner.check_track(x + (100.0 if k in (0, 5) else 0.0), y)


def test_allow_off_track_lets_the_stream_run_with_warnings(monkeypatch, capsys, files, oval):
    _, _, rows = oval
    rows = rows.copy()
    rows[:, 1] += 100.0
    argv = [*files, "--allow-off-track"]
    rc, replies, err = fpe_run(monkeypatch, capsys, argv, csv_lines(rows))
    assert rc == 0 and len(replies) == len(rows)
    assert all("warning" in r for r in replies)
    assert 1 <= len(err) <= 1 + (rows[-1, 0] - rows[0, 0]) / 5.0


@pytest.mark.parametrize("max_cells", [1 << 21, 1 << 12])
def test_near_path_raster_gives_the_search_s_answers(oval, max_cells):
    """Many points are judged on a raster (fine or coarse): exactly the answers of searching
    each point's nearest vertex within ON_TRACK_M."""
    from fpe_jax.geometry._path import _vertex_stride, near_path, nearest_vertex

    _, wp, _ = oval
    xy = build_path(wp)["xy_m"]
    rng = np.random.default_rng(7)
    pts = np.resize(xy, (300_000, 2)) + rng.uniform(-6.0, 6.0, (300_000, 2))
    idx, _ = nearest_vertex(pts, xy[:: _vertex_stride(xy)], ON_TRACK_M)
    near = near_path(pts, xy, max_cells=max_cells)
    assert 0.2 < near.mean() < 0.8
    np.testing.assert_array_equal(near, idx >= 0)
