"""A Kalman filter in the track frame over one history window: the frenet and line models'
state estimator (`Settings.estimator = "kalman"`).

The state is [s, ds/dt, d, dd/dt]: arc length [m], along-track speed [m/s], lateral offset [m]
(left positive) and its rate [m/s], each pair a constant-velocity model driven by white
acceleration that is constant over each interval between observations (noise
`filter_accel_mps2` along, `filter_lat_accel_mps2` across). The observations are the window's
positions projected onto the track (`fpe_jax.model.track_frame_window`), each with noise
`filter_obs_m` along and across. The filter starts at the oldest valid observation's stamp from
the window's robust Theil-Sen lines (a prior that no single outlier moves, so the gate
judges the first observations too) and runs over the window's stamps as they are
(irregular steps, gaps after dropouts); the window holds distinct observations only, so a
repeated row never adds an update. Each update's gain is scaled by a smooth gate weight of the
innovation's Mahalanobis distance m: w = sigmoid(GATE_SHARPNESS (filter_gate_sigma - m)), so an
outlier (a 0.5-2 m jump) leaves the state where the prediction put it, and the estimate stays
differentiable in every noise value. On a loop the along-track innovation is wrapped to +-L/2.

Both axes share only the gate weight, so the covariance stays block-diagonal and each axis is
a 2 x 2 filter written on scalars (the NumPy runner mirrors it step for step).

One window per call (`kalman_window`); vmap it over rows at the edge.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from fpe_jax.geometry._track import wrap_to
from fpe_jax.model._constants import (
    GATE_SHARPNESS,
    INIT_LAT_RATE_SIGMA_MPS,
    INIT_POS_SIGMA_M,
    INIT_SPEED_SIGMA_MPS,
)


def _predict(p, r, a, b, c, dt, q):
    """One constant-velocity step of dt [s] for one axis: position p, rate r, covariance
    [[a, b], [b, c]], acceleration variance q [m^2/s^4] constant over the step."""
    dt2 = dt * dt
    return (
        p + r * dt,
        r,
        a + 2.0 * b * dt + c * dt2 + 0.25 * q * dt2 * dt2,
        b + c * dt + 0.5 * q * dt2 * dt,
        c + q * dt2,
    )


def _update(p, r, a, b, c, nu, s_inn, w):
    """The weighted measurement update of one axis with innovation nu, its variance s_inn and
    gate weight w in [0, 1] (w = 1: the usual Kalman update; 0: none)."""
    kp, kr = w * a / s_inn, w * b / s_inn
    return p + kp * nu, r + kr * nu, a - kp * a, b - kp * b, c - kr * b


def kalman_window(
    age_s: Float[Array, " W"],
    s_m: Float[Array, " W"],
    d_m: Float[Array, " W"],
    valid: Bool[Array, " W"],
    prior: Float[Array, " 5"],
    accel_mps2: Float[Array, ""],
    lat_accel_mps2: Float[Array, ""],
    obs_m: Float[Array, ""],
    gate_sigma: Float[Array, ""],
    length_m: float | Float[Array, ""] | None = None,
) -> tuple[Float[Array, " 4"], Float[Array, "4 4"], Float[Array, ""]]:
    """The filtered state at the newest stamp of one right-aligned window.

    Args:
        age_s: (W,) age of each slot's observation before the newest [s] (>= 0, oldest first).
        s_m, d_m: (W,) the observations' arc length [m] and lateral offset [m].
        valid: (W,) which slots hold an observation (at least one must).
        prior: (5,) s [m], ds/dt [m/s], d [m], dd/dt [m/s] at the newest stamp from robust
            lines through the window (`fpe_jax.model.track_frame_lines`), carried back to
            the oldest observation (the filter's start), and the lines' speed age [s] (the
            median observation's age).
        accel_mps2, lat_accel_mps2, obs_m, gate_sigma: the noise values and gate (`Params`).
        length_m: the loop's length [m] (innovations along the track wrap to +-L/2), or None
            on an open path.

    Returns:
        mean (4,): s [m], ds/dt [m/s], d [m], dd/dt [m/s] at age 0 (the newest stamp);
        cov (4, 4): its covariance (block-diagonal: along, across);
        speed_age_s: the age [s] of the speed estimate: the time before the newest stamp at
            which a car under constant along-track acceleration had the speed the filter
            reports (a constant-velocity filter's speed averages over the recent window). It
            is the same linear filter, with the same gains, run on the observations
            z = age^2 / 2 of a unit acceleration: the rate it ends with is minus that time.
    """
    q_s, q_d, r2 = accel_mps2 * accel_mps2, lat_accel_mps2 * lat_accel_mps2, obs_m * obs_m
    # the constants of the scan's carry are made like an observation (`zeros_like`): inside
    # `jax.shard_map` (the fit's row blocks over devices) the carry then has the type the
    # observations give it after a step (one value per device), as a scan requires
    zero = jnp.zeros_like(s_m[0])
    p0 = r2 + INIT_POS_SIGMA_M**2
    v0, vd0 = (zero + x**2 for x in (INIT_SPEED_SIGMA_MPS, INIT_LAT_RATE_SIGMA_MPS))

    # the prior at the oldest valid observation's stamp (the robust lines carried back there)
    age0 = jnp.max(jnp.where(valid, age_s, 0.0))
    s_start = (prior[0] - prior[1] * age0, prior[1], p0, zero, v0)
    # the unit-acceleration channel: exact at the oldest stamp, the lines' speed age as its rate
    u_start = (0.5 * age0 * age0, -prior[4])
    d_start = (prior[2] - prior[3] * age0, prior[3], p0, zero, vd0)

    def step(carry, inp):
        age_prev, sx, dx, ux = carry
        age, zs, zd, ok = inp
        dt = age_prev - age
        sp, dp = _predict(*sx, dt, q_s), _predict(*dx, dt, q_d)
        nu_s = zs - sp[0]
        if length_m is not None:
            nu_s = wrap_to(nu_s, length_m)
        nu_d = zd - dp[0]
        ss_inn, sd_inn = sp[2] + r2, dp[2] + r2
        m = jnp.sqrt(nu_s * nu_s / ss_inn + nu_d * nu_d / sd_inn + 1e-12)
        w = jax.nn.sigmoid(GATE_SHARPNESS * (gate_sigma - m))
        su = _update(*sp, nu_s, ss_inn, w)
        du = _update(*dp, nu_d, sd_inn, w)
        # the same gains on the unit-acceleration observation
        kp, kr = w * sp[2] / ss_inn, w * sp[3] / ss_inn
        up = ux[0] + ux[1] * dt
        nu_u = 0.5 * age * age - up
        uu = (up + kp * nu_u, ux[1] + kr * nu_u)
        keep = lambda new, old: tuple(jnp.where(ok, n, o) for n, o in zip(new, old))  # noqa: E731
        return (jnp.where(ok, age, age_prev), keep(su, sx), keep(du, dx), keep(uu, ux)), None

    init = (age0, s_start, d_start, u_start)
    (age_last, sx, dx, ux), _ = jax.lax.scan(step, init, (age_s, s_m, d_m, valid))
    # to the newest stamp (a no-op when the newest slot holds an observation, as it must)
    sx, dx = _predict(*sx, age_last, q_s), _predict(*dx, age_last, q_d)
    mean = jnp.stack([sx[0], sx[1], dx[0], dx[1]])
    cov = jnp.stack(
        [
            jnp.stack([sx[2], sx[3], zero, zero]),
            jnp.stack([sx[3], sx[4], zero, zero]),
            jnp.stack([zero, zero, dx[2], dx[3]]),
            jnp.stack([zero, zero, dx[3], dx[4]]),
        ]
    )
    return mean, cov, -ux[1]


def kalman_params(params) -> tuple:
    """The filter's values of a `Params` in `kalman_window`'s order."""
    return (
        params.filter_accel_mps2,
        params.filter_lat_accel_mps2,
        params.filter_obs_m,
        params.filter_gate_sigma,
    )
