"""data/: the shipped tracks and the sample drive in every log format.

- Every sample format loads to the same Drive: ROS 2 MCAP, rosbag2 folder (also named by its
  metadata.yaml or its inner .mcap) and ROS 1 bag exactly (positions, stamps, truth; yaw to
  1e-12 rad through the quaternion); drive.csv to its 9 decimals (stamps exact to the ns); the
  header-less x,y,z file is the newest detection every 0.1 s, to its 6 decimals.
- The shipped files are what data/make_samples.py writes: a fresh run decodes to the same values
  (to 1e-9, in case another platform's floating point differs in the last bits), and two runs
  on one machine are byte-identical. `make_samples.py --check` compares the bytes with data/.
- The package's built-in tracks are byte copies of data/tracks/ and are what builtin_track
  returns; the simulator gives the same drive from the file as from the built-in name.
- Every data/ path the README names exists.
"""

from __future__ import annotations

import importlib.util
import json
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from fpe_jax import io
from fpe_jax.geometry._tracks import builtin_track
from fpe_jax.io import ros_msgs as rm
from fpe_jax.io.tables import read_table
from fpe_jax.sim import _sim as sim

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "data"
SAMPLES = DATA / "samples"
LOGS = ["drive.mcap", "drive_rosbag2", "drive_rosbag2/metadata.yaml", "drive.bag"]


def _load_script():
    spec = importlib.util.spec_from_file_location("make_samples", DATA / "make_samples.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def reference():
    return io.load_drive(SAMPLES / "drive.mcap")


@pytest.fixture(scope="module")
def fresh(tmp_path_factory):
    """The tree make_samples.py writes, in a new folder."""
    root = tmp_path_factory.mktemp("fresh") / "data"
    _load_script().write_all(root)
    return root


def test_data_is_small():
    size = sum(p.stat().st_size for p in DATA.rglob("*") if p.is_file())
    assert size < 2_000_000


@pytest.mark.parametrize("name", LOGS + ["drive_rosbag2/drive_rosbag2.mcap"])
def test_every_log_format_loads_to_the_same_drive(reference, name):
    d = io.load_drive(SAMPLES / name)
    assert d.meta["pose_topic"] == "/opp/pose" and d.meta["truth_topic"] == "/opp/odom"
    assert d.meta["t0_ns"] == reference.meta["t0_ns"]
    np.testing.assert_array_equal(d.t_s, reference.t_s)
    np.testing.assert_array_equal(d.xy_m, reference.xy_m)
    np.testing.assert_allclose(d.yaw_rad, reference.yaw_rad, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(d.truth_t_s, reference.truth_t_s)
    np.testing.assert_array_equal(d.truth_xy_m, reference.truth_xy_m)
    np.testing.assert_array_equal(d.truth_v_mps, reference.truth_v_mps)
    np.testing.assert_allclose(d.truth_yaw_rad, reference.truth_yaw_rad, rtol=0, atol=1e-12)


def test_sample_logs_are_the_simulated_drive(reference):
    res = sim.simulate("oval", duration_s=30.0, latency_s=0.3, seed=0)
    np.testing.assert_array_equal(rm.seconds_to_ns(reference.t_s), rm.seconds_to_ns(res.drive.t_s))
    # NumPy's vectorised sin/cos may round the last bit differently on another CPU (a 2-core
    # machine without AVX-512 simulated positions 1.4e-14 m from the committed samples), so
    # positions agree to a tolerance, not bitwise
    np.testing.assert_allclose(reference.xy_m, res.drive.xy_m, rtol=0, atol=1e-9)
    np.testing.assert_allclose(reference.truth_xy_m, res.drive.truth_xy_m, rtol=0, atol=1e-9)
    scenario = json.loads((SAMPLES / "scenario.json").read_text())
    assert scenario["track"] == "oval" and scenario["seed"] == 0
    assert scenario["n_detections"] == len(reference.t_s) == 330


def test_csv_sample_is_the_same_drive(reference):
    d = io.load_drive(SAMPLES / "drive.csv")
    assert d.meta["format"] == "csv" and d.meta["columns"] == ["t", "x", "y", "yaw"]
    np.testing.assert_array_equal(d.t_s, reference.t_s)  # stamps written to the nanosecond
    np.testing.assert_allclose(d.xy_m, reference.xy_m, rtol=0, atol=5e-10)
    np.testing.assert_allclose(d.yaw_rad, reference.yaw_rad, rtol=0, atol=5e-10 + 1e-12)


def test_xyz_sample_is_the_newest_detection_every_tenth_of_a_second(reference):
    d = io.load_drive(SAMPLES / "poses_xyz.csv", rate_hz=10.0)
    assert d.meta["format"] == "xyz-csv"
    n = len(d.t_s)
    assert n == int((reference.t_s[-1] - reference.t_s[0]) * 10) + 1
    np.testing.assert_allclose(d.t_s, np.arange(n) / 10.0, rtol=0, atol=1e-12)
    newest = [
        np.flatnonzero(reference.t_s <= reference.t_s[0] + k / 10 + 1e-9)[-1] for k in range(n)
    ]
    np.testing.assert_allclose(d.xy_m, reference.xy_m[newest], rtol=0, atol=5e-7)
    assert np.all(np.isnan(d.yaw_rad))
    z = read_table(SAMPLES / "poses_xyz.csv").data[:, 2]
    assert read_table(SAMPLES / "poses_xyz.csv").header is None and np.all(z == 0.0)


def test_cars_sample_feeds_batch():
    from fpe_jax.io import read_cars

    cars = read_cars(SAMPLES / "cars.csv")
    xy, _ = builtin_track("oval")
    assert cars.shape == (10, 4) and np.all(cars[:, 3] == 4.0)
    # every car is on the centerline, heading along it
    dist = np.min(np.linalg.norm(cars[:, None, :2] - xy[None], axis=2), axis=1)
    assert dist.max() < 1e-6


def _values(path: Path):
    """What a file says, as numbers/structures to compare across platforms."""
    if path.suffix == ".csv":
        t = read_table(path)
        return t.header, t.data
    if path.suffix == ".json":
        return json.loads(path.read_text())
    if path.suffix == ".yaml":
        return yaml.safe_load(path.read_text())
    d = io.load_drive(path)
    return d.t_s, d.xy_m, d.yaw_rad, d.truth_t_s, d.truth_xy_m, d.truth_yaw_rad, d.truth_v_mps


def test_shipped_data_is_what_the_script_writes(fresh):
    shipped = sorted(
        str(p.relative_to(DATA))
        for p in DATA.rglob("*")
        if p.is_file() and p.parent != DATA and "__pycache__" not in p.parts
    )
    written = sorted(str(p.relative_to(fresh)) for p in fresh.rglob("*") if p.is_file())
    assert shipped == written
    for name in written:
        a, b = _values(DATA / name), _values(fresh / name)
        if isinstance(a, tuple):
            for x, y in zip(a, b):
                if isinstance(x, np.ndarray):
                    np.testing.assert_allclose(x, y, rtol=0, atol=1e-9, err_msg=name)
                else:
                    assert x == y, name
        else:
            assert a == b, name


def test_make_samples_is_byte_deterministic(fresh, tmp_path):
    again = tmp_path / "data"
    _load_script().write_all(again)
    files = sorted(p.relative_to(fresh) for p in fresh.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(again) for p in again.rglob("*") if p.is_file())
    for f in files:
        assert (fresh / f).read_bytes() == (again / f).read_bytes(), f


@pytest.mark.parametrize("name", ["oval", "hairpin"])
def test_builtin_tracks_are_the_shipped_files(name):
    package = ROOT / "fpe_jax" / "builtin_tracks" / f"{name}.csv"
    assert package.read_bytes() == (DATA / "tracks" / f"{name}.csv").read_bytes()
    xy, hw = builtin_track(name)
    wp = io.load_waypoints(DATA / "tracks" / f"{name}.csv")
    assert wp.format == "f1tenth-centerline"
    np.testing.assert_array_equal(xy, wp.xy_m)
    assert hw == {"oval": 1.1, "hairpin": 0.9}[name]


def test_pyproject_ships_the_builtin_tracks():
    import tomllib

    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())
    patterns = cfg["tool"]["setuptools"]["package-data"]["fpe_jax"]
    shipped = {p for pat in patterns for p in (ROOT / "fpe_jax").glob(pat)}
    tracks = set((ROOT / "fpe_jax" / "builtin_tracks").glob("*.csv"))
    assert len(tracks) == 2
    assert {p for p in shipped if p.suffix == ".csv"} == tracks


def test_simulating_the_track_file_equals_the_builtin_name():
    a = sim.simulate("oval", duration_s=3.0, seed=4).drive
    b = sim.simulate(str(DATA / "tracks" / "oval.csv"), duration_s=3.0, seed=4).drive
    np.testing.assert_array_equal(a.t_s, b.t_s)
    np.testing.assert_array_equal(a.xy_m, b.xy_m)
    np.testing.assert_array_equal(a.truth_xy_m, b.truth_xy_m)


def test_readme_names_only_existing_data_files():
    text = (ROOT / "README.md").read_text() + (DATA / "README.md").read_text()
    named = set(re.findall(r"\bdata/[\w./-]*\w", text))
    assert "data/samples/drive.mcap" in named
    missing = sorted(p for p in named if not (ROOT / p).exists())
    assert not missing


def _perturb_csv(path: Path, delta: float) -> None:
    """Move the first x value of a drive CSV by delta (as another CPU's rounding would)."""
    lines = path.read_text().splitlines()
    cells = lines[1].split(",")
    cells[1] = f"{float(cells[1]) + delta:.9f}"
    lines[1] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")


def test_check_compares_values_within_its_stated_tolerance(fresh, tmp_path):
    """--check and the rewrite judge files by what they say, within make_samples.TOLERANCE: a
    last-digit difference (another CPU) passes and rewrites nothing; a real change is named."""
    import shutil

    script = _load_script()
    assert script.TOLERANCE == 1e-8
    copy = tmp_path / "data"
    shutil.copytree(fresh, copy)
    _perturb_csv(copy / "samples" / "drive.csv", 1e-9)
    track = copy / "tracks" / "oval.csv"
    rows = track.read_text().splitlines()
    x = float(rows[1].split(",")[0])
    rows[1] = rows[1].replace(repr(x), repr(float(np.nextafter(x, np.inf))), 1)
    track.write_text("\n".join(rows) + "\n")
    assert (copy / "samples" / "drive.csv").read_bytes() != (
        fresh / "samples/drive.csv"
    ).read_bytes()
    assert script.compare_trees(fresh, copy) == []
    before = {p: p.read_bytes() for p in copy.rglob("*") if p.is_file()}
    assert script._sync(fresh / "samples", copy / "samples") == []
    assert script._sync(fresh / "tracks", copy / "tracks") == []
    assert {p: p.read_bytes() for p in copy.rglob("*") if p.is_file()} == before
    _perturb_csv(copy / "samples" / "drive.csv", 1e-6)
    assert script.compare_trees(fresh, copy) == ["samples/drive.csv"]
    assert script._sync(fresh / "samples", copy / "samples") == [copy / "samples" / "drive.csv"]
    assert script.compare_trees(fresh, copy) == []
