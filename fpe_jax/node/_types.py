"""Message types of the live node, one rosbags type store per middleware flavour.

`typestore("ros1")` is rosbags' ROS 1 Noetic store, `typestore("ros2")` its ROS 2 Jazzy store, each
with the packages they lack registered from .msg files shipped in the package:

- apriltag_ros / apriltags2_ros / apriltag_msgs detections (fpe_jax/io/msgs, the files the log
  reader uses);
- ForzaETH's f110_msgs Obstacle, ObstacleArray, OppWpnt, OpponentTrajectory (fpe_jax/node/msgs/
  ros1 and ros2: the ROS 1 Obstacle carries s/d/vs/vd variances and OpponentTrajectory an id and a
  float64 lap count; the ROS 2 branches drop the variances, the id, and count laps in int64).

Type names are spelled "pkg/msg/Type" as rosbags spells them. JAX-free.
"""

from __future__ import annotations

import functools
from pathlib import Path

FLAVOURS = ("ros1", "ros2")
# the node's outputs: name -> (default topic, type); a topic of None switches one off
OUTPUTS = {
    "markers": ("/future_pose", "visualization_msgs/msg/MarkerArray"),
    "path": ("/future_pose/path", "nav_msgs/msg/Path"),
    "covariance": ("/future_pose/covariance", "geometry_msgs/msg/PoseWithCovarianceStamped"),
    "obstacles": ("/future_pose/obstacles", "f110_msgs/msg/ObstacleArray"),
    "trajectory": ("/opponent_trajectory", "f110_msgs/msg/OpponentTrajectory"),
}

_NODE_MSGS = Path(__file__).with_name("msgs")


def msg_files(flavour: str) -> dict[str, Path]:
    """{"pkg/msg/Type": .msg file} of the types this flavour adds to rosbags' store."""
    # imported here: the CLI reads OUTPUTS for its flags, and `fpe --help` loads no reader
    from fpe_jax.io import ros_msgs as rm

    _check_flavour(flavour)
    shipped = Path(rm.__file__).with_name("msgs")
    files = sorted(shipped.glob("*/*.msg")) + sorted((_NODE_MSGS / flavour).glob("*/*.msg"))
    return {f"{f.parent.name}/msg/{f.stem}": f for f in files}


def _check_flavour(flavour: str) -> None:
    if flavour not in FLAVOURS:
        raise ValueError(f"typestore: unknown flavour {flavour!r}, expected one of {FLAVOURS}")


@functools.cache
def typestore(flavour: str):
    """The rosbags `Typestore` of a flavour ("ros1": Noetic, "ros2": Jazzy) with the shipped
    packages registered. Cached: one store per flavour and process."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    from fpe_jax.io import ros_msgs as rm

    _check_flavour(flavour)
    store = get_typestore(Stores.ROS1_NOETIC if flavour == "ros1" else Stores.ROS2_JAZZY)
    types = {}
    for name, path in msg_files(flavour).items():
        pkg = name.split("/", 1)[0]
        # comments dropped and sibling types qualified, as the log reader reads these files
        types.update(get_types_from_msg(rm._qualified_fields(pkg, path.read_text()), name))
    if "tf2_msgs/msg/TFMessage" not in store.types:  # Noetic's store lacks it
        types.update(get_types_from_msg(rm._FIELDS["tf2_msgs/TFMessage"], "tf2_msgs/msg/TFMessage"))
    store.register(types)
    return store


def full_definition(flavour: str, type_name: str) -> str:
    """The complete message definition of `type_name` with its dependencies, in the text format
    of the flavour (ROS 1 `MSG:` sections as rosbag and genpy expect; ROS 2 as MCAP schemas)."""
    store = typestore(flavour)
    text, _ = store.generate_msgdef(type_name, ros_version=1 if flavour == "ros1" else 2)
    return text
