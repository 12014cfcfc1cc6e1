"""Waypoints: the track's reference line, from CSV variants or a nav_msgs/Path in a log."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from fpe_jax.errors import InputError
from fpe_jax.io import tables
from fpe_jax.io.logs import PATH_TYPES, is_log_path, open_log


@dataclasses.dataclass(frozen=True)
class Waypoints:
    """A reference line of the track, in file order.

    Attributes:
        xy_m: (K, 2) float64 x [m], y [m] in the map frame (K >= 3 distinct points).
        speed_mps: (K,) float64 reference speed [m/s] when the file has one, else None.
        source: the file it came from.
        format: "xy-csv" (header-less x,y[,yaw]), "csv", "f1tenth-centerline",
            "f1tenth-raceline" or "path" (nav_msgs/Path in a log).
    """

    xy_m: np.ndarray
    speed_mps: np.ndarray | None
    source: str
    format: str


def _from_table(path) -> Waypoints:
    table = tables.read_table(path)
    if table.header is None:
        # The 2019 project's waypoint file: `x, y, yaw` rows (yaw unused: the track recomputes it).
        if table.data.shape[1] not in (2, 3):
            raise InputError(
                path,
                f"header-less waypoint file with {table.data.shape[1]} columns",
                "x,y[,yaw] rows, or a header naming the x and y columns",
            )
        return Waypoints(table.data[:, :2], None, str(path), "xy-csv")
    xy = np.column_stack([table.column(tables.X_NAMES, "x"), table.column(tables.Y_NAMES, "y")])
    speed = table.column(tables.SPEED_NAMES, "speed", required=False)
    fmt = "csv"
    if "w_tr_right_m" in table.header:
        fmt = "f1tenth-centerline"
    elif "s_m" in table.header and "kappa_radpm" in table.header:
        fmt = "f1tenth-raceline"
    return Waypoints(xy, speed, str(path), fmt)


def _from_log(path, topic: str | None) -> Waypoints:
    log = open_log(path)
    paths = [t for t, i in log.topics.items() if i.msgtype in PATH_TYPES]
    if topic is None:
        if len(paths) != 1:
            raise InputError(
                path,
                f"{'no' if not paths else 'several'} nav_msgs/Path topics"
                + (f": {', '.join(paths)}" if paths else ""),
                "exactly one, or a topic named explicitly",
            )
        topic = paths[0]
    elif topic not in paths:
        raise InputError(
            path,
            f"no nav_msgs/Path topic {topic!r}",
            f"one of: {', '.join(paths) if paths else 'none present'}",
        )
    last = None
    for _, _, _, msg in log.messages([topic]):
        last = msg  # messages come in log-time order: the last one is the newest path
    if last is None:
        raise InputError(path, f"topic {topic!r} has no messages", "a nav_msgs/Path message")
    xy = np.array(
        [[ps.pose.position.x, ps.pose.position.y] for ps in last.poses], dtype=np.float64
    ).reshape(-1, 2)
    return Waypoints(xy, None, str(path), "path")


def load_waypoints(path, *, topic: str | None = None) -> Waypoints:
    """Read waypoints from a CSV or from the last nav_msgs/Path message in a ROS log.

    CSV forms: header-less `x,y[,yaw]` rows; a header with x/x_m and y/y_m columns (others
    allowed; v/speed/vx_mps kept as speed_mps); the F1TENTH centerline (`# x_m, y_m, ...`) and
    raceline (`# s_m; x_m; y_m; psi_rad; kappa_radpm; vx_mps; ax_mps2`). Logs: `topic` names the
    Path topic (default: the only one). Raises InputError for unreadable files, missing columns,
    non-numeric or non-finite values, and fewer than 3 distinct points.
    """
    if is_log_path(path):
        wp = _from_log(path, topic)
    elif topic is not None:
        raise InputError(path, "a topic was given but this is not a ROS log", "a .mcap/.bag")
    elif Path(path).suffix.lower() not in tables.TABLE_SUFFIXES and Path(path).exists():
        raise InputError(
            path, f"unknown waypoint format {Path(path).suffix!r}", ".csv or a ROS log"
        )
    else:
        wp = _from_table(path)
    bad = ~np.isfinite(wp.xy_m).all(axis=1)
    if bad.any():
        first = int(np.argmax(bad)) + 1
        raise InputError(
            path,
            f"{bad.sum()} waypoints are NaN or infinite (first: data row {first})",
            "finite x, y",
        )
    n = len(np.unique(wp.xy_m, axis=0))
    if n < 3:
        raise InputError(path, f"only {n} distinct waypoints", "at least 3")
    return wp
