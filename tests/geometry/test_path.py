"""Waypoint cleaning in `fpe_jax.geometry.build_path`: corners survive, only back-tracking goes.

A turn of 90 degrees or more onto new ground (a square, a hairpin drawn with few points) is part
of the track. What the cleaning removes is a stretch where the waypoints go back over ground the
path already covered (a hand-driven recording that backs up, as at the Levine seam), and points
closer than `min_step_m` to the previous kept one; `build_path` reports both by waypoint index.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from fpe_jax.geometry._path import build_path


def square_xy(side_m: float = 10.0, step_m: float = 1.0) -> np.ndarray:
    """Counter-clockwise square from the origin, one point every step_m, corner points included,
    the start not repeated at the end."""
    n = int(round(side_m / step_m))
    u = np.arange(n) * step_m
    return np.vstack(
        [
            np.column_stack([u, np.zeros(n)]),
            np.column_stack([np.full(n, side_m), u]),
            np.column_stack([side_m - u, np.full(n, side_m)]),
            np.column_stack([np.zeros(n), side_m - u]),
        ]
    )


def distance_to_path(points: np.ndarray, path_xy: np.ndarray) -> np.ndarray:
    """(P,) distance [m] of each point to the nearest vertex of a densely sampled path."""
    return np.min(np.linalg.norm(points[:, None, :] - path_xy[None, :, :], axis=2), axis=1)


CORNERS = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])


@pytest.mark.parametrize(
    "xy", [square_xy(), CORNERS, square_xy(step_m=0.25)], ids=["1m", "4-point", "0.25m"]
)
def test_square_keeps_its_corners(xy):
    p = build_path(xy)
    assert p["closed"]
    # Smoothing (0.3 m half-window) rounds each corner, cutting ~0.13 m; the rest is the square.
    assert 39.4 < p["length_m"] <= 40.0
    far = distance_to_path(np.array([[5.0, 0.0], [10.0, 5.0], [5.0, 10.0], [0.0, 5.0]]), p["xy_m"])
    assert np.all(far < 0.06)  # every side's middle is on the path
    assert np.all(distance_to_path(CORNERS, p["xy_m"]) < 0.2)  # and every corner, rounded
    assert p["removed_backtrack_idx"].size == 0


def test_l_shape_is_an_open_path_through_its_corner():
    leg1 = np.column_stack([np.arange(11.0), np.zeros(11)])
    leg2 = np.column_stack([np.full(5, 10.0), np.arange(1.0, 6.0)])
    p = build_path(np.vstack([leg1, leg2]))
    assert not p["closed"]
    assert 14.8 < p["length_m"] <= 15.0
    np.testing.assert_allclose(p["xy_m"][[0, -1]], [[0.0, 0.0], [10.0, 5.0]], atol=1e-12)
    assert distance_to_path(np.array([[10.0, 0.0]]), p["xy_m"])[0] < 0.2
    assert p["removed_backtrack_idx"].size == 0


@pytest.mark.parametrize(
    "xy, closed, length_m",
    [
        # one 163-degree turn between legs 1.5 m apart, two points per leg (open: the gap
        # between its ends is as short as its steps, so loop detection would close it)
        (np.array([[0, 0], [5, 0], [10, 0], [5, 1.5], [0, 1.5]], float), False, 20.22),
        # a 10 m x 1 m loop from its four corners: two hairpins of two 90-degree turns each
        (np.array([[0, 0], [10, 0], [10, 1], [0, 1]], float), True, 22.0),
    ],
    ids=["open-163deg", "closed-4-point"],
)
def test_hairpin_at_coarse_spacing_keeps_both_legs(xy, closed, length_m):
    p = build_path(xy, closed=None if closed else False)
    assert p["closed"] is closed
    assert length_m - 0.6 < p["length_m"] <= length_m + 1e-9
    # both legs are on the path: points along the way back are not dropped
    assert distance_to_path(np.array([[2.5, 0.0], [2.5, xy[-1, 1]]]), p["xy_m"]).max() < 0.06
    assert p["removed_backtrack_idx"].size == 0


def circle_xy(radius_m=10.0, step_m=0.05):
    a = np.arange(0.0, 2 * np.pi, step_m / radius_m)
    return radius_m * np.column_stack([np.cos(a), np.sin(a)])


def test_backing_up_is_removed_and_reported():
    """A recording that stops, backs up 0.8 m with 2 cm of lateral wobble, then drives on."""
    clean = circle_xy()
    rng = np.random.default_rng(0)
    k = 300  # backs up from waypoint k to k - 16 (0.8 m) and comes forward again
    back = clean[k - 1 : k - 17 : -1] * (1.0 + rng.uniform(-0.002, 0.002, (16, 1)))
    forward = clean[k - 16 : k] * (1.0 + rng.uniform(-0.002, 0.002, (16, 1)))
    noisy = np.vstack([clean[:k], back, forward, clean[k:]])
    p, ref = build_path(noisy), build_path(clean)
    removed = p["removed_backtrack_idx"]
    # the back-up and the drive forward over covered ground, all of it and nothing else
    assert removed.min() >= k and removed.max() < k + 32
    assert removed.size >= 20
    assert p["closed"] and abs(p["length_m"] - ref["length_m"]) < 0.02
    assert distance_to_path(p["xy_m"], ref["xy_m"]).max() < 0.01


def test_removed_points_are_reported_by_index():
    xy = np.array([[0, 0], [1, 0], [1.05, 0], [2, 0], [3, 0], [2.5, 0.01], [4, 0], [4, 4]], float)
    p = build_path(xy, closed=False)
    assert p["removed_close_idx"].tolist() == [2]  # 5 cm after the previous point
    assert p["removed_backtrack_idx"].tolist() == [5]  # half a metre back along the line
    assert p["removed_close_idx"].dtype == p["removed_backtrack_idx"].dtype == np.int64


def test_levine_is_cleaned_as_before(shared_data):
    """The hand-driven Levine loop: the same 63 back-tracking waypoints (the seam backs up
    ~0.8 m) and the same 2296 near duplicates as the reversal-only rule removed."""
    xy = np.loadtxt(shared_data / "levine" / "levine-waypoints.csv", delimiter=",")[:, :2]
    p = build_path(xy)
    ranges = [(1394, 1408), (2507, 2507), (2598, 2602), (2630, 2632), (2652, 2690)]
    expected = np.concatenate([np.arange(a, b + 1) for a, b in ranges])
    np.testing.assert_array_equal(p["removed_backtrack_idx"], expected)
    assert p["removed_close_idx"].size == 2296
    assert p["closed"] and 55.0 < p["length_m"] < 85.0


# ---- fpe info --waypoints -----------------------------------------------------------------------


def _csv(path, xy):
    np.savetxt(path, xy, delimiter=",", header="x,y", comments="", fmt="%.6f")
    return str(path)


def test_fpe_info_waypoints_reports_the_path_and_what_was_removed(tmp_path, capsys):
    from fpe_jax import cli

    xy = np.array([[0, 0], [1, 0], [1.05, 0], [2, 0], [3, 0], [2.5, 0.01], [4, 0], [4, 4]], float)
    wp = _csv(tmp_path / "wp.csv", xy)
    assert cli.main(["info", "--waypoints", wp]) == 0
    out = capsys.readouterr().out
    assert f"{wp}  (csv, 8 waypoints)" in out
    assert "path: open path, 7.8" in out  # 8 m, the corner at (4, 0) rounded by smoothing
    assert "removed: 1 within 0.15 m of the previous kept waypoint" in out
    assert "1 back-tracking: index 5 (0-based)" in out

    assert cli.main(["info", "--waypoints", _csv(tmp_path / "sq.csv", square_xy()), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)["waypoints"]
    assert info["n_waypoints"] == 40 and info["closed"] is True
    assert 39.4 < info["length_m"] <= 40.0
    assert info["removed"] == {"near_duplicate_idx": [], "backtracking_idx": []}


def test_fpe_info_with_a_log_and_waypoints(tmp_path, capsys):
    from fpe_jax import cli

    drive = tmp_path / "d.csv"
    drive.write_text("t,x,y\n0,0,0\n0.1,1,0\n")
    wp = _csv(tmp_path / "sq.csv", square_xy())
    assert cli.main(["info", str(drive), "--waypoints", wp, "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["format"] == "csv" and info["waypoints"]["n_waypoints"] == 40


def test_fpe_info_needs_a_log_or_waypoints(capsys):
    from fpe_jax import cli

    assert cli.main(["info"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "LOG" in err[0] and "--waypoints" in err[0]
