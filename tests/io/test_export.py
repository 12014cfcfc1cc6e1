"""`fpe export`: JSON, ROS 2 parameters and the StableHLO artifact, round-tripped to predictions."""

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import yaml
from helpers import FRESH
from helpers import NO_JAX as BLOCK_JAX  # blocks importing JAX

from fpe_jax import Params, Settings, State, Track, predict_batch, predict_drive
from fpe_jax.cli import main
from fpe_jax.errors import InputError
from fpe_jax.geometry._path import waypoints_sha256
from fpe_jax.io.config import params_to_config, read_config, write_config
from fpe_jax.io.export import INPUTS, ROS2_PARAMS, _yaml_scalar, load, to_ros2_yaml
from fpe_jax.predict._predict import states_from_drive
from fpe_jax.runner._runner import Runner, load_waypoints_xy
from fpe_jax.sim._sim import simulate
from fpe_jax.spec import SCHEMA_VERSION

ROOT = Path(__file__).resolve().parents[2]
TOL_M = 1e-6
BATCHES = (1, 7, 1000)


def fitted_params() -> Params:
    """Values as a fit leaves them: nothing round, every field away from its preset."""
    return Params.create(
        Settings(blend="heading"),
        lookahead_m=1.2873451,
        lookahead_gain_s=0.2331,
        weights=[0.93, 0.81, 0.7002, 0.61, 0.5, 0.43, 0.37, 0.3, 0.2549, 1e-06],
        delay_s=0.1617,
        speed_weight=0.7312,
        speed_mps=2.4186,
    )


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    """A tuned config (with the uncertainty and provenance sections a fit writes), the waypoints
    of the simulated oval, a simulated drive on it, and `fpe export --format all` of the config."""
    tmp = tmp_path_factory.mktemp("export")
    res = simulate("oval", duration_s=20.0, seed=3)
    params = fitted_params()
    cov = np.tile(np.diag([0.04, 0.01]), (10, 1, 1)) * np.arange(1, 11)[:, None, None]
    cfg = params_to_config(
        params,
        uncertainty={"frame": "track", "axes": ["along_m", "cross_m"], "cov_m2": cov.tolist()},
        provenance={"drives": ["sim:oval"], "fitted_at": "2026-11-22T04:00:00+00:00"},
    )
    write_config(tmp / "tuned.json", cfg)
    np.savetxt(tmp / "wp.csv", res.centerline_xy_m, delimiter=",", fmt="%.17g")
    out = tmp / "car"
    argv = ["export", str(tmp / "tuned.json"), "--format", "all", "--out", str(out)]
    assert main([*argv, "--waypoints", str(tmp / "wp.csv")]) == 0
    track = Track.from_waypoints(res.centerline_xy_m)
    return dict(tmp=tmp, out=out, cfg=cfg, params=params, drive=res.drive, track=track, argv=argv)


def test_all_writes_the_four_files(case):
    names = sorted(p.name for p in case["out"].iterdir())
    assert names == [
        "config.json",
        "params.yaml",
        "predictor.stablehlo",
        "predictor.stablehlo.json",
    ]
    assert read_config(case["out"] / "config.json") == read_config(case["tmp"] / "tuned.json")


def test_round_trip_runner_matches_jax(case):
    """(a) The car's NumPy runner, fed the exported config, predicts what the JAX path does."""
    drive = case["drive"]
    r = Runner.from_config(case["out"] / "config.json", case["tmp"] / "wp.csv")
    got = np.stack(
        [r.update(t, x, y, yaw) for t, (x, y), yaw in zip(drive.t_s, drive.xy_m, drive.yaw_rad)]
    )
    _, want = predict_drive(case["params"], drive, case["track"])
    assert np.max(np.abs(got[..., :2] - want[..., :2])) <= TOL_M
    assert np.max(np.abs(np.angle(np.exp(1j * (got[..., 2] - want[..., 2]))))) <= TOL_M


def test_round_trip_stablehlo_in_a_fresh_process(case):
    """(b) The artifact, loaded in a new process, predicts what the JAX path does, for 1, 7 and
    1000 cars, with only the states as inputs (params and track are baked in)."""
    params, track = case["params"], case["track"]
    states = states_from_drive(params, case["drive"], track)
    rows = np.random.default_rng(0).integers(len(case["drive"].t_s), size=max(BATCHES))
    states = jax.tree.map(lambda a: a[rows], states)
    names = [n for n, _ in INPUTS]
    np.savez(case["tmp"] / "in.npz", **{n: np.asarray(getattr(states, n)) for n in names})
    proc = subprocess.run(
        [sys.executable, "-c", FRESH, str(case["out"] / "predictor.stablehlo")]
        + [str(case["tmp"] / "in.npz"), str(case["tmp"] / "out.npz")],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    with np.load(case["tmp"] / "out.npz") as npz:  # closed: see test_cli_fit_evaluate_predict
        got = dict(npz)
    want = np.asarray(predict_batch(params, states, track))
    for b in BATCHES:
        assert got[f"b{b}"].shape == (b, 10, 3) and got[f"b{b}"].dtype == np.float64
        assert np.max(np.abs(got[f"b{b}"] - want[:b])) <= TOL_M
    # the defaults: no yaw rate, course = yaw, and the arc length of a global projection
    first = jax.tree.map(lambda a: a[:7], states)
    plain = State(x_m=first.x_m, y_m=first.y_m, yaw_rad=first.yaw_rad, v_mps=first.v_mps)
    s_m = jax.vmap(track.project)(jnp.stack([first.x_m, first.y_m], axis=1))
    want = np.asarray(predict_batch(params, dataclasses.replace(plain, s_m=s_m), track))
    assert np.max(np.abs(got["defaults"] - want)) <= TOL_M


def test_sidecar_documents_the_inputs(case):
    meta = json.loads((case["out"] / "predictor.stablehlo.json").read_text())
    assert [i["name"] for i in meta["inputs"]] == [n for n, _ in INPUTS]
    assert all(i["dtype"] == "float64" and i["shape"] == ["b"] for i in meta["inputs"])
    assert meta["output"]["shape"] == ["b", 10, 3]
    assert meta["track"]["closed"] is True and meta["config"] == case["cfg"]
    assert "cpu" in meta["platforms"]
    assert load(case["out"] / "predictor.stablehlo").meta == meta


def test_round_trip_ros2_yaml_holds_every_fitted_value(case):
    """(c) The ROS 2 parameter file parses and holds the fitted values exactly, typed."""
    text = (case["out"] / "params.yaml").read_text()
    version = f"config schema_version {SCHEMA_VERSION}"
    assert f"from tuned.json, {version}; fitted 2026-11-22T04:00:00+00:00" in text
    doc = yaml.safe_load(text)
    assert list(doc) == ["future_pose_estimator"]
    ros = doc["future_pose_estimator"]["ros__parameters"]
    cfg = case["cfg"]
    for name, section, key, kind, _ in ROS2_PARAMS:
        assert ros[name] == cfg[section][key], name
        if kind is list:
            assert all(type(v) is float for v in ros[name])
        else:
            assert type(ros[name]) is kind, name
    physical = case["params"].physical()
    assert ros["blend_weights"] == physical["weights"]
    assert ros["lookahead_distance_m"] == physical["lookahead_m"]
    assert ros["lookahead_gain_s"] == physical["lookahead_gain_s"]
    assert ros["delay_offset_s"] == physical["delay_s"]
    assert ros["speed_weight"] == physical["speed_weight"]
    assert ros["typical_speed_mps"] == physical["speed_mps"]
    # relative to the YAML's folder: the exported folder works wherever it is copied
    assert ros["waypoint_file"] == os.path.relpath(case["tmp"] / "wp.csv", case["out"])
    assert ros["waypoints_sha256"] == waypoints_sha256(load_waypoints_xy(case["tmp"] / "wp.csv"))
    assert ros["schema_version"] == SCHEMA_VERSION
    extra = {"schema_version", "waypoint_file", "waypoints_sha256"}
    assert set(ros) == {n for n, *_ in ROS2_PARAMS} | extra


def test_refuses_to_overwrite_without_force(case, capsys):
    before = {p.name: p.read_bytes() for p in case["out"].iterdir()}
    assert main([*case["argv"], "--waypoints", str(case["tmp"] / "wp.csv")]) == 2
    assert "exists" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in case["out"].iterdir()} == before
    for fmt, name in (("json", "config.json"), ("ros2", "params.yaml")):
        argv = ["export", str(case["tmp"] / "tuned.json"), "--format", fmt]
        assert main([*argv, "--out", str(case["out"] / name)]) == 2
        assert main([*argv, "--out", str(case["out"] / name), "--force"]) == 0
    assert read_config(case["out"] / "config.json") == case["cfg"]


def test_single_formats_and_node_name(case):
    tmp = case["tmp"]
    argv = ["export", str(tmp / "tuned.json"), "--format", "ros2", "--out", str(tmp / "n.yaml")]
    assert main([*argv, "--node", "/car1/predictor"]) == 0
    doc = yaml.safe_load((tmp / "n.yaml").read_text())
    assert doc["/car1/predictor"]["ros__parameters"]["waypoint_file"] == ""
    with pytest.raises(InputError, match="not a ROS 2 node name"):
        to_ros2_yaml(case["cfg"], node="bad node: {x}")
    # a bad input found late would leave half an export: nothing is written
    argv = ["export", str(tmp / "tuned.json"), "--format", "all", "--out", str(tmp / "half")]
    assert main([*argv, "--waypoints", str(tmp / "wp.csv"), "--node", "a b"]) == 2
    assert main([*argv, "--waypoints", str(tmp / "absent.csv")]) == 2
    assert not (tmp / "half").exists()


NO_JAX = (
    BLOCK_JAX
    + """
from fpe_jax.cli import main
rc = main(sys.argv[1:])
assert "jax" not in sys.modules
sys.exit(rc)
"""
)


@pytest.mark.parametrize("fmt", ["json", "ros2"])
def test_json_and_ros2_export_without_jax(case, tmp_path, fmt):
    argv = ["export", str(case["tmp"] / "tuned.json"), "--format", fmt]
    argv += ["--out", str(tmp_path / "out"), "--waypoints", str(case["tmp"] / "wp.csv")]
    proc = subprocess.run(
        [sys.executable, "-c", NO_JAX, *argv], capture_output=True, text=True, cwd=ROOT, timeout=60
    )
    assert proc.returncode == 0, proc.stderr
    if fmt == "json":
        assert read_config(tmp_path / "out") == case["cfg"]
    else:
        wp = case["tmp"] / "wp.csv"
        sha = waypoints_sha256(load_waypoints_xy(wp))
        rel = os.path.relpath(wp, tmp_path)
        want = to_ros2_yaml(
            case["cfg"], waypoint_file=rel, source="tuned.json", waypoints_sha256=sha
        )
        assert (tmp_path / "out").read_text() == want


def test_stablehlo_needs_the_waypoints(case, capsys):
    argv = ["export", str(case["tmp"] / "tuned.json"), "--format", "stablehlo"]
    assert main([*argv, "--out", str(case["tmp"] / "p.stablehlo")]) == 2
    assert "--waypoints" in capsys.readouterr().err
    assert not (case["tmp"] / "p.stablehlo").exists()


def test_export_rejects_newer_schema_and_missing_fields(tmp_path, case, capsys):
    newer = dict(case["cfg"], schema_version=7)
    (tmp_path / "newer.json").write_text(json.dumps(newer))
    argv = ["export", str(tmp_path / "newer.json"), "--format", "json", "--out"]
    assert main([*argv, str(tmp_path / "o.json")]) == 2
    assert "schema_version 7 is not supported" in capsys.readouterr().err
    lacking = json.loads(json.dumps(case["cfg"]))
    del lacking["settings"]["horizon"]
    (tmp_path / "lacking.json").write_text(json.dumps(lacking))
    argv = ["export", str(tmp_path / "lacking.json"), "--format", "ros2", "--out"]
    assert main([*argv, str(tmp_path / "o.yaml")]) == 2
    assert "'settings' lacks horizon" in capsys.readouterr().err


def test_load_rejects_what_is_not_an_artifact(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        load(tmp_path / "absent.stablehlo")
    (tmp_path / "junk.stablehlo").write_bytes(b"not flatbuffers at all")
    with pytest.raises(InputError, match="not a jax.export artifact"):
        load(tmp_path / "junk.stablehlo")


@pytest.mark.parametrize("value", [1e-06, 2.5e-12, 1e20, 0.1, 1.0, -3.0, 123456789.123])
def test_yaml_floats_stay_floats(value):
    assert type(yaml.safe_load(_yaml_scalar(value))) is float
    assert yaml.safe_load(_yaml_scalar(value)) == value
    assert yaml.safe_load(_yaml_scalar([value, value])) == [value, value]


def test_line_model_exports_its_profile_to_every_format(case, tmp_path):
    """A line-model config: the ROS 2 file carries the profile arrays, the StableHLO artifact
    and the runner predict what the JAX path does (track-frame inputs given, and omitted)."""
    from fpe_jax.geometry._path import waypoints_sha256
    from fpe_jax.model._line import learn_line

    drive, track = case["drive"], case["track"]
    wp = np.loadtxt(case["tmp"] / "wp.csv", delimiter=",")
    params = Params.create(
        Settings(model="line"),
        delay_s=0.2,
        offset_tau_s=0.9,
        speed_tau_s=0.2,
        **learn_line([drive], track),
    )
    cfg = params_to_config(params, line={"waypoints_sha256": waypoints_sha256(wp)})
    write_config(tmp_path / "line.json", cfg)
    out = tmp_path / "car"
    argv = ["export", str(tmp_path / "line.json"), "--format", "all", "--out", str(out)]
    assert main([*argv, "--waypoints", str(case["tmp"] / "wp.csv")]) == 0
    ros = yaml.safe_load((out / "params.yaml").read_text())["future_pose_estimator"]
    ros = ros["ros__parameters"]
    for key in ("line_offset_m", "line_speed_mps", "line_coverage"):
        assert ros[key] == cfg["params"][key]
    assert ros["offset_decay_s"] == 0.9 and ros["model"] == "line"
    states = jax.tree.map(lambda a: a[::7], states_from_drive(params, drive, track))
    want = np.asarray(predict_batch(params, states, track))
    f = load(out / "predictor.stablehlo")
    got = f(**{n: np.asarray(getattr(states, n)) for n, _ in INPUTS})
    assert np.max(np.abs(got - want)) <= TOL_M
    runner = Runner.from_config(out / "config.json", case["tmp"] / "wp.csv")
    rows = [
        runner.update(t, x, y, yaw) for t, (x, y), yaw in zip(drive.t_s, drive.xy_m, drive.yaw_rad)
    ]
    assert np.max(np.abs(np.stack(rows)[::7, :, :2] - want[..., :2])) <= TOL_M
    # without the track-frame inputs: the position, speed and course stand in
    plain = f(*(np.asarray(getattr(states, n)) for n in ("x_m", "y_m", "yaw_rad", "v_mps")))
    assert plain.shape == want.shape and np.all(np.isfinite(plain))


@pytest.mark.parametrize("fmt", ["stablehlo", "ros2", "all"])
def test_export_refuses_a_line_config_on_other_waypoints(case, tmp_path, fmt, capsys):
    """Like predict and run: the line was learned on other waypoints -> one line naming both
    files, exit 2, nothing written."""
    from fpe_jax.geometry._path import waypoints_sha256
    from fpe_jax.model._line import learn_line

    wp = np.loadtxt(case["tmp"] / "wp.csv", delimiter=",")
    params = Params.create(Settings(model="line"), **learn_line([case["drive"]], case["track"]))
    cfg = params_to_config(params, line={"waypoints_sha256": waypoints_sha256(wp)})
    write_config(tmp_path / "line.json", cfg)
    other = tmp_path / "other.csv"
    np.savetxt(other, wp * 1.01, delimiter=",")
    out = tmp_path / "out"
    argv = ["export", str(tmp_path / "line.json"), "--format", fmt, "--out", str(out)]
    assert main([*argv, "--waypoints", str(other)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "other.csv" in err and "line.json" in err
    assert not out.exists()


def test_all_failing_midway_leaves_no_partial_export(case, tmp_path, monkeypatch):
    """A write that fails after the StableHLO artifact (a full disk) leaves no folder, or an
    existing export exactly as it was: never a mixed or partial set a car could deploy."""
    import errno

    from fpe_jax.io import export as ex

    def full_disk(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(ex, "export_json", full_disk)
    out = tmp_path / "car"
    argv = ["export", str(case["tmp"] / "tuned.json"), "--format", "all", "--out", str(out)]
    argv += ["--waypoints", str(case["tmp"] / "wp.csv")]
    assert main(argv) != 0
    assert list(tmp_path.iterdir()) == []  # no folder, no temporary left
    out.mkdir()
    names = [*ex.ALL_FILES.values(), ex.ALL_FILES["stablehlo"] + ".json", "notes.txt"]
    for name in names:
        (out / name).write_text(f"old {name}")
    assert main([*argv, "--force"]) != 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["car"]
    assert {p.name: p.read_text() for p in out.iterdir()} == {n: f"old {n}" for n in names}


def test_ros2_params_file_reads_back_where_it_is_copied(case, tmp_path):
    """The exported folder moved elsewhere (as onto a car) still gives the config and its
    waypoints; changed waypoints are refused by their hash."""
    import shutil

    from fpe_jax.io.export import read_ros2_params

    argv = ["export", str(case["tmp"] / "tuned.json"), "--format", "ros2"]
    (tmp_path / "a").mkdir()
    shutil.copy(case["tmp"] / "wp.csv", tmp_path / "a" / "wp.csv")
    out = tmp_path / "a" / "params.yaml"
    assert main([*argv, "--out", str(out), "--waypoints", str(tmp_path / "a" / "wp.csv")]) == 0
    moved = shutil.copytree(tmp_path / "a", tmp_path / "car")
    shutil.rmtree(tmp_path / "a")
    cfg, wp = read_ros2_params(moved / "params.yaml")
    assert wp == moved / "wp.csv"
    for section in ("params", "settings"):
        assert cfg[section] == {
            k: v for k, v in case["cfg"][section].items() if k in cfg[section]
        }, section
    xy = load_waypoints_xy(wp)
    np.savetxt(moved / "wp.csv", xy + 0.5, delimiter=",", header="x,y", comments="")
    with pytest.raises(InputError, match="differ from those it was exported with"):
        read_ros2_params(moved / "params.yaml")
