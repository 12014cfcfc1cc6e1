"""The compilation cache, the JAX-free fast commands, progress lines and bucketed shapes."""

import dataclasses
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from fpe_jax.compile import _cache as cache
from fpe_jax.io.config import PRESET_DOCS
from fpe_jax.model._params import presets, with_settings
from fpe_jax.progress import Progress

ROOT = Path(__file__).resolve().parents[2]


def fpe(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "fpe_jax.cli", *args],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env={**os.environ, **(env or {})},
        timeout=600,
    )


@pytest.fixture(scope="module")
def drive_dir(tmp_path_factory) -> Path:
    """`fpe simulate --duration 12` (in this process: the commands under test read its files)."""
    from fpe_jax import cli

    out = tmp_path_factory.mktemp("sim") / "d"
    assert cli.main(["simulate", "--duration", "12", "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def cold_predict(tmp_path_factory, drive_dir) -> tuple[Path, subprocess.CompletedProcess]:
    """`fpe predict --quiet` with an empty cache folder: (folder holding cache/ and p.csv,
    result). Tests take copies (`cold_predict_into`)."""
    folder = tmp_path_factory.mktemp("cold")
    env = {"FPE_CACHE_DIR": str(folder / "cache")}
    return folder, fpe(*predict_args(drive_dir, folder / "p.csv"), "--quiet", env=env)


def cold_predict_into(
    tmp_path: Path, cold_predict: tuple[Path, subprocess.CompletedProcess], out: Path
) -> subprocess.CompletedProcess:
    """`cold_predict` as if run with FPE_CACHE_DIR=tmp_path/cache and --out out: its cache (the
    user's key included, modes kept) and predictions copied there; its result."""
    folder, result = cold_predict
    assert result.returncode == 0, result.stderr
    shutil.copytree(folder / "cache", tmp_path / "cache", symlinks=True)
    shutil.copyfile(folder / "p.csv", out)
    return result


@pytest.fixture(scope="module")
def uncached_predict(tmp_path_factory, drive_dir) -> tuple[subprocess.CompletedProcess, dict]:
    """`fpe predict` with FPE_NO_CACHE=1 and a cache folder of its own: (result, environment).
    With XLA's own optimisation (not the suite's debug build, see conftest) compiling lasts
    > 1 s, so it shows progress lines (warm, the whole command may not)."""
    folder = tmp_path_factory.mktemp("uncached")
    env = {"FPE_CACHE_DIR": str(folder / "cache"), "FPE_NO_CACHE": "1", "XLA_FLAGS": ""}
    return fpe(*predict_args(drive_dir, folder / "p.csv"), env=env), env


def predict_args(drive_dir: Path, out: Path) -> list[str]:
    wp = str(drive_dir / "waypoints.csv")
    return ["predict", str(drive_dir / "drive.mcap"), "--waypoints", wp, "--out", str(out)]


def test_preset_docs_name_every_preset():
    assert list(PRESET_DOCS) == list(presets)


# Runs `fpe_jax.cli.main` on each JSON argv of sys.argv[1:] in turn, in one fresh interpreter,
# and reports after each whether JAX got imported (by it: none of the ones before had)
_NO_JAX = """
import json, sys
from fpe_jax import cli
for argv in map(json.loads, sys.argv[1:]):
    try:
        rc = cli.main(argv)
    except SystemExit as e:
        rc = e.code
    print("JAX-IMPORTED" if "jax" in sys.modules else "no-jax", rc, argv, file=sys.stderr)
"""


def test_fast_commands_import_no_jax(tmp_path, drive_dir):
    from fpe_jax.io.config import params_to_config, write_config

    write_config(tmp_path / "c.json", params_to_config(presets["default"]))
    mcap, wp = str(drive_dir / "drive.mcap"), str(drive_dir / "waypoints.csv")
    commands = [
        ["--help"],
        ["presets"],
        ["info", mcap, "--waypoints", wp],
        ["cache", "info"],
        ["export", str(tmp_path / "c.json"), "--format", "json", "--out", str(tmp_path / "e.json")],
        ["export", str(tmp_path / "c.json"), "--format", "ros2", "--out", str(tmp_path / "e.yaml")],
        ["run", "--config", str(tmp_path / "c.json"), "--waypoints", wp],  # reads stdin
    ]
    r = subprocess.run(
        [sys.executable, "-c", _NO_JAX, *map(json.dumps, commands)],
        input="t,x,y\n0.0,1.0,2.0\n",
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    reports = [ln for ln in r.stderr.splitlines() if ln.startswith(("no-jax", "JAX-IMPORTED"))]
    assert len(reports) == len(commands), r.stderr[-2000:]
    for argv, report in zip(commands, reports):
        assert report.startswith("no-jax 0"), (argv, r.stderr[-2000:])


def cache_command(capsys, monkeypatch, cache_dir: Path, *args: str) -> tuple[int, str]:
    """`fpe cache ARGS` with FPE_CACHE_DIR=cache_dir, in this process (it imports no JAX:
    test_fast_commands_import_no_jax): (exit status, stdout)."""
    from helpers import cli_runner

    with monkeypatch.context() as m:
        m.setenv("FPE_CACHE_DIR", str(cache_dir))
        rc, out, _ = cli_runner(capsys, ["cache", *args])
    return rc, out


def test_cache_is_written_reused_and_survives_corrupt_entries(
    tmp_path, drive_dir, cold_predict, uncached_predict, capsys, monkeypatch
):
    env = {"FPE_CACHE_DIR": str(tmp_path / "cache")}

    def info_json(cache_dir: Path) -> dict:
        rc, out = cache_command(capsys, monkeypatch, cache_dir, "info", "--json")
        assert rc == 0
        return json.loads(out)

    cold_predict_into(tmp_path, cold_predict, tmp_path / "a.csv")
    info = info_json(tmp_path / "cache")
    assert info["path"] == str(tmp_path / "cache") and info["entries"] > 0 and info["bytes"] > 0
    [sub] = info["subfolders"]  # keyed by jax + jaxlib version, backend and x64 mode
    assert sub.startswith("jax-") and "jaxlib-" in sub and sub.endswith("_x64")
    # every entry overwritten with garbage: a recompile and one warning line, same predictions
    entries = [f for f in (tmp_path / "cache" / sub).rglob("*") if f.is_file()]
    for f in entries:
        f.write_bytes(b"not an executable" * 3)
    again = fpe(*predict_args(drive_dir, tmp_path / "b.csv"), "--quiet", env=env)
    assert again.returncode == 0, again.stderr
    lines = again.stderr.strip().splitlines()
    assert len(lines) == 2, again.stderr  # the one warning, then "wrote ..."
    assert lines[0].startswith("fpe: warning: unreadable compilation cache entry")
    assert "Traceback" not in again.stderr
    a = np.loadtxt(tmp_path / "a.csv", delimiter=",", skiprows=1)
    b = np.loadtxt(tmp_path / "b.csv", delimiter=",", skiprows=1)
    np.testing.assert_array_equal(a, b)
    # clear empties it; --no-cache and FPE_NO_CACHE=1 leave it empty
    rc, cleared = cache_command(capsys, monkeypatch, tmp_path / "cache", "clear")
    assert rc == 0 and "removed" in cleared
    assert info_json(tmp_path / "cache")["entries"] == 0
    off = fpe(*predict_args(drive_dir, tmp_path / "c.csv"), "--no-cache", "--quiet", env=env)
    assert off.returncode == 0, off.stderr
    assert info_json(tmp_path / "cache")["entries"] == 0
    off, off_env = uncached_predict
    assert off.returncode == 0, off.stderr
    assert info_json(Path(off_env["FPE_CACHE_DIR"]))["entries"] == 0


@pytest.fixture(scope="module")
def cold_evaluate(
    tmp_path_factory, drive_dir, cold_predict
) -> tuple[Path, subprocess.CompletedProcess]:
    """`fpe evaluate --preset frenet --json --quiet` after `cold_predict`, with a copy of its
    cache (it loads predict's executables and compiles its own): (folder holding that cache/
    and predict's p.csv, evaluate's result). Tests take copies."""
    folder = tmp_path_factory.mktemp("evaluated")
    cold_predict_into(folder, cold_predict, folder / "p.csv")
    env = {"FPE_CACHE_DIR": str(folder / "cache")}
    return folder, fpe(
        "evaluate", *log_args(drive_dir), "--preset", "frenet", "--json", "--quiet", env=env
    )


def log_args(drive_dir: Path) -> list[str]:
    return [str(drive_dir / "drive.mcap"), "--waypoints", str(drive_dir / "waypoints.csv")]


def cache_files(cache_dir: Path) -> dict:
    """Every file under cache_dir (by its path there): its bytes."""
    return {f.relative_to(cache_dir): f.read_bytes() for f in cache_dir.rglob("*") if f.is_file()}


def test_stored_executables_run_in_later_processes(
    tmp_path, drive_dir, cold_predict, cold_evaluate
):
    """Each command loads what earlier ones stored and stores what it compiled itself: every
    later process runs them and gets the same numbers (a process that had read entries of
    JAX's own cache once stored executables that failed elsewhere with "Function ... not
    found")."""
    env = {"FPE_CACHE_DIR": str(tmp_path / "cache")}

    def pair(p, e, out: Path, cache_dir: Path):
        """Predict p (into out), then evaluate e (loads predict's executables, compiles its
        own) with the cache in cache_dir: (predictions, metrics, the cache's files)."""
        assert p.returncode == 0 and e.returncode == 0, p.stderr + e.stderr
        assert "warning" not in p.stderr + e.stderr, p.stderr + e.stderr
        # --quiet: no progress lines, cold (compiling) or warm
        assert not [ln for ln in p.stderr.splitlines() if ln.startswith("[")], p.stderr
        return np.loadtxt(out, delimiter=",", skiprows=1), e.stdout, cache_files(cache_dir)

    folder, cold_e = cold_evaluate
    cold = pair(cold_predict[1], cold_e, folder / "p.csv", folder / "cache")
    shutil.copytree(folder / "cache", tmp_path / "cache", symlinks=True)
    out = tmp_path / "warm.csv"
    p = fpe(*predict_args(drive_dir, out), "--quiet", env=env)
    e = fpe("evaluate", *log_args(drive_dir), "--preset", "frenet", "--json", "--quiet", env=env)
    warm = pair(p, e, out, tmp_path / "cache")
    assert len(list((tmp_path / "cache").rglob("aot/*.exe"))) >= 3
    # the warm pair loaded everything and wrote nothing: any later process reads this same cache
    assert warm[2] == cold[2]
    np.testing.assert_array_equal(warm[0], cold[0])
    assert warm[1] == cold[1]


def test_executables_are_kept_by_shape_and_reloaded_from_disk(tmp_path, monkeypatch):
    import jax.numpy as jnp

    from fpe_jax.compile import _aot as aot

    monkeypatch.setattr(cache, "_ACTIVE", [tmp_path])

    def scaled(x, factor):
        return {"y": jnp.sin(x) * factor}

    x = np.linspace(0.0, 1.0, 7)
    first = aot.executable(scaled, x, 2.0)
    assert first.seconds["compile_s"] > 0 and len(list(tmp_path.rglob("*.exe"))) == 1
    assert aot.executable(scaled, x, 2.0).seconds["compile_s"] == 0.0  # kept in memory
    monkeypatch.setattr(aot, "_MEMO", {})
    again = aot.executable(scaled, x, 2.0)  # from disk: nothing traced or compiled
    assert again.seconds["trace_s"] == again.seconds["compile_s"] == 0.0
    assert again.seconds["load_s"] > 0
    np.testing.assert_allclose(again(x, 2.0)["y"], np.sin(x) * 2.0, rtol=1e-14)
    aot.executable(scaled, x, 3.0)  # a static value and a shape are part of the key
    aot.executable(scaled, x[:5], 2.0)
    assert len(list(tmp_path.rglob("*.exe"))) == 3


def test_threads_asking_for_one_executable_at_once_make_it_once(tmp_path, monkeypatch):
    """A fit scores the presets on a second thread while the first loads the solver and
    estimates states: an executable both ask for at once is loaded or compiled once."""
    import threading

    import jax.numpy as jnp

    from fpe_jax.compile import _aot as aot

    monkeypatch.setattr(cache, "_ACTIVE", [tmp_path])
    monkeypatch.setattr(aot, "_MEMO", {})
    built, build = [], aot._build

    def slow_build(*args):
        built.append(threading.current_thread().name)
        time.sleep(0.3)  # the other thread asks meanwhile
        return build(*args)

    monkeypatch.setattr(aot, "_build", slow_build)

    def shifted(x):
        return jnp.cos(x) + 1.0

    x = np.linspace(0.0, 1.0, 5)
    got = {}
    threads = [
        threading.Thread(target=lambda k=k: got.setdefault(k, aot.executable(shifted, x)(x)))
        for k in range(3)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(built) == 1 and len(list(tmp_path.rglob("*.exe"))) == 1
    for k in range(3):
        np.testing.assert_allclose(got[k], np.cos(x) + 1.0, rtol=1e-15)
    assert aot._MAKING == {}  # nothing left behind


def _spy_compile_options(monkeypatch) -> list:
    """Record the compiler_options of every XLA compilation from here on."""
    import jax

    seen, compile_ = [], jax.stages.Lowered.compile

    def spy(self, compiler_options=None, **kwargs):
        seen.append(compiler_options)
        return compile_(self, compiler_options=compiler_options, **kwargs)

    monkeypatch.setattr(jax.stages.Lowered, "compile", spy)
    return seen


def test_executables_compile_with_the_cpu_loop_emitters(monkeypatch):
    import jax.numpy as jnp

    from fpe_jax.compile import _aot as aot

    seen = _spy_compile_options(monkeypatch)
    x = np.linspace(0.0, 1.0, 11)
    exe = aot.executable(lambda x: jnp.cos(x) + 1.0, x)
    assert seen == [{"xla_cpu_use_fusion_emitters": False}]
    assert aot.CPU_COMPILER_OPTIONS == seen[0]
    np.testing.assert_allclose(exe(x), np.cos(x) + 1.0, rtol=1e-14)


def test_a_jaxlib_without_the_compiler_option_compiles_with_its_defaults(monkeypatch):
    import jax.numpy as jnp

    from fpe_jax.compile import _aot as aot

    monkeypatch.setattr(aot, "CPU_COMPILER_OPTIONS", {"xla_cpu_no_such_option": False})
    seen = _spy_compile_options(monkeypatch)
    x = np.linspace(0.0, 1.0, 13)
    exe = aot.executable(lambda x: jnp.sin(x) * 3.0, x)
    assert seen == [{"xla_cpu_no_such_option": False}, None]  # refused, then the defaults
    np.testing.assert_allclose(exe(x), np.sin(x) * 3.0, rtol=1e-14)


def test_the_fit_solver_compiles_with_xla_default_emitters(monkeypatch):
    """The solver's steps are repeated work: its program keeps XLA's default emitters."""
    import jax.numpy as jnp

    from fpe_jax.compile import _aot as aot
    from fpe_jax.fit import _fit as fit

    monkeypatch.setattr(aot, "FUSION_EMITTERS", set(aot.FUSION_EMITTERS))  # this test's lambda
    seen = _spy_compile_options(monkeypatch)
    x = np.linspace(0.0, 1.0, 17)
    exe = aot.executable(aot.fusion_emitters(lambda x: jnp.tan(x) - 1.0), x)
    assert seen == [None]
    np.testing.assert_allclose(exe(x), np.tan(x) - 1.0, rtol=1e-14)
    assert fit._solve in aot.FUSION_EMITTERS


def test_cache_dir_follows_xdg(monkeypatch, tmp_path):
    monkeypatch.delenv("FPE_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert cache.root_dir() == tmp_path / "fpe-jax"
    monkeypatch.setenv("FPE_NO_CACHE", "1")
    assert cache.disabled()
    monkeypatch.setenv("FPE_NO_CACHE", "0")
    assert not cache.disabled()


def test_clear_leaves_other_folders_alone(monkeypatch, tmp_path):
    monkeypatch.setenv("FPE_CACHE_DIR", str(tmp_path))
    (tmp_path / "jax-0.4.30_jaxlib-0.4.30_cpu_x64").mkdir()  # an older version's folder
    (tmp_path / "jax-0.4.30_jaxlib-0.4.30_cpu_x64" / "k-cache").write_bytes(b"1234")
    (tmp_path / "mine").mkdir()
    assert cache.clear()["entries"] == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine"]


class _Tty:
    def __init__(self, tty: bool):
        self.text, self.tty = "", tty

    def write(self, s):
        self.text += s

    def flush(self):
        pass

    def isatty(self):
        return self.tty


def test_progress_plain_lines_updating_line_and_quiet():
    log = _Tty(False)
    with Progress(stream=log, delay_s=0) as say:
        say("reading")
        say.count("predicting cars", 5, 10)
    lines = log.text.splitlines()
    assert [ln.split("] ", 1)[1] for ln in lines] == ["reading", "predicting cars 5/10", "done"]
    assert all(ln.startswith("[") and " s] " in ln for ln in lines)
    term = _Tty(True)
    with Progress(stream=term, tick_s=60, delay_s=0) as say:
        say("reading")
        say("predicting")
    assert term.text.count("\n") == 1 and term.text.endswith("done\n")  # one line, rewritten
    assert "\r\x1b[K" in term.text
    quiet = _Tty(True)
    with Progress(stream=quiet, quiet=True) as say:
        say("reading")
    assert quiet.text == ""
    # phases shorter than delay_s print nothing, and nothing follows an error
    short = _Tty(False)
    with pytest.raises(ValueError), Progress(stream=short, delay_s=60) as say:
        say("reading")
        raise ValueError("bad input")
    assert short.text == ""
    slow = _Tty(False)
    with pytest.raises(ValueError), Progress(stream=slow, tick_s=0.01, delay_s=0.05) as say:
        say("compiling")
        time.sleep(0.3)
        raise ValueError("bad input")
    assert slow.text.startswith("[") and slow.text.endswith("] compiling\n")  # no 'done'


def test_predict_shows_progress_unless_quiet(uncached_predict):
    r, _ = uncached_predict
    assert r.returncode == 0, r.stderr
    phases = [ln for ln in r.stderr.splitlines() if ln.startswith("[")]
    assert len(phases) >= 2 and phases[-1].endswith("done")
    # --quiet, cold and warm: test_stored_executables_run_in_later_processes


def test_bucket_sizes():
    from fpe_jax.compile._rows import bucket

    sizes = [bucket(n) for n in (0, 1, 64, 65, 96, 97, 129, 600, 668, 768, 769, 4696)]
    assert sizes == [64, 64, 64, 80, 96, 112, 160, 640, 768, 768, 896, 5120]
    assert all(bucket(n) < 1.25 * n + 1 for n in range(64, 20000))  # at most a quarter more rows
    # four sizes per doubling: drives within ~20 % of each other's length share a solver
    assert len({bucket(n) for n in range(1025, 2049)}) == 4


def _count_compilations():
    """A list that grows by one per XLA compilation until jax.monitoring's listeners are cleared."""
    import jax

    events = []

    def listen(name, *args, **kw):
        if name == "/jax/core/compile/backend_compile_duration":
            events.append(name)

    jax.monitoring.register_event_duration_secs_listener(listen)
    return events


def test_drives_of_similar_length_share_executables():
    """Two drives in one bucket: the second predict traces and compiles nothing new."""
    import jax

    from fpe_jax.geometry._track import Track
    from fpe_jax.predict._predict import predict_drive
    from fpe_jax.sim import _sim as sim

    a = sim.simulate("oval", duration_s=62.0, seed=1)
    b = sim.simulate("oval", duration_s=66.0, seed=2)
    assert len(a.drive.t_s) != len(b.drive.t_s)
    track = Track.from_waypoints(a.centerline_xy_m)
    # a horizon no other test uses: every drive shares the row blocks' executables, so with the
    # default one an earlier test would have compiled them already
    params = with_settings(presets["default"], horizon=13)
    events = _count_compilations()
    try:
        predict_drive(params, a.drive, track)
        first = len(events)
        _, poses = predict_drive(params, b.drive, track)
        assert len(events) == first, "the second drive compiled again"
    finally:
        jax.monitoring.clear_event_listeners()
    assert first > 0 and poses.shape == (len(b.drive.t_s), params.settings.horizon, 3)


def test_a_track_moved_by_whole_metres_shares_executables():
    """The local-origin shift (whole metres) or a CSV round trip moves a track's spacing in
    its last bit; its predictions still trace and compile nothing new."""
    import jax

    from fpe_jax.geometry._track import Track
    from fpe_jax.predict._predict import predict_drive
    from fpe_jax.sim import _sim as sim

    res = sim.simulate("oval", duration_s=20.0, seed=3)
    shift = np.array([3.0, -7.0])
    track, moved = (Track.from_waypoints(res.centerline_xy_m + d) for d in (0.0, shift))
    assert float(track.ds_m) != float(moved.ds_m) and track.n_points == moved.n_points
    drive = dataclasses.replace(res.drive, xy_m=res.drive.xy_m + shift)
    params = with_settings(presets["default"], horizon=11)  # a horizon no other test uses
    events = _count_compilations()
    try:
        _, poses = predict_drive(params, res.drive, track)
        first = len(events)
        _, moved_poses = predict_drive(params, drive, moved)
        assert len(events) == first, "the moved track compiled again"
    finally:
        jax.monitoring.clear_event_listeners()
    assert first > 0
    np.testing.assert_allclose(moved_poses[..., :2] - shift, poses[..., :2], atol=1e-9)


def _with_history(params, n: int):
    return dataclasses.replace(params, settings=dataclasses.replace(params.settings, history=n))


def test_both_estimators_states_come_from_one_executable():
    """A fit scores the Kalman filter's states (the line model, the frenet preset) and the
    Theil-Sen ones (the other presets) on the same datasets: made with kalman=True, one
    compiled program gives both, so the second estimator's states compile nothing."""
    import jax

    from fpe_jax.evaluate._evaluate import make_datasets
    from fpe_jax.geometry._track import Track
    from fpe_jax.sim import _sim as sim

    res = sim.simulate("oval", duration_s=20.0, seed=5)
    track = Track.from_waypoints(res.centerline_xy_m)
    # a history no other test uses: its windows' shapes are compiled here first
    kalman = _with_history(presets["frenet"], 7)
    ts_settings = dataclasses.replace(kalman.settings, estimator="theil-sen")
    theil_sen = dataclasses.replace(kalman, settings=ts_settings)
    (d,) = make_datasets([res.drive], [track], kalman.settings, "test", kalman=True)
    events = _count_compilations()
    try:
        a = d.states(theil_sen)
        first = len(events)
        b = d.states(kalman)
        assert len(events) == first, "the Kalman filter's states compiled a program of their own"
    finally:
        jax.monitoring.clear_event_listeners()
    assert first > 0
    assert a.filter_cov is None and a.window_s_m is None
    assert b.filter_cov.shape == (len(d.targets.rows), 4, 4) and b.window_s_m.shape[1] == 7
    np.testing.assert_array_equal(a.s_m, b.s_m)  # one projection, both estimators
    assert not np.array_equal(a.s_fit_m, b.s_fit_m)  # ... and their own track-frame estimates


def test_a_model_without_the_kalman_filter_never_runs_it(monkeypatch):
    """The blend and seed models start from the Theil-Sen states: predicting, evaluating or
    fitting them neither traces nor runs the Kalman filter (a larger program to compile, load
    and run), unless a Dataset is told that a Kalman model will follow (kalman=True)."""
    import importlib

    from fpe_jax.evaluate._evaluate import Dataset, make_targets
    from fpe_jax.geometry._track import Track
    from fpe_jax.sim import _sim as sim

    pr = importlib.import_module("fpe_jax.predict._predict")  # fpe_jax.predict is the function
    res = sim.simulate("oval", duration_s=20.0, seed=8)
    track = Track.from_waypoints(res.centerline_xy_m)
    # a history no other test uses: nothing compiled earlier hides a trace of the filter
    blend, seed = (_with_history(presets[n], 11) for n in ("default", "seed"))
    assert not pr.uses_filter(blend.settings)

    def no_filter(*args):
        raise AssertionError("the Kalman filter was traced for a model that does not use it")

    monkeypatch.setattr(pr, "_filter_state", no_filter)
    st = pr.states_from_drive(blend, res.drive, track)
    assert st.filter_cov is None and np.isfinite(st.s_fit_m).all()
    d = Dataset(res.drive, track, make_targets(res.drive, blend.settings))
    np.testing.assert_array_equal(d.states(blend).s_fit_m, st.s_fit_m[d.targets.rows])
    np.testing.assert_array_equal(d.states(seed).x_m, res.drive.xy_m[d.targets.rows, 0])
    monkeypatch.undo()
    frenet = _with_history(presets["frenet"], 11)  # a Kalman model after them
    np.testing.assert_array_equal(d.states(frenet).s_m, d.states(blend).s_m)
    assert d.states(frenet).filter_cov is not None


def test_a_dataset_estimates_its_states_once_for_every_model(monkeypatch):
    """The fitted line model, the seed preset (whose states are the recorded rows) and the
    other presets read one estimate of a dataset's states (kalman=True: as `fit` makes them)."""
    import fpe_jax.evaluate._evaluate as ev
    from fpe_jax.geometry._track import Track
    from fpe_jax.model._params import Settings
    from fpe_jax.sim import _sim as sim

    res = sim.simulate("oval", duration_s=20.0, seed=6)
    track = Track.from_waypoints(res.centerline_xy_m)
    (d,) = ev.make_datasets([res.drive], [track], Settings(), "test", kalman=True)
    calls = []
    real = ev.states_both
    monkeypatch.setattr(ev, "states_both", lambda *a, **k: calls.append(1) or real(*a, **k))
    seed = d.states(presets["seed"])
    others = [d.states(presets[name]) for name in ("frenet", "default", "ctrv")]
    assert len(calls) == 1
    rows = d.targets.rows
    np.testing.assert_array_equal(seed.x_m, res.drive.xy_m[rows, 0])  # the recorded rows
    assert not np.array_equal(others[1].x_m, seed.x_m)  # the estimate, not the rows
    assert others[0].filter_cov is not None and others[1].filter_cov is None


# `fpe` with a listener on XLA's compilations: prints how many ran
_COUNTING_FPE = """
import sys, jax
from fpe_jax import cli
compiles = []
jax.monitoring.register_event_duration_secs_listener(
    lambda name, *a, **k: compiles.append(name)
    if name == "/jax/core/compile/backend_compile_duration" else None
)
rc = cli.main(sys.argv[1:])
print("xla compilations:", len(compiles), file=sys.stderr)
sys.exit(rc)
"""


def test_a_warm_fit_compiles_nothing(tmp_path, drive_dir, cold_evaluate):
    """The second `fpe fit` of a drive, with the cache the first one filled, loads every
    executable it runs: no eager JAX operation compiles a program of its own. The first starts
    from the cache that predict and evaluate filled: it loads theirs and compiles the rest."""
    shutil.copytree(cold_evaluate[0] / "cache", tmp_path / "cache", symlinks=True)
    env = {**os.environ, "FPE_CACHE_DIR": str(tmp_path / "cache")}
    argv = ["fit", *log_args(drive_dir)]
    counts = []
    for k in range(2):
        r = subprocess.run(
            [sys.executable, "-c", _COUNTING_FPE, *argv, "--out", str(tmp_path / f"c{k}.json")],
            capture_output=True,
            text=True,
            cwd=ROOT,
            env=env,
            timeout=600,
        )
        assert r.returncode == 0, r.stderr
        counts.append(int(r.stderr.rsplit("xla compilations:", 1)[1]))
    assert counts[0] > 0 and counts[1] == 0, counts
    a, b = (json.loads((tmp_path / f"c{k}.json").read_text()) for k in range(2))
    for c in (a, b):  # when and how long, not what
        del c["provenance"]["fitted_at"], c["provenance"]["solver"]["seconds"]
    assert a == b
