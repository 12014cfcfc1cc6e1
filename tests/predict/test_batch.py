"""Chunked batch prediction (`fpe_jax.predict`), the projection grid, and `fpe batch`."""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fpe_jax import State, Track, predict_batch, presets, stack_params
from fpe_jax.cli import main
from fpe_jax.errors import InputError
from fpe_jax.io import read_cars, write_poses
from fpe_jax.predict import _batch as batch
from fpe_jax.predict._batch import (
    BatchPredictor,
    ProjectionGrid,
    cast_floats,
    chunk_size,
    predict_chunked,
    states_from_array,
)

# Most tests share these shapes, so each compiled chunk is reused instead of recompiled.
N_CARS, CHUNK = 70, 32


def _peanut_xy(n=400):
    """A closed loop with two concave flanks (points near it have two candidate branches)."""
    th = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    r = 8.0 + 3.0 * np.cos(2 * th)
    return np.column_stack([r * np.cos(th), 0.6 * r * np.sin(th)])


def _u_path_xy():
    """An open U-turn: two parallel legs 3 m apart joined by a half circle."""
    leg = np.linspace(0.0, 10.0, 60)
    arc = np.linspace(-np.pi / 2, np.pi / 2, 40)[1:-1]
    return np.vstack(
        [
            np.column_stack([leg, np.full_like(leg, -1.5)]),
            np.column_stack([10.0 + 1.5 * np.cos(arc), 1.5 * np.sin(arc)]),
            np.column_stack([leg[::-1], np.full_like(leg, 1.5)]),
        ]
    )


@pytest.fixture(scope="module")
def loop():
    return Track.from_waypoints(_peanut_xy())


@pytest.fixture(scope="module")
def loop_grid(loop):
    return ProjectionGrid.build(loop)


def _near_track_points(track, n, spread_m, seed=0):
    rng = np.random.default_rng(seed)
    i = rng.integers(0, track.n_points, n)
    return np.asarray(track.xy_m)[i] + rng.normal(0.0, spread_m, (n, 2)), i


def _cars(track, n, seed=0):
    """(n, 5) cars near the track, heading roughly along it, 0-6 m/s."""
    rng = np.random.default_rng(seed)
    p, i = _near_track_points(track, n, 0.3, seed)
    yaw = np.asarray(track.heading_rad)[i] + rng.normal(0.0, 0.2, n)
    return np.column_stack([p, yaw, rng.uniform(0.0, 6.0, n), rng.normal(0.0, 0.3, n)])


@jax.jit
def _project_all(track, xy_m):
    return jax.vmap(track.project)(xy_m)


def _exact_states(track, cars):
    """States whose arc-length hint is the exhaustive projection (what the grid must give)."""
    st = jax.tree.map(jnp.asarray, states_from_array(cars))
    s = _project_all(track, jnp.stack([st.x_m, st.y_m], axis=1))
    return dataclasses.replace(st, s_m=s)


# ---- projection grid ---------------------------------------------------------------------------


@pytest.mark.parametrize("closed", [True, False])
def test_grid_projection_equals_exhaustive_search(closed):
    track = Track.from_waypoints(_peanut_xy() if closed else _u_path_xy(), closed=closed)
    grid = ProjectionGrid.build(track)
    p, _ = _near_track_points(track, 4000, 0.6, seed=1)
    exact = np.asarray(_project_all(track, jnp.asarray(p)))
    s, ok = jax.jit(jax.vmap(lambda g, q: g.project(q), in_axes=(None, 0)))(grid, jnp.asarray(p))
    ok = np.asarray(ok)
    assert ok.mean() > 0.97  # within the 1.5 m margin almost every cell is complete
    np.testing.assert_allclose(np.asarray(s)[ok], exact[ok], atol=1e-9)


def test_grid_lists_only_segments_that_can_be_nearest():
    """A cell 1.2 m beside a straight path: every point of it has its nearest segment among the
    cell's candidates, and the list holds little more than those (the coarse bound alone kept
    17 segments here; the lattice test keeps 9, of which 3 are the nearest somewhere)."""
    xy = np.column_stack([np.linspace(0.0, 20.0, 201), np.zeros(201)])  # 0.1 m segments
    track = Track.from_waypoints(xy, closed=False)
    grid = ProjectionGrid.build(track, max_candidates=64)
    p = np.array([10.03, 1.2])
    row, ok = grid.locate(jnp.asarray(p))
    assert bool(ok)
    candidates = set(np.asarray(grid.candidates[int(row)]).tolist())
    origin, cell = np.asarray(grid.origin_m), float(grid.cell_m)
    u = np.linspace(0.0, 1.0, 60)
    points = origin + (np.floor((p - origin) / cell) + np.stack(np.meshgrid(u, u), -1)) * cell
    points = points.reshape(-1, 2)
    a, b = np.asarray(track.xy_m)[:-1], np.asarray(track.xy_m)[1:]
    dist = batch._seg_dist(points[:, None], a, b)  # (points, segments)
    nearest = set(np.argmin(dist, axis=1).tolist())
    assert nearest <= candidates and len(nearest) == 3
    assert len(candidates) <= 9


def test_grid_is_the_same_whatever_the_lattice_pass_size(loop, loop_grid, monkeypatch):
    """The lattice test runs over whole cells in passes of a bounded size: passes of 7 pairs,
    far fewer than most cells hold, give the default build's grid exactly."""
    monkeypatch.setattr(
        batch, "_lattice_test", functools.partial(batch._lattice_test, pairs_per_pass=7)
    )
    small = ProjectionGrid.build(loop)
    for a, b in zip(jax.tree.leaves(small), jax.tree.leaves(loop_grid)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert small.shape == loop_grid.shape and small.n_complete == loop_grid.n_complete


def test_levine_grid_of_16_covers_every_point_within_half_a_metre(shared_data, monkeypatch):
    """On the real Levine loop, cells of at most 16 segments (the default) answer every point
    within 0.5 m of the centre line, exactly; the coarse bound alone leaves some of them to the
    exhaustive fallback (cells it lists more than 16 segments for)."""
    wps = np.loadtxt(shared_data / "levine" / "levine-waypoints.csv", delimiter=",")[:, :2]
    track = Track.from_waypoints(wps)
    normal = np.stack([-np.sin(track.heading_rad), np.cos(track.heading_rad)], axis=1)
    offsets = np.linspace(-0.5, 0.5, 11)
    p = jnp.asarray((track.xy_m[:, None] + offsets[:, None] * normal[:, None]).reshape(-1, 2))
    project = jax.jit(jax.vmap(lambda g, q: g.project(q), in_axes=(None, 0)))
    s, ok = project(ProjectionGrid.build(track), p)
    assert bool(np.all(ok))
    # as near as the exhaustive search's point (points on a vertex's normal tie between segments)
    dist = jax.jit(jax.vmap(lambda t, q, s: jnp.linalg.norm(q - t.point_at(s)), (None, 0, 0)))
    np.testing.assert_allclose(dist(track, p, s), dist(track, p, _project_all(track, p)), atol=1e-9)
    monkeypatch.setattr(batch, "_lattice_test", lambda cell, *_: np.ones(len(cell), dtype=bool))
    _, ok_coarse = project(ProjectionGrid.build(track), p)
    assert not np.all(ok_coarse)


def test_grid_flags_points_it_cannot_answer(loop, loop_grid):
    far = jnp.asarray([[100.0, 100.0], [0.0, 0.0], [-50.0, 3.0]])  # off-grid; centre of the loop
    _, ok = jax.jit(jax.vmap(lambda g, q: g.project(q), in_axes=(None, 0)))(loop_grid, far)
    assert not np.any(np.asarray(ok))


def test_grid_project_single_point_under_jit(loop, loop_grid):
    p = loop.xy_m[17] + jnp.asarray([0.05, -0.02])
    s, ok = jax.jit(lambda g, q: g.project(q))(loop_grid, p)
    assert bool(ok)
    np.testing.assert_allclose(
        float(s), float(jax.jit(lambda t, q: t.project(q))(loop, p)), atol=1e-9
    )


# ---- chunked prediction ------------------------------------------------------------------------


@pytest.mark.parametrize("preset", ["default", "pure-pursuit", "seed", "ctrv"])
def test_chunked_equals_predict_batch_float64(loop, loop_grid, preset):
    cars = _cars(loop, N_CARS)  # 2 chunks of 32 + a padded one
    params = presets[preset]
    ref = np.asarray(predict_batch(params, _exact_states(loop, cars), loop))
    info = {}
    out = predict_chunked(
        params, cars, loop, dtype="float64", chunk=CHUNK, grid=loop_grid, info=info
    )
    assert out.shape == (N_CARS, params.settings.horizon, 3) and out.dtype == np.float64
    assert info["chunk"] == CHUNK and info["n_chunks"] == 3 and info["n_off_grid"] == 0
    assert info["tail_chunk"] == 8  # the last 6 cars run in the next power of two, not in 32
    np.testing.assert_allclose(out, ref, atol=1e-9)


def test_float32_is_default_and_close_to_float64(loop, loop_grid):
    cars = _cars(loop, N_CARS, seed=3)
    p = presets["default"]
    out32 = predict_chunked(p, cars, loop, grid=loop_grid, chunk=CHUNK)
    out64 = predict_chunked(p, cars, loop, dtype="float64", grid=loop_grid, chunk=CHUNK)
    assert out32.dtype == np.float32
    np.testing.assert_allclose(out32[..., :2], out64[..., :2], atol=2e-3)


def test_stacked_parameter_sets(loop, loop_grid):
    cars = _cars(loop, N_CARS, seed=4)
    sets = [presets["default"], presets["pure-pursuit"], presets["linear"]]
    stacked = stack_params(sets)
    out = predict_chunked(stacked, cars, loop, dtype="float64", chunk=CHUNK, grid=loop_grid)
    assert out.shape == (3, N_CARS, 10, 3)
    states = _exact_states(loop, cars)
    core = np.asarray(predict_batch(stacked, states, loop))  # the core's (P, N, H, 3) path
    np.testing.assert_allclose(out, core, atol=1e-9)
    for k, params in enumerate(sets):
        np.testing.assert_allclose(core[k], np.asarray(predict_batch(params, states, loop)))


def test_off_grid_cars_use_the_exhaustive_projection(loop, loop_grid):
    cars = _cars(loop, N_CARS, seed=5)
    cars[3, :2] = [40.0, -30.0]  # far outside the grid
    cars[7, :2] = [0.0, 0.0]  # centre of the loop: > margin from the track
    info = {}
    out = predict_chunked(
        presets["default"], cars, loop, dtype="float64", grid=loop_grid, chunk=CHUNK, info=info
    )
    assert info["n_off_grid"] == 2
    ref = np.asarray(predict_batch(presets["default"], _exact_states(loop, cars), loop))
    np.testing.assert_allclose(out, ref, atol=1e-9)


def test_state_input_keeps_given_hints(loop, loop_grid):
    cars = _cars(loop, N_CARS, seed=6)
    exact = _exact_states(loop, cars)
    hint = np.asarray(exact.s_m).copy()
    hint[::2] = np.nan  # unknown: projected by the grid
    st = dataclasses.replace(states_from_array(cars), s_m=hint)
    out = predict_chunked(
        presets["default"], st, loop, dtype="float64", grid=loop_grid, chunk=CHUNK
    )
    ref = np.asarray(predict_batch(presets["default"], exact, loop))
    np.testing.assert_allclose(out, ref, atol=1e-9)


def test_chunks_with_every_hint_given_equal_predict_batch(loop, loop_grid):
    """Chunks whose cars all carry hints skip the grid; cars off the grid then need no
    exhaustive search, and a chunk with one unknown hint still projects it."""
    cars = _cars(loop, N_CARS, seed=7)
    cars[:3, :2] = [[100.0, 100.0], [0.0, 0.0], [-50.0, 3.0]]  # off the grid
    exact = _exact_states(loop, cars)
    hint = np.asarray(exact.s_m).copy()
    hint[-1] = np.nan  # the last chunk has one car to project
    st = dataclasses.replace(states_from_array(cars), s_m=hint)
    info = {}
    out = predict_chunked(
        presets["default"], st, loop, dtype="float64", grid=loop_grid, chunk=CHUNK, info=info
    )
    assert info["n_off_grid"] == 0
    ref = np.asarray(predict_batch(presets["default"], exact, loop))
    np.testing.assert_allclose(out, ref, atol=1e-9)  # other shapes: XLA may round differently


def test_single_car_and_empty_batch(loop, loop_grid):
    info = {}
    one = predict_chunked(presets["default"], _cars(loop, 1), loop, grid=loop_grid, info=info)
    assert one.shape == (1, 10, 3) and info["chunk"] == 1
    none = predict_chunked(presets["default"], np.zeros((0, 4)), loop, grid=loop_grid)
    assert none.shape == (0, 10, 3)


def test_writes_into_a_given_array(loop, loop_grid, tmp_path):
    cars = _cars(loop, N_CARS, seed=7)
    mm = np.lib.format.open_memmap(
        tmp_path / "o.npy", mode="w+", dtype=np.float32, shape=(N_CARS, 10, 3)
    )
    res = predict_chunked(presets["default"], cars, loop, grid=loop_grid, chunk=CHUNK, out=mm)
    assert res is mm
    mm.flush()
    np.testing.assert_array_equal(np.load(tmp_path / "o.npy"), res)
    with pytest.raises(InputError, match="shape"):
        predict_chunked(presets["default"], cars, loop, grid=loop_grid, out=np.empty((3, 10, 3)))


def test_progress_reports_every_chunk(loop, loop_grid):
    seen = []
    predict_chunked(
        presets["default"],
        _cars(loop, N_CARS),
        loop,
        grid=loop_grid,
        chunk=32,
        progress=lambda done, n: seen.append((done, n)),
    )
    assert seen == [(32, 70), (64, 70), (70, 70)]


def test_one_worker_equals_several(loop, loop_grid):
    """Chunks computed on threads land in the same places as chunks computed one by one."""
    cars = _cars(loop, N_CARS, seed=10)
    kw = dict(grid=loop_grid, chunk=CHUNK)
    one = BatchPredictor(presets["default"], loop, workers=1, **kw)(cars)
    many = BatchPredictor(presets["default"], loop, workers=3, **kw)(cars)
    np.testing.assert_array_equal(one, many)


def test_repeated_calls_run_all_chunks_at_once_with_the_same_result(loop, loop_grid):
    """The first call runs its first chunk alone (it compiles); later calls put every chunk on
    the threads at once, a smaller last chunk included."""
    cars = _cars(loop, N_CARS, seed=11)
    predictor = BatchPredictor(presets["default"], loop, grid=loop_grid, chunk=CHUNK, workers=3)
    first = predictor(cars)
    names = ("x_m", "y_m", "yaw_rad", "v_mps", "yaw_rate_rps", "s_m")
    assert predictor._compiled == {(names, CHUNK)}
    np.testing.assert_array_equal(predictor(cars), first)
    info = {}
    np.testing.assert_array_equal(predictor(cars[:CHUNK], info=info), first[:CHUNK])
    assert info["tail_chunk"] == 0
    np.testing.assert_array_equal(predictor(cars[:20], info=info), first[:20])
    assert info["chunk"] == CHUNK and info["tail_chunk"] == 0  # one chunk: no separate tail


def test_chunk_size_rules():
    assert chunk_size(1) == 1
    assert chunk_size(1000) == 1024
    assert chunk_size(10**6) == 1 << 14
    assert chunk_size(1000, chunk=300) == 300
    assert chunk_size(5, chunk=8, multiple=4) == 8
    assert chunk_size(3, chunk=8, multiple=3) == 6
    with pytest.raises(InputError):
        chunk_size(10, chunk=0)


def test_cast_floats_keeps_static_and_integer_fields(loop, loop_grid):
    t32 = cast_floats(loop, "float32")
    assert t32.xy_m.dtype == np.float32 and t32.closed == loop.closed
    g32 = cast_floats(loop_grid, np.float32)
    assert g32.keys.dtype == np.int32 and g32.candidates.dtype == np.int32
    assert g32.geometry.dtype == np.float32
    assert g32.origin_m.dtype == np.float32 and g32.shape == loop_grid.shape
    with pytest.raises(InputError, match="dtype"):
        cast_floats(loop, "float16")


def test_states_from_array_shapes():
    st = states_from_array(np.ones((3, 4)))
    assert np.all(st.yaw_rate_rps == 0) and st.s_m is None
    with pytest.raises(InputError, match="shape"):
        states_from_array(np.ones((3, 6)))


# ---- files and the CLI -------------------------------------------------------------------------


def test_read_cars_csv_and_npy(tmp_path):
    p = tmp_path / "cars.csv"
    p.write_text("x,y,yaw,v,yaw_rate\n1,2,0.1,3,0.05\n4,5,0.2,6,0\n")
    np.testing.assert_allclose(read_cars(p), [[1, 2, 0.1, 3, 0.05], [4, 5, 0.2, 6, 0]])
    q = tmp_path / "cars4.csv"
    q.write_text("v,yaw,x,y\n3,0.1,1,2\n")  # any column order
    np.testing.assert_allclose(read_cars(q), [[1, 2, 0.1, 3]])
    n = tmp_path / "cars.npy"
    np.save(n, np.ones((2, 5), dtype=np.float32))
    assert read_cars(n).shape == (2, 5)


@pytest.mark.parametrize(
    "name, content, match",
    [
        ("a.csv", "x,y,yaw\n1,2,3\n", "lacks v"),
        ("b.csv", "1,2,3,4\n", "no header"),
        ("c.csv", "x,y,yaw,v\n1,2,3,4\n1,nan,3,4\n", "NaN or inf, first car index 1"),
        ("d.csv", "x,y,yaw,v\n", "no data rows|no cars"),
    ],
)
def test_read_cars_errors(tmp_path, name, content, match):
    p = tmp_path / name
    p.write_text(content)
    with pytest.raises(InputError, match=match):
        read_cars(p)


def test_read_cars_npy_errors(tmp_path):
    p = tmp_path / "bad.npy"
    np.save(p, np.ones((3, 3)))
    with pytest.raises(InputError, match="shape"):
        read_cars(p)
    q = tmp_path / "junk.npy"
    q.write_bytes(b"not an array")
    with pytest.raises(InputError, match="npy"):
        read_cars(q)
    with pytest.raises(InputError, match="does not exist"):
        read_cars(tmp_path / "missing.npy")


def test_write_poses_csv_layout_and_overwrite(tmp_path):
    poses = np.arange(2 * 3 * 3, dtype=np.float32).reshape(2, 3, 3)
    out = tmp_path / "p.csv"
    write_poses(out, poses, 0.1)
    rows = out.read_text().splitlines()
    assert rows[0] == "car,step,horizon_s,x,y,yaw"
    assert rows[1] == "0,1,0.100,0.000000,1.000000,2.000000"
    assert rows[6] == "1,3,0.300,15.000000,16.000000,17.000000"
    with pytest.raises(InputError, match="exists"):
        write_poses(out, poses, 0.1)
    write_poses(out, poses, 0.1, force=True)
    with pytest.raises(InputError, match="OUT.npy or OUT.csv"):
        write_poses(tmp_path / "p.txt", poses, 0.1)


@pytest.fixture()
def cli_files(tmp_path, loop):
    wp = tmp_path / "wp.csv"
    np.savetxt(wp, _peanut_xy(), delimiter=",")
    cars = _cars(loop, N_CARS, seed=8)
    csv = tmp_path / "cars.csv"
    np.savetxt(csv, cars, delimiter=",", header="x,y,yaw,v,yaw_rate", comments="")
    npy = tmp_path / "cars.npy"
    np.save(npy, cars[:, :4])
    return wp, csv, npy, cars


def test_cli_batch_npy_and_csv(tmp_path, cli_files, loop):
    wp, csv, npy, cars = cli_files
    out = tmp_path / "o.npy"
    args = [str(csv), "--waypoints", str(wp), "--preset", "default", "--out", str(out)]
    assert main(["batch", *args, "--dtype", "float64", "--chunk", str(CHUNK)]) == 0
    poses = np.load(out)
    assert poses.shape == (N_CARS, 10, 3) and poses.dtype == np.float64
    track = Track.from_waypoints(_peanut_xy())
    ref = np.asarray(predict_batch(presets["default"], _exact_states(track, cars), track))
    np.testing.assert_allclose(poses, ref, atol=1e-9)
    assert main(["batch", *args]) == 2  # exists, no --force
    assert main(["batch", *args, "--force", "--chunk", str(CHUNK)]) == 0
    assert np.load(out).dtype == np.float32

    out_csv = tmp_path / "o.csv"
    common = ["--waypoints", str(wp), "--preset", "seed", "--chunk", str(CHUNK)]
    assert main(["batch", str(npy), *common, "--out", str(out_csv)]) == 0
    table = np.loadtxt(out_csv, delimiter=",", skiprows=1)
    assert table.shape == (N_CARS * 10, 7)  # car, step, horizon_s, x, y, yaw, off_track
    assert not table[:, 6].any()
    np.testing.assert_allclose(table[:10, 2], np.arange(1, 11) * 0.1)


def test_cli_batch_reports_bad_input(tmp_path, cli_files, capsys):
    wp, csv, _, _ = cli_files
    bad = tmp_path / "bad.csv"
    bad.write_text("x,y,v\n1,2,3\n")
    common = ["--waypoints", str(wp), "--preset", "default"]
    assert main(["batch", str(bad), *common, "--out", str(tmp_path / "o.npy")]) == 2
    err = capsys.readouterr().err
    assert "bad.csv" in err and "lacks yaw" in err and err.count("\n") == 1
    assert main(["batch", str(csv), *common, "--out", str(tmp_path / "o.txt")]) == 2
    assert "OUT.npy or OUT.csv" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # argparse: exactly one of --config / --preset
        main(["batch", str(csv), "--waypoints", str(wp), "--out", str(tmp_path / "o.npy")])


def test_jit_and_vmap_of_grid_locate(loop_grid):
    p = jnp.asarray([[0.0, 0.0], [8.0, 0.0]])
    flat, ok = jax.jit(jax.vmap(loop_grid.locate))(p)
    assert flat.shape == (2,) and ok.dtype == jnp.bool_


def test_state_fields_follow_predict_batch_defaults(loop, loop_grid):
    """A State built by hand (yaw rate, course, age defaulted) predicts as the array form."""
    cars = _cars(loop, CHUNK, seed=9)
    st = State(
        x_m=jnp.asarray(cars[:, 0]),
        y_m=jnp.asarray(cars[:, 1]),
        yaw_rad=jnp.asarray(cars[:, 2]),
        v_mps=jnp.asarray(cars[:, 3]),
    )
    kw = dict(dtype="float64", grid=loop_grid, chunk=CHUNK)
    a = predict_chunked(presets["ctrv"], st, loop, **kw)
    b = predict_chunked(presets["ctrv"], cars[:, :4], loop, **kw)
    np.testing.assert_allclose(a, b)


@pytest.mark.parametrize("origin", [[-12.0, 7.0], [5e5, 5e6]])
def test_with_origin_is_the_float64_sum_cast_back(origin):
    """`with_origin` adds the map origin in float64, block by block and in place where the
    poses' dtype can hold the result, exactly as adding it to a float64 copy and casting back."""
    from fpe_jax.predict._batch import with_origin

    rng = np.random.default_rng(3)
    poses = rng.normal(0.0, 30.0, (1001, 10, 3)).astype(np.float32)
    origin = np.asarray(origin)
    ref = np.array(poses, dtype=np.float64)
    ref[..., :2] += origin
    ref = ref.astype(poses.dtype if np.abs(origin).max() <= 1000.0 else np.float64)
    out = with_origin(poses.copy(), origin, block=97)
    assert out.dtype == ref.dtype
    np.testing.assert_array_equal(out, ref)
