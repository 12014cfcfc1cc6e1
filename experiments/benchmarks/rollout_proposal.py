"""Study: where the batch predictor's time goes, and a faster pure-pursuit step (a proposal for
`fpe_jax.rollout`, measured here on a copy; the product code is unchanged).

Compares, on the Levine track with N cars (default 16384: one chunk) in float32, in one process:
  core      `predict_batch` as it is (position blend, hints given);
  proposal  the same model with three changes to the pure-pursuit step, each toggled separately:
            A. projection by Newton steps along the *segment* (chord) instead of the interpolated
               heading: converges to the exact polyline projection (`Track.project`'s), two
               gathers per step and no trig;
            B. tan(clip(atan(z))) = clip(z, +-tan(max_steer)): no atan/tan per step;
            C. carry the heading as a unit vector rotated by the half-step angle: one sin/cos
               pair per step instead of two;
  bare      the kinematic bicycle without a track (the ceiling).
Rates are per wall second (median of 7) and per CPU second of this process (robust to other
load on a shared machine). Also reports the proposal's largest deviation from the core.

Usage: python experiments/benchmarks/rollout_proposal.py [N]   (default 16384: one chunk)
"""

from __future__ import annotations

import dataclasses
import functools
import sys
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1]))
sys.path.insert(0, str(HERE))

from run import _bare_rollout, load_levine, make_cars, timed_runs  # noqa: E402

from fpe_jax import Track, presets  # noqa: E402
from fpe_jax.batch import cast_floats, states_from_array  # noqa: E402
from fpe_jax.path import wrap_angle  # noqa: E402
from fpe_jax.predict import predict_batch  # noqa: E402


def _lookup(track, table, s):
    """Row of the packed segment table (x0, y0, x1, y1) holding arc length s, and the fraction."""
    m = track.n_points
    u = jnp.mod(s, track.length_m) / track.ds_m
    i = jnp.clip(jnp.floor(u).astype(jnp.int32), 0, m - 1)
    return table[i], u - i


def proposed_blend(params, state, track, *, chord=True, no_atan=True, unit_heading=True):
    """`fpe_jax.rollout.rollout_blend` (position blend) with changes A, B, C; closed tracks."""
    st = params.settings
    w = params.weights
    v = params.speed_weight * state.v_mps + (1.0 - params.speed_weight) * params.speed_mps
    wb = st.wheelbase_m
    lookahead = params.lookahead_m + params.lookahead_gain_s * v
    times = jnp.concatenate([params.delay_s[None], jnp.full((st.horizon,), st.dt_s, w.dtype)])
    xy = track.xy_m
    table = jnp.concatenate([xy, jnp.roll(xy, -1, axis=0)], axis=1)  # (M, 4), built once

    def project(x, y, s):
        if not chord:
            return track.project_local(jnp.stack([x, y]), s)
        for _ in range(2):
            r, f = _lookup(track, table, s)
            abx, aby = r[2] - r[0], r[3] - r[1]
            s = s + ((x - r[0] - f * abx) * abx + (y - r[1] - f * aby) * aby) / track.ds_m
        return s

    def step(c, dt):
        x, y, yaw, cy, sy, s = c
        if not unit_heading:
            cy, sy = jnp.cos(yaw), jnp.sin(yaw)
        s = project(x, y, s)
        r, f = _lookup(track, table, s + lookahead)
        dx = r[0] + f * (r[2] - r[0]) - x
        dy = r[1] + f * (r[3] - r[1]) - y
        d2 = dx * dx + dy * dy + 1e-12
        z = 2.0 * wb * (cy * dy - sy * dx) / d2
        if no_atan:
            tan_steer = jnp.clip(z, -np.tan(st.max_steer_rad), np.tan(st.max_steer_rad))
        else:
            tan_steer = jnp.tan(jnp.clip(jnp.arctan(z), -st.max_steer_rad, st.max_steer_rad))
        dyaw = v / wb * tan_steer * dt
        if unit_heading:
            ch, sh = jnp.cos(0.5 * dyaw), jnp.sin(0.5 * dyaw)
            cm, sm = cy * ch - sy * sh, sy * ch + cy * sh
            cy, sy = cm * ch - sm * sh, sm * ch + cm * sh
        else:
            mid = yaw + 0.5 * dyaw
            cm, sm = jnp.cos(mid), jnp.sin(mid)
        c = (x + v * dt * cm, y + v * dt * sm, yaw + dyaw, cy, sy, s)
        return c, c[:3]

    s0 = project(state.x_m, state.y_m, state.s_m)
    init = (state.x_m, state.y_m, state.yaw_rad, jnp.cos(state.yaw_rad), jnp.sin(state.yaw_rad), s0)
    _, (xs, ys, yaws) = jax.lax.scan(step, init, times)
    pp = jnp.stack([xs, ys, wrap_angle(yaws)], axis=-1)[1:]
    t = jnp.cumsum(times)[1:]
    lin = jnp.stack(
        [
            state.x_m + v * t * jnp.cos(state.yaw_rad),
            state.y_m + v * t * jnp.sin(state.yaw_rad),
            jnp.broadcast_to(state.yaw_rad, t.shape),
        ],
        axis=-1,
    )
    xy_out = w[:, None] * lin[:, :2] + (1.0 - w[:, None]) * pp[:, :2]
    yaw_out = wrap_angle(lin[:, 2] + (1.0 - w) * wrap_angle(pp[:, 2] - lin[:, 2]))
    return jnp.concatenate([xy_out, yaw_out[:, None]], axis=1)


def measure(n: int = 16384) -> list[dict]:
    """Rates of the core, the proposal's steps, the ceiling and both end-to-end paths at N = n."""
    wps = load_levine()
    track64 = Track.from_waypoints(wps)
    cars = make_cars(track64, n)
    project = jax.jit(jax.vmap(lambda t, q: t.project(q), in_axes=(None, 0)))
    s_hint = np.asarray(project(track64, jnp.asarray(cars[:, :2])))
    variants = {
        "core predict_batch": None,
        "A chord projection": dict(chord=True, no_atan=False, unit_heading=False),
        "A+B (+ no atan/tan)": dict(chord=True, no_atan=True, unit_heading=False),
        "A+B+C (+ unit heading)": dict(chord=True, no_atan=True, unit_heading=True),
    }
    rows = []

    def add(name, res, dev):
        rows.append(dict(variant=name, n_cars=n, max_dev_m=dev, **res))

    with jax.enable_x64(False):
        track = jax.tree.map(jnp.asarray, cast_floats(track64, "float32"))
        params = jax.tree.map(jnp.asarray, cast_floats(presets["default"], "float32"))
        st = dataclasses.replace(states_from_array(cars), s_m=s_hint)
        st = jax.tree.map(jnp.asarray, cast_floats(st, "float32"))
        ref = np.asarray(predict_batch(params, st, track))
        for name, kw in variants.items():
            if kw is None:
                fn = predict_batch
            else:
                fn = eqx.filter_jit(
                    jax.vmap(functools.partial(proposed_blend, **kw), in_axes=(None, 0, None))
                )
            out = np.asarray(fn(params, st, track))
            res = timed_runs(lambda f=fn: jax.block_until_ready(f(params, st, track)), n, runs=7)
            add(name, res, float(np.max(np.abs(out[..., :2] - ref[..., :2]))))
        bare = jax.jit(jax.vmap(_bare_rollout))
        args = [st.x_m, st.y_m, st.yaw_rad, st.v_mps, 0.1 * st.yaw_rate_rps]
        jax.block_until_ready(bare(*args))
        res = timed_runs(lambda: jax.block_until_ready(bare(*args)), n, runs=7)
        add("bare bicycle (ceiling)", res, None)

    # end to end (cars array in, NumPy out, grid projection): as it is, and with the proposal
    # patched into the batch module's compiled chunk (a process-local substitution, undone)
    import fpe_jax.batch as batch

    original = batch.predict_batch
    try:
        for name, fn in (
            ("end to end, core", None),
            ("end to end, proposal", jax.vmap(proposed_blend, in_axes=(None, 0, None))),
        ):
            if fn is not None:
                batch.predict_batch = fn
                jax.clear_caches()  # the compiled chunk must be retraced with the substitute
            predictor = batch.BatchPredictor(presets["default"], track64)
            predictor(cars)
            add(name, timed_runs(lambda p=predictor: p(cars), n, runs=7), None)
    finally:
        batch.predict_batch = original
        jax.clear_caches()
    return rows


def main() -> None:
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 16384
    rows = measure(n)
    print(f"N = {n} cars, float32, Levine track; rates in ten-step predictions per second")
    print(f"{'variant':26s} {'wall':>10s} {'per CPU-s':>10s} {'max |dxy| vs core [m]':>22s}")
    for r in rows:
        dev = "-" if r["max_dev_m"] is None else f"{r['max_dev_m']:.2e}"
        print(f"{r['variant']:26s} {r['rate_per_s']:10.3g} {r['rate_per_cpu_s']:10.3g} {dev:>22s}")


if __name__ == "__main__":
    main()
