"""The real-motion study's loaders and sensor pipeline (experiments/real_drives/run.py) on tiny
synthetic trajectories in the sources' formats, read from a git repository at a commit as the
study reads its mirrors: a MATLAB file with `states` (N, 3) x, y, yaw at a fixed rate, and a
stamped vehicle-state CSV with the track's two edges as header-less x, y[, z] tables."""

from __future__ import annotations

import importlib.util
import io
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.io

from fpe_jax.sim._sim import Sensor, observe

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def study():
    spec = importlib.util.spec_from_file_location(
        "real_drives_run", ROOT / "experiments" / "real_drives" / "run.py"
    )
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # its dataclasses resolve their annotations through it
    spec.loader.exec_module(mod)
    yield mod
    del sys.modules[spec.name]


def circle_poses(rate_hz=60.0, duration_s=16.0, radius_m=1.2, v_mps=1.5, ccw=True):
    """(N, 3) x, y, yaw of a car on a circle centred at (0.5, -2) [m]."""
    t = np.arange(int(duration_s * rate_hz)) / rate_hz
    sign = 1.0 if ccw else -1.0
    ang = sign * v_mps / radius_m * t
    xy = np.stack([0.5 + radius_m * np.cos(ang), -2.0 + radius_m * np.sin(ang)], axis=1)
    yaw = ang + sign * np.pi / 2
    return np.column_stack([xy, np.angle(np.exp(1j * yaw))])


def mat_bytes(states: np.ndarray) -> bytes:
    buf = io.BytesIO()
    scipy.io.savemat(buf, {"states": states, "inputs": np.zeros((len(states), 2))})
    return buf.getvalue()


def git_repo_with(tmp_path: Path, files: dict[str, bytes]) -> tuple[Path, str]:
    """A mirror root holding owner+name/repo with `files` ({path: bytes}) committed;
    -> (root, commit)."""
    repo = tmp_path / "mirror" / "owner+name" / "repo"
    for rel, data in files.items():
        (repo / rel).parent.mkdir(parents=True, exist_ok=True)
        (repo / rel).write_bytes(data)
    run = lambda *a: subprocess.run(["git", "-C", str(repo), *a], check=True, capture_output=True)  # noqa: E731
    run("init", "-q")
    run("add", ".")
    run("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "data")
    return tmp_path / "mirror", run("rev-parse", "HEAD").stdout.decode().strip()


def source(study, commit, rel, track="circle"):
    return study.Source(
        name="synthetic",
        repo="owner/name",
        licence="test",
        commit=commit,
        path=rel,
        rate_hz=60.0,
        track=track,
        description="synthetic circle",
    )


def test_reads_the_file_at_its_commit_and_loads_the_poses(study, tmp_path):
    states = circle_poses()
    root, commit = git_repo_with(tmp_path, {"d/run 1.mat": mat_bytes(states)})
    src = source(study, commit, "d/run 1.mat")
    poses = study.load_mocap_mat(study.read_source(root, src), 60.0, src.name)
    np.testing.assert_array_equal(poses["xy_m"], states[:, :2])
    np.testing.assert_array_equal(poses["yaw_rad"], states[:, 2])
    assert poses["t_s"][1] == pytest.approx(1 / 60.0, abs=1e-15)


def test_absent_mirror_or_file_is_file_not_found(study, tmp_path):
    src = source(study, "0" * 40, "x.mat")
    with pytest.raises(FileNotFoundError, match="no mirror of owner/name"):
        study.read_source(tmp_path, src)
    root, commit = git_repo_with(tmp_path, {"a.mat": b""})
    with pytest.raises(FileNotFoundError, match="b.mat"):
        study.read_source(root, source(study, commit, "b.mat"))


def test_a_file_without_states_is_refused_by_name(study):
    buf = io.BytesIO()
    scipy.io.savemat(buf, {"inputs": np.zeros((5, 2))})
    with pytest.raises(ValueError, match="run.mat: expected an \\(N, 3\\) array 'states'"):
        study.load_mocap_mat(buf.getvalue(), 60.0, "run.mat")


@pytest.mark.parametrize("ccw", [True, False])
def test_circle_waypoints_follow_the_drive(study, ccw):
    st = circle_poses(ccw=ccw)
    loop = study.fit_circle(st[:, :2], st[:, 2])
    np.testing.assert_allclose(np.hypot(loop[:, 0] - 0.5, loop[:, 1] + 2.0), 1.2, atol=1e-9)
    # the loop runs the way the car does: the cross product of radius and step has its sign
    r, step = loop[0] - (0.5, -2.0), loop[1] - loop[0]
    assert np.sign(r[0] * step[1] - r[1] * step[0]) == (1 if ccw else -1)


def test_case_is_the_trajectory_through_the_detector_split_in_time(study):
    st = circle_poses()
    poses = dict(t_s=np.arange(len(st)) / 60.0, xy_m=st[:, :2], yaw_rad=st[:, 2])
    case = study.make_case(source(study, "0" * 40, "x.mat"), poses, seed=3)
    fit, test = case.fit_drive, case.test_drive
    # 60 / 40 in time, and no detection in both
    t_end = poses["t_s"][-1]
    assert fit.t_s[-1] <= 0.6 * t_end < test.t_s[0]
    # detections at the detector's rate (11.5 Hz less ~2 % dropouts) arrive 0.3 s after capture
    n = len(fit.t_s) + len(test.t_s)
    assert 0.85 * 11.5 * t_end < n < 1.05 * 11.5 * t_end
    assert fit.t_s[0] >= study.LATENCY_S
    # truth is the recorded trajectory itself
    np.testing.assert_array_equal(fit.truth_xy_m, st[: len(fit.truth_xy_m), :2])
    # detections lie near the truth at their capture time (noise + rare 0.5-2 m outliers)
    cap = fit.t_s - study.LATENCY_S
    true_xy = np.stack([np.interp(cap, poses["t_s"], st[:, c]) for c in (0, 1)], axis=1)
    err = np.linalg.norm(fit.xy_m - true_xy, axis=1)
    assert np.median(err) < 0.15 and np.mean(err < 0.5) > 0.9


def test_observe_with_a_clean_sensor_reports_the_truth_after_the_delay():
    st = circle_poses(duration_s=4.0)
    t = np.arange(len(st)) / 60.0 + 100.0  # an offset time origin is kept
    d = observe(t, st[:, :2], st[:, 2], st[:, :2], latency_s=0.25, seed=1, sensor=Sensor.clean())
    cap = d.t_s - 0.25
    assert cap[0] >= 100.0 and d.t_s[-1] <= t[-1] + 1e-9
    true_xy = np.stack([np.interp(cap, t, st[:, c]) for c in (0, 1)], axis=1)
    np.testing.assert_allclose(d.xy_m, true_xy, atol=1e-12)
    # the same seed gives the same detections
    d2 = observe(t, st[:, :2], st[:, 2], st[:, :2], latency_s=0.25, seed=1, sensor=Sensor.clean())
    np.testing.assert_array_equal(d.t_s, d2.t_s)


def test_observe_refuses_stamps_that_go_back():
    st = circle_poses(duration_s=1.0)
    t = np.arange(len(st)) / 60.0
    t[5] = t[4]
    with pytest.raises(Exception, match="strictly increasing"):
        observe(t, st[:, :2], st[:, 2], st[:, :2])


def test_the_real_sources_load_from_the_mirror(study):
    """Every registered source reads from its mirror where one is present (skipped without)."""
    import os

    root = Path(os.environ.get("FPE_MIRROR", "/work/.mirror"))
    present = [s for s in study.SOURCES if study.mirror_dir(root, s).is_dir()]
    if not present:
        pytest.skip(f"no source mirror under {root} (set FPE_MIRROR to a folder of git mirrors)")
    for src in present:
        poses, edges = study.load_source(root, src)
        assert len(poses["t_s"]) > 300 and np.all(np.isfinite(poses["xy_m"]))
        assert len(edges) == (2 if src.track == "edges" else 0)


@pytest.fixture(scope="module")
def diagnosis():
    spec = importlib.util.spec_from_file_location(
        "real_drives_diagnose", ROOT / "experiments" / "real_drives" / "diagnose.py"
    )
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize("ccw", [True, False])
def test_the_diagnosis_finds_the_circle_and_a_slide(diagnosis, ccw):
    """The circle through a drive's positions (centre, radius) and the angle from the yaw to
    the direction of motion: 0 for a car heading where it goes, the added angle for a car
    whose yaw is turned from it."""
    st = circle_poses(ccw=ccw)
    t = np.arange(len(st)) / 60.0
    centre, radius = diagnosis.circle(st[:, :2])
    np.testing.assert_allclose(centre, (0.5, -2.0), atol=1e-9)
    assert radius == pytest.approx(1.2, abs=1e-9)
    assert diagnosis.slip_deg(t, st[:, :2], st[:, 2]) == pytest.approx(0.0, abs=0.01)
    turned = st[:, 2] - np.radians(4.0)  # the yaw 4 deg to the right of the motion
    assert diagnosis.slip_deg(t, st[:, :2], turned) == pytest.approx(4.0, abs=0.01)


def test_the_steady_part_leaves_out_the_run_up_and_the_stop(study):
    """A car that starts at rest, circles at 1.5 m/s and stops: the steady part is where it
    covers at least 80 % of its median speed over half a second, and nothing else changes."""
    st = circle_poses(duration_s=12.0)
    t = np.arange(len(st)) / 60.0
    # along the same circle: still for 1 s, up to speed by 2 s, steady, stopped from 11 s on
    v = np.interp(t, [0.0, 1.0, 2.0, 10.0, 11.0, 12.0], [0.0, 0.0, 1.5, 1.5, 0.0, 0.0])
    ang = np.concatenate([[0.0], np.cumsum(v[1:] * np.diff(t))]) / 1.2
    xy = np.stack([0.5 + 1.2 * np.cos(ang), -2.0 + 1.2 * np.sin(ang)], axis=1)
    poses = dict(t_s=t, xy_m=xy, yaw_rad=ang + np.pi / 2)
    part = study.steady_part(poses)
    # 80 % of 1.5 m/s is reached 1.8 s in (the window's mean speed lags by nothing on a ramp:
    # it is centred) and left 10.2 s in, to within a frame and the chord's shortfall
    assert part["t_s"][0] == pytest.approx(1.8, abs=0.05)
    assert part["t_s"][-1] == pytest.approx(10.2, abs=0.05)
    rows = slice(int(np.argmin(np.abs(t - part["t_s"][0]))), None)
    np.testing.assert_array_equal(part["xy_m"], xy[rows][: len(part["t_s"])])
    # a steady recording is kept whole but for its first and last quarter second
    whole = dict(t_s=t, xy_m=st[:, :2], yaw_rad=st[:, 2])
    assert len(study.steady_part(whole)["t_s"]) == len(t) - 30


# --- stamped state CSV with track edges (the IAC sources) ---------------------------------------

STATE_HEADER = "# time(s),x(m),y(m),vx(m/s),vy(m/s),phi(rad),delta(rad),omega(rad/s)"
EPOCH_NS = 1692117187_463807580


def ring(radius_m: float, n: int, z: float | None = None) -> np.ndarray:
    """(n, 2 or 3) points of a counter-clockwise circle about the origin, open (no repeat)."""
    a = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    xy = radius_m * np.stack([np.cos(a), np.sin(a)], axis=1)
    return xy if z is None else np.column_stack([xy, np.full(n, z)])


def state_csv(t_s: np.ndarray, xy: np.ndarray, yaw: np.ndarray) -> bytes:
    """The poses as the sources' CSV: epoch stamps (t_s after EPOCH_NS, to the nanosecond),
    the header as a comment line."""
    rows = [STATE_HEADER]
    for t, (x, y), p in zip(t_s, xy, yaw):
        ns = EPOCH_NS + round(t * 1e9)
        rows.append(f"{ns // 10**9}.{ns % 10**9:09d},{x:.8f},{y:.8f},0.0,0.0,{p:.8f},0.0,0.0")
    return ("\n".join(rows) + "\n").encode()


def oval_drive(rate_hz=25.0, v_mps=20.0, radius_m=98.0):
    """A car 2 s at rest in a pit 30 m inside a ring track (edges at 95 m and 105 m), 1 s to
    drive onto the track, 30 s round it counter-clockwise at v, 2 s at rest, 2 s on again:
    (t_s, xy, yaw)."""
    t = np.arange(int(37.0 * rate_hz)) / rate_hz
    ang = np.zeros_like(t)
    r = np.full_like(t, radius_m)
    pit = t < 3.0
    r[t < 2.0] = radius_m - 30.0
    r[(t >= 2.0) & pit] = radius_m - 30.0 * (3.0 - t[(t >= 2.0) & pit])
    lap = (t >= 3.0) & (t < 33.0)
    ang[lap] = v_mps / radius_m * (t[lap] - 3.0)
    ang[t >= 33.0] = ang[lap][-1]
    again = t >= 35.0
    ang[again] += v_mps / radius_m * (t[again] - 35.0)
    xy = np.stack([r * np.cos(ang), r * np.sin(ang)], axis=1)
    return t, xy, ang + np.pi / 2


def state_source(study, commit, edges=("e/inner.csv", "e/outer.csv")):
    return study.Source(
        name="synthetic oval",
        repo="owner/name",
        licence="test",
        commit=commit,
        path="d/run.csv",
        rate_hz=None,
        track="edges",
        description="synthetic oval",
        reader="state-csv",
        edges=edges,
        min_speed_mps=5.0,
    )


def table_bytes(a: np.ndarray) -> bytes:
    return ("\n".join(",".join(repr(float(v)) for v in row) for row in a) + "\n").encode()


def test_the_state_csv_keeps_its_stamps_positions_and_yaw(study):
    t, xy, yaw = oval_drive()
    poses = study.load_state_csv(state_csv(t, xy, yaw), "d/run.csv")
    # stamps from the first one, exact to the nanosecond: an epoch stamp in float64 would
    # already be off by up to 1.2e-7 s
    np.testing.assert_allclose(poses["t_s"], t, atol=1e-12)
    np.testing.assert_allclose(poses["xy_m"], xy, atol=1e-8)
    np.testing.assert_allclose(poses["yaw_rad"], yaw, atol=1e-8)


def test_a_state_csv_without_the_columns_or_stamps_is_refused_by_name(study):
    bad = b"# time(s),x(m),y(m)\n1.0,0.0,0.0\n2.0,1.0,0.0\n3.0,2.0,0.0\n"
    with pytest.raises(ValueError, match="run.csv: expected columns time, x, y, phi"):
        study.load_state_csv(bad, "d/run.csv")
    t, xy, yaw = oval_drive()
    t[5] = t[4]
    with pytest.raises(ValueError, match="run.csv: .*increasing stamps"):
        study.load_state_csv(state_csv(t, xy, yaw), "d/run.csv")
    with pytest.raises(ValueError, match="run.csv: line 3 has 2 cells"):
        study.load_state_csv(b"# time(s),x(m),y(m),phi\n1,0,0,0\n2,0\n", "d/run.csv")


def test_the_moving_part_ends_at_the_first_stop(study):
    t, xy, yaw = oval_drive()
    part = study.moving_part(dict(t_s=t, xy_m=xy, yaw_rad=yaw), 5.0)
    # the speed over 12 rows (0.48 s) centred: out of the pit at 30 m/s from 2 s, it covers
    # 5 m/s x 0.48 s from t = 2 - 0.24 + 0.08; stopping from 20 m/s after its last move at
    # 32.96 s, until t = 32.96 + 0.24 - 0.12 (each to a row: 0.04 s)
    assert part["t_s"][0] == pytest.approx(1.84, abs=0.041)
    assert part["t_s"][-1] == pytest.approx(33.08, abs=0.041)
    with pytest.raises(ValueError, match="never reaches 50"):
        study.moving_part(dict(t_s=t, xy_m=xy, yaw_rad=yaw), 50.0)


def test_the_centre_line_is_midway_and_runs_the_cars_way(study):
    inner, outer = ring(95.0, 600), ring(105.0, 653)
    t, xy, yaw = oval_drive()
    lap = (t >= 3.0) & (t < 33.0)
    for sign in (1.0, -1.0):  # counter-clockwise, then the mirror image: clockwise
        m = np.array([1.0, sign])
        mid = study.centre_line((inner * m, outer * m), xy[lap] * m, sign * yaw[lap])
        # midway to within the outer ring's 0.1 m densified chords
        np.testing.assert_allclose(np.hypot(*mid.T), 100.0, atol=0.01)
        step = mid[1] - mid[0]
        assert np.sign(mid[0, 0] * step[1] - mid[0, 1] * step[0]) == sign


def test_a_drive_from_the_pit_starts_where_it_joins_the_track(study):
    t, xy, yaw = oval_drive()
    poses = dict(t_s=t, xy_m=xy, yaw_rad=yaw)
    part = study.from_track_entry(poses, (ring(95.0, 600), ring(105.0, 653)))
    # the first pose within 5 m of the 100 m centre: r = 68 + 30 (t - 2) >= 95 from t = 2.9 s
    assert part["t_s"][0] == pytest.approx(2.92, abs=1e-9)
    np.testing.assert_array_equal(part["xy_m"], xy[t >= 2.9 + 1e-9])
    with pytest.raises(ValueError, match="never within 5.0 m"):
        study.from_track_entry(poses, (ring(195.0, 600), ring(205.0, 653)))


def test_an_edges_source_loads_from_its_mirror_and_becomes_a_case(study, tmp_path):
    t, xy, yaw = oval_drive()
    root, commit = git_repo_with(
        tmp_path,
        {
            "d/run.csv": state_csv(t, xy, yaw),
            "e/inner.csv": table_bytes(ring(95.0, 600, z=-34.0)),
            "e/outer.csv": table_bytes(ring(105.0, 653, z=-34.0)),
        },
    )
    src = state_source(study, commit)
    poses, edges = study.load_source(root, src)
    assert [e.shape for e in edges] == [(600, 2), (653, 2)]
    # on the track from 2.92 s to its stop (`moving_part`): the pit and the second stint left
    # out
    assert poses["t_s"][0] == pytest.approx(2.92, abs=1e-6)
    assert poses["t_s"][-1] == pytest.approx(33.08, abs=0.041)
    case = study.make_case(src, poses, 0, edges)
    np.testing.assert_allclose(np.hypot(*case.waypoints_xy_m.T), 100.0, atol=0.01)
    fit, test = case.fit_drive, case.test_drive
    split = fit.t_s[0] + 0.6 * (test.t_s[-1] - fit.t_s[0])  # 60 / 40 of the detections' time
    assert fit.t_s[-1] <= split < test.t_s[0]
    assert poses["t_s"][0] + study.LATENCY_S <= fit.t_s[0] and test.t_s[-1] <= poses["t_s"][-1]
    with pytest.raises(FileNotFoundError, match="e/missing.csv"):
        study.read_edges(root, state_source(study, commit, ("e/inner.csv", "e/missing.csv")))
    with pytest.raises(ValueError, match="needs the two edges, got 0"):
        study.make_case(src, poses, 0)
