"""`fpe batch` streamed: cars read a block at a time (`io.CarFile`), poses written as chunks
finish (`io.PosesFile`) on a writer thread, the same bytes as predicting the whole array."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fpe_jax import pipeline
from fpe_jax.errors import InputError
from fpe_jax.io import CarFile, PosesFile, read_cars, write_poses

DATA = Path(__file__).resolve().parents[2] / "data"
WAYPOINTS = DATA / "tracks" / "oval.csv"
CHUNK = 256
N_CARS = 3 * CHUNK + 40  # three full chunks and a partial one (run in 64 rows)
FAR_M = np.array([512345.0, 5401234.0])  # a UTM-sized map origin: float64 poses


def _cars(wp_xy: np.ndarray, n: int = N_CARS, seed: int = 0) -> np.ndarray:
    """(n, 5) cars near the waypoints; in every chunk some lie 2-3 m to the side (off the
    projection grid: the exhaustive search) and some 40 m away (off the track)."""
    rng = np.random.default_rng(seed)
    i = rng.integers(0, len(wp_xy) - 1, n)
    d = wp_xy[i + 1] - wp_xy[i]
    yaw = np.arctan2(d[:, 1], d[:, 0])
    normal = np.column_stack([-np.sin(yaw), np.cos(yaw)])
    xy = wp_xy[i] + normal * rng.uniform(-0.4, 0.4, (n, 1))
    cars = np.column_stack(
        [xy, yaw + rng.normal(0, 0.1, n), rng.uniform(1, 6, n), rng.normal(0, 0.3, n)]
    )
    side = np.arange(5, n, 97)  # off the grid, every chunk and the last one
    cars[side, :2] += normal[side] * 2.5
    far = np.arange(11, n, 131)
    cars[far, :2] += 40.0
    return cars


def _whole_array(cars_path, wp_path, out, *, dtype="float32", chunk=CHUNK):
    """`fpe batch` as one array: every car read, predicted in memory, moved to the map frame,
    judged on or off the track, then written whole (what the command did before streaming)."""
    from fpe_jax.drive import map_origin
    from fpe_jax.geometry._track import Track
    from fpe_jax.predict._batch import off_track_cars, predict_chunked, with_origin

    pred = pipeline.load_predictor(str(wp_path), preset="default")
    origin = map_origin(pred.waypoints_xy_m)
    track = Track.from_waypoints(pred.waypoints_xy_m - origin)
    cars = read_cars(cars_path)
    cars[:, :2] -= origin
    poses = predict_chunked(pred.params, cars, track, dtype=dtype, chunk=chunk)
    poses = with_origin(poses, origin)
    off = off_track_cars(pred.params, cars[:, :2], track)
    write_poses(out, poses, pred.params.settings.dt_s, off_track=off)
    return poses, off


@pytest.fixture(scope="module")
def oval_xy() -> np.ndarray:
    return np.loadtxt(WAYPOINTS, delimiter=",")[:, :2]


@pytest.mark.parametrize(
    "suffix, dtype, far",
    [(".npy", "float32", False), (".npy", "float64", False), (".npy", "float32", True),
     (".csv", "float32", False)],
)  # fmt: skip
def test_streamed_output_is_the_whole_array_output_byte_for_byte(
    tmp_path, oval_xy, suffix, dtype, far
):
    shift = FAR_M if far else np.zeros(2)
    wp = tmp_path / "wp.csv"
    np.savetxt(wp, oval_xy + shift, delimiter=",", header="x,y", comments="")
    cars = _cars(oval_xy)
    cars[:, :2] += shift
    src = tmp_path / "cars.npy"
    np.save(src, cars)
    ref_poses, ref_off = _whole_array(src, wp, tmp_path / f"ref{suffix}", dtype=dtype)
    warned, seen = [], []
    res = pipeline.predict_cars(
        src, wp, out=tmp_path / f"out{suffix}", dtype=dtype, chunk=CHUNK, warn=warned.append,
        on_chunk=lambda done, n: seen.append(done),
    )  # fmt: skip
    assert (tmp_path / f"out{suffix}").read_bytes() == (tmp_path / f"ref{suffix}").read_bytes()
    assert res.poses_m.dtype == (np.float64 if far or dtype == "float64" else np.float32)
    assert res.poses_m.tobytes() == ref_poses.tobytes()
    assert res.shape == (N_CARS, 10, 3)
    assert seen == [CHUNK, 2 * CHUNK, 3 * CHUNK, N_CARS]
    # the off-track cars, each flagged and named in one warning
    far_rows = np.arange(11, N_CARS, 131)
    assert (
        np.flatnonzero(res.off_track).tolist()
        == far_rows.tolist()
        == np.flatnonzero(ref_off).tolist()
    )
    assert len(warned) == 1
    assert f"{len(far_rows)} of {N_CARS} cars of {src}" in warned[0]
    assert "rows " + ", ".join(map(str, far_rows)) in warned[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        ["wp.csv", "cars.npy", f"ref{suffix}", f"out{suffix}"]
    )  # no temporary file left


def test_streamed_array_input_and_no_output_equal_the_file_run(tmp_path, oval_xy):
    cars = _cars(oval_xy, seed=1)
    src = tmp_path / "cars.npy"
    np.save(src, cars)
    before = cars.copy()
    in_memory = pipeline.predict_cars(cars, str(WAYPOINTS), chunk=CHUNK)
    np.testing.assert_array_equal(cars, before)  # the caller's array is not changed
    to_file = pipeline.predict_cars(src, str(WAYPOINTS), chunk=CHUNK, out=tmp_path / "p.npy")
    assert in_memory.poses_m.tobytes() == np.load(tmp_path / "p.npy").tobytes()
    assert in_memory.off_track.tolist() == to_file.off_track.tolist()


def test_a_bad_car_late_in_the_file_leaves_no_output_and_the_old_one_intact(tmp_path, oval_xy):
    cars = _cars(oval_xy)
    cars[3, 3] = 500.0  # a speed beyond the limit in the first chunk
    cars[N_CARS - 2, 1] = np.nan  # and a NaN in the last: the NaN is what read_cars reports
    src = tmp_path / "cars.npy"
    np.save(src, cars)
    out = tmp_path / "p.npy"
    out.write_bytes(b"the user's file")
    with pytest.raises(InputError) as whole:
        read_cars(src)
    with pytest.raises(InputError) as streamed:
        pipeline.predict_cars(src, str(WAYPOINTS), chunk=CHUNK, out=out, force=True)
    assert str(streamed.value) == str(whole.value)
    assert f"first car index {N_CARS - 2}" in str(streamed.value)
    assert out.read_bytes() == b"the user's file"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cars.npy", "p.npy"]


def test_the_output_may_not_be_the_input(tmp_path, oval_xy):
    src = tmp_path / "cars.npy"
    np.save(src, _cars(oval_xy, n=10))
    before = src.read_bytes()
    with pytest.raises(InputError, match="same file as the input"):
        pipeline.predict_cars(src, str(WAYPOINTS), out=tmp_path / "." / "cars.npy", force=True)
    assert src.read_bytes() == before


# ---- reading cars a block at a time -------------------------------------------------------------


@pytest.mark.parametrize(
    "layout",
    ["float64", "float32", "big-endian", "int32", "fortran", "four columns"],
)
def test_car_file_blocks_are_read_cars_rows(tmp_path, layout):
    rng = np.random.default_rng(2)
    cars = rng.uniform(-50, 50, (1000, 5))
    arr = {
        "float64": cars,
        "float32": cars.astype(np.float32),
        "big-endian": cars.astype(">f8"),
        "int32": cars.astype(np.int32),
        "fortran": np.asfortranarray(cars),
        "four columns": cars[:, :4],
    }[layout]
    path = tmp_path / "cars.npy"
    np.save(path, arr)
    whole = read_cars(path)
    np.testing.assert_array_equal(whole, np.asarray(arr, dtype=np.float64))
    f = CarFile.open(path)
    assert (f.n_cars, f.n_columns) == arr.shape
    blocks = list(f.blocks(333))
    assert [len(b) for b in blocks] == [333, 333, 333, 1]
    for b in blocks:
        assert b.dtype == np.float64 and b.flags.c_contiguous
    assert np.concatenate(blocks).tobytes() == whole.tobytes()
    assert f.read(990, 2000).tobytes() == whole[990:].tobytes()


def test_car_file_of_a_csv_is_read_cars(tmp_path):
    path = tmp_path / "cars.csv"
    path.write_text("v,yaw,x,y\n3,0.1,1,2\n4,0.2,5,6\n")
    f = CarFile.open(path)
    np.testing.assert_array_equal(f.read(0, 2), read_cars(path))
    np.testing.assert_array_equal(f.read(1, 2), [[5, 6, 0.2, 4]])


@pytest.mark.parametrize(
    "row, col, value, match",
    [
        (700, 2, np.inf, "1 row\\(s\\) with NaN or inf, first car index 700"),
        (650, 3, 300.0, "v of car 650 is 300"),
        (900, 0, -2e8, "x of car 900 is -2e\\+08"),
    ],
)
def test_car_file_gives_read_cars_errors_from_any_block(tmp_path, row, col, value, match):
    cars = np.random.default_rng(3).uniform(-5, 5, (1000, 5))
    cars[row, col] = value
    path = tmp_path / "cars.npy"
    np.save(path, cars)
    with pytest.raises(InputError, match=match) as whole:
        read_cars(path)
    f = CarFile.open(path)
    f.read(0, 256)  # a good block reads
    with pytest.raises(InputError) as block:
        f.read(row - 10, row + 10)
    assert str(block.value) == str(whole.value)


@pytest.mark.parametrize(
    "arr, match",
    [
        (np.ones((3, 3)), "shape"),
        (np.ones((0, 5)), "no cars"),
        (np.ones((2, 5), dtype=bool), "dtype bool"),
        (np.ones((2, 5), dtype=complex), "dtype complex"),
    ],
)
def test_car_file_refuses_what_read_cars_refuses(tmp_path, arr, match):
    path = tmp_path / "cars.npy"
    np.save(path, arr)
    for read in (read_cars, CarFile.open):
        with pytest.raises(InputError, match=match):
            read(path)


# ---- writing poses a block at a time ----------------------------------------------------------


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_poses_file_writes_what_np_save_writes(tmp_path, dtype):
    poses = np.random.default_rng(4).normal(0, 10, (101, 7, 3)).astype(dtype)
    np.save(tmp_path / "ref.npy", poses)
    with PosesFile(tmp_path / "out.npy", 101, 7, dtype, 0.1) as f:
        for a in range(0, 101, 25):
            f.write(poses[a : a + 25])
    assert (tmp_path / "out.npy").read_bytes() == (tmp_path / "ref.npy").read_bytes()
    # rows rewritten in place: two runs of consecutive cars
    fixed = poses.copy()
    rows = np.array([3, 4, 5, 90])
    fixed[rows] = -1.0
    with PosesFile(tmp_path / "patched.npy", 101, 7, dtype, 0.1) as f:
        f.write(poses)
        f.patch(rows, fixed[rows])
    assert np.load(tmp_path / "patched.npy").tobytes() == fixed.tobytes()


def test_poses_file_csv_in_blocks_is_write_poses_whole(tmp_path):
    poses = np.random.default_rng(5).normal(0, 10, (45, 4, 3)).astype(np.float32)
    off = np.arange(45) % 7 == 0
    write_poses(tmp_path / "ref.csv", poses, 0.05, off_track=off)
    with PosesFile(tmp_path / "out.csv", 45, 4, np.float32, 0.05, off_track=True) as f:
        for a in range(0, 45, 10):
            f.write(poses[a : a + 10], off[a : a + 10])
    assert (tmp_path / "out.csv").read_text() == (tmp_path / "ref.csv").read_text()
    with PosesFile(tmp_path / "x.csv", 45, 4, np.float32, 0.05) as f:
        f.write(poses)
        with pytest.raises(ValueError, match="cannot rewrite"):
            f.patch(np.array([1]), poses[:1])


def test_poses_file_keeps_nothing_of_a_failed_or_short_write(tmp_path):
    poses = np.zeros((10, 2, 3), dtype=np.float32)
    out = tmp_path / "p.npy"
    out.write_bytes(b"old")
    with pytest.raises(KeyboardInterrupt):
        with PosesFile(out, 10, 2, np.float32, 0.1, force=True) as f:
            f.write(poses[:5])
            raise KeyboardInterrupt
    with pytest.raises(ValueError, match="wrote 5 of 10 cars"):
        with PosesFile(out, 10, 2, np.float32, 0.1, force=True) as f:
            f.write(poses[:5])
    with pytest.raises(ValueError, match="block of shape"):
        with PosesFile(out, 10, 2, np.float32, 0.1, force=True) as f:
            f.write(np.zeros((11, 2, 3)))
    with pytest.raises(InputError, match="exists"):
        PosesFile(out, 10, 2, np.float32, 0.1).__enter__()
    assert out.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["p.npy"]


# ---- the pieces: origin, off-track judge, writer thread -----------------------------------------


@pytest.mark.parametrize("origin", [[-14.0, -1.0], [999.0, -1000.0], [0.5, 3.25], [5e5, 5e6]])
def test_with_origin_keeps_every_bit_of_the_float64_sum(origin):
    """Bit for bit (signed zeros, subnormals, inf, NaN, every exponent) the float64 sum cast
    to the result's dtype, whether the sum runs in float32 or float64."""
    from fpe_jax.predict._batch import with_origin

    rng = np.random.default_rng(6)
    mantissa, exponent = rng.uniform(-1, 1, (3000, 10, 3)), rng.integers(-150, 40, (3000, 10, 3))
    poses = (mantissa * 2.0**exponent).astype(np.float32)
    poses.reshape(-1)[:8] = [-0.0, 0.0, np.inf, -np.inf, np.nan, 1e-45, -1e-45, 3.4e38]
    ref = poses.astype(np.float64)
    ref[..., :2] += origin
    ref = ref.astype(np.float32 if np.abs(origin).max() <= 1000 else np.float64)
    assert with_origin(poses.copy(), origin, block=977).tobytes() == ref.tobytes()
    out = np.empty(poses.shape, ref.dtype)
    assert with_origin(poses, origin, out=out) is out and out.tobytes() == ref.tobytes()
    strided = with_origin(poses[:, ::2].copy()[:, :], origin)  # rows of 15 values
    assert strided.tobytes() == np.ascontiguousarray(ref[:, ::2]).tobytes()


def test_near_path_judged_in_blocks_gives_the_one_shot_answers(oval_xy):
    from fpe_jax.geometry import NearPath, near_path

    rng = np.random.default_rng(7)
    pts = oval_xy[rng.integers(0, len(oval_xy), 5000)] + rng.normal(0, 3, (5000, 2))
    pts[:50] += 1e6  # far outside the raster
    judge = NearPath(oval_xy, max_cells=2000)  # fewer cells than points: the raster pays
    whole = near_path(pts, oval_xy)  # more cells than points: every point searched
    assert 0 < whole.sum() < len(pts)
    blocks = np.concatenate([judge(pts[a : a + 700], len(pts)) for a in range(0, 5000, 700)])
    assert blocks.tolist() == whole.tolist()
    assert judge._padded is not None  # the raster was built once and kept
    assert judge(pts[:300]).tolist() == whole[:300].tolist()  # few points: searched each


def test_overlapped_raises_the_consumers_error_and_stops_the_producer():
    made, consumed, closed = [], [], []

    def items():
        try:
            for k in range(100):
                made.append(k)
                yield (k,)
        finally:
            closed.append(True)

    def consume(k):
        if k == 3:
            raise OSError("disk full")
        consumed.append(k)

    with pytest.raises(OSError, match="disk full"):
        pipeline._overlapped(consume, items(), depth=2)
    assert consumed == [0, 1, 2] and closed == [True] and len(made) < 100
    done = []
    pipeline._overlapped(lambda k: done.append(k), ((k,) for k in range(50)), depth=2)
    assert done == list(range(50))
