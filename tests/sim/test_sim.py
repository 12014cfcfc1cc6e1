"""The drive simulator and its built-in tracks: determinism, latency, realism, sensor statistics,
files written by `fpe simulate`."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fpe_jax import cli, io
from fpe_jax.errors import InputError
from fpe_jax.geometry._tracks import builtin_track, loop_arclength, loop_curvature, resample_loop
from fpe_jax.sim._sim import Driver, Sensor, SimResult, simulate

BUILTINS = ["oval", "hairpin", "random:0", "random:6"]


@pytest.fixture(scope="module")
def drives() -> dict[str, SimResult]:
    """One 120 s default drive per built-in track (shared by the realism tests)."""
    return {name: simulate(name, duration_s=120.0, seed=1) for name in BUILTINS}


def _distance_to_loop(points_m: np.ndarray, loop_m: np.ndarray) -> np.ndarray:
    """Distance [m] from every 5th point (P, 2) to a closed loop (K, 2), to within 1 cm."""
    dense = resample_loop(loop_m, 0.02)[0]
    return np.array([np.sqrt(np.min(np.sum((dense - p) ** 2, axis=1))) for p in points_m[::5]])


def _truth_at(res: SimResult, t_s: np.ndarray) -> np.ndarray:
    """(N, 2) true position at times t_s, linearly interpolated from the 50 Hz truth."""
    d = res.drive
    return np.stack([np.interp(t_s, d.truth_t_s, d.truth_xy_m[:, c]) for c in (0, 1)], axis=1)


# --- determinism and the time base --------------------------------------------------------------


def test_same_seed_same_drive_other_seed_other_drive():
    a, b = (simulate("hairpin", duration_s=20.0, seed=5) for _ in range(2))
    for field in ("t_s", "xy_m", "yaw_rad", "truth_t_s", "truth_xy_m", "truth_yaw_rad"):
        np.testing.assert_array_equal(getattr(a.drive, field), getattr(b.drive, field))
    np.testing.assert_array_equal(a.outlier, b.outlier)
    assert a.scenario == b.scenario
    c = simulate("hairpin", duration_s=20.0, seed=6)
    assert not np.array_equal(a.drive.truth_xy_m, c.drive.truth_xy_m)


def test_time_base_truth_rate_and_scenario():
    res = simulate("oval", duration_s=10.0, latency_s=0.25, seed=2)
    d = res.drive
    assert d.truth_t_s[0] == 0.0 and d.truth_t_s[-1] == pytest.approx(10.0)
    np.testing.assert_allclose(np.diff(d.truth_t_s), 0.02, atol=1e-9)  # 50 Hz
    assert d.t_s[0] >= 0.25 and d.t_s[-1] <= 10.0
    np.testing.assert_allclose(d.t_s - res.capture_t_s, 0.25, atol=1e-12)
    assert np.all(np.abs(d.truth_yaw_rad) <= np.pi) and np.all(np.abs(d.yaw_rad) <= np.pi)
    s = res.scenario
    assert (s["track"], s["seed"], s["latency_s"], s["duration_s"]) == ("oval", 2, 0.25, 10.0)
    assert {"sim_version", "vehicle", "driver", "sensor"} <= set(s)
    json.dumps(s)  # every setting is JSON-serialisable
    assert res.centerline_xy_m.shape[1] == 2 and res.half_width_m == 1.1


@pytest.mark.parametrize("latency_s", [0.0, 0.3, 0.45])
def test_latency_is_exactly_what_was_asked(latency_s):
    res = simulate("hairpin", duration_s=30.0, latency_s=latency_s, seed=3, sensor=Sensor.clean())
    d = res.drive
    lags = np.arange(0.0, 0.8, 0.005)
    err = [np.median(np.linalg.norm(d.xy_m - _truth_at(res, d.t_s - lag), axis=1)) for lag in lags]
    assert abs(lags[int(np.argmin(err))] - latency_s) <= 0.02
    # Noise-free detections are the truth `latency_s` before their stamp (up to interpolation).
    ok = d.t_s - latency_s >= 0
    gap = np.linalg.norm(d.xy_m[ok] - _truth_at(res, d.t_s[ok] - latency_s), axis=1)
    assert gap.max() < 0.01


# --- the car: speeds, on track, stops -----------------------------------------------------------


@pytest.mark.parametrize("name", BUILTINS)
def test_speeds_within_2_to_8_mps(drives, name):
    v = drives[name].drive.truth_v_mps
    assert v.min() >= 2.0 and v.max() <= 8.0
    assert v.max() - v.min() > 0.5  # it does slow down for turns


@pytest.mark.parametrize("name", BUILTINS)
def test_car_stays_on_track(drives, name):
    res = drives[name]
    off_m = _distance_to_loop(res.drive.truth_xy_m, res.centerline_xy_m)
    assert off_m.max() < res.half_width_m  # the car's centre stays on the track surface
    assert off_m.max() > 0.1  # and it does not just trace the centerline


def test_speed_factor_scales_the_pace_from_the_start():
    """A drive at speed factor f starts at f times the default drive's speed (not at the
    unscaled pace, braking down to its own) and never exceeds f times the top speed."""
    base = simulate("oval", duration_s=10.0, seed=5).drive.truth_v_mps
    slow = simulate("oval", duration_s=10.0, seed=5, driver=Driver(speed_factor=0.5))
    v = slow.drive.truth_v_mps
    assert v[0] == pytest.approx(0.5 * base[0], rel=1e-12)
    assert v.max() <= 0.5 * Driver().v_max_mps


def test_stops_brake_to_zero_wait_and_go_on():
    res = simulate("oval", duration_s=120.0, seed=4, driver=Driver(stops_per_min=3.0))
    v = res.drive.truth_v_mps
    stopped = v < 0.05
    starts = np.flatnonzero(np.diff(stopped.astype(int)) == 1)
    ends = np.flatnonzero(np.diff(stopped.astype(int)) == -1)
    assert len(starts) >= 2 and len(ends) >= 2
    waits_s = [(e - s) * 0.02 for s, e in zip(starts, ends[ends > starts[0]])]
    assert all(0.9 <= w <= 3.2 for w in waits_s)
    assert v.min() >= 0.0 and v.max() <= 8.0
    assert np.all(np.isfinite(res.truth_yaw_rate_rps)) and np.abs(res.truth_yaw_rate_rps).max() < 5


# --- the sensor ---------------------------------------------------------------------------------


@pytest.mark.parametrize("name", BUILTINS)
def test_detection_rate_10_to_12_hz(drives, name):
    d = drives[name].drive
    rate_hz = (len(d.t_s) - 1) / (d.t_s[-1] - d.t_s[0])
    assert 10.0 <= rate_hz <= 12.0
    dt = np.diff(d.t_s)
    assert dt.std() > 0.005  # jittered, not a fixed clock


def test_outlier_fraction_about_one_percent():
    res = simulate("oval", duration_s=400.0, seed=7, sensor=Sensor.clean(outlier_prob=0.01))
    d = res.drive
    jump_m = np.linalg.norm(d.xy_m - _truth_at(res, res.capture_t_s), axis=1)
    big = jump_m > 0.4
    assert 0.005 <= big.mean() <= 0.02
    np.testing.assert_array_equal(big, res.outlier)
    assert jump_m[big].min() >= 0.49 and jump_m[big].max() <= 2.01


def test_noise_grows_with_range_and_yaw_noise(drives):
    res = drives["oval"]
    d, ok = res.drive, ~res.outlier
    err = np.linalg.norm(d.xy_m - _truth_at(res, res.capture_t_s), axis=1)[ok]
    rng_m = res.range_m[ok]
    assert 1.8 <= rng_m.min() and rng_m.max() <= 4.2  # the trailing car is 2-4 m behind
    near, far = err[rng_m < 2.6], err[rng_m > 3.4]
    assert np.median(far) > 1.2 * np.median(near)
    assert 0.05 < np.sqrt(np.mean((err / rng_m) ** 2)) < 0.1  # ~5-10 % of range (thesis)
    truth_yaw = np.interp(res.capture_t_s, d.truth_t_s, np.unwrap(d.truth_yaw_rad))
    yaw_err = np.angle(np.exp(1j * (d.yaw_rad - truth_yaw)))
    assert 0.04 < yaw_err.std() < 0.06


def test_dropouts_are_more_likely_in_fast_turns():
    kw = dict(duration_s=300.0, seed=8)
    every = simulate("hairpin", **kw, sensor=Sensor.clean())  # same capture times, no misses
    some = simulate("hairpin", **kw, sensor=Sensor.clean(miss_prob=0.02, miss_per_radps=0.3))
    missed = ~np.isin(every.capture_t_s, some.capture_t_s)
    d = every.drive
    yaw_rate = np.abs(np.interp(every.capture_t_s, d.truth_t_s, every.truth_yaw_rate_rps))
    slow, fast = missed[yaw_rate < 0.5].mean(), missed[yaw_rate > 1.8].mean()
    assert slow < 0.05 and fast > 2 * slow
    assert some.drive.meta["n_dropped"] == missed.sum()


# --- tracks -------------------------------------------------------------------------------------


def test_builtin_track_shapes():
    oval, hw = builtin_track("oval")
    assert hw == 1.1 and np.ptp(oval, axis=0) == pytest.approx([30.0, 12.0], abs=0.1)
    hairpin, hw = builtin_track("hairpin")
    assert 1.4 < 1.0 / np.abs(loop_curvature(hairpin)).max() < 1.6 and hw < 1.4
    for seed in range(5):
        xy, hw = builtin_track(f"random:{seed}")
        assert 60.0 <= loop_arclength(xy)[-1] <= 120.0
        # Distant parts of the loop stay apart: no self-intersection, no touching track surfaces.
        s = loop_arclength(xy)[:-1]
        far = np.abs(s[:, None] - s[None, :])
        far = np.minimum(far, s[-1] - far) > 6.0
        dist = np.linalg.norm(xy[:, None] - xy[None, :], axis=-1)
        assert dist[far].min() > 2 * hw
    a, b = builtin_track("random:3")[0], builtin_track("random:4")[0]
    assert a.shape != b.shape or not np.allclose(a, b)
    with pytest.raises(InputError, match="unknown built-in track"):
        builtin_track("square")


def test_bad_arguments_raise_input_error():
    with pytest.raises(InputError, match="duration"):
        simulate("oval", duration_s=0.0)
    with pytest.raises(InputError, match="latency"):
        simulate("oval", duration_s=1.0, latency_s=-0.1)


def test_f1tenth_raceline_drive(shared_data):
    tracks = shared_data / "tracks"
    res = simulate(
        tracks / "Spielberg_centerline.csv",
        raceline=tracks / "Spielberg_raceline.csv",
        duration_s=60.0,
        seed=0,
    )
    v = res.drive.truth_v_mps
    assert v.min() >= 2.0 and v.max() <= 8.0
    assert _distance_to_loop(res.drive.truth_xy_m, res.centerline_xy_m).max() < 1.1 + 0.15
    # The centerline (not the raceline) is what predictors get.
    np.testing.assert_array_equal(
        res.centerline_xy_m, io.load_waypoints(tracks / "Spielberg_centerline.csv").xy_m
    )
    assert res.scenario["track"] == "Spielberg_centerline"


# --- `fpe simulate` -----------------------------------------------------------------------------


def test_cli_simulate_writes_three_files_and_refuses_a_used_folder(tmp_path, capsys):
    out = tmp_path / "sim"
    argv = ["simulate", "--track", "hairpin", "--duration", "8", "--latency", "0.4"]
    argv += ["--seed", "2", "--out", str(out)]
    assert cli.main(argv) == 0
    assert sorted(p.name for p in out.iterdir()) == ["drive.mcap", "scenario.json", "waypoints.csv"]
    assert (out / "waypoints.csv").read_text().splitlines()[0] == "x,y"
    scenario = json.loads((out / "scenario.json").read_text())
    assert (scenario["track"], scenario["seed"], scenario["latency_s"]) == ("hairpin", 2, 0.4)

    expected = simulate("hairpin", duration_s=8.0, latency_s=0.4, seed=2)
    drive = io.load_drive(out / "drive.mcap")
    np.testing.assert_allclose(drive.t_s, expected.drive.t_s, atol=1e-9)
    np.testing.assert_allclose(drive.xy_m, expected.drive.xy_m, atol=1e-9)
    np.testing.assert_allclose(drive.truth_xy_m, expected.drive.truth_xy_m, atol=1e-9)
    waypoints = io.load_waypoints(out / "waypoints.csv").xy_m
    np.testing.assert_allclose(waypoints, expected.centerline_xy_m, atol=1e-6)

    capsys.readouterr()
    assert cli.main(argv) == 2  # an existing, non-empty folder
    assert "not empty" in capsys.readouterr().err
    assert cli.main([*argv, "--force"]) == 0


def test_simulate_folder_that_is_a_file(tmp_path):
    target = tmp_path / "taken"
    target.write_text("")
    assert cli.main(["simulate", "--duration", "2", "--out", str(target)]) == 2
