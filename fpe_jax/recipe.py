"""Fit recipes (TOML): which drives, which waypoints, what to fit, where the config goes.

out = "levine.json"            # paths are relative to the recipe's folder
waypoints = "../../shared/data/levine/levine-waypoints.csv"
holdout = 0.4                  # or [[test_drives]] for separate held-out drives
model = "line"                 # or "blend" (then also fit = [...] and blend = "auto")
solver = "bfgs"                # or "lm"

[settings]                     # the car and the prediction grid (default: F1TENTH, 10 x 0.1 s)
wheelbase_m = 2.578            # also max_steer_rad, dt_s, horizon

[[drives]]
path = "../../shared/data/levine/actual-poses.csv"
rate_hz = 10                   # also: pose_topic, truth_topic, waypoints, log_time

[[drives]]
path = "drives/camera.bag"     # AprilTag detections + TF: also tag_id (0), drop_outside_tf,
tag_to_base = [-0.2, 0.0, 0.2, 3.14159]  # and the tag's mount ("x,y,z,yaw" or 4 numbers)

[[drives]]
simulate = { track = "oval", duration_s = 120, latency_s = 0.3, seed = 1 }
"""

from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path

from fpe_jax.drive import Drive
from fpe_jax.errors import InputError

DRIVE_KEYS = {
    "path",
    "rate_hz",
    "pose_topic",
    "truth_topic",
    "waypoints",
    "log_time",
    "simulate",
    "tag_id",
    "tag_to_base",
    "drop_outside_tf",
}
TOP_KEYS = {
    "out",
    "waypoints",
    "holdout",
    "fit",
    "model",
    "blend",
    "solver",
    "drives",
    "test_drives",
    "settings",
}
SETTINGS_KEYS = ("wheelbase_m", "max_steer_rad", "dt_s", "horizon")  # params.USER_SETTINGS


@dataclasses.dataclass
class Recipe:
    """A loaded recipe: drives with their waypoints (K, 2) [m], and the fit options."""

    source: Path
    out: Path | None
    drives: list[tuple[Drive, object, str]]  # (drive, waypoints xy (K, 2), description)
    test_drives: list[tuple[Drive, object, str]]
    holdout: float
    fit: tuple[str, ...] | None
    blend: str
    model: str | None
    solver: str | None
    settings: dict  # {"[settings] key": (Settings field, value)}, see config.apply_settings


def _load_entry(entry: dict, base: Path, default_wp: str | None, source: Path):
    from fpe_jax import io
    from fpe_jax.io.apriltag import parse_tag_to_base

    unknown = set(entry) - DRIVE_KEYS
    if unknown:
        raise InputError(source, f"unknown drive keys {sorted(unknown)}", f"{sorted(DRIVE_KEYS)}")
    if "simulate" in entry:
        from fpe_jax.sim import simulate

        spec = dict(entry["simulate"])
        track = spec.pop("track", "oval")
        res = simulate(track, **spec)
        desc = f"simulate:{track}:seed={spec.get('seed', 0)}:latency={spec.get('latency_s', 0.3)}"
        return res.drive, res.centerline_xy_m, desc
    if "path" not in entry:
        raise InputError(source, "a drive has neither 'path' nor 'simulate'", "one of them")
    wp = entry.get("waypoints", default_wp)
    if wp is None:
        raise InputError(source, f"no waypoints for drive {entry['path']}", "a 'waypoints' key")
    drive = io.load_drive(
        base / entry["path"],
        pose_topic=entry.get("pose_topic"),
        truth_topic=entry.get("truth_topic"),
        rate_hz=entry.get("rate_hz"),
        log_time=entry.get("log_time", False),
        tag_id=entry.get("tag_id"),
        tag_to_base=parse_tag_to_base(entry.get("tag_to_base"), f"{source}: tag_to_base"),
        drop_outside_tf=entry.get("drop_outside_tf", False),
    )
    return drive, io.load_waypoints(base / wp).xy_m, str(base / entry["path"])


def load_recipe(path) -> Recipe:
    """Read a recipe TOML and load every drive it names (simulated ones are generated)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such recipe file", "a TOML recipe such as fit/levine.toml")
    try:
        spec = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise InputError(path, f"not valid TOML ({e})", "a TOML recipe") from None
    unknown = set(spec) - TOP_KEYS
    if unknown:
        raise InputError(path, f"unknown keys {sorted(unknown)}", f"{sorted(TOP_KEYS)}")
    if not spec.get("drives"):
        raise InputError(path, "no [[drives]]", "at least one [[drives]] entry")
    table = spec.get("settings", {})
    if not isinstance(table, dict) or set(table) - set(SETTINGS_KEYS):
        bad = sorted(set(table) - set(SETTINGS_KEYS)) if isinstance(table, dict) else table
        raise InputError(path, f"[settings] has {bad!r}", f"keys from {', '.join(SETTINGS_KEYS)}")
    base = path.parent
    wp = spec.get("waypoints")
    drives = [_load_entry(e, base, wp, path) for e in spec["drives"]]
    tests = [_load_entry(e, base, wp, path) for e in spec.get("test_drives", [])]
    fit = spec.get("fit")
    from fpe_jax.cli import SOLVERS

    if spec.get("solver", SOLVERS[0]) not in SOLVERS:
        raise InputError(path, f"solver = {spec['solver']!r}", f"one of {', '.join(SOLVERS)}")
    return Recipe(
        source=path,
        out=base / spec["out"] if "out" in spec else None,
        drives=drives,
        test_drives=tests,
        holdout=float(spec.get("holdout", 0.3)),
        fit=tuple(fit) if fit is not None else None,
        blend=spec.get("blend", "auto"),
        model=spec.get("model"),
        solver=spec.get("solver"),
        settings={f"[settings] {k}": (k, v) for k, v in table.items()},
    )
