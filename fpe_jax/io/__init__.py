"""Drive logs in, predictions out -- without a ROS installation (NumPy only; no JAX here).

Readers: `load_drive` (ROS 2 MCAP, rosbag2 folders, ROS 1 bags, CSV) -> `Drive`;
`load_waypoints` (CSV variants, nav_msgs/Path in a log) -> `Waypoints`; `describe_log`;
`fpe_jax.io.stream.read_observations` (`fpe run`'s stdin lines -> stamped observations);
`read_cars` (`fpe batch`'s cars, CSV or .npy; `CarFile` reads them a block at a time).
Writers: `write_predictions` (CSV / MCAP), `write_drive_mcap` (simulated drives),
`write_drive_csv` (a drive's observations), `write_poses` (`fpe batch`'s output, .npy or CSV;
`PosesFile` writes it a block at a time),
`check_output_path` (and `check_not_input`: never an input); every file goes through the one
atomic writer `atomic_output` (`write_text`, `write_bytes`). AprilTag detections plus the log's
TF are composed into map-frame poses by `fpe_jax.io.apriltag` (TF math: `fpe_jax.io.tf`).
Configs: `fpe_jax.io.config` reads, checks and writes tuned configs (JSON; `read_config` needs no
JAX, `config_to_params` builds the model's Params). Exports: `fpe_jax.io.export` writes a config
in the forms on-car runners take (JSON, ROS 2 parameter YAML, StableHLO; only StableHLO imports
JAX, inside its functions). Both are imported by name, not by `import fpe_jax.io`, which stays
NumPy-only.
Every bad input raises `fpe_jax.errors.InputError`.
"""

from fpe_jax.io.drives import describe_log, dropped_note, load_drive
from fpe_jax.io.tables import CarFile, read_cars
from fpe_jax.io.waypoints import Waypoints, load_waypoints
from fpe_jax.io.writers import (
    PosesFile,
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
    "CarFile",
    "PosesFile",
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
