"""Hostile input, the parts that need geometry: the drive-vs-track check (other track, reversed,
shifted) and the O(P + K) nearest-vertex search it runs on; export's waypoints taken from the
config's provenance (missing or changed file)."""

from __future__ import annotations

import numpy as np
import pytest

from fpe_jax import cli
from fpe_jax.errors import InputError
from fpe_jax.geometry._path import build_path, check_on_track, nearest_vertex, track_agreement
from fpe_jax.io.config import params_to_config, write_config
from fpe_jax.model._params import presets
from fpe_jax.sim._sim import simulate


def test_nearest_vertex_equals_the_exhaustive_search():
    rng = np.random.default_rng(0)
    ver = rng.uniform(0.0, 50.0, (3000, 2))
    ver[7] = ver[3]  # a tie: the lowest index wins, as np.argmin
    pts = np.vstack([rng.uniform(-10.0, 60.0, (5000, 2)), ver[3] + 0.01])
    idx, dist = nearest_vertex(pts, ver, 3.0)
    d = np.hypot(*(pts[:, None, :] - ver[None, :, :]).transpose(2, 0, 1))
    near = d.min(axis=1) <= 3.0
    assert near.sum() > 1000 and (~near).sum() > 100
    np.testing.assert_array_equal(idx[near], d.argmin(axis=1)[near])
    np.testing.assert_allclose(dist[near], d.min(axis=1)[near])
    assert np.all(idx[~near] == -1) and np.all(np.isinf(dist[~near]))
    assert idx[-1] == 3


@pytest.fixture(scope="module")
def drives(shared_data):
    """name -> (observations (N, 2), centerline (K, 2)): simulated drives and the Levine lap."""
    out = {}
    for name in ("oval", "hairpin", "random:7", str(shared_data / "tracks/Monza_centerline.csv")):
        res = simulate(name, duration_s=30.0, seed=1)
        out[name.rsplit("/")[-1]] = (res.drive.xy_m, res.centerline_xy_m)
    lev = shared_data / "levine"
    out["levine"] = (
        np.loadtxt(lev / "actual-poses.csv", delimiter=",")[:, :2],
        np.loadtxt(lev / "levine-waypoints.csv", delimiter=",")[:, :2],
    )
    return out


def _agree(xy, wp):
    p = build_path(wp)
    return track_agreement(xy, p["xy_m"], p["heading_rad"])


def test_own_drives_are_on_their_track(drives):
    for name, (xy, wp) in drives.items():
        a = _agree(xy, wp)
        assert a["share_near"] >= 0.95 and a["share_along"] >= 0.9, (name, a)


@pytest.mark.parametrize(
    "case, words",
    [
        ("other track", "different map frame"),
        ("reversed", "reverse direction"),
        ("shifted 50 m", "different map frame"),
    ],
)
@pytest.mark.parametrize("name", ["oval", "Monza_centerline.csv", "levine"])
def test_wrong_waypoints_are_caught(drives, name, case, words):
    xy, wp = drives[name]
    other = "hairpin" if name != "hairpin" else "oval"
    wrong = {
        "other track": drives[other][1],
        "reversed": wp[::-1],
        "shifted 50 m": wp + [50.0, 0.0],
    }[case]
    p = build_path(wrong)
    with pytest.raises(InputError, match=words) as e:
        check_on_track(xy, p["xy_m"], p["heading_rad"], source="wp.csv", drive="d.csv")
    assert str(e.value).startswith("wp.csv: ") and "--allow-off-track" in str(e.value)
    a = check_on_track(xy, p["xy_m"], p["heading_rad"], source="wp.csv", drive="d", allow=True)
    assert a["share_near"] < 0.8 or a["share_along"] < 0.5  # what tripped it


def _write_csv(path, rows, header):
    path.write_text(
        header + "\n" + "".join(",".join(map(repr, map(float, r))) + "\n" for r in rows)
    )
    return path


@pytest.fixture(scope="module")
def files(tmp_path_factory, drives):
    """A drive CSV on the oval, its waypoints, the same reversed, and the hairpin's."""
    root = tmp_path_factory.mktemp("on_track")
    res = simulate("oval", duration_s=10.0, seed=3)
    d = res.drive
    log = _write_csv(root / "drive.csv", np.column_stack([d.t_s, d.xy_m, d.yaw_rad]), "t,x,y,yaw")
    wp = res.centerline_xy_m
    return dict(
        log=log,
        wp=_write_csv(root / "wp.csv", wp, "x,y"),
        reversed=_write_csv(root / "reversed.csv", wp[::-1], "x,y"),
        other=_write_csv(root / "hairpin.csv", drives["hairpin"][1], "x,y"),
    )


@pytest.mark.parametrize("wp", ["reversed", "other"])
@pytest.mark.parametrize(
    "command",
    [
        "fit {log} --waypoints {wp} --out {out}",
        "evaluate {log} --waypoints {wp} --preset default",
        "predict {log} --waypoints {wp} --out {out}",
        "plot {log} --waypoints {wp} --preset default --out {out}",
    ],
    ids=["fit", "evaluate", "predict", "plot"],
)
def test_commands_refuse_off_track_drives(files, tmp_path, capsys, command, wp):
    out = tmp_path / ("out.png" if command.startswith("plot") else "out.csv")
    if command.startswith("fit"):
        out = tmp_path / "out.json"
    argv = command.format(log=files["log"], wp=files[wp], out=out).split()
    assert cli.main([*argv, "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert str(files[wp]) in err and "--allow-off-track" in err
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_allow_off_track_overrides(files, tmp_path, capsys):
    out = tmp_path / "pred.csv"
    argv = f"predict {files['log']} --waypoints {files['reversed']} --out {out} --quiet".split()
    assert cli.main([*argv, "--allow-off-track"]) == 0
    assert out.exists()
    good = tmp_path / "good.csv"
    assert cli.main(f"predict {files['log']} --waypoints {files['wp']} --out {good}".split()) == 0


def _config_with_provenance(tmp_path, wp_file, sha=None):
    from fpe_jax.geometry._path import waypoints_sha256

    sha = sha or waypoints_sha256(np.loadtxt(wp_file, delimiter=",", skiprows=1))
    prov = {"waypoints": {"file": str(wp_file), "sha256": sha}}
    path = tmp_path / "tuned.json"
    write_config(path, params_to_config(presets["default"], provenance=prov))
    return path


def test_export_takes_the_waypoints_from_the_provenance(files, tmp_path, capsys):
    wp = tmp_path / "wp.csv"
    wp.write_bytes(files["wp"].read_bytes())
    cfg = _config_with_provenance(tmp_path, wp)
    out = tmp_path / "p.yaml"
    assert cli.main(["export", str(cfg), "--format", "ros2", "--out", str(out)]) == 0
    assert f"provenance: {wp}" in capsys.readouterr().err
    assert 'waypoint_file: "wp.csv"' in out.read_text()  # relative to the YAML's folder

    before = {p: p.read_bytes() for p in tmp_path.iterdir()}
    cases = {
        "changed": (lambda: wp.write_text("x,y\n0,0\n10,0\n10,10\n0,10\n"), "changed since"),
        "missing": (wp.unlink, "is missing"),
    }
    for name, (damage, words) in cases.items():
        damage()
        target = tmp_path / f"{name}.stablehlo"
        assert cli.main(["export", str(cfg), "--format", "stablehlo", "--out", str(target)]) == 2
        err = capsys.readouterr().err
        assert words in err and "--waypoints" in err and len(err.strip().splitlines()) == 1, err
        assert not target.exists()
    assert {p: p.read_bytes() for p in tmp_path.iterdir()} == {
        p: b for p, b in before.items() if p != wp
    }


def test_export_rejects_a_malformed_provenance_entry(files, tmp_path, capsys):
    cfg = _config_with_provenance(tmp_path, files["wp"], sha="not-a-hash")
    assert (
        cli.main(["export", str(cfg), "--format", "json", "--out", str(tmp_path / "c.json")]) == 2
    )
    assert "provenance.waypoints" in capsys.readouterr().err


def test_states_from_drive_in_blocks_equal_one_block(monkeypatch):
    """A long log runs in blocks (bounded memory); the projection continues across them."""
    import importlib

    from fpe_jax.geometry._track import Track

    predict = importlib.import_module("fpe_jax.predict._predict")  # fpe_jax.predict is a name

    res = simulate("hairpin", duration_s=40.0, seed=4)
    track = Track.from_waypoints(res.centerline_xy_m)
    params = presets["default"]
    whole = predict.states_from_drive(params, res.drive, track)
    rows = importlib.import_module("fpe_jax.compile._rows")
    monkeypatch.setattr(rows, "PREDICT_CHUNK", 100)
    assert len(list(rows.row_blocks(len(res.drive.t_s)))) >= 4
    blocks = predict.states_from_drive(params, res.drive, track)
    for name in ("x_m", "y_m", "s_m", "s_fit_m", "sdot_mps", "offset_m", "v_mps"):
        np.testing.assert_allclose(getattr(blocks, name), getattr(whole, name), atol=1e-9)


def _loop(length_m: float, aspect: float) -> np.ndarray:
    """An ellipse of about `length_m` [m] whose axes are in the ratio `aspect`, 0.5 m spacing."""
    t = np.linspace(0.0, 2 * np.pi, int(length_m / 0.5), endpoint=False)
    xy = np.column_stack([np.cos(t), np.sin(t) / aspect])
    perimeter = np.sum(np.hypot(*np.diff(np.vstack([xy, xy[:1]]), axis=0).T))
    return xy * (length_m / perimeter)


def test_projection_grid_grows_with_track_length_not_area():
    """The issue's grid held a cell per bounding-box cell (0.83 GB for one car on a 1 km oval);
    now memory and build peak follow the length: equal lengths, 10x the area, same size."""
    import tracemalloc

    import jax

    from fpe_jax.geometry._track import Track
    from fpe_jax.predict._batch import ProjectionGrid

    sizes = {}
    for aspect in (1.0, 12.0):
        track = Track.from_waypoints(_loop(400.0, aspect))
        tracemalloc.start()
        grid = ProjectionGrid.build(track)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        nbytes = sum(x.nbytes for x in jax.tree.leaves(grid))
        nx, ny = grid.shape
        sizes[aspect] = (nbytes, peak, nx * ny, grid.n_complete, float(track.length_m))
    (b1, p1, c1, r1, l1), (b2, p2, c2, r2, l2) = sizes[1.0], sizes[12.0]
    assert abs(l1 - l2) < 0.02 * l1 and c1 > 2.5 * c2  # same length; the round one's box is larger
    # the same number of stored cells and build peak; the row width K is the longest candidate
    # list, set by the sharpest bend (the thin loop's 0.7 m radius ends), not by the area
    assert max(r1, r2) < 1.3 * min(r1, r2) and max(p1, p2) < 1.3 * min(p1, p2)
    # per metre of track (measured: grid 4.3 kB round, 5.6 kB thin; build peak 150 MB of fixed
    # passes + ~60 kB)
    for nbytes, peak in ((b1, p1), (b2, p2)):
        assert nbytes < 8e3 * l1 and peak < 2e8 + 1e5 * l1


def _speedway(straight_m=600.0, radius_m=200.0, spacing_m=2.0):
    """A 1.5-mile speedway's centre line (K, 2) [m], counter-clockwise: two straights, two
    half circles."""
    n_s, n_c = int(straight_m / spacing_m), int(np.pi * radius_m / spacing_m)
    a = np.linspace(-0.5 * np.pi, 0.5 * np.pi, n_c, endpoint=False)
    right = np.column_stack([straight_m / 2 + radius_m * np.cos(a), radius_m * np.sin(a)])
    top = np.column_stack(
        [np.linspace(straight_m / 2, -straight_m / 2, n_s, endpoint=False), np.full(n_s, radius_m)]
    )
    return np.vstack([right, top, -right, -top])


def _racing_line_drive(center_xy_m, seed=0):
    """Observations (N, 2) [m] of a car 3-6 m inside (left of) the centre line at 60 m/s, 10 Hz,
    0.3 m noise: a real racing line on a wide track."""
    p = build_path(center_xy_m)
    rng = np.random.default_rng(seed)
    s = np.arange(0.0, 2 * p["length_m"], 6.0)
    k = np.searchsorted(np.cumsum(np.hypot(*np.diff(p["xy_m"], axis=0).T)), s % p["length_m"])
    k = np.minimum(k, len(p["xy_m"]) - 1)
    offset = 4.5 + 1.5 * np.sin(2 * np.pi * s / 700.0)
    h = p["heading_rad"][k]
    xy = p["xy_m"][k] + offset[:, None] * np.column_stack([-np.sin(h), np.cos(h)])
    return xy + rng.normal(0.0, 0.3, xy.shape)


def test_a_racing_line_on_a_full_size_track_is_on_it_and_wrong_frames_are_caught():
    from fpe_jax.geometry._path import ON_TRACK_M, on_track_m

    center = _speedway()
    xy = _racing_line_drive(center)
    p = build_path(center)
    assert 10.0 < on_track_m(p["xy_m"]) < 12.0  # 1 % of the 1077 m extent
    # a fixed 3 m refused it: most of the drive is further from the centre line
    assert track_agreement(xy, p["xy_m"], p["heading_rad"], near_m=ON_TRACK_M)["share_near"] < 0.8
    a = check_on_track(xy, p["xy_m"], p["heading_rad"], source="wp.csv", drive="d.csv")
    assert a["share_near"] >= 0.95 and a["share_along"] >= 0.95, a
    # the 1:10 bound is unchanged: the oval's extent is 32 m
    assert on_track_m(build_path(simulate("oval", duration_s=1.0).centerline_xy_m)["xy_m"]) == 3.0
    wrong = {
        "shifted 50 m": (center + [0.0, 50.0], "different map frame"),
        "reversed": (center[::-1], "reverse direction"),
        "a smaller speedway": (_speedway(400.0, 150.0), "different map frame"),
        "a UTM frame": (center + [4.8e5, 4.4e6], "different map frame"),
    }
    for name, (wp, words) in wrong.items():
        q = build_path(wp)
        with pytest.raises(InputError, match=words):
            check_on_track(xy, q["xy_m"], q["heading_rad"], source="wp.csv", drive=name)


def test_fpe_predict_takes_a_full_size_racing_line_without_flags(tmp_path, capsys):
    center = _speedway()
    xy = _racing_line_drive(center)[:300]
    t = np.arange(len(xy)) * 0.1
    log = _write_csv(tmp_path / "drive.csv", np.column_stack([t, xy]), "t,x,y")
    wp = _write_csv(tmp_path / "wp.csv", center, "x,y")
    out = tmp_path / "pred.csv"
    argv = ["predict", str(log), "--waypoints", str(wp), "--out", str(out), "--quiet"]
    assert cli.main(argv) == 0, capsys.readouterr().err
    assert out.exists()
    shifted = _write_csv(tmp_path / "shifted.csv", center + [0.0, 50.0], "x,y")
    argv[3] = str(shifted)
    assert cli.main([*argv[:5], str(tmp_path / "p2.csv"), "--quiet"]) == 2
    assert "different map frame" in capsys.readouterr().err
