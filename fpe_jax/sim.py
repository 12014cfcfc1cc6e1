"""Synthetic drives of a leading race car, seen through a trailing car's camera (the default data).

The leading car is deliberately *not* from the predictor's model family (kinematic bicycle + pure
pursuit), so fitting to these drives is honest:

- vehicle: dynamic single-track model with linear tyres, load transfer and the F1TENTH parameters
  (the CommonRoad "ST" model), blended into a kinematic bicycle below ~1 m/s where the dynamic
  equations become singular; RK4 at 100 Hz; first-order, rate-limited steering servo.
- driver: pure pursuit with a speed-dependent lookahead on a reference path (raceline or
  centerline) shifted by a slowly wandering lateral offset; a speed profile (raceline speeds or a
  curvature limit with accel/brake passes) tracked by a P-controller; optional stops.
- sensor (after the thesis' AprilTag setup): detections at ~11.5 Hz with random inter-arrival
  times, a fixed latency (a detection shows the car `latency_s` before its stamp), noise growing
  with the range to the trailing car, yaw noise, ~1 % outliers, more dropouts in fast turns.
- camera (optional, `Camera`): the trailing car's own motion (on the centerline, the sensor's
  gap behind), its camera's field of view and the leading car's tag: detections drop out when
  the tag leaves the view, and `write_simulation` writes the thesis' AprilTag layout.

Everything is NumPy + `math`, deterministic per seed. Time starts at 0 at the first truth sample.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np

from fpe_jax.drive import Drive
from fpe_jax.errors import InputError
from fpe_jax.path import build_path, left_normals, nearest_index, wrap_angle
from fpe_jax.spec import check_half_width, check_simulation
from fpe_jax.tracks import builtin_track, is_builtin, loop_arclength, loop_curvature, resample_loop

SIM_VERSION = "1.0"
DT_S = 0.01  # RK4 and driver step (100 Hz)
TRUTH_EVERY = 2  # truth is recorded every 2nd step (50 Hz)
REF_SPACING_M = 0.1  # the driver's reference path is resampled at this spacing
# The closed loop keeps ~300 bytes per 10 ms step in Python lists: 2 hours are ~0.2 GB (the
# same again for the sensor), where a day would be several GB. Longer drives: several seeds.
MAX_DURATION_S = 7200.0
G_MPS2 = 9.81


@dataclasses.dataclass(frozen=True)
class Vehicle:
    """Dynamic single-track vehicle: F1TENTH parameters (CommonRoad vehicle 2 scaled to 1:10)."""

    mu: float = 1.0489  # tyre-road friction coefficient [-]
    c_sf: float = 4.718  # front cornering stiffness coefficient [1/rad]
    c_sr: float = 5.4562  # rear cornering stiffness coefficient [1/rad]
    lf_m: float = 0.15875  # centre of gravity to front axle [m]
    lr_m: float = 0.17145  # centre of gravity to rear axle [m]
    h_cg_m: float = 0.074  # centre of gravity height [m]
    mass_kg: float = 3.74
    inertia_kgm2: float = 0.04712  # yaw moment of inertia [kg m^2]
    steer_max_rad: float = 0.4189
    steer_rate_max_rps: float = 3.2  # [rad/s]
    accel_max_mps2: float = 9.51
    v_switch_mps: float = 7.319  # above it the motor is power-limited: a_max * v_switch / v
    servo_tau_s: float = 0.1  # first-order steering servo lag [s]
    v_kinematic_mps: float = 0.5  # at or below: purely kinematic
    v_dynamic_mps: float = 1.0  # at or above: purely dynamic; smoothstep blend in between


@dataclasses.dataclass(frozen=True)
class Driver:
    """The leading car's driver: pure pursuit on a wandering line, P-controlled speed, stops."""

    lookahead_min_m: float = 0.5
    lookahead_time_s: float = 0.3  # lookahead = max(lookahead_min_m, lookahead_time_s * v)
    offset_max_m: float = 0.3  # lateral offset amplitude on a 1.1 m half-width track; scales
    offset_period_s: tuple[float, float] = (6.0, 20.0)  # periods of the offset's sinusoids
    edge_margin_m: float = 0.3  # the offset never puts the aim point closer to an edge
    lat_accel_mps2: float = 5.0  # curvature speed limit v = sqrt(a_lat / |kappa|)
    accel_mps2: float = 3.0  # speed profile's forward pass
    brake_mps2: float = 4.0  # speed profile's backward pass
    v_min_mps: float = 2.0
    v_max_mps: float = 8.0
    raceline_speed_scale: float = 0.9  # raceline speeds (at the grip limit) x this, clipped
    speed_gain_1ps: float = 2.0  # P-controller: a = gain * (v_target - v) [1/s]
    speed_preview_s: float = 0.3  # the target speed is read this far ahead on the path
    speed_factor: float = 1.0  # the target speed profile x this (1.0: drives bit-identical)
    stops_per_min: float = 0.0  # Poisson rate of stops (brake to 0, wait, go on)
    stop_wait_s: tuple[float, float] = (1.0, 3.0)
    stop_brake_mps2: float = 3.0


@dataclasses.dataclass(frozen=True)
class Sensor:
    """AprilTag-like detector on a trailing car that follows `ego_gap_m` behind on the track."""

    rate_hz: float = 11.5  # mean detection rate before dropouts (thesis: 11-12 Hz)
    jitter_frac: float = 0.15  # inter-arrival times uniform in (1 +- jitter_frac) / rate_hz
    sigma_m: float = 0.02  # position noise along the line of sight: sigma_m + sigma_per_m * range
    sigma_per_m: float = 0.06  # [m per m of range]
    lateral_ratio: float = 0.35  # noise across the line of sight, relative (bearing is sharper)
    yaw_sigma_rad: float = 0.05
    outlier_prob: float = 0.01  # a detection jumps 0.5-2 m in a random direction
    outlier_jump_m: tuple[float, float] = (0.5, 2.0)
    miss_prob: float = 0.02  # dropout probability on straights
    miss_per_radps: float = 0.15  # + this per rad/s of |yaw rate| above miss_yaw_rate_rps
    miss_yaw_rate_rps: float = 1.0
    ego_gap_m: tuple[float, float] = (2.0, 4.0)  # trailing car's distance behind along the track

    @classmethod
    def clean(cls, **changes) -> Sensor:
        """A perfect detector: no noise, no outliers, no dropouts (same timing as the default)."""
        base = dict(sigma_m=0.0, sigma_per_m=0.0, yaw_sigma_rad=0.0, outlier_prob=0.0)
        return cls(**(base | dict(miss_prob=0.0, miss_per_radps=0.0) | changes))


@dataclasses.dataclass(frozen=True)
class Camera:
    """The trailing car's camera and the tag on the leading car (the thesis' AprilTag setup).

    Frames: the trailing car's base_link (x forward, z up), its laser, the camera's optical frame
    on top of the laser; the tag on the leading car's base frame, upright, facing `tag_yaw_rad`.
    A capture sees the tag when the camera's optical centre has it within half the horizontal
    field of view, within range, and the tag faces the camera within `max_incidence_rad`.
    """

    laser_xyz_m: tuple[float, float, float] = (0.27, 0.0, 0.1)  # laser in base_link
    camera_xyz_m: tuple[float, float, float] = (0.0, 0.0, 0.06)  # camera in laser (on top)
    hfov_rad: float = 1.1  # horizontal field of view (~63 deg: a C910 webcam at 640x480)
    max_range_m: float = 5.0  # the thesis: 0.1085 m tags are found up to ~5 m at 640x480
    max_incidence_rad: float = 1.2  # tag normal vs the line to the camera (~69 deg)
    tag_id: int = 0
    tag_size_m: float = 0.1085
    tag_xyz_m: tuple[float, float, float] = (-0.2, 0.0, 0.2)  # tag centre in the car's frame
    tag_yaw_rad: float = math.pi  # the tag faces backwards, towards the trailing car


@dataclasses.dataclass(frozen=True)
class SimResult:
    """A simulated drive and what it was made from.

    Attributes:
        drive: detections (t_s (N,) arrival stamps [s], xy_m (N, 2), yaw_rad (N,)) and 50 Hz truth.
        centerline_xy_m: (K, 2) the track's centerline [m] (what predictors get; not the raceline).
        half_width_m: track half-width [m].
        reference_xy_m: (R, 2) the path the driver followed (raceline or centerline) [m].
        truth_yaw_rate_rps: (M,) true yaw rate at the truth stamps [rad/s].
        truth_steer_rad: (M,) true front-wheel steering angle [rad].
        capture_t_s: (N,) when each detection's image was taken [s] (= stamp - latency).
        outlier: (N,) which detections are outliers.
        range_m: (N,) distance from the trailing car's camera to the car at capture [m].
        scenario: every setting, the seed, latency, track name and simulator version (JSON-able).
        ego_t_s, ego_xy_m, ego_yaw_rad: with a `Camera`, the trailing car's pose at the 50 Hz
            truth stamps (the last stretched to the last detection's stamp) [s], [m], [rad].
        missed_t_s: with a `Camera`, the stamps [s] of captures that gave no detection.
    """

    drive: Drive
    centerline_xy_m: np.ndarray
    half_width_m: float
    reference_xy_m: np.ndarray
    truth_yaw_rate_rps: np.ndarray
    truth_steer_rad: np.ndarray
    capture_t_s: np.ndarray
    outlier: np.ndarray
    range_m: np.ndarray
    scenario: dict[str, Any]
    ego_t_s: np.ndarray | None = None
    ego_xy_m: np.ndarray | None = None
    ego_yaw_rad: np.ndarray | None = None
    missed_t_s: np.ndarray | None = None


def simulate(
    track: str | Path | np.ndarray,
    *,
    duration_s: float,
    latency_s: float = 0.3,
    seed: int = 0,
    raceline: str | Path | None = None,
    half_width_m: float | None = None,
    vehicle: Vehicle = Vehicle(),
    driver: Driver = Driver(),
    sensor: Sensor = Sensor(),
    camera: Camera | None = None,
) -> SimResult:
    """Simulate the leading car for `duration_s` and what the trailing car's detector reports.

    Args:
        track: a built-in name (``oval``, ``hairpin``, ``random:SEED``), a centerline/waypoint
            file (read with `fpe_jax.io.load_waypoints`; speeds in it are used if no raceline is
            given), or a (K, 2) closed centerline [m].
        duration_s: length of the drive [s]; truth covers [0, duration_s] at 50 Hz.
        latency_s: detection latency [s]: a detection stamped t shows the car at t - latency_s.
        seed: seeds every random choice; equal seeds give identical results.
        raceline: optional raceline/waypoint file with speeds; the driver follows it instead of
            the centerline, at its (scaled, clipped) speeds.
        half_width_m: track half-width [m]; default: the built-in's, else 1.1 (F1TENTH tracks).
        vehicle, driver, sensor: model settings.
        camera: the trailing car's camera and the leading car's tag: adds field-of-view dropouts
            and the trailing car's motion (None: neither; every other number is the same).

    Returns:
        A `SimResult`; detections stamped after `duration_s` are not recorded.
    """
    check_simulation(duration_s, latency_s, seed, driver.stops_per_min)
    name, center, hw, ref_xy, ref_v = _resolve_track(track, raceline, half_width_m)
    check_drivable(center, vehicle, track if isinstance(track, str | Path) else "track")
    if raceline is not None:
        check_drivable(ref_xy, vehicle, raceline)
    rng_drive, rng_offset, rng_sensor = (
        np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(3)
    )

    ref = _reference_path(ref_xy, ref_v, center, hw, driver)
    n_steps = int(round(duration_s / DT_S))
    t_steps = np.arange(n_steps + 1) * DT_S
    offset_m = _smooth_random(rng_offset, driver.offset_max_m * hw / 1.1, driver.offset_period_s)
    offset_m = offset_m(t_steps)
    start = int(rng_drive.integers(len(ref["xy"])))
    stop_times_s, stop_waits_s = _stop_schedule(rng_drive, duration_s, driver)
    states = _drive(ref, start, offset_m, stop_times_s, stop_waits_s, vehicle, driver)

    truth = states[::TRUTH_EVERY]
    truth_t = t_steps[::TRUTH_EVERY]
    det = _detect(rng_sensor, t_steps, states, center, duration_s, latency_s, sensor, camera)

    scenario = dict(
        sim_version=SIM_VERSION,
        track=name,
        track_file=None if isinstance(track, np.ndarray) or is_builtin(str(track)) else str(track),
        raceline=None if raceline is None else str(raceline),
        half_width_m=hw,
        duration_s=float(duration_s),
        latency_s=float(latency_s),
        seed=int(seed),
        dt_s=DT_S,
        truth_rate_hz=1.0 / (DT_S * TRUTH_EVERY),
        vehicle=dataclasses.asdict(vehicle),
        driver=dataclasses.asdict(driver),
        sensor=dataclasses.asdict(sensor),
    )
    extra: dict[str, Any] = {}
    meta_extra: dict[str, Any] = {}
    if camera is not None:
        scenario["camera"] = dataclasses.asdict(camera)
        ego_t = truth_t.copy()
        ego_xy, ego_yaw = _ego_pose(truth[:, 0:2], det["gap_fn"](truth_t), center)
        if len(det["stamp"]):  # lookups never extrapolate: the TF must reach the last stamp
            ego_t[-1] = max(ego_t[-1], float(det["stamp"][-1]))
        extra = dict(ego_t_s=ego_t, ego_xy_m=ego_xy, ego_yaw_rad=ego_yaw, missed_t_s=det["missed"])
        meta_extra = dict(n_out_of_view=det["n_out_of_view"])
    drive = Drive(
        t_s=det["stamp"],
        xy_m=det["xy"],
        yaw_rad=det["yaw"],
        truth_t_s=truth_t,
        truth_xy_m=truth[:, 0:2].copy(),
        truth_yaw_rad=wrap_angle(truth[:, 2]),
        truth_v_mps=truth[:, 3].copy(),
        meta=dict(
            source="fpe_jax.sim",
            track=name,
            seed=int(seed),
            latency_s=float(latency_s),
            sim_version=SIM_VERSION,
            n_captured=det["n_captured"],
            n_dropped=det["n_captured"] - len(det["stamp"]),
            n_outliers=int(det["outlier"].sum()),
            **meta_extra,
        ),
    )
    return SimResult(
        drive=drive,
        centerline_xy_m=center,
        half_width_m=hw,
        reference_xy_m=ref_xy,
        truth_yaw_rate_rps=truth[:, 4].copy(),
        truth_steer_rad=truth[:, 5].copy(),
        capture_t_s=det["capture"],
        outlier=det["outlier"],
        range_m=det["range"],
        scenario=scenario,
        **extra,
    )


def observe(
    t_s: np.ndarray,
    xy_m: np.ndarray,
    yaw_rad: np.ndarray,
    centerline_xy_m: np.ndarray,
    *,
    latency_s: float = 0.3,
    seed: int = 0,
    sensor: Sensor = Sensor(),
    meta: dict[str, Any] | None = None,
) -> Drive:
    """A recorded trajectory seen through the simulator's detector (`Sensor`: capture timing,
    range-dependent noise, outliers, dropouts, then `latency_s` of delay), as `simulate` sees
    its own drives.

    Args:
        t_s: (N,) strictly increasing stamps of the recorded poses [s].
        xy_m: (N, 2) recorded positions [m]; yaw_rad: (N,) recorded heading [rad].
        centerline_xy_m: (K, 2) closed loop the trailing car drives on (sets the range) [m].
        latency_s, seed, sensor: as `simulate`'s.
        meta: provenance added to the drive's meta.

    Returns:
        A Drive: detections stamped at arrival (captures from t_s[0] on, relative time kept),
        truth = the recorded poses (speed from their differences).
    """
    t = np.asarray(t_s, dtype=float)
    xy = np.asarray(xy_m, dtype=float)
    yaw = np.unwrap(np.asarray(yaw_rad, dtype=float))
    if t.ndim != 1 or len(t) < 3 or np.any(np.diff(t) <= 0) or xy.shape != (len(t), 2):
        raise InputError(
            "trajectory",
            f"stamps {t.shape} and positions {xy.shape} do not form a drive",
            "(N,) strictly increasing stamps, N >= 3, and (N, 2) positions",
        )
    t0 = t[0]
    rel = t - t0
    v = np.hypot(*np.gradient(xy, rel, axis=0).T)
    r = np.gradient(yaw, rel)
    states = np.stack([xy[:, 0], xy[:, 1], yaw, v, r], axis=1)
    rng = np.random.default_rng(np.random.SeedSequence(seed).spawn(3)[2])
    det = _detect(
        rng, rel, states, np.asarray(centerline_xy_m, float), rel[-1], latency_s, sensor, None
    )
    return Drive(
        t_s=det["stamp"] + t0,
        xy_m=det["xy"],
        yaw_rad=det["yaw"],
        truth_t_s=t.copy(),
        truth_xy_m=xy.copy(),
        truth_yaw_rad=wrap_angle(yaw),
        truth_v_mps=v,
        meta=dict(
            source="fpe_jax.sim.observe",
            seed=int(seed),
            latency_s=float(latency_s),
            sim_version=SIM_VERSION,
            n_captured=det["n_captured"],
            n_dropped=det["n_captured"] - len(det["stamp"]),
            n_outliers=int(det["outlier"].sum()),
        )
        | (meta or {}),
    )


# --- track and reference path -------------------------------------------------------------------


def _resolve_track(track, raceline, half_width_m):
    """-> (name, centerline (K, 2), half-width [m], reference xy (R, 2), its speeds (R,) | None)."""
    if isinstance(track, np.ndarray):
        name, center, hw, speeds = "array", np.asarray(track, dtype=float), 1.1, None
        if center.ndim != 2 or center.shape[1] != 2 or len(center) < 3:
            raise InputError("track", f"array of shape {center.shape}", "a (K, 2) closed loop")
    elif isinstance(track, str) and is_builtin(track):
        name, speeds = track, None
        center, hw = builtin_track(track)
    elif Path(track).exists():
        wp = _load_waypoints(track)
        name, center, hw, speeds = Path(track).stem, wp.xy_m, 1.1, wp.speed_mps
    else:
        expected = "oval, hairpin, random:SEED or a centerline/waypoint file"
        raise InputError(track, "is neither a built-in track nor an existing file", expected)
    hw = check_half_width(half_width_m if half_width_m is not None else hw, "half-width")
    if raceline is None:
        return name, center, hw, center, speeds
    rl = _load_waypoints(raceline)
    return name, center, hw, rl.xy_m, rl.speed_mps


def check_drivable(xy_m, vehicle: Vehicle, source) -> None:
    """InputError (naming `source`) unless the car can drive the closed loop (K, 2) [m]: the size
    limits of every command (`fpe_jax.spec.check_track_size`, which also catches a far spike),
    and no stretch one turning circle long (2 pi R, R = wheelbase / tan(steer_max)) that turns by
    more than a full circle, i.e. a loop tighter than the car's turning radius. Judged over that
    length, so the kinks of hand-recorded waypoints (a corner at a point) pass."""
    # the cleaned, smoothed loop every command builds (with its size checks)
    path = build_path(np.asarray(xy_m, dtype=np.float64), closed=True, source=str(source))
    h, ds, m = path["heading_rad"], path["ds_m"], len(path["heading_rad"])
    r_min = (vehicle.lf_m + vehicle.lr_m) / math.tan(vehicle.steer_max_rad)
    turn = wrap_angle(np.roll(h, -1) - h)  # per point, the closing one included
    n = max(1, int(round(2 * math.pi * r_min / ds)))  # may be laps of a small loop
    total = np.concatenate([[0.0], np.cumsum(np.tile(turn, n // m + 2)[: m + n])])
    worst = float(np.max(np.abs(total[n : n + m] - total[:m])))
    if worst > 2 * math.pi * 1.001:  # a circle of radius R turns exactly 2 pi over 2 pi R
        raise InputError(
            source,
            f"turns by {worst:.1f} rad within {n * ds:.2f} m: tighter than the car's turning "
            f"radius {r_min:.2f} m (it could never follow it)",
            f"a loop with no turn tighter than a {r_min:.2f} m radius",
        )


def _load_waypoints(path):
    from fpe_jax.io import load_waypoints  # only file-based tracks need the io package

    return load_waypoints(path)


def _reference_path(xy_m, speed_mps, center_xy_m, half_width_m, driver: Driver) -> dict:
    """Resample the driver's path and precompute what the 100 Hz loop reads (as Python lists).

    Returns dict: xy (R, 2) array, and lists x, y, nx, ny (left unit normal), v (target speed
    [m/s]), lo/hi (allowed lateral offset [m] that keeps the aim point `edge_margin_m` inside the
    track, so a raceline that touches an edge is followed with that margin), and spacing [m].
    """
    xy, v = resample_loop(xy_m, REF_SPACING_M, speed_mps)
    spacing = loop_arclength(xy)[-1] / len(xy)
    if v is None:
        v = _speed_profile(loop_curvature(xy, smooth_m=1.0), spacing, driver)
    else:
        v = np.clip(v * driver.raceline_speed_scale, driver.v_min_mps, driver.v_max_mps)
    normal = left_normals(xy)
    # Signed distance of each path point from the centerline (zero when the path is it).
    idx = nearest_index(xy, center_xy_m)
    side = np.sum((xy - center_xy_m[idx]) * left_normals(center_xy_m)[idx], axis=1)
    room = max(half_width_m - driver.edge_margin_m, 0.0)
    lo, hi = -room - side, room - side
    return dict(
        xy=xy,
        x=xy[:, 0].tolist(),
        y=xy[:, 1].tolist(),
        nx=normal[:, 0].tolist(),
        ny=normal[:, 1].tolist(),
        v=v.tolist(),
        lo=lo.tolist(),
        hi=hi.tolist(),
        spacing=float(spacing),
    )


def _speed_profile(kappa: np.ndarray, spacing_m: float, driver: Driver) -> np.ndarray:
    """(R,) speeds [m/s]: the lateral-acceleration limit, then accel (forward) and brake
    (backward) passes around the loop (two laps each, so the wrap-around is consistent)."""
    v = np.minimum(driver.v_max_mps, np.sqrt(driver.lat_accel_mps2 / np.abs(kappa).clip(1e-9)))
    v = v.tolist()
    n = len(v)
    acc2, brk2 = 2 * driver.accel_mps2 * spacing_m, 2 * driver.brake_mps2 * spacing_m
    for k in range(1, 2 * n):
        v[k % n] = min(v[k % n], math.sqrt(v[(k - 1) % n] ** 2 + acc2))
    for k in range(2 * n - 2, -1, -1):
        v[k % n] = min(v[k % n], math.sqrt(v[(k + 1) % n] ** 2 + brk2))
    return np.maximum(np.array(v), driver.v_min_mps)


def _smooth_random(rng, amplitude: float, period_s, n: int = 3):
    """A smooth random signal, n sinusoids of random period/phase with |value| <= amplitude, as a
    function of time (N,) [s] -> (N,), to sample anywhere."""
    periods = rng.uniform(*period_s, size=n)
    phases = rng.uniform(0.0, 2 * math.pi, size=n)
    weights = rng.uniform(0.5, 1.0, size=n)
    weights *= amplitude / weights.sum()
    return lambda t_s: np.sin(2 * math.pi * t_s[:, None] / periods + phases) @ weights


def _stop_schedule(rng, duration_s: float, driver: Driver) -> tuple[list[float], list[float]]:
    """Stop start times [s] (a Poisson process) and each stop's standstill time [s]."""
    n_max = int(duration_s * driver.stops_per_min / 60.0 * 3 + 10)
    gaps = rng.exponential(60.0 / max(driver.stops_per_min, 1e-12), size=n_max)
    waits = rng.uniform(*driver.stop_wait_s, size=n_max)
    if driver.stops_per_min <= 0:
        return [], []
    times = np.cumsum(gaps)
    keep = times < duration_s
    return times[keep].tolist(), waits[keep].tolist()


# --- vehicle and driver -------------------------------------------------------------------------


def _drive(ref, start, offset_m, stop_times_s, stop_waits_s, veh: Vehicle, drv: Driver):
    """Run the closed loop (driver at 100 Hz, RK4 at 100 Hz) from path point `start`.

    Returns (S + 1, 7) states per step: x [m], y [m], yaw [rad] (unwrapped), v [m/s],
    yaw rate [rad/s], steering angle [rad], slip angle at the centre of gravity [rad].
    """
    px, py, nx, ny, vref, lo, hi = (ref[k] for k in ("x", "y", "nx", "ny", "v", "lo", "hi"))
    n_ref, spacing = len(px), ref["spacing"]
    lf, lr = veh.lf_m, veh.lr_m
    lwb = lf + lr
    d_max, a_max, v_sw = veh.steer_max_rad, veh.accel_max_mps2, veh.v_switch_mps
    f = _make_dynamics(veh)
    h = DT_S

    i = start
    off0 = min(max(offset_m[0], lo[i]), hi[i])
    x, y = px[i] + off0 * nx[i], py[i] + off0 * ny[i]
    j = (i + 1) % n_ref
    yaw = math.atan2(py[j] - py[i - 1], px[j] - px[i - 1])
    # the car starts at its own target pace (speed_factor), not at the unscaled profile's
    v, r, steer, beta = vref[i] * drv.speed_factor, 0.0, 0.0, 0.0
    mode, next_stop, stop_k, wait_until, steer_cmd = "drive", 0, 0, 0.0, 0.0
    out = []
    for k, off in enumerate(offset_m.tolist()):
        out.append((x, y, yaw, v, r, steer, beta))
        if k == len(offset_m) - 1:
            break
        t = k * h
        # Nearest path point: walk from the last one (the car moves < 0.1 m per step).
        dist = (x - px[i]) ** 2 + (y - py[i]) ** 2
        for step in (1, -1):
            while True:
                c = (i + step) % n_ref
                dc = (x - px[c]) ** 2 + (y - py[c]) ** 2
                if dc >= dist:
                    break
                i, dist = c, dc
        # Pure pursuit from the rear axle to the offset path point one lookahead ahead.
        look_m = max(drv.lookahead_min_m, drv.lookahead_time_s * v)
        g = (i + int(look_m / spacing)) % n_ref
        off = min(max(off, lo[g]), hi[g])
        cy, sy = math.cos(yaw), math.sin(yaw)
        gx, gy = px[g] + off * nx[g] - (x - lr * cy), py[g] + off * ny[g] - (y - lr * sy)
        lateral = -sy * gx + cy * gy
        if mode == "drive" or v > 0.5:  # a stopping driver holds the wheel still
            steer_cmd = math.atan(2.0 * lwb * lateral / max(gx * gx + gy * gy, 1e-6))
            steer_cmd = min(max(steer_cmd, -d_max), d_max)
        # Speed: profile read slightly ahead; stops override it.
        v_target = vref[(i + int(v * drv.speed_preview_s / spacing)) % n_ref] * drv.speed_factor
        brake = a_max
        if mode == "drive" and next_stop < len(stop_times_s) and t >= stop_times_s[next_stop]:
            mode, stop_k = "brake", next_stop
        if mode == "brake" and v < 0.05:
            mode, wait_until = "wait", t + stop_waits_s[stop_k]
        if mode == "wait" and t >= wait_until:
            mode = "drive"
            while next_stop < len(stop_times_s) and stop_times_s[next_stop] <= t:
                next_stop += 1
        if mode != "drive":
            v_target, brake = 0.0, drv.stop_brake_mps2
        a_top = a_max if v <= v_sw else a_max * v_sw / v  # motor power limit
        a = min(max(drv.speed_gain_1ps * (v_target - v), -brake), a_top)
        # RK4 with the driver's commands held over the step.
        k1 = f(steer, v, yaw, r, beta, steer_cmd, a)
        k2 = f(*_add(steer, v, yaw, r, beta, k1, 0.5 * h), steer_cmd, a)
        k3 = f(*_add(steer, v, yaw, r, beta, k2, 0.5 * h), steer_cmd, a)
        k4 = f(*_add(steer, v, yaw, r, beta, k3, h), steer_cmd, a)
        w6 = h / 6.0
        x, y, steer, v, yaw, r, beta = (
            q + w6 * (a + 2 * b + 2 * c + d)
            for q, a, b, c, d in zip((x, y, steer, v, yaw, r, beta), k1, k2, k3, k4)
        )
        steer = min(max(steer, -d_max), d_max)
        v = max(v, 0.0)  # the driver never reverses
    return np.array(out)


def _add(steer, v, yaw, r, beta, k, h):
    """The RK4 stage state: (steer, v, yaw, r, beta) + h * derivative (k[0:2] are x', y')."""
    return steer + h * k[2], v + h * k[3], yaw + h * k[4], r + h * k[5], beta + h * k[6]


def _make_dynamics(veh: Vehicle):
    """The single-track right-hand side as a closure over the vehicle constants.

    f(steer, v, yaw, yaw_rate, beta, steer_cmd, a) -> (x', y', steer', v', yaw', yaw_rate', beta').
    Positions do not enter the dynamics, so they are not arguments.
    """
    mu, lf, lr, h = veh.mu, veh.lf_m, veh.lr_m, veh.h_cg_m
    m, inertia = veh.mass_kg, veh.inertia_kgm2
    c_sf, c_sr, g = veh.c_sf, veh.c_sr, G_MPS2
    lwb = lf + lr
    tau, rate_max, d_max = veh.servo_tau_s, veh.steer_rate_max_rps, veh.steer_max_rad
    v_kin, v_dyn = veh.v_kinematic_mps, veh.v_dynamic_mps
    # At low speed the tyre model's yaw rate and slip are tied to the kinematic ones by a fast
    # first-order relaxation, so the state is consistent when the dynamic model takes over.
    relax = 1.0 / 0.05
    yaw_gain = mu * m / (inertia * lwb)

    def f(steer, v, yaw, r, beta, steer_cmd, a):
        d_steer = min(max((steer_cmd - steer) / tau, -rate_max), rate_max)
        if (steer >= d_max and d_steer > 0) or (steer <= -d_max and d_steer < 0):
            d_steer = 0.0
        if v <= v_kin:
            w = 0.0
        elif v >= v_dyn:
            w = 1.0
        else:
            u = (v - v_kin) / (v_dyn - v_kin)
            w = u * u * (3.0 - 2.0 * u)
        dx = dy = d_yaw = d_r = d_beta = 0.0
        if w < 1.0:  # kinematic bicycle referenced at the centre of gravity
            tan_d = math.tan(steer)
            beta_k = math.atan(tan_d * lr / lwb)
            r_k = v * math.cos(beta_k) * tan_d / lwb
            q = 1.0 - w
            dx += q * v * math.cos(yaw + beta_k)
            dy += q * v * math.sin(yaw + beta_k)
            d_yaw += q * r_k
            d_r += q * relax * (r_k - r)
            d_beta += q * relax * (beta_k - beta)
        if w > 0.0:  # dynamic single-track with load transfer (only evaluated for v > v_kin)
            ff = c_sf * (g * lr - a * h)  # front/rear cornering stiffness x normal load / mass
            fr = c_sr * (g * lf + a * h)
            dx += w * v * math.cos(yaw + beta)
            dy += w * v * math.sin(yaw + beta)
            d_yaw += w * r
            moment = (
                lf * ff * steer + (lr * fr - lf * ff) * beta - (lf * lf * ff + lr * lr * fr) * r / v
            )
            d_r += w * yaw_gain * moment
            d_beta += w * (
                mu / (v * lwb) * (ff * steer - (fr + ff) * beta + (lr * fr - lf * ff) * r / v) - r
            )
        return dx, dy, d_steer, a, d_yaw, d_r, d_beta

    return f


# --- sensor -------------------------------------------------------------------------------------


def _project_s(points_m: np.ndarray, loop_m: np.ndarray) -> np.ndarray:
    """(P,) arc length [m] of each point's (P, 2) orthogonal projection onto a closed loop (K, 2)
    (onto one of the two segments at its nearest vertex)."""
    s = loop_arclength(loop_m)
    k = nearest_index(points_m, loop_m)
    best_s, best_d2 = np.zeros(len(points_m)), np.full(len(points_m), np.inf)
    for a in (k - 1) % len(loop_m), k:
        b = (a + 1) % len(loop_m)
        seg = loop_m[b] - loop_m[a]
        seg_len2 = np.maximum(np.sum(seg * seg, axis=1), 1e-18)
        u = np.clip(np.sum((points_m - loop_m[a]) * seg, axis=1) / seg_len2, 0.0, 1.0)
        d2 = np.sum((loop_m[a] + u[:, None] * seg - points_m) ** 2, axis=1)
        better = d2 < best_d2
        best_s = np.where(better, s[a] + u * np.sqrt(seg_len2), best_s)
        best_d2 = np.minimum(d2, best_d2)
    return best_s


def _ego_pose(lead_xy_m: np.ndarray, gap_m: np.ndarray, center_xy_m: np.ndarray):
    """The trailing car with a camera: on the centerline, gap_m (N,) [m] behind the leading car's
    (lead_xy_m (N, 2)) projection onto it. Returns xy (N, 2) [m] and heading (N,) [rad] (the
    centerline's, interpolated between vertex tangents)."""
    s = loop_arclength(center_xy_m)
    closed = np.vstack([center_xy_m, center_xy_m[:1]])
    s_ego = np.mod(_project_s(lead_xy_m, center_xy_m) - gap_m, s[-1])
    ego = np.stack([np.interp(s_ego, s, closed[:, 0]), np.interp(s_ego, s, closed[:, 1])], 1)
    d = np.roll(center_xy_m, -1, axis=0) - np.roll(center_xy_m, 1, axis=0)
    heading = np.unwrap(np.append(np.arctan2(d[:, 1], d[:, 0]), math.atan2(d[0, 1], d[0, 0])))
    return ego, wrap_angle(np.interp(s_ego, s, heading))


def _in_view(ego_xy, ego_yaw, lead_xy, lead_yaw, cam: Camera) -> np.ndarray:
    """(N,) whether the trailing car's camera sees the leading car's tag (planar geometry)."""

    def ahead(xy, yaw, offset):
        c, s = np.cos(yaw), np.sin(yaw)
        return xy + np.stack([c * offset[0] - s * offset[1], s * offset[0] + c * offset[1]], 1)

    cam_xy = ahead(ego_xy, ego_yaw, np.add(cam.laser_xyz_m, cam.camera_xyz_m))
    tag_xy = ahead(lead_xy, lead_yaw, cam.tag_xyz_m)
    d = tag_xy - cam_xy
    dist = np.linalg.norm(d, axis=1)
    bearing = wrap_angle(np.arctan2(d[:, 1], d[:, 0]) - ego_yaw)
    face = lead_yaw + cam.tag_yaw_rad
    cos_incidence = -(np.cos(face) * d[:, 0] + np.sin(face) * d[:, 1]) / np.maximum(dist, 1e-9)
    return (
        (np.abs(bearing) <= cam.hfov_rad / 2)
        & (dist <= cam.max_range_m)
        & (cos_incidence >= math.cos(cam.max_incidence_rad))
    )


def _detect(
    rng, t_steps, states, center_xy_m, duration_s, latency_s, sen: Sensor, cam: Camera | None
) -> dict:
    """Detections of the car: capture times, what the detector reports, and when it arrives.

    Every random number is drawn for every capture whatever the settings, so a clean sensor sees
    the same capture times as a noisy one with the same seed; a camera only removes detections.
    """
    period = 1.0 / sen.rate_hz
    n_max = int(duration_s * sen.rate_hz * 1.5) + 10
    gaps = period * (1.0 + rng.uniform(-sen.jitter_frac, sen.jitter_frac, size=n_max))
    capture = rng.uniform(0.0, period) + np.concatenate([[0.0], np.cumsum(gaps[:-1])])
    u_miss, u_out = rng.uniform(size=n_max), rng.uniform(size=n_max)
    jump_m = rng.uniform(*sen.outlier_jump_m, size=n_max)
    jump_dir = rng.uniform(0.0, 2 * math.pi, size=n_max)
    z_along, z_across, z_yaw = rng.standard_normal((3, n_max))
    wander = _smooth_random(rng, 0.5 * (sen.ego_gap_m[1] - sen.ego_gap_m[0]), (5.0, 15.0))
    gap_m = np.mean(sen.ego_gap_m) + wander(capture)

    keep = capture + latency_s <= duration_s + 1e-9
    capture = capture[keep]
    x, y, yaw, _, r = (np.interp(capture, t_steps, states[:, c]) for c in range(5))
    yaw_true = yaw
    # The trailing car drives on the centerline, gap_m behind the car's projection onto it
    # (for the noise, the projection is the nearest centerline vertex).
    s = loop_arclength(center_xy_m)
    closed = np.vstack([center_xy_m, center_xy_m[:1]])
    s_ego = np.mod(s[:-1][nearest_index(np.stack([x, y], 1), center_xy_m)] - gap_m[keep], s[-1])
    ego = np.stack([np.interp(s_ego, s, closed[:, 0]), np.interp(s_ego, s, closed[:, 1])], 1)
    los = np.stack([x, y], 1) - ego
    range_m = np.linalg.norm(los, axis=1)
    los /= np.maximum(range_m, 1e-9)[:, None]
    sigma = sen.sigma_m + sen.sigma_per_m * range_m
    z_along, z_across = z_along[keep] * sigma, z_across[keep] * sigma * sen.lateral_ratio
    xy = np.stack([x, y], 1) + los * z_along[:, None]
    xy += np.stack([-los[:, 1], los[:, 0]], 1) * z_across[:, None]
    outlier = u_out[keep] < sen.outlier_prob
    jump = jump_m[keep] * outlier
    xy += np.stack([np.cos(jump_dir[keep]), np.sin(jump_dir[keep])], 1) * jump[:, None]
    yaw = wrap_angle(yaw + sen.yaw_sigma_rad * z_yaw[keep])
    fast = np.maximum(np.abs(r) - sen.miss_yaw_rate_rps, 0.0)
    seen = u_miss[keep] >= np.minimum(sen.miss_prob + sen.miss_per_radps * fast, 0.9)
    extra = {}
    if cam is not None:
        ego_xy, ego_yaw = _ego_pose(np.stack([x, y], 1), gap_m[keep], center_xy_m)
        visible = _in_view(ego_xy, ego_yaw, np.stack([x, y], 1), yaw_true, cam)
        extra = dict(
            n_out_of_view=int(np.sum(seen & ~visible)),
            missed=capture[~(seen & visible)] + latency_s,
            gap_fn=lambda t: np.mean(sen.ego_gap_m) + wander(t),
        )
        seen &= visible
    return dict(
        capture=capture[seen],
        stamp=capture[seen] + latency_s,
        xy=xy[seen],
        yaw=yaw[seen],
        outlier=outlier[seen],
        range=range_m[seen],
        n_captured=int(len(capture)),
        **extra,
    )


# --- files --------------------------------------------------------------------------------------

POSE_TOPIC, ODOM_TOPIC, TF_TOPIC = "/opp/pose", "/opp/odom", "/tf"
MAP_FRAME, CAR_FRAME = "map", "other_base_link"


SIMULATION_FILES = ("drive.mcap", "waypoints.csv", "scenario.json")  # what write_simulation writes


def check_simulation_out(out_dir, inputs) -> None:
    """InputError if a file `write_simulation` would write into `out_dir` is one of the `inputs`
    (the track and raceline files; built-in track names and None are skipped), however spelled
    (`fpe_jax.io.writers.check_not_input`): `--force` never replaces what the simulation read."""
    from fpe_jax.io.writers import check_not_input

    files = [p for p in inputs if p is not None and not (isinstance(p, str) and is_builtin(p))]
    for name in SIMULATION_FILES:
        check_not_input(Path(out_dir) / name, files)


def write_simulation(
    res: SimResult, out_dir: str | Path, *, force: bool = False, layout: str | None = None
) -> list[Path]:
    """Write a simulated drive as DIR/drive.mcap, DIR/waypoints.csv and DIR/scenario.json.

    layout "map" (the default without a camera): drive.mcap holds `/opp/pose`
    (geometry_msgs/PoseStamped detections, stamped at arrival), `/opp/odom` (nav_msgs/Odometry
    truth, 50 Hz) and `/tf` (map -> other_base_link truth, 50 Hz).
    layout "apriltag" (the default with a camera; needs one): the thesis' recording instead --
    `/tag_detections` (apriltag_ros/msg/AprilTagDetectionArray: the tag's pose in the camera
    frame, an empty array for each capture without a detection), `/tf` (the trailing car's
    map -> base_link, 50 Hz), `/tf_static` (base_link -> laser -> camera, tag_0 ->
    other_base_link) and `/opp/odom`; each detection composes back to the map-frame pose the
    "map" layout would hold (see `fpe_jax.io.apriltag`).
    waypoints.csv holds the centerline (header ``x,y``, metres); scenario.json every setting.

    Raises InputError if `out_dir` is a file, or an existing non-empty folder and not `force`.
    Returns the written paths.
    """
    import json

    from fpe_jax.io import write_drive_mcap
    from fpe_jax.io.writers import write_text, write_xy_csv

    layout = layout or ("map" if res.ego_t_s is None else "apriltag")
    if layout not in ("map", "apriltag"):
        raise InputError("layout", f"{layout!r}", "map or apriltag")
    if layout == "apriltag" and res.ego_t_s is None:
        raise InputError("layout", "apriltag needs a drive simulated with a camera", "camera=")
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(out, "is a file", "a folder to write the simulated drive into")
    if out.is_dir() and any(out.iterdir()) and not force:
        raise InputError(out, "exists and is not empty; pass --force to write into it")
    check_simulation_out(out, (res.scenario.get("track_file"), res.scenario.get("raceline")))
    out.mkdir(parents=True, exist_ok=True)
    d = res.drive
    truth = dict(t_s=d.truth_t_s, xy_m=d.truth_xy_m, yaw_rad=d.truth_yaw_rad)
    odom = dict(
        truth,
        topic=ODOM_TOPIC,
        v_mps=d.truth_v_mps,
        yaw_rate_rps=res.truth_yaw_rate_rps,
        frame_id=MAP_FRAME,
        child_frame_id=CAR_FRAME,
    )
    if layout == "map":
        mcap = write_drive_mcap(
            out / "drive.mcap",
            pose=dict(
                topic=POSE_TOPIC, t_s=d.t_s, xy_m=d.xy_m, yaw_rad=d.yaw_rad, frame_id=MAP_FRAME
            ),
            odom=odom,
            tf=dict(truth, topic=TF_TOPIC, parent=MAP_FRAME, child=CAR_FRAME),
            force=force,
        )
        topics = dict(pose=POSE_TOPIC, odom=ODOM_TOPIC, tf=TF_TOPIC, frames=[MAP_FRAME, CAR_FRAME])
    else:
        mcap, topics = _write_apriltag_layout(res, out / "drive.mcap", odom, force)
    waypoints = write_xy_csv(out / "waypoints.csv", res.centerline_xy_m, force=force)
    scenario = out / "scenario.json"
    summary = dict(
        topics=topics,
        n_detections=len(d.t_s),
        n_truth=len(d.truth_t_s),
        n_outliers=d.meta["n_outliers"],
        n_dropped=d.meta["n_dropped"],
    )
    write_text(scenario, json.dumps(res.scenario | summary, indent=2) + "\n", force=force)
    return [mcap, waypoints, scenario]


def apriltag_layout(res: SimResult) -> dict[str, Any]:
    """The keyword arguments of `fpe_jax.io.apriltag.apriltag_events` for a drive simulated with
    a `Camera`: its detections, the trailing car's motion, the mounts and the tag."""
    from fpe_jax.io import apriltag as at
    from fpe_jax.io.tf import Rigid

    if res.ego_t_s is None:
        raise InputError("layout", "apriltag needs a drive simulated with a camera", "camera=")
    cam = Camera(**res.scenario["camera"])
    d = res.drive
    return dict(
        detections=dict(t_s=d.t_s, xy_m=d.xy_m, yaw_rad=d.yaw_rad),
        ego=dict(t_s=res.ego_t_s, xy_m=res.ego_xy_m, yaw_rad=res.ego_yaw_rad),
        laser_in_base=Rigid.make(cam.laser_xyz_m, [0.0, 0.0, 0.0, 1.0]),
        camera_in_laser=Rigid.make(cam.camera_xyz_m, at.OPTICAL_IN_BODY.q[0]),
        tag_in_car=at.tag_mount(*cam.tag_xyz_m, cam.tag_yaw_rad),
        empty_t_s=res.missed_t_s,
        tag_id=cam.tag_id,
        tag_size_m=cam.tag_size_m,
    )


def _write_apriltag_layout(res: SimResult, path: Path, odom: dict, force: bool):
    """The "apriltag" layout of `write_simulation`: (written path, scenario topics)."""
    from fpe_jax.io import apriltag as at

    layout = apriltag_layout(res)
    written = at.write_apriltag_mcap(path, odom=odom, force=force, **layout)
    f = at.FRAMES
    tag = at.tag_frame_name(layout["tag_id"], "apriltag_ros")
    topics = dict(
        detections=at.DETECTION_TOPIC, odom=ODOM_TOPIC, tf=TF_TOPIC, tf_static="/tf_static"
    )
    return written, dict(
        topics, frames=[f["map"], f["base"], f["laser"], f["camera"], tag, f["car"]]
    )
