"""`State`: the leading car's state at prediction time, the named data the estimator produces
and every rollout consumes (below both, so the estimator does not import the rollout); `Poses`:
what the rollouts predict from it."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float

# a field holds values, or only their shape and dtype (a State to compile for, `fpe_jax.compile`)
Value = ArrayLike | jax.ShapeDtypeStruct


class State(eqx.Module):
    """The leading car's state at prediction time (scalars; add a leading axis for batches).

    Attributes:
        x_m, y_m: position [m] (the newest observation).
        yaw_rad: heading of the car body [rad].
        v_mps: speed [m/s].
        yaw_rate_rps: yaw rate [rad/s].
        course_rad: direction of motion [rad] (differs from yaw when sliding or noisy).
        s_m: arc length hint [m]: where on the track the car is (from a windowed projection).
        s_fit_m, sdot_mps, offset_m: the track-frame estimate (`track_frame_lines` or the
            Kalman filter): arc length [m], along-track speed [m/s] and lateral offset [m] at
            the newest stamp, and sdot_age_s, how old the speed is [s] (the window's middle);
            None: the frenet and line rollouts take them from x, y, v and the course.
        window_age_s, window_s_m, window_d_m, window_valid: (W,) the history window in the
            track frame, oldest first, for the Kalman estimator to filter with the params at
            hand (`fpe_jax.predict.filtered`; a fit changes the filter's values): each slot's
            age before the newest observation [s], arc length [m], lateral offset [m] and 1.0
            where it holds an observation (0.0 where not); window_prior (5,): the window's
            Theil-Sen s [m], ds/dt [m/s], d [m], dd/dt [m/s] at the newest stamp and the
            median observation's age [s] (the filter's start). None: the track-frame estimate
            above is used as it is.
        filter_cov: (4, 4) the Kalman filter's covariance of its estimate of s [m], ds/dt
            [m/s], d [m], dd/dt [m/s] at the newest stamp (`fpe_jax.model.kalman_window`);
            None without the filter.
    """

    x_m: Float[Value, "*batch"]
    y_m: Float[Value, "*batch"]
    yaw_rad: Float[Value, "*batch"]
    v_mps: Float[Value, "*batch"]
    yaw_rate_rps: Float[Value, "*batch"] | None = None
    course_rad: Float[Value, "*batch"] | None = None
    s_m: Float[Value, "*batch"] | None = None
    s_fit_m: Float[Value, "*batch"] | None = None
    sdot_mps: Float[Value, "*batch"] | None = None
    offset_m: Float[Value, "*batch"] | None = None
    sdot_age_s: Float[Value, "*batch"] | None = None
    window_age_s: Float[Value, "*batch W"] | None = None
    window_s_m: Float[Value, "*batch W"] | None = None
    window_d_m: Float[Value, "*batch W"] | None = None
    window_valid: Float[Value, "*batch W"] | None = None
    window_prior: Float[Value, "*batch 5"] | None = None
    filter_cov: Float[Value, "*batch 4 4"] | None = None

    def __post_init__(self):
        # omitted fields: no turn, moving along the body heading
        if self.yaw_rate_rps is None:
            self.yaw_rate_rps = jnp.zeros_like(self.x_m)
        if self.course_rad is None:
            self.course_rad = self.yaw_rad


class Poses(eqx.Module):
    """Predicted poses at t + h * dt_s, h = 1..H: fields (H,) for one car, leading axes for cars
    and parameter sets. x_m, y_m: position [m]; yaw_rad: heading of the car body [rad]."""

    x_m: Float[ArrayLike, "*batch H"]
    y_m: Float[ArrayLike, "*batch H"]
    yaw_rad: Float[ArrayLike, "*batch H"]

    @property
    def xy_m(self) -> Float[ArrayLike, "*batch H 2"]:
        """Positions [m], (..., H, 2) as the targets they are scored against."""
        # cut from the packed array: the fit's gradient compiles (bitwise) as through `predict`
        return self.packed()[..., :2]

    def packed(self) -> Float[ArrayLike, "*batch H 3"]:
        """(..., H, 3) x, y, yaw: the array of predict, predict_batch, the CLI and the exports."""
        xp = np if isinstance(self.x_m, np.ndarray) else jnp  # finished predictions stay NumPy
        return xp.stack([self.x_m, self.y_m, self.yaw_rad], axis=-1)
