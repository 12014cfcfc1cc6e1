"""`fpe_jax.pipeline`: each pipeline function, called directly, writes the same files (byte for
byte) and returns the same numbers as the CLI command that calls it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers import cli_runner

from fpe_jax import pipeline
from fpe_jax.errors import InputError

DATA = Path(__file__).resolve().parents[1] / "data"
LOG = str(DATA / "samples" / "drive.mcap")
WAYPOINTS = str(DATA / "tracks" / "oval.csv")
CARS = str(DATA / "samples" / "cars.csv")


def run_cli(capsys, *argv) -> str:
    """stdout of `fpe ARGV` run in-process, which must succeed."""
    return cli_runner(capsys, argv, expect=0)[1]


@pytest.fixture(scope="module")
def tuned(tmp_path_factory) -> str:
    """A config fitted by the CLI on the sample drive (its uncertainty included)."""
    path = tmp_path_factory.mktemp("fit") / "tuned.json"
    from fpe_jax.cli import main

    assert main(["fit", LOG, "--waypoints", WAYPOINTS, "--out", str(path), "--quiet"]) == 0
    return str(path)


@pytest.mark.parametrize("predictor", ["preset", "config"])
def test_predict_log_writes_what_fpe_predict_writes(tmp_path, capsys, tuned, predictor):
    flags = ["--preset", "seed"] if predictor == "preset" else ["--config", tuned]
    kw = dict(preset="seed") if predictor == "preset" else dict(config=tuned)
    run_cli(capsys, "predict", LOG, "--waypoints", WAYPOINTS, *flags, "--out", f"{tmp_path}/c.csv")
    res = pipeline.predict_log(LOG, WAYPOINTS, **kw, out=tmp_path / "p.csv")
    assert (tmp_path / "p.csv").read_bytes() == (tmp_path / "c.csv").read_bytes()
    assert res.poses_m.shape == (len(res.stamps_s), 10, 3)
    assert (res.cov_m2 is None) == (predictor == "preset")
    # the poses returned are the ones written (CSV rows: stamp, step, x, y, yaw, ...)
    first = (tmp_path / "p.csv").read_text().splitlines()[1].split(",")
    assert float(first[0]) == pytest.approx(res.stamps_s[0], abs=1e-9)


def test_predict_log_takes_arrays_and_a_drive(tmp_path):
    from fpe_jax import io

    drive = io.load_drive(LOG)
    wp = io.load_waypoints(WAYPOINTS).xy_m
    from_files = pipeline.predict_log(LOG, WAYPOINTS, preset="linear")
    from_arrays = pipeline.predict_log(drive, wp, preset="linear")
    np.testing.assert_array_equal(from_arrays.poses_m, from_files.poses_m)
    np.testing.assert_array_equal(from_arrays.stamps_s, from_files.stamps_s)


def test_evaluate_log_returns_what_fpe_evaluate_prints(capsys, tuned):
    out = run_cli(capsys, "evaluate", LOG, "--waypoints", WAYPOINTS, "--config", tuned, "--json")
    res = pipeline.evaluate_log(LOG, WAYPOINTS, config=tuned)
    assert json.loads(out) == json.loads(json.dumps(res.metrics))
    assert "coverage_1sigma" in res.metrics  # the config's uncertainty was attached
    assert res.predictor.config["schema_version"] == 2


def test_fit_logs_writes_what_fpe_fit_writes(tmp_path, capsys, tuned):
    res = pipeline.fit_logs([LOG], WAYPOINTS, out=tmp_path / "p.json")
    written = json.loads((tmp_path / "p.json").read_text())
    assert written == json.loads(json.dumps(res.config))
    cli = json.loads(Path(tuned).read_text())
    # everything but the clock (when, and how long the solve took) is equal
    for cfg in (cli, written):
        cfg["provenance"].pop("fitted_at")
        cfg["provenance"]["solver"].pop("seconds")
    assert written == cli


def test_predict_cars_writes_what_fpe_batch_writes(tmp_path, capsys):
    run_cli(
        capsys, "batch", CARS, "--waypoints", WAYPOINTS, "--preset", "default", "--out",
        f"{tmp_path}/c.npy",
    )  # fmt: skip
    seen = []
    res = pipeline.predict_cars(
        CARS, WAYPOINTS, out=tmp_path / "p.npy", on_chunk=lambda d, n: seen.append((d, n))
    )
    assert (tmp_path / "p.npy").read_bytes() == (tmp_path / "c.npy").read_bytes()
    np.testing.assert_array_equal(np.load(tmp_path / "p.npy"), res.poses_m)
    assert seen[-1] == (len(res.poses_m), len(res.poses_m))


def test_predict_cars_warns_of_cars_off_the_track(tmp_path):
    from fpe_jax import io

    cars = np.array(io.read_cars(CARS), dtype=np.float64)
    cars[:2, :2] += 500.0  # two cars in another map frame
    warned = []
    res = pipeline.predict_cars(cars, WAYPOINTS, out=tmp_path / "p.csv", warn=warned.append)
    assert res.off_track.tolist() == [True, True] + [False] * (len(cars) - 2)
    assert len(warned) == 1 and "the cars" in warned[0]
    rows = np.loadtxt(tmp_path / "p.csv", delimiter=",", skiprows=1)
    assert rows[:, -1].reshape(len(cars), -1)[:, 0].tolist() == res.off_track.tolist()


def test_predict_log_adaptive_writes_what_fpe_predict_adapt_writes(tmp_path, capsys):
    argv = ["predict", LOG, "--waypoints", WAYPOINTS, "--adapt", "--delay", "0.1"]
    run_cli(capsys, *argv, "--out", f"{tmp_path}/c.csv", "--save-state", f"{tmp_path}/c.json")
    kw = dict(delay_s=0.1, out=tmp_path / "p.csv", save_state=tmp_path / "p.json")
    res = pipeline.predict_log_adaptive(LOG, WAYPOINTS, **kw)
    assert (tmp_path / "p.csv").read_bytes() == (tmp_path / "c.csv").read_bytes()
    learned, cli_learned = (json.loads((tmp_path / f).read_text()) for f in ("p.json", "c.json"))
    assert learned["line"] == cli_learned["line"] and learned["params"] == cli_learned["params"]
    assert res.poses_m.shape == (len(res.stamps_s), 10, 3)


def test_pipelines_never_write_over_their_inputs(tmp_path):
    log = tmp_path / "drive.csv"
    pipeline.convert_log(LOG, log)
    before = log.read_bytes()
    for f, kw in (
        (pipeline.convert_log, {}),
        (pipeline.predict_log, dict(waypoints=WAYPOINTS)),
    ):
        with pytest.raises(InputError, match="drive.csv"):
            f(log, out=log, force=True, **kw)
    assert log.read_bytes() == before


def test_plot_log_draws_what_fpe_plot_draws(tmp_path, capsys, tuned):
    run_cli(capsys, "plot", LOG, "--waypoints", WAYPOINTS, "--config", tuned, "--out",
            f"{tmp_path}/c.png")  # fmt: skip
    phases = []
    res = pipeline.plot_log(
        LOG, WAYPOINTS, tmp_path / "p.png", config=tuned, progress=phases.append
    )
    assert (tmp_path / "p.png").read_bytes() == (tmp_path / "c.png").read_bytes()
    assert res.metrics["n_predictions"] > 0
    assert phases[0] == "loading JAX" and phases[-1].startswith("drawing")


def test_plot_log_predicts_in_the_local_frame(tmp_path):
    """`fpe plot` predicts in the drive's local frame like `fpe evaluate`: on UTM-sized
    coordinates both score the same predictions, equal to those near the origin."""
    from fpe_jax import io

    drive = io.load_drive(LOG)
    wp = io.load_waypoints(WAYPOINTS).xy_m
    shift = np.array([5.0e5, 4.0e6])
    far = drive.shifted(0.0, -shift)
    near = pipeline.evaluate_log(drive, wp).metrics
    evaluated = pipeline.evaluate_log(far, wp + shift).metrics
    plotted = pipeline.plot_log(far, wp + shift, tmp_path / "far.png").metrics
    for key in ("ade_m", "fde_m", "n_predictions"):
        assert plotted[key] == evaluated[key], key
        assert plotted[key] == pytest.approx(near[key], rel=1e-9), key


def test_convert_and_describe_match_the_cli(tmp_path, capsys):
    run_cli(capsys, "convert", LOG, "--out", f"{tmp_path}/c.csv")
    pipeline.convert_log(LOG, tmp_path / "p.csv")
    assert (tmp_path / "p.csv").read_bytes() == (tmp_path / "c.csv").read_bytes()
    out = run_cli(capsys, "info", LOG, "--waypoints", WAYPOINTS, "--json")
    assert json.loads(out) == pipeline.describe(LOG, WAYPOINTS)


def test_simulate_to_writes_what_fpe_simulate_writes(tmp_path, capsys):
    run_cli(capsys, "simulate", "--duration", "4", "--out", f"{tmp_path}/c")
    pipeline.simulate_to(tmp_path / "p", duration_s=4.0)
    for name in sorted(p.name for p in (tmp_path / "c").iterdir()):
        assert (tmp_path / "p" / name).read_bytes() == (tmp_path / "c" / name).read_bytes(), name


def test_pipelines_refuse_bad_outputs_before_the_work(tmp_path):
    (tmp_path / "exists.csv").write_text("x\n")
    with pytest.raises(InputError, match="exists"):
        pipeline.predict_log(LOG, WAYPOINTS, out=tmp_path / "exists.csv")
    with pytest.raises(InputError, match="unknown output format"):
        pipeline.predict_log(LOG, WAYPOINTS, out=tmp_path / "p.txt")
    with pytest.raises(InputError, match="unknown figure type"):
        pipeline.plot_log(LOG, WAYPOINTS, tmp_path / "f.gif")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exists.csv"]


def test_off_track_drives_are_refused_in_every_pipeline():
    from fpe_jax import io

    wp = io.load_waypoints(WAYPOINTS).xy_m + 500.0  # another map frame
    for f in (pipeline.predict_log, pipeline.evaluate_log):
        with pytest.raises(InputError, match="lie within"):
            f(LOG, wp)
    assert pipeline.evaluate_log(LOG, wp, allow_off_track=True).metrics["n_predictions"] > 0
