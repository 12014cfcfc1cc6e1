"""Drive logs in, predictions out -- without a ROS installation (NumPy only; no JAX here).

Readers: `load_drive` (ROS 2 MCAP, rosbag2 folders, ROS 1 bags, CSV) -> `Drive`;
`load_waypoints` (CSV variants, nav_msgs/Path in a log) -> `Waypoints`; `describe_log`;
`fpe_jax.io.stream.read_observations` (`fpe run`'s stdin lines -> stamped observations);
`read_cars` (`fpe batch`'s cars, CSV or .npy).
Writers: `write_predictions` (CSV / MCAP), `write_drive_mcap` (simulated drives),
`write_drive_csv` (a drive's observations), `write_poses` (`fpe batch`'s output, .npy or CSV),
`check_output_path` (and `check_not_input`: never an input); every file goes through the one
atomic writer `atomic_output` (`write_text`, `write_bytes`). AprilTag detections plus the log's
TF are composed into map-frame poses by `fpe_jax.io.apriltag` (TF math: `fpe_jax.io.tf`).
Every bad input raises `fpe_jax.errors.InputError`.
"""

from fpe_jax.io.drives import describe_log, dropped_note, load_drive
from fpe_jax.io.tables import read_cars
from fpe_jax.io.waypoints import Waypoints, load_waypoints
from fpe_jax.io.writers import (
    atomic_output,
    check_not_input,
    check_output_path,
    check_output_paths,
    write_bytes,
    write_drive_csv,
    write_drive_mcap,
    write_poses,
    write_predictions,
    write_text,
)

__all__ = [
    "Waypoints",
    "atomic_output",
    "check_not_input",
    "check_output_path",
    "check_output_paths",
    "describe_log",
    "dropped_note",
    "load_drive",
    "load_waypoints",
    "read_cars",
    "write_bytes",
    "write_drive_csv",
    "write_drive_mcap",
    "write_poses",
    "write_predictions",
    "write_text",
]
