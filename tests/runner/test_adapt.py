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
from fpe_jax.runner._adapt import AdaptiveRunner, kernel, start_config
from fpe_jax.runner._runner import Runner
from fpe_jax.sim._sim import simulate, write_simulation

TOL = 1e-6


class Recording(AdaptiveRunner):
    """Keeps every sample it learns from: (s [m], d [m], v [m/s], the speed's age [s])."""

    def learn(self, s_m, d_m, v_mps, v_age_s=0.0):
        self.seen = [*getattr(self, "seen", []), (s_m, d_m, v_mps, v_age_s)]
        super().learn(s_m, d_m, v_mps, v_age_s)


def _spread(at_m, n, spacing):
    """Each position's two profile points (2, M) and linear weights (2, M) on a loop."""
    u = at_m / spacing
    i = jnp.floor(u)
    f = u - i
    return jnp.stack([i % n, (i + 1) % n]).astype(jnp.int32), jnp.stack([1.0 - f, f])


@jax.jit
def profile_jax(s_m, d_m, v_mps, age_s, prior, length_m, kern, decay, min_samples):
    """The profile (3, P) offset [m], speed [m/s], coverage learned from samples (M,) on a loop
    of length_m, all at once: the offset at s, the speed at s - v age; each weighs
    decay ** (laps between it and the point's newest sample of either kind), is spread to its
    two points, summed, smoothed circularly and blended with the prior (3, P) by coverage."""
    n = prior.shape[1]
    spacing = length_m / n
    step = jnp.diff(s_m)
    step = (step + 0.5 * length_m) % length_m - 0.5 * length_m
    s0 = s_m[0] % length_m
    unwrapped = jnp.concatenate([jnp.array([s0]), s0 + jnp.cumsum(step)])
    lap = jnp.maximum(jax.lax.cummax(jnp.floor(unwrapped / length_m)), 0.0)
    has_v = jnp.isfinite(v_mps)
    v = jnp.where(has_v, v_mps, 0.0)
    idx_d, w_d = _spread(s_m % length_m, n, spacing)
    idx_v, w_v = _spread((s_m - v * age_s) % length_m, n, spacing)
    w_v = jnp.where(has_v[None, :], w_v, 0.0)
    lap2 = jnp.tile(lap, 2)
    newest = jnp.zeros(n).at[idx_d.ravel()].max(lap2).at[idx_v.ravel()].max(lap2)
    w_d = w_d * decay ** (newest[idx_d] - lap[None, :])
    w_v = w_v * decay ** (newest[idx_v] - lap[None, :])

    def add(idx, c):
        return jnp.zeros(n).at[idx.ravel()].add(c.ravel())

    raw = jnp.stack(
        [
            add(idx_d, w_d),
            add(idx_d, w_d * d_m[None, :]),
            add(idx_v, w_v),
            add(idx_v, w_v * v[None, :]),
        ]
    )
    half = (kern.shape[0] - 1) // 2
    padded = jnp.concatenate([raw[:, -half:], raw, raw[:, :half]], axis=1)
    sm = jax.vmap(lambda r: jnp.convolve(r, kern, mode="valid"))(padded)
    c = jnp.clip(jnp.minimum(sm[0], sm[2]) / min_samples, 0.0, 1.0)
    offset = jnp.where((sm[0] > 1e-9) & (c > 0), sm[1] / jnp.maximum(sm[0], 1e-9), 0.0)
    speed = jnp.where((sm[2] > 1e-9) & (c > 0), sm[3] / jnp.maximum(sm[2], 1e-9), 0.0)
    known = c + (1 - c) * prior[2]
    v_known = (c * speed + (1 - c) * prior[2] * prior[1]) / jnp.where(known > 0, known, 1.0)
    return jnp.stack(
        [c * offset + (1 - c) * prior[0], jnp.where(known > 0, v_known, prior[1]), known]
    )


def _check_against_jax(r: Recording) -> None:
    seen = np.array(r.seen)
    prior = np.stack([r._prior_offset, r._prior_speed, r._prior_coverage])
    kern = kernel(r._spacing, True, r._n)
    want = profile_jax(*seen.T, prior, r.path.length_m, kern, r.lap_decay, r.min_samples)
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


def test_jax_profile_under_jit_and_vmap_equals_one_call(laps):
    wp, drive = laps
    r = Recording(None, wp)
    for t, (x, y), yaw in zip(drive.t_s[:150], drive.xy_m[:150], drive.yaw_rad[:150]):
        r.update(t, x, y, yaw)
    seen = np.array(r.seen)
    prior = np.zeros((3, r._n))
    kern = kernel(r._spacing, True, r._n)
    one = profile_jax(*seen.T, prior, r.path.length_m, kern, 0.25, 0.5)
    decays = jnp.array([0.25, 0.5, 1.0])
    many = jax.vmap(lambda a: profile_jax(*seen.T, prior, r.path.length_m, kern, a, 0.5))(decays)
    np.testing.assert_allclose(many[0], one, atol=1e-12)
    assert not np.allclose(many[0], many[2])  # no decay within the first lap... but across


def test_with_no_decay_and_no_prior_the_profile_is_fpe_line_on_the_same_samples(laps):
    """lap_decay 1, min_samples 1, speeds taken where they were measured: the profile is
    fpe_jax.model.line_from_samples of the runner's own samples, before its prior (all of the
    loop covered)."""
    from fpe_jax.model._line import LineSamples, line_from_samples

    wp, drive = laps

    class Now(AdaptiveRunner):  # the speed sample at the newest position (age 0)
        def learn(self, s_m, d_m, v_mps, v_age_s=0.0):
            self.seen = [*getattr(self, "seen", []), (s_m, d_m, v_mps)]
            super().learn(s_m, d_m, v_mps, 0.0)

    r = Now(None, wp, lap_decay=1.0, min_samples=1.0)
    for t, (x, y), yaw in zip(drive.t_s, drive.xy_m, drive.yaw_rad):
        r.update(t, x, y, yaw)
    s, d, v = np.array(r.seen).T
    ls = LineSamples(np.arange(len(s)) * 0.1, s, d, v)
    want = line_from_samples([ls], Track.from_waypoints(wp))
    got = r.profile()
    for k in want:
        np.testing.assert_allclose(got[k], want[k], atol=TOL, err_msg=k)


def test_it_learns_a_new_line_within_two_laps():
    """A car that moves 0.6 m to the left: the learned offset follows within two laps."""
    res = simulate("oval", duration_s=40.0, seed=5)
    wp, drive = res.centerline_xy_m, res.drive
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
    write_simulation(simulate("oval", duration_s=30.0, seed=1), root / "a")
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


def test_fpe_run_adapt_without_a_config(logs, tmp_path):
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
    proc = subprocess.run(cmd, input="", capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "--config" in proc.stderr


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
