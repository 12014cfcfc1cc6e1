"""The NumPy-only runner: parity with the JAX predictor, no JAX imported, streaming CLI, errors."""

import importlib
import inspect
import json
import select
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import CASES, CHECK_NO_JAX, NO_JAX, assert_parity, predictor, run_drive, track_drive

from fpe_jax import Params, Settings, Track, predict_drive, presets
from fpe_jax.errors import InputError
from fpe_jax.io.config import params_to_config, write_config
from fpe_jax.io.stream import _Skip, parse_line
from fpe_jax.model import _params as params
from fpe_jax.runner import _runner as runner
from fpe_jax.runner._runner import GoalScan, Runner, RunnerPath, run_stream
from fpe_jax.spec import SCHEMA_VERSION

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def sim_drive():
    return track_drive("oval")


@pytest.fixture(scope="module")
def levine():
    return track_drive("levine")


def write_waypoints(path: Path, xy: np.ndarray) -> Path:
    np.savetxt(path, xy, delimiter=",", fmt="%.17g")  # exact round trip of the floats
    return path


# ---- the constants the runner mirrors --------------------------------------------------------


def test_the_runner_shares_the_models_constants():
    """The runner defines none of the model's numbers itself: it takes the JAX-free modules'
    (`fpe_jax.model._constants`, `fpe_jax.geometry._path`, `fpe_jax.spec`), which the JAX model
    uses too."""
    from fpe_jax.geometry import _path
    from fpe_jax.model import _constants, _estimate, _kalman
    from fpe_jax.model import _rollout as rollout

    assert (runner.BLEND_MODES, runner.MODELS) == (params.BLEND_MODES, params.MODELS)
    shared = {n: getattr(_constants, n) for n in dir(_constants) if n.isupper()}
    assert len(shared) == 9
    for name in shared:
        assert getattr(runner, name) is getattr(_constants, name), name
        users = [m for m in (rollout, _kalman, _estimate) if hasattr(m, name)]
        assert users and all(getattr(m, name) is shared[name] for m in users), name
    # both projections search the window `_path.window_points` sizes from the same spacing
    assert runner.window_points is _path.window_points
    from fpe_jax.geometry import builtin_track

    hairpin = builtin_track("hairpin")[0]
    for wp in (hairpin, hairpin[::7] * 1.3):  # windows of 20/40 and 21/41 points
        path, track = runner.RunnerPath(wp), Track.from_waypoints(wp)
        n_back, n_ahead = track.window
        assert (path._window_lo, path._window_hi) == (-n_back, n_ahead)
        assert n_back * path.ds_m >= _path.WINDOW_BEHIND_M > (n_back - 1) * path.ds_m
        assert n_ahead * path.ds_m >= _path.WINDOW_AHEAD_M > (n_ahead - 1) * path.ds_m
    local = inspect.signature(Track.project_local).parameters
    assert local["iters"].default is _path.LOCAL_PROJECTION_ITERS is runner.LOCAL_PROJECTION_ITERS
    src = inspect.getsource(_estimate.track_frame_window)
    assert "iters=TRACK_FRAME_ITERS" in src
    # no assignment of a shared name in the runner's own source
    runner_src = inspect.getsource(importlib.import_module("fpe_jax.runner._runner"))
    for name in [*shared, "LOCAL_PROJECTION_ITERS"]:
        assert f"\n{name} = " not in runner_src, name


# ---- parity with the JAX predictor -----------------------------------------------------------


@pytest.mark.parametrize(("track", "name"), CASES)
def test_parity_with_the_jax_predictor(track, name):
    wp, drive = track_drive(track)
    p = predictor(name)
    _, pred_jax = predict_drive(p, drive, Track.from_waypoints(wp))
    assert_parity(run_drive(Runner(params_to_config(p), wp), drive), pred_jax)


def line_params(wp, drive, upto_s: float, estimator: str = "theil-sen") -> Params:
    """A line-model Params learned from the drive's first upto_s seconds (the rest of the track
    uncovered when that is less than a lap: the fallback is tested too)."""
    from fpe_jax.model._line import learn_line

    profile = learn_line([drive.slice_time(-np.inf, upto_s)], Track.from_waypoints(wp))
    return Params.create(
        Settings(model="line", estimator=estimator),
        delay_s=0.12,
        offset_tau_s=0.8,
        speed_tau_s=0.3,
        pace_return_1ps=0.7,
        position_smoothing=0.6,
        **profile,
    )


@pytest.mark.parametrize(
    "case", ["sim", "sim-partial", "levine", "sim-kalman", "sim-partial-kalman", "levine-kalman"]
)
def test_parity_of_the_line_model(sim_drive, levine, case):
    from fpe_jax.geometry._path import waypoints_sha256

    wp, drive = levine if case.startswith("levine") else sim_drive
    estimator = "kalman" if case.endswith("kalman") else "theil-sen"
    p = line_params(wp, drive, 4.0 if "partial" in case else np.inf, estimator)
    cov = np.asarray(p.line_coverage)
    assert (cov.min() == 0.0) == ("partial" in case)
    _, pred_jax = predict_drive(p, drive, Track.from_waypoints(wp))
    cfg = params_to_config(p, line={"waypoints_sha256": waypoints_sha256(wp)})
    assert_parity(run_drive(Runner(cfg, wp), drive), pred_jax)


def test_reset_starts_a_new_drive(sim_drive):
    wp, drive = sim_drive
    r = Runner(params_to_config(presets["default"]), wp)
    first = run_drive(r, drive)
    r.reset()
    np.testing.assert_array_equal(run_drive(r, drive), first)


@pytest.mark.parametrize("closed", [True, False])
def test_path_geometry_matches_track(sim_drive, closed):
    """Every query, on a loop (across its seam, over several laps) and on an open path (past its
    ends, where the window is clamped)."""
    wp = sim_drive[0] if closed else sim_drive[0][: len(sim_drive[0]) // 2]
    track, path = Track.from_waypoints(wp), RunnerPath(wp)
    assert path.closed == track.closed == closed
    rng = np.random.default_rng(1)
    span = (-3.0, 2 * path.length_m + 3.0) if closed else (-1.0, path.length_m + 1.0)
    s = rng.uniform(*span, 300)
    s[:4] = [0.0, path.length_m, -1e-9, path.length_m - 1e-9]
    p = np.stack([path.point_at(si) for si in s]) + rng.normal(0, 0.3, (300, 2))
    hint = s + rng.normal(0, 0.5, 300)

    @jax.jit
    @jax.vmap
    def want(p, s, hint):
        return jnp.stack(
            [
                track.project(p),
                track.project_window(p, hint),
                track.project_local(p, hint),
                *track.point_at(s),
            ]
        )

    got = [
        [
            path.project(*pi),
            path.project_window(*pi, h),
            path.project_local(*pi, h),
            *path.point_at(si),
        ]
        for pi, si, h in zip(p, s, hint)
    ]
    np.testing.assert_allclose(np.array(got), want(p, s, hint), rtol=0, atol=1e-9)


@pytest.mark.parametrize("closed", [True, False])
@pytest.mark.parametrize("name", ["default", "heading-blend", "shrunk-speed"])
def test_predict_from_state_on_arrays_equals_one_car_at_a_time(sim_drive, name, closed):
    """The vectorised path (the SciPy baseline's model) gives each car's scalar prediction, on a
    loop and past the ends of an open path; with_params swaps the values, keeps the track."""
    wp = sim_drive[0] if closed else sim_drive[0][: len(sim_drive[0]) // 2]
    base = Runner(params_to_config(Params.create(predictor(name).settings, weights=1.0)), wp)
    r = base.with_params(predictor(name).physical())
    assert r.path is base.path
    want_r = Runner(params_to_config(predictor(name)), wp)
    rng = np.random.default_rng(4)
    n = 50
    s = rng.uniform(-2.0, r.path.length_m + 2.0, n)
    xy = np.stack([r.path.point_at(si) for si in s]) + rng.normal(0, 0.3, (n, 2))
    yaw, v = rng.uniform(-np.pi, np.pi, n), rng.uniform(0.0, 4.0, n)
    got = r.predict_from_state(xy[:, 0], xy[:, 1], yaw, v, s)
    one = [r.predict_from_state(*xy[k], yaw[k], v[k], s[k]) for k in range(n)]
    want = [want_r.predict_from_state(*xy[k], yaw[k], v[k], s[k]) for k in range(n)]
    assert got.shape == (n, r.horizon, 3)
    np.testing.assert_allclose(got, np.stack(one), rtol=0, atol=1e-9)
    np.testing.assert_array_equal(np.stack(one), np.stack(want))


def test_goal_scan_equals_full_scan(levine):
    wp = levine[0]
    rng = np.random.default_rng(2)
    pts = wp[rng.integers(len(wp), size=400)] + rng.normal(0, 1.5, (400, 2))
    for radius in (0.3, 2.0):
        scan = GoalScan(wp, radius)
        for x, y in pts:
            within = np.flatnonzero(np.hypot(wp[:, 0] - x, wp[:, 1] - y) <= radius)
            assert scan.goal(x, y) == tuple(wp[within[-1] if len(within) else 0])
    far = GoalScan(wp, 2.0).goal(1e4, 1e4)  # no waypoint near: row 0, as the original
    assert far == tuple(wp[0])


# ---- without JAX -----------------------------------------------------------------------------


def run_python(code: str, *args: str, stdin: str = "") -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", NO_JAX + code + CHECK_NO_JAX, *args],
        input=stdin,
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=60,
    )


def test_runner_works_where_jax_cannot_be_imported(tmp_path, sim_drive):
    wp, drive = sim_drive
    p = predictor("heading-blend")
    write_config(tmp_path / "cfg.json", params_to_config(p))
    write_waypoints(tmp_path / "wp.csv", wp)
    np.save(tmp_path / "obs.npy", np.column_stack([drive.t_s, drive.xy_m, drive.yaw_rad]))
    code = """
import numpy as np
from fpe_jax.runner._runner import Runner
r = Runner.from_config(sys.argv[1] + "/cfg.json", sys.argv[1] + "/wp.csv")
obs = np.load(sys.argv[1] + "/obs.npy")
np.save(sys.argv[1] + "/pred.npy", np.stack([r.update(*row) for row in obs]))
try:
    import jax
except ImportError:
    pass
else:
    raise AssertionError("the blocker let jax in")
"""
    proc = run_python(code, str(tmp_path))
    assert proc.returncode == 0, proc.stderr
    _, pred_jax = predict_drive(p, drive, Track.from_waypoints(wp))
    assert_parity(np.load(tmp_path / "pred.npy"), pred_jax)


CLI = "from fpe_jax.cli import main\nrc = main(sys.argv[1:])\n"


def test_fpe_run_streams_csv_and_json_without_jax(tmp_path, sim_drive):
    wp, drive = sim_drive
    cfg = params_to_config(presets["default"])
    write_config(tmp_path / "cfg.json", cfg)
    write_waypoints(tmp_path / "wp.csv", wp)
    obs = np.column_stack([drive.t_s, drive.xy_m, drive.yaw_rad])[:30]
    rows = [tuple(float(v) for v in row) for row in obs]
    lines = ["t,x,y,yaw"]  # header, then CSV and JSON lines mixed, and two bad lines
    for k, (t, x, y, yaw) in enumerate(rows):
        if k % 2:
            lines.append(json.dumps({"t": t, "x": x, "y": y, "yaw": yaw}))
        else:
            lines.append(f"{t!r},{x!r},{y!r},{yaw!r}")
    lines.insert(5, "1.0,oops,2.0,0.1")  # line 6
    lines.insert(9, '{"t": 1.0, "x": 2.0}')  # line 10
    lines.append("")  # a trailing blank line is no observation
    proc = run_python(
        CLI + "sys.stdout.flush()\nsys.exit(rc)",
        "run",
        "--config",
        str(tmp_path / "cfg.json"),
        "--waypoints",
        str(tmp_path / "wp.csv"),
        stdin="\n".join(lines) + "\n",
    )
    assert proc.returncode == 0, proc.stderr
    err = proc.stderr.strip().splitlines()
    assert len(err) == 2
    assert err[0].startswith("fpe run: line 6:") and "'oops'" in err[0] and "skipped" in err[0]
    assert err[1].startswith("fpe run: line 10:") and "lacks t, x or y" in err[1]
    out = [json.loads(line) for line in proc.stdout.splitlines()]
    assert [o["stamp"] for o in out] == [r[0] for r in rows]
    r = Runner(cfg, wp)
    want = np.stack([r.update(*row) for row in rows])
    np.testing.assert_array_equal(np.array([o["poses"] for o in out]), want)


def test_fpe_run_flushes_each_prediction(tmp_path, sim_drive):
    """An on-car process writes one observation and waits for its prediction."""
    wp = sim_drive[0]
    write_config(tmp_path / "cfg.json", params_to_config(presets["ctrv"]))
    write_waypoints(tmp_path / "wp.csv", wp)
    cmd = [sys.executable, "-m", "fpe_jax.cli", "run", "--config", str(tmp_path / "cfg.json")]
    cmd += ["--waypoints", str(tmp_path / "wp.csv")]
    with subprocess.Popen(
        cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=ROOT
    ) as proc:
        try:
            proc.stdin.write("t,x,y\n")
            for k in range(3):
                proc.stdin.write(f"{0.1 * k},{wp[k * 3, 0]},{wp[k * 3, 1]}\n")
                proc.stdin.flush()
                # the reply must come while stdin stays open: the line was flushed at once
                ready, _, _ = select.select([proc.stdout], [], [], 30.0)
                assert ready, "no prediction within 30 s of its observation"
                reply = json.loads(proc.stdout.readline())
                assert reply["stamp"] == pytest.approx(0.1 * k) and len(reply["poses"]) == 10
            proc.stdin.close()
            assert proc.wait(timeout=30) == 0
        finally:
            proc.kill()


# ---- errors ----------------------------------------------------------------------------------


def test_from_config_rejects_newer_schema_and_missing_fields(tmp_path, sim_drive):
    wp = write_waypoints(tmp_path / "wp.csv", sim_drive[0])
    cfg = params_to_config(presets["default"])
    newer = dict(cfg, schema_version=99)
    (tmp_path / "newer.json").write_text(json.dumps(newer))
    with pytest.raises(InputError, match="schema_version 99 is not supported"):
        Runner.from_config(tmp_path / "newer.json", wp)
    lacking = json.loads(json.dumps(cfg))
    del lacking["params"]["delay_s"]
    (tmp_path / "lacking.json").write_text(json.dumps(lacking))
    with pytest.raises(InputError, match="'params' lacks delay_s"):
        Runner.from_config(tmp_path / "lacking.json", wp)
    for section, key, value, message in (
        ("settings", "model", "magic", "settings.model is 'magic'"),
        ("settings", "dt_s", "fast", "settings.dt_s is 'fast'"),
        ("settings", "history", 2.5, "settings.history is 2.5"),
        ("params", "weights", [0.5] * 3, "params.weights is"),
        ("params", "delay_s", None, "params.delay_s is None"),
    ):
        bad = json.loads(json.dumps(cfg))
        bad[section][key] = value
        with pytest.raises(InputError, match=message):
            Runner(bad, sim_drive[0])
    with pytest.raises(InputError, match="no such config file"):
        Runner.from_config(tmp_path / "absent.json", wp)


def test_fpe_run_reports_a_newer_schema_in_one_line(tmp_path, sim_drive):
    wp = write_waypoints(tmp_path / "wp.csv", sim_drive[0])
    cfg = dict(params_to_config(presets["default"]), schema_version=SCHEMA_VERSION + 1)
    (tmp_path / "cfg.json").write_text(json.dumps(cfg))
    proc = run_python(
        CLI + "sys.exit(rc)", "run", "--config", str(tmp_path / "cfg.json"), "--waypoints", str(wp)
    )
    assert proc.returncode == 2
    newer = f"schema_version {SCHEMA_VERSION + 1} is not supported"
    assert proc.stderr.count("\n") == 1 and newer in proc.stderr


def test_update_rejects_bad_observations_and_keeps_its_state(sim_drive):
    wp = sim_drive[0]
    r = Runner(params_to_config(presets["default"]), wp)
    r.update(0.0, *wp[0])
    before = r.update(0.1, *wp[2])
    with pytest.raises(InputError, match="not after"):
        r.update(0.1, *wp[4])
    with pytest.raises(InputError, match="finite"):
        r.update(0.2, float("nan"), 1.0)
    fresh = Runner(params_to_config(presets["default"]), wp)
    fresh.update(0.0, *wp[0])
    fresh.update(0.1, *wp[2])
    np.testing.assert_array_equal(r.update(0.2, *wp[4]), fresh.update(0.2, *wp[4]))
    assert before.shape == (10, 3)


def test_parse_line():
    assert parse_line("1.5,2,3,0.25", None, None) == (1.5, 2.0, 3.0, 0.25)
    assert parse_line("1.5,2,3,", None, None) == (1.5, 2.0, 3.0, None)
    assert parse_line('{"t": 1, "x": 2, "y": 3, "yaw": null}', None, None) == (1.0, 2.0, 3.0, None)
    assert parse_line('{"t": 1, "x": 2, "y": 3, "yaw": 0.5}', None, None) == (1.0, 2.0, 3.0, 0.5)
    assert parse_line("9,1,2,3", (3, 1, 2, None, 4), None) == (3.0, 1.0, 2.0, None)
    assert parse_line("1,2,0", None, 10.0) == (None, 1.0, 2.0, None)  # x,y,z: z unused
    assert parse_line('{"x": 1, "y": 2}', None, 10.0) == (None, 1.0, 2.0, None)
    for bad in ("1,2", "1,2,3,4,5", "a,2,3,4", '{"t": 1, "x": true, "y": 2}', "{not json"):
        with pytest.raises(_Skip):
            parse_line(bad, None, None)
    # the layout of the whole stream is wrong: x,y,z without a rate, a stamp with one
    for text, rate in (("1.5, 2, 3", None), ('{"t": 1, "x": 2, "y": 3}', 10.0)):
        with pytest.raises(InputError):
            parse_line(text, None, rate)


def test_run_stream_header_names_the_columns(sim_drive):
    import io

    wp = sim_drive[0]
    r = Runner(params_to_config(presets["constant-velocity"]), wp)
    lines = ["# comment", "y_m, stamp, x_m", "0.0,0.0,1.0", "0.1,0.1,1.2", "0.2,0.2,1.4"]
    out, err = io.StringIO(), io.StringIO()
    assert run_stream(r, lines, out, err) == 0
    assert err.getvalue() == ""
    replies = [json.loads(line) for line in out.getvalue().splitlines()]
    assert [o["stamp"] for o in replies] == [0.0, 0.1, 0.2]
    assert replies[-1]["poses"][0][0] > 1.4  # moving along +x at ~2 m/s


def test_benchmark_update_reports_median_and_p99(levine):
    res = runner.benchmark_update(levine[0], n_updates=50)
    assert set(res) >= {"median_ms", "p99_ms"}
    assert 0 < res["median_ms"] <= res["p99_ms"]
