"""The scene a viewer shows: the track, the observed cars, each car's predicted path and the
1-sigma ellipse of every predicted step. One description (`prediction_scene`, `ellipse_axes`,
the styles below), written two ways:

- Foxglove's protobuf schemas (`foxglove.SceneUpdate`, `foxglove.PosesInFrame`): what
  `fpe_jax.node.SceneSink` serves over Foxglove's WebSocket protocol and records to MCAP
  (`fpe node --foxglove`, `fpe view`). Topics: `/track`, `/observations`,
  `/predictions/<car>/path`, `/predictions/<car>/ellipses`.
- ROS 2 messages (`visualization_msgs/MarkerArray`, `nav_msgs/Path`): what `write_predictions`
  adds to `fpe predict --out X.mcap`, a ROS 2 log that rosbags and ROS 2 tools read (rosbags
  cannot open an MCAP that holds protobuf schemas) and Foxglove shows as well. Topics: `/track`,
  `/future_pose/path`, `/future_pose/ellipses`.

Validity: an invalid prediction (made from too little history) is drawn as a grey line without
ellipses, and its path (`PosesInFrame` / `nav_msgs/Path`) is not written, so a consumer of the
path topic only ever sees valid predictions. A step whose pose is not finite is left out; a step
whose covariance is not finite, not symmetric or not positive semi-definite gets no ellipse.

NumPy only (no JAX); foxglove is imported only by the functions that build its messages.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from fpe_jax.io import ros_msgs as rm

# Foxglove topics (SceneSink) and ROS 2 topics (write_predictions' MCAP)
TRACK_TOPIC = "/track"
OBSERVATIONS_TOPIC = "/observations"
ROS_PATH_TOPIC = "/future_pose/path"
ROS_ELLIPSES_TOPIC = "/future_pose/ellipses"

# RGBA in [0, 1]
TRACK_RGBA = (0.55, 0.55, 0.6, 1.0)
OBSERVATION_RGBA = (0.1, 0.45, 0.95, 1.0)
PREDICTION_RGBA = (1.0, 0.5, 0.0, 1.0)
ELLIPSE_RGBA = (1.0, 0.5, 0.0, 0.3)
INVALID_RGBA = (0.5, 0.5, 0.5, 0.7)
TRACK_WIDTH_M = 0.05
PATH_WIDTH_M = 0.04
ELLIPSE_HEIGHT_M = 0.02  # the flat third axis of an ellipse drawn as an ellipsoid
OBSERVATION_SIZE_M = 0.3  # sphere diameter; the heading arrow is twice as long


def path_topic(car_id: str) -> str:
    """Foxglove topic of a car's predicted path (`PosesInFrame`)."""
    return f"/predictions/{car_id}/path"


def ellipses_topic(car_id: str) -> str:
    """Foxglove topic of a car's predicted line and ellipses (`SceneUpdate`)."""
    return f"/predictions/{car_id}/ellipses"


def ellipse_axes(cov_xy_m2) -> tuple[np.ndarray, np.ndarray]:
    """The 1-sigma ellipse of 2-D covariances: diameters and orientation.

    Args:
        cov_xy_m2: (..., 2, 2) covariance of x, y [m^2].

    Returns:
        diam_m: (..., 2) full lengths [m] of the major and minor axis (2 sqrt(eigenvalue)).
        yaw_rad: (...) direction of the major axis [rad] in (-pi/2, pi/2].
        Both NaN where the covariance is not finite, not symmetric or not positive semi-definite
        (an eigenvalue below -1e-9 of the mean variance).
    """
    c = np.asarray(cov_xy_m2, dtype=np.float64)
    if c.shape[-2:] != (2, 2):
        raise ValueError(f"ellipse_axes: covariance has shape {c.shape}, expected (..., 2, 2)")
    a, b, b_t, d = c[..., 0, 0], c[..., 0, 1], c[..., 1, 0], c[..., 1, 1]
    mean = (a + d) / 2
    radius = np.hypot((a - d) / 2, b)  # eigenvalues mean +- radius, in closed form
    lam = np.stack([mean + radius, mean - radius], axis=-1)
    yaw = 0.5 * np.arctan2(2 * b, a - d)
    ok = (
        np.isfinite(c).all(axis=(-2, -1))
        & (np.abs(b - b_t) <= 1e-9 * (np.abs(a) + np.abs(d)))
        & (lam[..., 1] >= -1e-9 * np.abs(mean))
    )
    diam = 2 * np.sqrt(np.clip(np.where(ok[..., None], lam, 0.0), 0.0, None))
    return np.where(ok[..., None], diam, np.nan), np.where(ok, yaw, np.nan)


@dataclasses.dataclass(frozen=True)
class PredictionScene:
    """What a viewer draws of one prediction of H steps (H' <= H finite steps, K <= H' ellipses).

    Attributes:
        xy_m: (H', 2) predicted positions x [m], y [m] of the finite steps.
        yaw_rad: (H',) predicted headings [rad].
        stamps_ns: (H',) int64 time each step predicts [ns].
        valid: whether the prediction is valid (else drawn grey, without ellipses or path).
        ellipse_xy_m: (K, 2) ellipse centres [m].
        ellipse_diam_m: (K, 2) major and minor axis lengths [m] (1 sigma each side).
        ellipse_yaw_rad: (K,) major axis direction [rad].
        lifetime_ns: how long after the observation the drawing stays without a newer one:
            until its last step's time (0: until replaced).
    """

    xy_m: np.ndarray
    yaw_rad: np.ndarray
    stamps_ns: np.ndarray
    valid: bool
    ellipse_xy_m: np.ndarray
    ellipse_diam_m: np.ndarray
    ellipse_yaw_rad: np.ndarray
    lifetime_ns: int


def prediction_scene(
    stamp_ns: int | np.integer, poses, cov_xy_m2, step_stamps_ns, valid: bool = True
) -> PredictionScene:
    """The drawing of one prediction made at `stamp_ns` [ns].

    Args:
        stamp_ns: the stamp of the observation the prediction was made from [ns].
        poses: (H, 3) predicted x [m], y [m], yaw [rad].
        cov_xy_m2: (H, 2, 2) map-frame covariance of each predicted position [m^2] (NaN: none).
        step_stamps_ns: (H,) int time each step predicts [ns].
        valid: False for a prediction from too little history (see the module docstring).
    """
    poses = np.asarray(poses, dtype=np.float64)
    cov = np.asarray(cov_xy_m2, dtype=np.float64)
    steps = np.asarray(step_stamps_ns, dtype=np.int64)
    h = len(poses)
    if poses.shape != (h, 3) or cov.shape != (h, 2, 2) or steps.shape != (h,):
        raise ValueError(
            f"prediction: poses {poses.shape}, cov_xy_m2 {cov.shape} and step_stamps_ns "
            f"{steps.shape} do not agree (expected (H, 3), (H, 2, 2), (H,))"
        )
    finite = np.isfinite(poses).all(axis=1)
    diam, yaw = ellipse_axes(cov)
    has = finite & np.isfinite(yaw) & bool(valid)
    lifetime = int(steps[-1] - stamp_ns) if h and steps[-1] > stamp_ns else 0
    return PredictionScene(
        xy_m=poses[finite, :2],
        yaw_rad=poses[finite, 2],
        stamps_ns=steps[finite],
        valid=bool(valid),
        ellipse_xy_m=poses[has, :2],
        ellipse_diam_m=diam[has],
        ellipse_yaw_rad=yaw[has],
        lifetime_ns=lifetime,
    )


def _closed(xy_m, closed: bool) -> np.ndarray:
    xy = np.asarray(xy_m, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] != 2:
        raise ValueError(f"track: centre line has shape {xy.shape}, expected (N, 2)")
    return np.vstack([xy, xy[:1]]) if closed and len(xy) else xy


# ---- Foxglove (protobuf) ---------------------------------------------------------------------


def _fg_time(ns: int):
    import foxglove.messages as fm

    sec, nsec = divmod(int(ns), 1_000_000_000)
    return fm.Timestamp(sec=sec, nsec=nsec)


def _fg_color(rgba):
    import foxglove.messages as fm

    r, g, b, a = rgba
    return fm.Color(r=r, g=g, b=b, a=a)


def _fg_pose(x: float, y: float, yaw: float):
    import foxglove.messages as fm

    q = rm.yaw_to_quaternion(yaw)
    return fm.Pose(
        position=fm.Vector3(x=float(x), y=float(y), z=0.0),
        orientation=fm.Quaternion(x=q["x"], y=q["y"], z=q["z"], w=q["w"]),
    )


def _fg_line(xy_m, rgba, width_m: float):
    import foxglove.messages as fm

    return fm.LinePrimitive(
        type=fm.LinePrimitiveLineType.LineStrip,
        pose=_fg_pose(0.0, 0.0, 0.0),
        thickness=width_m,
        points=[fm.Point3(x=x, y=y, z=0.0) for x, y in np.asarray(xy_m).tolist()],
        color=_fg_color(rgba),
    )


def foxglove_track(xy_m, stamp_ns: int | np.integer, frame_id: str, closed: bool = False):
    """`SceneUpdate` with the entity `centre_line`: the track's line (N, 2) [m], closed if asked."""
    import foxglove.messages as fm

    entity = fm.SceneEntity(
        timestamp=_fg_time(stamp_ns),
        frame_id=frame_id,
        id="centre_line",
        lines=[_fg_line(_closed(xy_m, closed), TRACK_RGBA, TRACK_WIDTH_M)],
    )
    return fm.SceneUpdate(entities=[entity])


def foxglove_observation(
    car_id: str, stamp_ns: int | np.integer, x_m: float, y_m: float, yaw_rad: float, frame_id: str
):
    """`SceneUpdate` with one entity `car_id`: a sphere at the observed position and, when the
    heading is known, an arrow along it."""
    import foxglove.messages as fm

    pose = _fg_pose(x_m, y_m, yaw_rad if np.isfinite(yaw_rad) else 0.0)
    size = OBSERVATION_SIZE_M
    arrows = []
    if np.isfinite(yaw_rad):
        arrows.append(
            fm.ArrowPrimitive(
                pose=pose,
                shaft_length=1.4 * size,
                shaft_diameter=0.25 * size,
                head_length=0.6 * size,
                head_diameter=0.6 * size,
                color=_fg_color(OBSERVATION_RGBA),
            )
        )
    entity = fm.SceneEntity(
        timestamp=_fg_time(stamp_ns),
        frame_id=frame_id,
        id=car_id,
        spheres=[
            fm.SpherePrimitive(
                pose=pose,
                size=fm.Vector3(x=size, y=size, z=size),
                color=_fg_color(OBSERVATION_RGBA),
            )
        ],
        arrows=arrows,
        metadata=[fm.KeyValuePair(key="car", value=car_id)],
    )
    return fm.SceneUpdate(entities=[entity])


def foxglove_prediction(
    car_id: str, stamp_ns: int | np.integer, scene: PredictionScene, frame_id: str
):
    """[(topic, message)] of one prediction: the path (`PosesInFrame`, valid predictions only;
    timestamp = the observation's stamp) and a `SceneUpdate` whose entity `car_id` holds the
    line through the predicted positions and one flat ellipsoid per ellipse."""
    import foxglove.messages as fm

    stamp = _fg_time(stamp_ns)
    out = []
    if scene.valid:
        poses = [_fg_pose(x, y, a) for (x, y), a in zip(scene.xy_m.tolist(), scene.yaw_rad)]
        out.append(
            (path_topic(car_id), fm.PosesInFrame(timestamp=stamp, frame_id=frame_id, poses=poses))
        )
    spheres = [
        fm.SpherePrimitive(
            pose=_fg_pose(x, y, a),
            size=fm.Vector3(x=float(d1), y=float(d2), z=ELLIPSE_HEIGHT_M),
            color=_fg_color(ELLIPSE_RGBA),
        )
        for (x, y), (d1, d2), a in zip(
            scene.ellipse_xy_m.tolist(), scene.ellipse_diam_m.tolist(), scene.ellipse_yaw_rad
        )
    ]
    rgba = PREDICTION_RGBA if scene.valid else INVALID_RGBA
    sec, nsec = divmod(scene.lifetime_ns, 1_000_000_000)
    lifetime = fm.Duration(sec=sec, nsec=nsec)
    entity = fm.SceneEntity(
        timestamp=stamp,
        frame_id=frame_id,
        id=car_id,
        lifetime=lifetime,
        lines=[_fg_line(scene.xy_m, rgba, PATH_WIDTH_M)],
        spheres=spheres,
        metadata=[
            fm.KeyValuePair(key="car", value=car_id),
            fm.KeyValuePair(key="valid", value=str(scene.valid).lower()),
            fm.KeyValuePair(key="step_stamps_ns", value=",".join(map(str, scene.stamps_ns))),
        ],
    )
    out.append((ellipses_topic(car_id), fm.SceneUpdate(entities=[entity])))
    return out


# ---- ROS 2 (message dicts for mcap_ros2's writer) --------------------------------------------


def ros2_marker(
    stamp_ns: int | np.integer,
    frame_id: str,
    ns: str,
    ident: int,
    kind: int,
    rgba,
    *,
    scale=(0.08, 0.08, 0.08),
    pose=(0.0, 0.0, 0.0),
    points=(),
    action: int = 0,
    lifetime_ns: int = 0,
) -> dict:
    """A `visualization_msgs/Marker` dict: `pose` x [m], y [m], yaw [rad]; `points` (K, 2) [m];
    action 0 = ADD (replaces the marker with the same ns and id), 3 = DELETEALL."""
    r, g, b, a = rgba
    x, y, yaw = pose
    return {
        "header": {"stamp": rm.stamp_dict(stamp_ns), "frame_id": frame_id},
        "ns": ns,
        "id": ident,
        "type": kind,
        "action": action,
        "pose": {
            "position": {"x": float(x), "y": float(y), "z": 0.0},
            "orientation": rm.yaw_to_quaternion(yaw),
        },
        "scale": dict(zip("xyz", map(float, scale))),
        "color": {"r": r, "g": g, "b": b, "a": a},
        "lifetime": rm.stamp_dict(lifetime_ns),
        "points": [{"x": px, "y": py, "z": 0.0} for px, py in np.asarray(points).tolist()],
    }


def ros2_track(xy_m, stamp_ns: int | np.integer, frame_id: str, closed: bool = False) -> dict:
    """`visualization_msgs/MarkerArray` dict: the track's line as one LINE_STRIP (ns `track`)."""
    xy = _closed(xy_m, closed)
    scale = (TRACK_WIDTH_M,) * 3
    marker = ros2_marker(
        stamp_ns, frame_id, "track", 0, rm.MARKER_LINE_STRIP, TRACK_RGBA, scale=scale, points=xy
    )
    return {"markers": [marker]}


def ros2_prediction(stamp_ns: int | np.integer, scene: PredictionScene, frame_id: str) -> list:
    """[(topic, type, message dict)] of one prediction: `nav_msgs/Path` on /future_pose/path
    (valid predictions only; header.stamp = the observation's stamp, each pose stamped with the
    time its step predicts) and a `visualization_msgs/MarkerArray` on /future_pose/ellipses
    (DELETEALL, then one flat SPHERE per ellipse, ns `future_pose_ellipses`, id = step index
    among the drawn ones; lifetime until the last step's time)."""
    out = []
    if scene.valid:
        poses = [
            {
                "header": {"stamp": rm.stamp_dict(n), "frame_id": frame_id},
                "pose": {
                    "position": {"x": x, "y": y, "z": 0.0},
                    "orientation": rm.yaw_to_quaternion(a),
                },
            }
            for (x, y), a, n in zip(scene.xy_m.tolist(), scene.yaw_rad.tolist(), scene.stamps_ns)
        ]
        header = {"stamp": rm.stamp_dict(stamp_ns), "frame_id": frame_id}
        out.append((ROS_PATH_TOPIC, "nav_msgs/Path", {"header": header, "poses": poses}))
    ns = "future_pose_ellipses"
    markers = [ros2_marker(stamp_ns, frame_id, ns, 0, 0, ELLIPSE_RGBA, action=3)]
    for k, ((x, y), (d1, d2), a) in enumerate(
        zip(scene.ellipse_xy_m.tolist(), scene.ellipse_diam_m.tolist(), scene.ellipse_yaw_rad)
    ):
        markers.append(
            ros2_marker(
                stamp_ns,
                frame_id,
                ns,
                k,
                rm.MARKER_SPHERE,
                ELLIPSE_RGBA,
                scale=(d1, d2, ELLIPSE_HEIGHT_M),
                pose=(x, y, a),
                lifetime_ns=scene.lifetime_ns,
            )
        )
    out.append((ROS_ELLIPSES_TOPIC, "visualization_msgs/MarkerArray", {"markers": markers}))
    return out
