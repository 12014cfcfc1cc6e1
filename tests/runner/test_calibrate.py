"""Online calibration of the ellipses (fpe_jax.runner._calibrate, AdaptiveRunner(calibrate=True)):
the update's exact values on a hand-made case, the runner's scales against a JAX computation of
the same update over whole arrays, its saved state, and that it runs without JAX."""

import copy
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import CHECK_NO_JAX, NO_JAX

from fpe_jax.errors import InputError
from fpe_jax.io.config import read_config, write_config
from fpe_jax.runner._adapt import AdaptiveRunner, start_config
from fpe_jax.runner._calibrate import EllipseCalibration
from fpe_jax.sim._sim import simulate

BASE = [[[0.09, 0.0], [0.0, 0.04]], [[0.16, 0.0], [0.0, 0.25]]]  # sd 0.3 / 0.2, 0.4 / 0.5 m


def test_the_update_on_a_hand_made_case():
    """One prediction along +x (the path heading 0), steps at 1 and 2 m; decay 0.5, n0 1."""
    cal = EllipseCalibration(BASE, dt_s=0.1, delay_s=0.3, decay=0.5, prior_samples=1.0)
    assert cal.record(10.0, [[1.0, 0.0], [2.0, 0.0]], [0.0, 0.0])
    assert not cal.record(10.04, [[9.0, 9.0], [9.0, 9.0]], [0.0, 0.0])  # within dt / 2
    # seen at 10.4 - 0.3 = 10.1 s: step 1; residual (0.6, 0.2): z = (4, 1)
    assert cal.observe(10.4, 1.6, 0.2) == 1
    np.testing.assert_allclose(cal.scale, [[2.5, 1.0], [2.5, 1.0]], rtol=1e-15)
    # the same step again is not realised twice
    assert cal.observe(10.42, 5.0, 5.0) == 0
    # 10.46 s -> u = 1.6: step 2 against (1.6, 0) between the steps: residual (0, 0.5), z = (0, 1)
    assert cal.observe(10.46, 1.6, 0.5) == 1
    # step 2: ((0, 1) + 1 x (2.5, 1)) / (1 + 1)
    np.testing.assert_allclose(cal.scale, [[2.5, 1.0], [1.25, 1.0]], rtol=1e-12, atol=1e-12)
    assert cal.errors == 2 and cal.weights.tolist() == [1.0, 1.0]
    # a prediction turned by 90 deg: along is +y; a second error of step 1 decays the first
    cal.record(20.0, [[0.0, 1.0], [0.0, 2.0]], [math.pi / 2, math.pi / 2])
    assert cal.observe(20.4, 0.3, 1.3) == 1  # residual (0.3, 0.3): along 0.3, cross -0.3
    # step 1: S = 0.5 (4, 1) + (1, 2.25), W = 1.5; scale = (S + (1, 1)) / 2.5
    want1 = (np.array([2.0, 0.5]) + [1.0, 2.25] + 1.0) / 2.5
    np.testing.assert_allclose(cal.scale[0], want1, rtol=1e-12)
    # step 2 leans on step 1 through the prior: S = (0, 1), W = 1 before, no new error
    np.testing.assert_allclose(cal.scale[1], (np.array([0.0, 1.0]) + want1) / 2.0, rtol=1e-12)
    # the covariance: the variances scaled, the correlation kept
    corr = [[[1.0, 0.0], [0.0, 4.0]], [[4.0, 1.0], [1.0, 1.0]]]
    cal2 = EllipseCalibration(corr, dt_s=0.1, delay_s=0.0)
    cal2.scale[:] = [[4.0, 9.0], [1.0, 4.0]]
    np.testing.assert_allclose(
        cal2.covariance(), [[[4.0, 0.0], [0.0, 36.0]], [[4.0, 2.0], [2.0, 4.0]]], rtol=1e-15
    )


def test_bounded_and_reset():
    """At 100 Hz every step of every prediction is realised once; the predictions held stay
    within the bound; a reset forgets the pending ones and keeps the scales."""
    h = 5
    cal = EllipseCalibration([np.eye(2) * 0.01] * h, dt_s=0.1, delay_s=0.2)
    xy = np.zeros((h, 2))
    stamps, want = [], 0
    for k in range(300):
        t = k * 0.01
        cal.observe(t, 0.0, 0.0)
        if cal.record(t, xy, np.zeros(h)):
            stamps.append(t)
        assert len(cal._pending) <= 2 * (h + 2) + 4
    assert 0.05 <= min(np.diff(stamps)) and max(np.diff(stamps)) <= 0.06 + 1e-9
    # each recorded prediction has realised each step whose time (less the delay, within half
    # a step) has come by the last observation
    for t0 in stamps:
        want += sum(1 for s in range(1, h + 1) if math.floor((2.99 - 0.2 - t0) / 0.1 + 0.5) >= s)
    assert cal.errors == want
    # no error at all (the prediction was right): each step n0 / (W + n0) of the one before
    want_scale = np.cumprod(5.0 / (cal.weights + 5.0))
    np.testing.assert_allclose(cal.scale, np.stack([want_scale] * 2, -1), rtol=1e-12)
    scale = cal.scale.copy()
    cal.reset()
    assert len(cal._pending) == 0 and cal.observe(10.0, 1.0, 1.0) == 0
    np.testing.assert_array_equal(cal.scale, scale)


@pytest.mark.parametrize(
    "cov, kw, words",
    [
        ([[[0.0, 0.0], [0.0, 1.0]]], {}, "zero variance"),
        ([[1.0, 0.0]], {}, "(H, 2, 2)"),
        ([np.eye(2).tolist()], {"decay": 0.0}, "calibration decay"),
        ([np.eye(2).tolist()], {"prior_samples": 0.0}, "prior_samples"),
    ],
)
def test_bad_settings_are_refused(cov, kw, words):
    with pytest.raises(InputError, match=words.replace("(", r"\(").replace(")", r"\)")):
        EllipseCalibration(cov, 0.1, 0.3, **kw)


@jax.jit
def calibration_jax(obs, rec_t, rec_xy, rec_heading, rec_obs, rec_seg, var, consts):
    """The scales (H, 2) of the calibration written over whole arrays: obs (I, 4) stamp [s],
    x, y [m] and segment (the resets between) of each observation in order; the recorded
    predictions' stamps (J,), positions (J, H, 2), headings (J, H), the index of the last
    observation before each was recorded (J,) and their segments (J,); var (H, 2) the base
    variances; consts (dt, delay, decay, n0). Every pair (observation i, prediction j) of a
    segment with i after j's recording realises step h = round(u) the first time it is met."""
    dt, delay, decay, n0 = consts
    n_steps = var.shape[0]
    u = (obs[:, None, 0] - delay - rec_t[None, :]) / dt  # (I, J)
    int_t = rec_obs.dtype
    h = jnp.floor(u + 0.5).astype(int_t)
    i = jnp.arange(obs.shape[0], dtype=int_t)[:, None]
    ok = (obs[:, None, 3] == rec_seg[None, :]) & (i > rec_obs[None, :])
    ok = ok & (h >= 1) & (h <= n_steps)
    prev_same = jnp.concatenate([jnp.zeros_like(ok[:1]), ok[:-1] & (h[:-1] == h[1:])])
    first = ok & ~prev_same
    lo = jnp.floor(u).astype(int_t)
    f = u - lo.astype(u.dtype)
    a = jnp.clip(lo, 1, n_steps) - 1
    b = jnp.clip(lo + 1, 1, n_steps) - 1
    j = jnp.arange(rec_t.shape[0], dtype=int_t)[None, :]
    pa, pb = rec_xy[j, a], rec_xy[j, b]  # (I, J, 2)
    p = jnp.where((lo >= 1) & (lo < n_steps), f, 0.0)[..., None] * (pb - pa) + pa
    r = obs[:, None, 1:3] - p
    hh = jnp.clip(h, 1, n_steps) - 1
    head = rec_heading[j, hh]
    c, s = jnp.cos(head), jnp.sin(head)
    along, cross = c * r[..., 0] + s * r[..., 1], -s * r[..., 0] + c * r[..., 1]
    z = jnp.stack([along**2, cross**2], -1) / var[hh]  # (I, J, 2)

    def sums(k):  # step k + 1's decayed sums, in order of observation then recording
        m = (first & (hh == k)).ravel().astype(jnp.float64)
        later = jnp.sum(m) - jnp.cumsum(m)
        w = m * decay**later
        return w @ z.reshape(-1, 2), jnp.sum(w)

    sum_z, weight = jax.vmap(sums)(jnp.arange(n_steps, dtype=int_t))

    def chain(prev, k):
        out = (sum_z[k] + n0 * prev) / (weight[k] + n0)
        return out, out

    return jax.lax.scan(chain, jnp.ones(2), jnp.arange(n_steps, dtype=int_t))[1]


def _config_with_ellipses(wp, horizon=10):
    cfg = start_config(None, wp, settings={"horizon": horizon}, delay_s=0.3)
    steps = np.arange(1, horizon + 1)
    cov = [[[0.01 * k, 0.001 * k], [0.001 * k, 0.004 * k]] for k in steps]
    return cfg | {"uncertainty": {"frame": "track", "cov_m2": cov}}


class Captured(AdaptiveRunner):
    """Keeps what its calibration was given: observations (stamp, x, y, segment) and recorded
    predictions (stamp, xy, heading, the last observation's index, segment)."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.obs, self.recs, self.seg = [], [], 0
        cal = self.calibration
        observe, record = cal.observe, cal.record

        def obs(t, x, y):
            self.obs.append((t, x, y, self.seg))
            return observe(t, x, y)

        def rec(t, xy, heading):
            kept = record(t, xy, heading)
            if kept:
                self.recs.append((t, np.array(xy), np.array(heading), len(self.obs) - 1, self.seg))
            return kept

        cal.observe, cal.record = obs, rec

    def reset(self):
        super().reset()
        self.seg = getattr(self, "seg", 0) + 1


def _scales_jax(r: Captured):
    cal = r.calibration
    t, xy, head, at, seg = (np.array(v) for v in zip(*r.recs))
    var = np.stack([cal.base[:, 0, 0], cal.base[:, 1, 1]], -1)
    consts = jnp.array([cal.dt_s, cal.delay_s, cal.decay, cal.prior_samples])
    return calibration_jax(np.array(r.obs), t, xy, head, at, seg.astype(float), var, consts)


def test_the_runners_calibration_matches_a_jax_computation():
    """The oval at the detector's rate, with a restarted clock in the middle: the incremental
    scales equal the whole-array computation; the predictions are those without it."""
    res = simulate("oval", duration_s=30.0, seed=5)
    wp, drive = res.centerline_xy_m, res.drive
    cfg = _config_with_ellipses(wp)
    r = Captured(cfg, wp, calibrate=True)
    plain = AdaptiveRunner(copy.deepcopy(cfg), wp)
    half = len(drive.t_s) // 2
    rows = list(zip(drive.t_s.tolist(), drive.xy_m.tolist(), drive.yaw_rad.tolist()))
    for k, (t, (x, y), yaw) in enumerate(rows):
        if k == half:  # out of sight, then the clock restarts
            r.reset(), plain.reset()
        t = t - drive.t_s[half] + 0.5 if k >= half else t
        np.testing.assert_array_equal(r.update(t, x, y, yaw), plain.update(t, x, y, yaw))
        if k in (40, half - 1, half + 60):
            np.testing.assert_allclose(r.calibration.scale, _scales_jax(r), rtol=1e-9)
    cal = r.calibration
    np.testing.assert_allclose(cal.scale, _scales_jax(r), rtol=1e-9)
    assert cal.errors > 1000 and len(r.recs) > 200
    # the oval's errors are not the made-up ellipses': the scales moved off 1
    assert np.max(np.abs(np.log(cal.scale))) > 0.5


def test_jax_calibration_under_vmap_equals_one_call():
    res = simulate("oval", duration_s=8.0, seed=6)
    wp, drive = res.centerline_xy_m, res.drive
    r = Captured(_config_with_ellipses(wp, horizon=5), wp, calibrate=True)
    for t, (x, y), yaw in zip(drive.t_s, drive.xy_m, drive.yaw_rad):
        r.update(t, x, y, yaw)
    cal = r.calibration
    t, xy, head, at, seg = (np.array(v) for v in zip(*r.recs))
    var = np.stack([cal.base[:, 0, 0], cal.base[:, 1, 1]], -1)
    decays = jnp.array([cal.decay, 0.5])

    def one(d):
        consts = jnp.stack([cal.dt_s, cal.delay_s, d, cal.prior_samples])
        return calibration_jax(np.array(r.obs), t, xy, head, at, seg.astype(float), var, consts)

    many = jax.vmap(one)(decays)
    np.testing.assert_allclose(many[0], _scales_jax(r), rtol=1e-12)
    np.testing.assert_allclose(many[0], cal.scale, rtol=1e-9)
    assert not np.allclose(many[0], many[1])


def test_the_saved_state_holds_the_calibrated_ellipses(tmp_path):
    res = simulate("oval", duration_s=15.0, seed=7)
    wp, drive = res.centerline_xy_m, res.drive
    r = AdaptiveRunner(_config_with_ellipses(wp), wp, calibrate=True)
    for t, (x, y), yaw in zip(drive.t_s, drive.xy_m, drive.yaw_rad):
        r.update(t, x, y, yaw)
    write_config(tmp_path / "s.json", r.state_config())
    cfg = read_config(tmp_path / "s.json")
    np.testing.assert_allclose(cfg["uncertainty"]["cov_m2"], r.covariance(), rtol=1e-15)
    saved = cfg["provenance"]["adapted"]["calibration"]
    assert saved["errors"] == r.calibration.errors and np.shape(saved["scale"]) == (10, 2)
    # resumed from it, the saved ellipses are the prior
    again = AdaptiveRunner(cfg, wp, calibrate=True)
    np.testing.assert_allclose(again.covariance(), r.covariance(), rtol=1e-15)
    # off by default: no ellipses saved, none to report
    plain = AdaptiveRunner(_config_with_ellipses(wp), wp)
    assert plain.covariance() is None and plain.state_config()["uncertainty"] is None
    with pytest.raises(InputError, match="has no uncertainty to calibrate"):
        AdaptiveRunner(None, wp, calibrate=True)


def test_the_calibrating_runner_works_where_jax_cannot_be_imported(tmp_path):
    import json
    import subprocess
    import sys

    res = simulate("oval", duration_s=6.0, seed=5)
    wp, drive = res.centerline_xy_m, res.drive
    np.save(tmp_path / "wp.npy", wp)
    np.save(tmp_path / "obs.npy", np.column_stack([drive.t_s, drive.xy_m]))
    (tmp_path / "cfg.json").write_text(json.dumps(_config_with_ellipses(wp)))
    code = f"""
import json
import numpy as np
from fpe_jax.runner._adapt import AdaptiveRunner
cfg = json.loads(open({str(tmp_path / "cfg.json")!r}).read())
r = AdaptiveRunner(cfg, np.load({str(tmp_path / "wp.npy")!r}), calibrate=True)
for t, x, y in np.load({str(tmp_path / "obs.npy")!r}).tolist():
    r.update(t, x, y)
r.state_config()
assert r.calibration.errors > 100, r.calibration.errors
"""
    proc = subprocess.run(
        [sys.executable, "-c", NO_JAX + code + CHECK_NO_JAX],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    from fpe_jax import io
    from fpe_jax.sim._sim import write_simulation

    root = tmp_path_factory.mktemp("calibrate_cli")
    write_simulation(simulate("oval", duration_s=20.0, seed=1), root / "a")
    wp = io.load_waypoints(root / "a" / "waypoints.csv").xy_m
    write_config(root / "tuned.json", _config_with_ellipses(wp))
    return root


def test_fpe_predict_adapt_calibrate_ellipses_writes_them_and_saves_them(logs, tmp_path):
    from fpe_jax import cli, io
    from fpe_jax.runner._adapt import predict_drive_adaptive

    log, wp = str(logs / "a" / "drive.mcap"), str(logs / "a" / "waypoints.csv")
    out, state = tmp_path / "p.csv", tmp_path / "state.json"
    argv = ["predict", log, "--waypoints", wp, "--adapt", "--config", str(logs / "tuned.json")]
    argv += ["--calibrate-ellipses", "--out", str(out), "--save-state", str(state)]
    assert cli.main(argv) == 0
    rows = np.genfromtxt(out, delimiter=",", names=True)
    cfg = read_config(logs / "tuned.json")
    drive = io.load_drive(log)
    runner, poses, cov = predict_drive_adaptive(
        drive, io.load_waypoints(wp).xy_m, cfg, calibrate=True, with_covariance=True
    )
    np.testing.assert_allclose(rows["x"].reshape(-1, 10), poses[..., 0], atol=1e-8)
    for name, (a, b) in {"cov_xx_m2": (0, 0), "cov_xy_m2": (0, 1), "cov_yy_m2": (1, 1)}.items():
        np.testing.assert_allclose(rows[name].reshape(-1, 10), cov[..., a, b], rtol=1e-8)
    # the map-frame ellipses are the calibrated track-frame ones turned: same determinant
    np.testing.assert_allclose(np.linalg.det(cov[-1]), np.linalg.det(runner.covariance()))
    saved = read_config(state)
    np.testing.assert_allclose(saved["uncertainty"]["cov_m2"], runner.covariance(), rtol=1e-12)
    assert saved["provenance"]["adapted"]["calibration"]["errors"] == runner.calibration.errors
    # without the flag the predictions are the same, and no ellipses are written or saved
    plain = tmp_path / "plain.csv"
    argv = ["predict", log, "--waypoints", wp, "--adapt", "--config", str(logs / "tuned.json")]
    assert cli.main([*argv, "--out", str(plain)]) == 0
    rows_plain = np.genfromtxt(plain, delimiter=",", names=True)
    assert "cov_xx_m2" not in rows_plain.dtype.names
    np.testing.assert_array_equal(rows_plain["x"], rows["x"])


@pytest.mark.parametrize(
    "extra, words",
    [
        (["--calibrate-ellipses"], "--calibrate-ellipses: given without --adapt"),
        (["--adapt", "--calibrate-ellipses"], "given without a config with ellipses"),
    ],
)
def test_fpe_predict_calibrate_ellipses_refuses_bad_combinations(
    logs, tmp_path, capsys, extra, words
):
    from fpe_jax import cli

    argv = ["predict", str(logs / "a" / "drive.mcap"), "--waypoints"]
    argv += [str(logs / "a" / "waypoints.csv"), "--out", str(tmp_path / "p.csv")]
    assert cli.main([*argv, *extra, "--quiet"]) == 2
    assert words in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_fpe_run_adapt_calibrate_ellipses_replies_carry_them(logs, monkeypatch, capsys):
    """`fpe run --adapt --config C --calibrate-ellipses`: each reply's "cov_m2" (H x 2 x 2, map
    frame) is the calibrated track-frame ellipses of a reference runner fed the same stream,
    turned by the path heading at each step; the poses are those without the flag, which adds
    no "cov_m2"."""
    from helpers import fpe_run

    from fpe_jax import io

    drive = io.load_drive(logs / "a" / "drive.mcap")
    wp = io.load_waypoints(logs / "a" / "waypoints.csv").xy_m
    rows = np.column_stack([drive.t_s - drive.t_s[0], drive.xy_m])[:120]
    lines = ["t,x,y", *(f"{t!r},{x!r},{y!r}" for t, x, y in rows.tolist())]
    argv = ["--waypoints", str(logs / "a" / "waypoints.csv"), "--adapt"]
    argv += ["--config", str(logs / "tuned.json")]
    rc, replies, err = fpe_run(monkeypatch, capsys, [*argv, "--calibrate-ellipses"], lines)
    assert rc == 0 and len(replies) == len(rows), err
    ref, want = AdaptiveRunner(read_config(logs / "tuned.json"), wp, calibrate=True), []
    for t, x, y in rows.tolist():
        ref.update(t, x, y)
        h = np.array([ref.path.heading_at(s) for s in ref._step_s_m])
        c, s = np.cos(h), np.sin(h)
        rot = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
        want.append(rot @ ref.covariance() @ np.swapaxes(rot, -1, -2))
    got = np.array([r["cov_m2"] for r in replies])
    assert got.shape == (len(rows), 10, 2, 2)
    np.testing.assert_allclose(got, np.array(want), rtol=1e-12, atol=1e-15)
    assert ref.calibration.errors > 100
    rc, plain, _ = fpe_run(monkeypatch, capsys, argv, lines)
    assert rc == 0 and "cov_m2" not in plain[0]
    np.testing.assert_array_equal([r["poses"] for r in plain], [r["poses"] for r in replies])


@pytest.mark.parametrize(
    "extra, words",
    [
        (["--calibrate-ellipses"], "--calibrate-ellipses: given without --adapt"),
        (["--adapt", "--calibrate-ellipses"], "given without a config with ellipses"),
    ],
)
def test_fpe_run_calibrate_ellipses_refuses_bad_combinations(
    logs, monkeypatch, capsys, extra, words
):
    from helpers import fpe_run

    argv = ["--waypoints", str(logs / "a" / "waypoints.csv"), *extra]
    if "--adapt" not in extra:
        argv += ["--config", str(logs / "tuned.json")]
    rc, replies, err = fpe_run(monkeypatch, capsys, argv, ["t,x,y", "0.0,1.0,2.0"])
    assert rc == 2 and replies == []
    assert any(words in line for line in err), err
