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

import importlib
from pathlib import Path

# public name -> the module that defines it, imported on first use: a command that needs one
# reader (or none: `fpe presets`) loads only that
_LAZY = {
    "CarFile": "tables",
    "PosesFile": "writers",
    "Waypoints": "waypoints",
    "atomic_output": "writers",
    "check_not_input": "writers",
    "check_output_path": "writers",
    "check_output_paths": "writers",
    "describe_log": "drives",
    "dropped_note": "drives",
    "load_drive": "drives",
    "load_waypoints": "waypoints",
    "read_cars": "tables",
    "write_bytes": "writers",
    "write_drive_csv": "writers",
    "write_drive_mcap": "writers",
    "write_poses": "writers",
    "write_predictions": "writers",
    "write_text": "writers",
}
__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name in _LAZY:
        value = getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    elif (Path(__file__).parent / f"{name}.py").is_file():  # a module: `io.apriltag`
        value = importlib.import_module(f"{__name__}.{name}")
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
