"""Any car, any track size: settings flags and recipe [settings], and no (N, H, track) work."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fpe_jax.cli import main
from fpe_jax.evaluate._evaluate import _heading_chunk, path_heading
from fpe_jax.geometry._track import Track
from fpe_jax.geometry._tracks import builtin_track
from fpe_jax.model._params import presets, with_settings
from fpe_jax.model._rollout import State
from fpe_jax.sim import _sim as sim

# CommonRoad vehicle 2 (a BMW 320i, wheelbase 2.578 m) on grip 1.6, driven at 12-25 m/s
FULL_SIZE_CAR = sim.Vehicle(
    mu=1.6,
    c_sf=20.89,
    c_sr=20.89,
    lf_m=1.1566,
    lr_m=1.4224,
    h_cg_m=0.574,
    mass_kg=1225.0,
    inertia_kgm2=1538.0,
    steer_max_rad=1.066,
    steer_rate_max_rps=0.8,
    accel_max_mps2=11.5,
    v_switch_mps=20.0,
    v_kinematic_mps=2.0,
    v_dynamic_mps=4.0,
)


@pytest.fixture(scope="module")
def full_size_drive(tmp_path_factory):
    """The built-in oval scaled x6, 40 s of a full-size car, 25 Hz detections."""
    center, hw = builtin_track("oval")
    k = 6.0
    driver = sim.Driver(
        lookahead_min_m=4.0,
        lookahead_time_s=0.4,
        edge_margin_m=0.3 * k,
        lat_accel_mps2=15.0,
        accel_mps2=8.0,
        brake_mps2=8.0,
        v_min_mps=12.0,
        v_max_mps=25.0,
    )
    res = sim.simulate(
        center * k,
        duration_s=40.0,
        latency_s=0.1,
        seed=1,
        half_width_m=hw * k,
        vehicle=FULL_SIZE_CAR,
        driver=driver,
        sensor=sim.Sensor(rate_hz=25.0, sigma_m=0.1, sigma_per_m=0.005, ego_gap_m=(12.0, 24.0)),
    )
    out = tmp_path_factory.mktemp("fullsize")
    sim.write_simulation(res, out)
    return out, res


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err
    err = [line for line in err.strip().splitlines() if not line.startswith("[")]  # progress
    assert len(err) == 1 and err[0].startswith("fpe: error:"), err
    return err[0]


def test_full_size_drive_fits_through_the_cli_with_settings_flags(full_size_drive, capsys):
    out, res = full_size_drive
    assert np.median(res.drive.truth_v_mps) > 12.0
    log = [str(out / "drive.mcap"), "--waypoints", str(out / "waypoints.csv")]
    topics = ["--pose-topic", "/opp/pose", "--truth-topic", "/opp/odom"]
    cfg = out / "config.json"
    car = ["--wheelbase", "2.578", "--max-steer", "0.5", "--dt", "0.1", "--horizon", "12"]
    assert main(["fit", *log, *topics, *car, "--out", str(cfg), "--blend", "position"]) == 0
    config = json.loads(cfg.read_text())
    s = config["settings"]
    assert (s["wheelbase_m"], s["max_steer_rad"], s["horizon"]) == (2.578, 0.5, 12)
    assert len(config["params"]["weights"]) == 12
    assert np.shape(config["uncertainty"]["cov_m2"]) == (12, 2, 2)
    held = config["provenance"]["heldout"]
    assert len(held["fitted"]["per_step_m"]) == 12 and len(held["seed"]["per_step_m"]) == 12
    # at 12-25 m/s a 1.2 s prediction spans 15-30 m: the fit must do far better than that
    assert held["fitted"]["fde_m"] < 5.0
    capsys.readouterr()
    pred = out / "pred.csv"
    assert main(["predict", *log, *topics, "--config", str(cfg), "--out", str(pred)]) == 0
    assert main(["evaluate", *log, *topics, "--config", str(cfg), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["ade_m"] < held["fitted"]["ade_m"] * 3
    # a config carries its own settings: a flag next to it is refused, not silently ignored
    assert main(["evaluate", *log, *topics, "--config", str(cfg), "--horizon", "5"]) == 2
    assert "--horizon" in _one_error_line(capsys)


@pytest.mark.parametrize(
    "flag, value",
    [
        ("--horizon", "0"),
        ("--horizon", "100000"),
        ("--max-steer", "2"),
        ("--dt", "nan"),
        ("--dt", "0"),
        ("--wheelbase", "-1"),
        ("--wheelbase", "inf"),
    ],
)
def test_bad_settings_flags_are_one_line_exit_2(full_size_drive, tmp_path, capsys, flag, value):
    out, _ = full_size_drive
    argv = ["evaluate", str(out / "drive.mcap"), "--waypoints", str(out / "waypoints.csv")]
    assert main([*argv, "--pose-topic", "/opp/pose", "--preset", "linear", flag, value]) == 2
    assert flag in _one_error_line(capsys)


def test_recipe_settings_table_is_checked(tmp_path, capsys):
    recipe = tmp_path / "r.toml"
    recipe.write_text(
        'out = "c.json"\n[settings]\nwheelbase = 2.5\n'
        '[[drives]]\nsimulate = { track = "oval", duration_s = 20 }\n'
    )
    assert main(["fit", str(recipe)]) == 2
    line = _one_error_line(capsys)
    assert "[settings]" in line and "wheelbase_m" in line
    recipe.write_text(
        'out = "c.json"\n[settings]\nhorizon = 2.5\n'
        '[[drives]]\nsimulate = { track = "oval", duration_s = 20 }\n'
    )
    assert main(["fit", str(recipe)]) == 2
    assert "[settings] horizon" in _one_error_line(capsys)
    assert not (tmp_path / "c.json").exists()


def test_with_settings_reads_weights_off_by_lead_time():
    seed = presets["seed"]  # weights 0.7^i at 0.1 s steps
    half = with_settings(seed, dt_s=0.05, horizon=20)
    w = np.asarray(half.weights)
    np.testing.assert_allclose(w[1::2], np.asarray(seed.weights), rtol=1e-12)
    assert half.settings.model == "seed" and half.settings.max_steer_rad == 0.5236
    longer = with_settings(presets["default"], horizon=15, wheelbase_m=2.578)
    assert longer.weights.shape == (15,) and longer.settings.wheelbase_m == 2.578
    with pytest.raises(ValueError, match="unknown"):
        with_settings(seed, model="cv")


def _avals(jaxpr):
    """Every intermediate value's shape in a closed jaxpr, sub-jaxprs (scan, jit) included."""
    for eqn in jaxpr.eqns:
        for v in eqn.outvars:
            yield tuple(v.aval.shape)
        for p in eqn.params.values():
            for sub in p if isinstance(p, tuple | list) else (p,):
                inner = getattr(sub, "jaxpr", None)
                if inner is not None:
                    yield from _avals(getattr(inner, "jaxpr", inner))


def test_uncertainty_frame_never_builds_predictions_by_track_points():
    """A 2 km loop at 0.1 m (20,000 points), 8 predictions of 10 steps: no intermediate may
    scale with the track's size, where the global projection built (8, 10, 20,000)."""
    t = np.linspace(0, 2 * np.pi, 2000, endpoint=False)
    radius = 2000.0 / (2 * np.pi)
    track = Track.from_waypoints(np.stack([radius * np.cos(t), radius * np.sin(t)], 1))
    m = track.n_points
    assert m > 15_000
    n, h = 8, 10
    xy = jnp.zeros((n, h, 2))
    jaxpr = jax.make_jaxpr(_heading_chunk)(track, xy, jnp.zeros((n, 2)), jnp.zeros(n))
    sizes = [int(np.prod(s)) for s in _avals(jaxpr.jaxpr)]
    assert max(sizes) < m, f"an intermediate of {max(sizes)} values on a {m}-point track"

    # and the result equals the global projection's on a drive around the loop
    s0 = np.linspace(0.0, 1500.0, n)
    ang = (s0[:, None] + 2.0 * np.arange(1, h + 1)[None, :]) / radius
    pts = np.stack([(radius + 0.5) * np.cos(ang), (radius + 0.5) * np.sin(ang)], -1)
    start = np.stack([radius * np.cos(s0 / radius), radius * np.sin(s0 / radius)], -1)
    # one compiled program each (op by op, every primitive of the projection compiled alone)
    s_hint = jax.jit(jax.vmap(track.project))(jnp.asarray(start))
    states = State(
        x_m=jnp.asarray(start[:, 0]),
        y_m=jnp.asarray(start[:, 1]),
        yaw_rad=jnp.zeros(n),
        v_mps=jnp.zeros(n),
        s_m=s_hint,
    )
    got = path_heading(track, pts, states)
    want = jax.jit(jax.vmap(jax.vmap(lambda p: track.heading_at(track.project(p)))))(
        jnp.asarray(pts)
    )
    np.testing.assert_allclose(got, np.asarray(want), atol=1e-9)


def test_forged_npy_header_is_refused_before_allocating(tmp_path, capsys):
    """A .npy whose header declares 29 TiB (more than the file holds): one line, exit 2."""
    forged = tmp_path / "forged.npy"
    with open(forged, "wb") as f:  # 1e12 x 4 float64 declared (29 TiB), 3 rows present
        header = {"descr": "<f8", "fortran_order": False, "shape": (10**12, 4)}
        np.lib.format.write_array_header_1_0(f, header)
        f.write(np.zeros((3, 4)).tobytes())
    out = tmp_path / "out.npy"
    wp = tmp_path / "wp.csv"
    wp.write_text("x,y\n" + "\n".join(f"{np.cos(a):.6f},{np.sin(a):.6f}" for a in range(0, 6)))
    argv = ["batch", str(forged), "--waypoints", str(wp), "--preset", "linear", "--out", str(out)]
    assert main(argv) == 2
    line = _one_error_line(capsys)
    assert "header declares" in line and str(forged) in line
    assert not out.exists()


@pytest.mark.parametrize("duration", ["1e12", "nan", "7201"])
def test_simulate_duration_is_limited_up_front(tmp_path, capsys, duration):
    argv = ["simulate", "--track", "oval", "--duration", duration, "--out", str(tmp_path / "d")]
    assert main(argv) == 2
    assert "duration" in _one_error_line(capsys)
    assert not (tmp_path / "d").exists()


@pytest.mark.parametrize("preset", ["default", "seed"])
def test_runner_honours_a_full_size_cars_settings(full_size_drive, preset):
    """The NumPy runner reads wheelbase, steering limit, step and horizon from the config and
    matches the JAX prediction on a full-size drive (parity 1e-6 m)."""
    from fpe_jax.io.config import params_to_config
    from fpe_jax.predict._predict import predict_drive
    from fpe_jax.runner._runner import Runner

    _, res = full_size_drive
    p = with_settings(presets[preset], wheelbase_m=2.578, max_steer_rad=0.5, dt_s=0.05, horizon=24)
    drive = res.drive.slice_time(0.0, 8.0)
    wp = res.centerline_xy_m
    _, want = predict_drive(p, drive, Track.from_waypoints(wp))
    r = Runner(params_to_config(p), wp)
    got = np.stack(
        [r.update(t, x, y, yaw) for t, (x, y), yaw in zip(drive.t_s, drive.xy_m, drive.yaw_rad)]
    )
    assert got.shape == want.shape == (len(drive.t_s), 24, 3)
    assert np.max(np.abs(got[..., :2] - want[..., :2])) <= 1e-6
