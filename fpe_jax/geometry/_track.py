"""`Track`: a uniformly resampled path the leading car follows, with arc-length geometry.

Built once from waypoints in NumPy (cleaning, loop detection, resampling, smoothing); every query
(`point_at`, `heading_at`, `project*`) is a pure JAX function, differentiable in the arc length.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from fpe_jax.compile._arrays import device_array
from fpe_jax.geometry._path import (
    BRANCH_COS,
    BRANCH_M,
    LOCAL_PROJECTION_ITERS,
    build_path,
    window_points,
)


class Track(eqx.Module):
    """A path resampled at uniform spacing, closed (a loop) or open.

    Attributes:
        xy_m: (M, 2) resampled points x [m], y [m]; on a loop point M-1 connects back to point 0.
        heading_rad: (M,) path heading at each point [rad].
        ds_m: () spacing between consecutive points [m].
        length_m: () total arc length [m] (closing segment included on loops).
        raw_xy_m: (K, 2) the waypoints as given, in their order (the legacy goal scan reads them).
        seg_m: (M, 8) segment i from point i to the next: start x, y [m], chord x, y [m] (zero
            after the last point of an open path), and the unit path tangents at its start and
            end (tx, ty each): everything a lookup needs in one gathered row.
        closed: static; True for a loop (arc length wraps), False for an open path (clamps).
        window: static; the points (behind, ahead) `project_window` searches around its hint
            (`window_points` of the spacing). Shapes must be static, and counts rather than the
            spacing itself let tracks whose spacing differs in its last bit (a local-origin
            shift, a CSV round trip) share compiled programs; the traced `ds_m` does the
            arithmetic.
    """

    xy_m: Float[Array, "M 2"]
    heading_rad: Float[Array, " M"]
    ds_m: Float[Array, ""]
    length_m: Float[Array, ""]
    raw_xy_m: Float[Array, "K 2"]
    seg_m: Float[Array, "M 8"]
    closed: bool = eqx.field(static=True)
    window: tuple[int, int] = eqx.field(static=True, default=window_points(0.1))

    @classmethod
    def from_waypoints(cls, waypoints_xy_m, **kwargs) -> Track:
        """Build a track from waypoints (K, 2) x [m], y [m]; keyword options as in
        `fpe_jax.geometry.build_path` (ds_m, closed, smooth_m, min_step_m, backtrack_tol_m,
        source)."""
        p = build_path(waypoints_xy_m, **kwargs)
        xy = p["xy_m"]
        tangent = np.stack([np.cos(p["heading_rad"]), np.sin(p["heading_rad"])], axis=1)
        seg = np.concatenate([xy, tangent], axis=1)  # the next point's row: point, tangent
        nxt = np.roll(seg, -1, axis=0) if p["closed"] else np.vstack([seg[1:], seg[-1:]])
        return cls(
            xy_m=device_array(p["xy_m"]),
            heading_rad=device_array(p["heading_rad"]),
            ds_m=device_array(p["ds_m"]),
            length_m=device_array(p["length_m"]),
            raw_xy_m=device_array(p["raw_xy_m"]),
            seg_m=device_array(np.concatenate([xy, nxt[:, :2] - xy, tangent, nxt[:, 2:]], axis=1)),
            closed=p["closed"],
            window=window_points(p["ds_m"]),
        )

    @property
    def n_points(self) -> int:
        return self.xy_m.shape[0]

    def _locate(self, s_m):
        """Segment index i, next index j and fraction f in [0, 1] for arc length s [m]."""
        m = self.n_points
        if self.closed:
            # wrap the integer index, not s: XLA runs a float remainder element by element on
            # CPU; removing it made a batch rollout step ~1.5x faster
            u = s_m / self.ds_m
            u_floor = jnp.floor(u)
            i = u_floor.astype(jnp.int32) % m
            return i, (i + 1) % m, u - u_floor
        u = jnp.clip(s_m, 0.0, self.length_m) / self.ds_m
        i = jnp.clip(jnp.floor(u).astype(jnp.int32), 0, m - 2)
        return i, i + 1, u - i.astype(u.dtype)

    def _segment(self, s_m):
        """The `seg_m` row (8,) of the segment holding arc length s, and the fraction in it."""
        i, _, f = self._locate(s_m)
        return self.seg_m[i], f

    def point_at(self, s_m: Float[ArrayLike, ""]) -> Float[Array, "2"]:
        """Position (2,) [m] at arc length s [m]; wraps on loops, clamps on open paths."""
        row, f = self._segment(s_m)
        return row[:2] + f * row[2:4]

    def heading_at(self, s_m: Float[ArrayLike, ""]) -> Float[Array, ""]:
        """Path heading [rad] at arc length s [m], interpolated without a wrap jump."""
        i, j, f = self._locate(s_m)
        h0 = self.heading_rad[i]
        return wrap_angle(h0 + f * wrap_angle(self.heading_rad[j] - h0))

    def _project_segments(self, p_m, idx, heading_rad=None):
        """Closest point of p (2,) on the segments starting at indices idx (n,): arc length [m].
        With a heading [rad] (NaN: unknown), the nearest segment within 45 degrees of it where
        that lies within 2 m of p (`fpe_jax.geometry.BRANCH_COS`, `BRANCH_M`)."""
        rows = self.seg_m[idx]
        a, ab = rows[:, :2], rows[:, 2:4]
        t = jnp.clip(
            jnp.sum((p_m[None, :] - a) * ab, -1) / jnp.maximum(jnp.sum(ab * ab, -1), 1e-12), 0, 1
        )
        d2 = jnp.sum((a + t[:, None] * ab - p_m[None, :]) ** 2, -1)
        k = jnp.argmin(d2)
        if heading_rad is not None:
            agree = rows[:, 4] * jnp.cos(heading_rad) + rows[:, 5] * jnp.sin(heading_rad)
            d2_agree = jnp.where(agree >= BRANCH_COS, d2, jnp.inf)
            ka = jnp.argmin(d2_agree)
            k = jnp.where(d2_agree[ka] <= BRANCH_M * BRANCH_M, ka, k)
        return (idx[k].astype(t.dtype) + t[k]) * self.ds_m

    def project(self, p_m: Float[Array, "2"], heading_rad=None) -> Float[Array, ""]:
        """Arc length [m] of the closest point of the whole track to p (2,) [m] (global search);
        given the car's heading [rad] (NaN: unknown), of the branch that agrees with it where the
        track crosses itself (`fpe_jax.geometry.BRANCH_COS`)."""
        last = self.n_points if self.closed else self.n_points - 1
        return self._project_segments(p_m, jnp.arange(last), heading_rad)

    def continuous(self, s_m, s_ref_m):
        """s [m] moved by whole laps to within half a lap of s_ref [m] on a loop (as is on an
        open path): the seam rule of `project_window`."""
        return s_ref_m + wrap_to(s_m - s_ref_m, self.length_m) if self.closed else s_m

    def project_window(
        self, p_m: Float[Array, "2"], s_hint_m: Float[Array, ""]
    ) -> Float[Array, ""]:
        """Arc length [m] of the closest point within [s_hint - behind, s_hint + ahead]
        (`_path.WINDOW_BEHIND_M`, `WINDOW_AHEAD_M`, in whole points: `window`).

        The window keeps a car on its own stretch of path: never snapped to the far side of a
        hairpin or across the seam of a noisy loop.
        """
        n_back, n_ahead = self.window
        i0 = jnp.floor(s_hint_m / self.ds_m).astype(jnp.int32)
        idx = i0 + jnp.arange(-n_back, n_ahead + 1, dtype=jnp.int32)
        if self.closed:
            idx = jnp.mod(idx, self.n_points)
            s = self._project_segments(p_m, idx)
            # keep s continuous with the hint across the seam (no jump by one lap length)
            return s_hint_m + wrap_to(s - s_hint_m, self.length_m)
        return self._project_segments(p_m, jnp.clip(idx, 0, self.n_points - 2))

    def project_local(
        self,
        p_m: Float[Array, "2"],
        s_hint_m: Float[Array, ""],
        iters: int = LOCAL_PROJECTION_ITERS,
    ) -> Float[Array, ""]:
        """Arc length [m] near s_hint by Newton steps along the path tangent: O(1).

        For the hot path of a rollout, where the car moves < 1 m between steps and stays near
        the path. The tangent is interpolated between the segment's end tangents, so the result
        is continuous in p and in the hint (a chord's direction would jump at every point, and
        a car off the path would then land 4 cm apart on either side of one). One gathered row
        and no trigonometry per step; `iters` is static.
        """
        s = s_hint_m
        for _ in range(iters):
            row, f = self._segment(s)
            g = 1.0 - f
            # component-wise: a vmapped jnp.dot becomes a slow batched matmul on CPU
            ex, ey = p_m[0] - row[0] - f * row[2], p_m[1] - row[1] - f * row[3]
            tx, ty = g * row[4] + f * row[6], g * row[5] + f * row[7]
            # |t| is 1 to within (turn per point)^2 / 8; the fixed point does not depend on it
            s = s + ex * tx + ey * ty
        return s


def wrap_angle(a):
    """Wrap angles [rad] to [-pi, pi): the JAX twin of `fpe_jax.geometry.wrap_angle`.

    Written with floor instead of %: XLA runs a float remainder element by element on CPU,
    which is slow in a batch rollout.
    """
    return a - (2 * jnp.pi) * jnp.floor((a + jnp.pi) * (0.5 / jnp.pi))


def wrap_to(x, period):
    """Wrap x to [-period / 2, period / 2)."""
    return (x + 0.5 * period) % period - 0.5 * period


@jax.jit
def arclength_along(track: Track, xy_m: Float[Array, "N 2"], s_before_m=None) -> Float[Array, " N"]:
    """Arc length [m] of each point of a drive (N, 2), each projected in a window around the last.

    The first point is projected globally (`s_before_m` None or NaN), or in the window around
    `s_before_m` [m] (the arc length of the point before it, for a drive cut in blocks); later
    points stay continuous (no jumps across a hairpin or the seam), so s may exceed the lap length
    on loops (it counts laps). A NaN start lets the first block of a drive share the compiled
    function of the blocks after it.
    """
    if s_before_m is None:
        s0 = track.project(xy_m[0])
    else:
        s0 = jnp.where(jnp.isnan(s_before_m), track.project(xy_m[0]), s_before_m)

    def step(s_prev, p):
        s = track.project_window(p, s_prev)
        return s, s

    _, s = jax.lax.scan(step, s0, xy_m)
    return s


@jax.jit
def arclength_along_heading(
    track: Track, xy_m: Float[Array, "N 2"], heading_rad: Float[Array, " N"], s_before_m
) -> Float[Array, " N"]:
    """`arclength_along` for a drive whose headings [rad] (N,) are known where finite (NaN where
    not, e.g. a car without orientation that has not moved yet): until the first known heading
    each point is projected globally onto the branch that agrees with it (`Track.project`),
    then in the window around the last. `s_before_m` NaN starts the drive; a number continues it.
    """

    def step(carry, inp):
        s_prev, settled = carry
        p, h = inp

        def search(_):
            s = track.project(p, h)
            return jnp.where(jnp.isnan(s_prev), s, track.continuous(s, s_prev))

        hint = jax.lax.cond(settled, lambda _: s_prev, search, None)
        s = track.project_window(p, hint)
        return (s, settled | ~jnp.isnan(h)), s

    s_before = jnp.asarray(s_before_m, dtype=xy_m.dtype)
    _, s = jax.lax.scan(step, (s_before, ~jnp.isnan(s_before)), (xy_m, heading_rad))
    return s


def project_rollout(
    track: Track, xy_m: Float[Array, "H 2"], start_xy_m: Float[Array, "2"], s_start_m
) -> Float[Array, " H"]:
    """Arc length [m] of each point of one predicted path (H, 2), from the car's own place.

    Each point is projected in a window around the previous point's arc length plus the distance
    moved since (from `start_xy_m` (2,) at `s_start_m` [m] for the first): O(H x window) work,
    independent of the track's size, and never snapped to another part of the track.
    """

    def step(carry, p):
        s_prev, p_prev = carry
        s = track.project_window(p, s_prev + jnp.linalg.norm(p - p_prev))
        return (s, p), s

    _, s = jax.lax.scan(step, (s_start_m, start_xy_m), xy_m)
    return s
