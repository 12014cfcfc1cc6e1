"""In-race learning (fpe_jax.runner): the incremental update against a JAX computation of the
same profile, what it learns, its saved state, and the CLI's --adapt."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fpe_jax import Params, Settings, Track, cli, predict_drive, presets
from fpe_jax.errors import InputError
from fpe_jax.geometry._path import waypoints_sha256
from fpe_jax.io.config import params_to_config, read_config, write_config
from fpe_jax.runner._adapt import (
    CHANGE_LOG_SPEED,
    CHANGE_OFFSET_M,
    CHANGE_WINDOW_M,
    MAX_SAMPLE_SPEED_MPS,
    MIN_RESIDUAL_SPEED_MPS,
    PASS_GAP_S,
    AdaptiveRunner,
    kernel,
    start_config,
)
from fpe_jax.runner._runner import Runner
from fpe_jax.sim._sim import simulate, write_simulation

TOL = 1e-6


class Recording(AdaptiveRunner):
    """Keeps every sample it learns from: (stamp [s], s [m], d [m], v [m/s], the speed's age
    [s], 1 if the runner was reset just before it else 0)."""

    def reset(self):
        super().reset()
        self._was_reset = True

    def learn(self, stamp_s, s_m, d_m, v_mps, v_age_s=0.0):
        row = (stamp_s, s_m, d_m, v_mps, v_age_s, float(getattr(self, "_was_reset", False)))
        self.seen = [*getattr(self, "seen", []), row]
        self._was_reset = False
        super().learn(stamp_s, s_m, d_m, v_mps, v_age_s)


def _spread(at_m, n, spacing):
    """A position's two profile points (2,) on a loop and their linear weights (2,)."""
    u = (at_m % (n * spacing)) / spacing
    i = jnp.floor(u)
    f = u - i
    return jnp.stack([i % n, (i + 1) % n]).astype(jnp.int32), jnp.stack([1.0 - f, f])


def _arc(to_m, from_m, length_m):
    return (to_m - from_m + 0.5 * length_m) % length_m - 0.5 * length_m


@jax.jit
def profile_jax(samples, prior, length_m, kern, decay, change_decay, min_samples):
    """The profile (3, P) offset [m], speed [m/s], coverage learned from samples (M, 6) (stamp,
    s, d, v, the speed's age, reset before) on a loop of length_m: the learning rule written
    over whole arrays and scanned over the samples. Per point: the current pass's sums and the
    passes' before (a sample more than PASS_GAP_S after the point's previous one, or after a
    reset, starts a new pass: before <- current + keep x before, keep <- decay); the change
    detector's window means of the residuals against the previous passes' profile (kernel-
    smoothed, read at the sample's two points), beyond the thresholds: keep <- change_decay
    where the car passes and, as it starts, back over the window (a reset restarts the
    window). The profile: the sums current + keep x before smoothed circularly, blended with
    the prior (3, P) by coverage. Rows whose seventh column is 0 are padding and change
    nothing."""
    n = prior.shape[1]
    spacing = length_m / n
    half = (kern.shape[0] - 1) // 2
    point_m = jnp.arange(n, dtype=jnp.float64) * spacing

    def smooth(raw):
        padded = jnp.concatenate([raw[:, -half:], raw, raw[:, :half]], axis=1)
        return jax.vmap(lambda r: jnp.convolve(r, kern, mode="valid"))(padded)

    def step(state, row):
        new, _ = learn(state, row[:6])
        return jax.tree.map(lambda a, b: jnp.where(row[6] > 0, a, b), new, state), None

    def learn(state, row):
        cur, before, keep, last, resid, resid_at, changed = state
        t, s, d, v, age, was_reset = row
        reset = was_reset > 0  # the clock and the detector's window restart
        last = jnp.where(reset, -jnp.inf, last)
        resid = jnp.where(reset, 0.0, resid)
        resid_at = jnp.where(reset, jnp.nan, resid_at)
        changed = changed & ~reset
        has_v = jnp.isfinite(v) & (jnp.abs(v) <= MAX_SAMPLE_SPEED_MPS)
        v = jnp.where(has_v, v, 0.0)
        places = [
            (0, _spread(s, n, spacing), d, True),
            (1, _spread(s - v * age, n, spacing), v, has_v),
        ]
        in_pass = (t - last >= 0.0) & (t - last <= PASS_GAP_S)
        prev = smooth(jnp.where(in_pass[None, :], before, cur + keep[None, :] * before))
        r = []
        for kind, (idx, w), value, ok in places:
            w_sum, x_sum = w @ prev[2 * kind, idx], w @ prev[2 * kind + 1, idx]
            known = ok & (w_sum >= min_samples)
            before_value = x_sum / jnp.where(known, w_sum, 1.0)
            if kind == 0:
                res = value - before_value
            else:
                low = MIN_RESIDUAL_SPEED_MPS
                res = jnp.log(jnp.maximum(value, low) / jnp.maximum(before_value, low))
            r.append(jnp.where(known, res, 0.0))
        a = jnp.where(
            jnp.isnan(resid_at),
            1.0,
            -jnp.expm1(-jnp.abs(_arc(s, resid_at, length_m)) / CHANGE_WINDOW_M),
        )
        resid = resid + a * (jnp.stack(r) - resid)
        now = (jnp.abs(resid[0]) > CHANGE_OFFSET_M) | (jnp.abs(resid[1]) > CHANGE_LOG_SPEED)
        back = _arc(s, point_m, length_m)
        window = in_pass & (back >= 0.0) & (back <= CHANGE_WINDOW_M) & now & ~changed
        keep = jnp.where(window, change_decay, keep)
        for kind, (idx, w), value, ok in places:
            for j, wj in zip(idx, w):
                fold = ~((t - last[j] >= 0.0) & (t - last[j] <= PASS_GAP_S))
                b_new = jnp.where(fold, cur[:, j] + keep[j] * before[:, j], before[:, j])
                c_new = jnp.where(fold, 0.0, cur[:, j])
                k_new = jnp.where(now, change_decay, jnp.where(fold, decay, keep[j]))
                c_new = c_new.at[2 * kind].add(wj).at[2 * kind + 1].add(wj * value)
                cur = cur.at[:, j].set(jnp.where(ok, c_new, cur[:, j]))
                before = before.at[:, j].set(jnp.where(ok, b_new, before[:, j]))
                keep = keep.at[j].set(jnp.where(ok, k_new, keep[j]))
                last = last.at[j].set(jnp.where(ok, t, last[j]))
        return (cur, before, keep, last, resid, s, now), None

    zeros = jnp.zeros((4, n))
    start = (zeros, zeros, jnp.zeros(n), jnp.full(n, -jnp.inf), jnp.zeros(2), jnp.nan, False)
    start = jax.tree.map(jnp.asarray, start)
    (cur, before, keep, *_), _ = jax.lax.scan(step, start, samples)
    sm = smooth(cur + keep[None, :] * before)
    c = jnp.clip(jnp.minimum(sm[0], sm[2]) / min_samples, 0.0, 1.0)
    offset = jnp.where((sm[0] > 1e-9) & (c > 0), sm[1] / jnp.maximum(sm[0], 1e-9), 0.0)
    speed = jnp.where((sm[2] > 1e-9) & (c > 0), sm[3] / jnp.maximum(sm[2], 1e-9), 0.0)
    known = c + (1 - c) * prior[2]
    v_known = (c * speed + (1 - c) * prior[2] * prior[1]) / jnp.where(known > 0, known, 1.0)
    return jnp.stack(
        [c * offset + (1 - c) * prior[0], jnp.where(known > 0, v_known, prior[1]), known]
    )


def _padded(seen) -> np.ndarray:
    """The samples (M, 6) as (M', 7) rows, M' a multiple of 512, the real ones marked 1: one
    compiled profile_jax serves every checkpoint of a drive instead of one per sample count."""
    rows = np.array(seen)
    out = np.zeros((-(-len(rows) // 512) * 512, 7))
    out[: len(rows), :6], out[: len(rows), 6] = rows, 1.0
    return out


def _check_against_jax(r: Recording) -> None:
    prior = np.stack([r._prior_offset, r._prior_speed, r._prior_coverage])
    kern = kernel(r._spacing, True, r._n)
    want = profile_jax(
        _padded(r.seen), prior, r.path.length_m, kern, r.lap_decay, r.change_decay, r.min_samples
    )
    got = np.stack(list(r.profile().values()))
    assert np.max(np.abs(got - np.asarray(want))) <= TOL


@pytest.fixture(scope="module")
def laps():
    """Three laps of the oval (about 12 s each) and its waypoints."""
    res = simulate("oval", duration_s=40.0, seed=5)
    return res.centerline_xy_m, res.drive


@pytest.mark.parametrize("start", ["nothing", "blend config", "line config"])
def test_the_update_matches_a_jax_computation_of_the_same_profile(laps, start):
    wp, drive = laps
    cfg = None
    if start == "blend config":
        cfg = params_to_config(presets["default"])
    elif start == "line config":
        from fpe_jax.model._line import learn_line

        other = simulate("oval", duration_s=8.0, seed=9).drive  # part of a lap: a partial prior
        profile = learn_line([other], Track.from_waypoints(wp))
        p = Params.create(Settings(model="line", estimator="kalman"), delay_s=0.2, **profile)
        cfg = params_to_config(p, line={"waypoints_sha256": waypoints_sha256(wp)})
    r = Recording(cfg, wp)
    for k, (t, (x, y), yaw) in enumerate(zip(drive.t_s, drive.xy_m, drive.yaw_rad)):
        r.update(t, x, y, yaw)
        if k in (5, 60, 200):
            _check_against_jax(r)
    assert r.laps >= 2 and r.samples > 300
    _check_against_jax(r)
    cov = r.profile()["line_coverage"]
    assert np.mean(cov >= 0.99) >= 0.9 and cov.min() > 0.3, cov  # the loop seen
    # out of sight, then 0.6 m further left on a restarted clock: new passes, the detector
    r.reset()
    xy = _moved_left(wp, drive.xy_m, 0.6)
    for k, (t, (x, y), yaw) in enumerate(zip(drive.t_s[:200], xy[:200], drive.yaw_rad[:200])):
        r.update(t, x, y, yaw)
        if k in (30, 120):
            _check_against_jax(r)
    assert r.changes >= 1
    _check_against_jax(r)


def _moved_left(wp, xy_m, by_m):
    """Positions (N, 2) [m] moved by_m [m] to the left of the centerline."""
    path = Runner(start_config(None, wp), wp).path
    out = []
    for x, y in xy_m:
        h = path.heading_at(path.project(x, y))
        out.append((x - by_m * np.sin(h), y + by_m * np.cos(h)))
    return np.array(out)


def test_jax_profile_under_jit_and_vmap_equals_one_call(laps):
    wp, drive = laps
    r = Recording(None, wp)
    for t, (x, y), yaw in zip(drive.t_s[:150], drive.xy_m[:150], drive.yaw_rad[:150]):
        r.update(t, x, y, yaw)
    seen = _padded(r.seen)
    prior = np.zeros((3, r._n))
    kern = kernel(r._spacing, True, r._n)
    one = profile_jax(seen, prior, r.path.length_m, kern, 0.25, 0.0, 0.5)
    decays = jnp.array([0.25, 0.5, 1.0])
    many = jax.vmap(lambda a: profile_jax(seen, prior, r.path.length_m, kern, a, 0.0, 0.5))(decays)
    np.testing.assert_allclose(many[0], one, atol=1e-12)
    assert not np.allclose(many[0], many[2])  # no decay within the first lap... but across


def test_with_no_decay_and_no_prior_the_profile_is_fpe_line_on_the_same_samples(laps):
    """lap_decay and change_decay 1, min_samples 1, speeds taken where they were measured: the
    profile is fpe_jax.model.line_from_samples of the runner's own samples, before its prior
    (all of the loop covered)."""
    from fpe_jax.model._line import LineSamples, line_from_samples

    wp, drive = laps

    class Now(AdaptiveRunner):  # the speed sample at the newest position (age 0)
        def learn(self, stamp_s, s_m, d_m, v_mps, v_age_s=0.0):
            self.seen = [*getattr(self, "seen", []), (s_m, d_m, v_mps)]
            super().learn(stamp_s, s_m, d_m, v_mps, 0.0)

    r = Now(None, wp, lap_decay=1.0, change_decay=1.0, min_samples=1.0)
    for t, (x, y), yaw in zip(drive.t_s, drive.xy_m, drive.yaw_rad):
        r.update(t, x, y, yaw)
    s, d, v = np.array(r.seen).T
    ls = LineSamples(np.arange(len(s)) * 0.1, s, d, v)
    want = line_from_samples([ls], Track.from_waypoints(wp))
    got = r.profile()
    for k in want:
        np.testing.assert_allclose(got[k], want[k], atol=TOL, err_msg=k)


def test_it_learns_a_new_line_within_two_laps(laps):
    """A car that moves 0.6 m to the left: the learned offset follows within two laps."""
    wp, drive = laps
    r = AdaptiveRunner(None, wp)
    path = r.path
    h = np.array([path.heading_at(s) for s in np.zeros(1)])  # noqa: F841 (path warm)
    t_lap = 12.0
    for t, (x, y), yaw in zip(drive.t_s, drive.xy_m, drive.yaw_rad):
        if t > t_lap:
            s = path.project(x, y)
            hd = path.heading_at(s)
            x, y = x - 0.6 * np.sin(hd), y + 0.6 * np.cos(hd)
        r.update(t, x, y, yaw)
        if t > t_lap and t - t_lap < 1.0:
            before = r.profile()["line_offset_m"].copy() if t - t_lap < 0.2 else before  # noqa
    after = r.profile()["line_offset_m"]
    # after more than two laps on the new line, 0.6 m further left nearly everywhere
    shift = np.median(after - before)
    assert 0.5 < shift < 0.7, shift


def _changed_driver(wp, drive, **kw) -> tuple[AdaptiveRunner, np.ndarray, tuple]:
    """Three laps of a drive, a reset (the clock restarting), one lap 0.6 m further left: the
    runner, its offset profile before the reset, and (the offset read, the profile, s [m]) 10 m
    ahead of the car at the first update at which it had found the change."""
    r = AdaptiveRunner(None, wp, **kw)
    for t, (x, y), yaw in zip(drive.t_s, drive.xy_m, drive.yaw_rad):
        r.update(t, x, y, yaw)
    before = r.profile()["line_offset_m"]
    changes = r.changes
    r.reset()
    xy = _moved_left(wp, drive.xy_m, 0.6)
    one_lap = drive.t_s < drive.t_s[0] + 12.0
    ahead_read = (np.nan, None, np.nan)
    for t, (x, y), yaw in zip(drive.t_s[one_lap], xy[one_lap], drive.yaw_rad[one_lap]):
        r.update(t, x, y, yaw)
        if r.changed and not np.isfinite(ahead_read[0]):
            s_ahead = r._s_m + 10.0
            ahead_read = (r._line_at(s_ahead)[0], r.profile()["line_offset_m"], s_ahead)
    return r, before, (changes, *ahead_read)


def test_a_changed_driver_is_learned_in_one_pass_even_across_a_reset(laps):
    """Three laps on its line, then out of sight (a reset, the clock restarting) and one lap
    0.6 m further left: the detector finds the change (and nothing before it), the road ahead
    is read with the change carried on, and the lap after the reset replaces the passes
    before wherever it went; without the detector a quarter of the old line stays."""
    wp, drive = laps
    r, before, (changes_before, read, profile, s_ahead) = _changed_driver(wp, drive)
    assert changes_before == 0  # an unchanged driver keeps its averaging over laps
    assert r.changes >= 1
    shift = r.profile()["line_offset_m"] - before
    assert abs(np.median(shift) - 0.6) < 0.08, np.median(shift)
    # the road the car had not passed since read the old line with the change carried on
    old_there = r._profile_at(list(profile), s_ahead)
    assert abs(read - old_there - 0.6) < 0.2, (read, old_there)

    plain, before, (_, read, _, _) = _changed_driver(wp, drive, detect_changes=False)
    assert plain.changes == 0 and not np.isfinite(read)
    shift = np.median(plain.profile()["line_offset_m"] - before)
    assert 0.3 < shift < 0.52, shift  # 0.6 / (1 + 0.25 + ...) where both were seen


def test_the_saved_state_is_a_config_the_runner_and_jax_read(laps, tmp_path):
    wp, drive = laps
    r = AdaptiveRunner(None, wp, settings={"horizon": 20})
    for t, (x, y), yaw in zip(drive.t_s, drive.xy_m, drive.yaw_rad):
        r.update(t, x, y, yaw)
    write_config(tmp_path / "state.json", r.state_config({"drives": ["d"]}))
    cfg = read_config(tmp_path / "state.json")
    assert cfg["settings"]["model"] == "line" and cfg["settings"]["horizon"] == 20
    assert cfg["provenance"]["adapted"]["laps"] == r.laps
    np.testing.assert_array_equal(cfg["params"]["line_offset_m"], r.profile()["line_offset_m"])
    # the offline predictor with that config, and the plain runner, agree on another drive
    from fpe_jax.io.config import config_to_params

    other = simulate("oval", duration_s=6.0, seed=8).drive
    _, pred_jax = predict_drive(config_to_params(cfg), other, Track.from_waypoints(wp))
    plain = Runner(cfg, wp)
    rows = zip(other.t_s, other.xy_m, other.yaw_rad)
    pred = np.stack([plain.update(t, x, y, yaw) for t, (x, y), yaw in rows])
    assert np.max(np.abs(pred[..., :2] - np.asarray(pred_jax)[..., :2])) <= TOL


def test_start_config_errors_and_defaults(laps):
    wp, _ = laps
    cfg = start_config(None, wp)
    assert cfg["settings"]["model"] == "line" and set(cfg["params"]["line_coverage"]) == {0.0}
    with pytest.raises(InputError, match="given with a config"):
        start_config(params_to_config(presets["default"]), wp, settings={"horizon": 20})
    with pytest.raises(InputError, match="lap_decay"):
        AdaptiveRunner(None, wp, lap_decay=0.0)
    with pytest.raises(InputError, match="change_decay"):
        AdaptiveRunner(None, wp, lap_decay=0.25, change_decay=0.5)


def test_the_runner_interface_is_the_runners(laps):
    wp, drive = laps
    a, b = AdaptiveRunner(None, wp), Runner(start_config(None, wp), wp)
    t, (x, y), yaw = drive.t_s[0], drive.xy_m[0], drive.yaw_rad[0]
    # before the car is seen anywhere both predict alike: the prior (own offset and speed)
    np.testing.assert_allclose(a.update(t, x, y, yaw), b.update(t, x, y, yaw), atol=TOL)
    assert a.samples == 1 and (a.horizon, a.dt_s, a.model) == (b.horizon, b.dt_s, b.model)
    a.update(t + 0.1, x, y, yaw)  # a repeated row teaches nothing
    assert a.samples == 1
    a.reset()  # a new drive: the history goes, what was learned stays
    assert a.samples == 1 and a.profile()["line_coverage"].max() > 0


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    root = tmp_path_factory.mktemp("adapt_cli")
    # a lap and a third (about 12 s a lap): --adapt completes a lap, and every row of the log
    # goes through the Python runner several times
    write_simulation(simulate("oval", duration_s=16.0, seed=1), root / "a")
    return root / "a"


def test_fpe_predict_adapt_streams_the_learning_runner_and_saves_its_state(logs, tmp_path):
    from fpe_jax import io
    from fpe_jax.runner._adapt import predict_drive_adaptive

    log, wp = str(logs / "drive.mcap"), str(logs / "waypoints.csv")
    out, state = tmp_path / "p.csv", tmp_path / "state.json"
    argv = ["predict", log, "--waypoints", wp, "--adapt", "--out", str(out)]
    assert cli.main([*argv, "--save-state", str(state), "--horizon", "20", "--delay", "0.3"]) == 0
    rows = np.genfromtxt(out, delimiter=",", names=True)
    drive = io.load_drive(log)
    xy = io.load_waypoints(wp).xy_m
    runner, want = predict_drive_adaptive(drive, xy, settings={"horizon": 20}, delay_s=0.3)
    assert rows["step"].max() == 20 and len(rows) == 20 * len(drive.t_s)
    np.testing.assert_allclose(rows["x"].reshape(-1, 20), want[..., 0], atol=1e-8)
    cfg = read_config(state)
    assert cfg["params"]["delay_s"] == 0.3 and cfg["provenance"]["adapted"]["laps"] >= 1
    # the other commands read it; starting from it, --adapt goes on learning
    capsys_free = ["evaluate", log, "--waypoints", wp, "--config", str(state), "--quiet"]
    assert cli.main(capsys_free) == 0
    again = tmp_path / "again.json"
    argv = ["predict", log, "--waypoints", wp, "--adapt", "--config", str(state)]
    assert cli.main([*argv, "--out", str(tmp_path / "q.csv"), "--save-state", str(again)]) == 0
    assert read_config(again)["provenance"]["adapted"]["samples"] == runner.samples


@pytest.mark.parametrize(
    "extra, words",
    [
        (["--save-state", "s.json"], "--save-state: given without --adapt"),
        (["--adapt", "--preset", "default"], "--preset: given with --adapt"),
        (["--adapt", "--config", "CFG", "--horizon", "20"], "given with a config"),
    ],
)
def test_fpe_predict_adapt_refuses_bad_combinations(logs, tmp_path, capsys, extra, words):
    cfg = tmp_path / "c.json"
    write_config(cfg, params_to_config(presets["default"]))
    extra = [str(cfg) if e == "CFG" else str(tmp_path / e) if e == "s.json" else e for e in extra]
    argv = ["predict", str(logs / "drive.mcap"), "--waypoints", str(logs / "waypoints.csv")]
    assert cli.main([*argv, "--out", str(tmp_path / "p.csv"), *extra, "--quiet"]) == 2
    assert words in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.json"]


def test_fpe_run_adapt_without_a_config(logs, tmp_path, capsys):
    import subprocess
    import sys

    from fpe_jax import io

    drive = io.load_drive(logs / "drive.mcap")
    lines = ["t,x,y"] + [
        f"{t!r},{x!r},{y!r}" for t, (x, y) in zip(drive.t_s[:40].tolist(), drive.xy_m[:40].tolist())
    ]
    cmd = [sys.executable, "-m", "fpe_jax.cli", "run", "--waypoints", str(logs / "waypoints.csv")]
    proc = subprocess.run(
        [*cmd, "--adapt"],
        input="\n".join(lines) + "\n",
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    got = np.array([json.loads(ln)["poses"] for ln in proc.stdout.splitlines()])
    r = AdaptiveRunner(None, io.load_waypoints(logs / "waypoints.csv").xy_m)
    rows = zip(drive.t_s[:40].tolist(), drive.xy_m[:40].tolist())
    want = np.stack([r.update(t, x, y) for t, (x, y) in rows])
    np.testing.assert_allclose(got, want, atol=1e-9)
    # without --adapt a config is required: refused before stdin is read, so in-process
    capsys.readouterr()
    assert cli.main(cmd[3:]) == 2 and "--config" in capsys.readouterr().err


def test_the_adaptive_runner_works_where_jax_cannot_be_imported(laps, tmp_path):
    import subprocess
    import sys

    wp, drive = laps
    np.save(tmp_path / "wp.npy", wp)
    np.save(tmp_path / "obs.npy", np.column_stack([drive.t_s, drive.xy_m])[:200])
    code = f"""
import sys
class NoJax:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in ("jax", "jaxlib", "equinox", "optimistix"):
            raise ImportError(name + " is blocked: this process has no JAX")
sys.meta_path.insert(0, NoJax())
import numpy as np
from fpe_jax.runner._adapt import AdaptiveRunner
r = AdaptiveRunner(None, np.load({str(tmp_path / "wp.npy")!r}))
for t, x, y in np.load({str(tmp_path / "obs.npy")!r}).tolist():
    r.update(t, x, y)
r.state_config()
leaked = [m for m in ("jax", "jaxlib", "equinox", "optimistix") if m in sys.modules]
assert not leaked, leaked
print(r.samples)
"""
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert int(proc.stdout) > 100
