"""Tuned configs: versioned JSON holding physical parameter values, settings, uncertainty and the
fit's provenance. Readable without JAX (`read_config` is plain JSON + checks) so the NumPy runner
can load the same files.

Schema (version 2):
    {"schema_version": 2,
     "params": {"lookahead_m", "lookahead_gain_s", "weights": [H], "delay_s", "speed_weight",
                "speed_mps", optional: "offset_tau_s", "speed_tau_s", "pace_return_1ps",
                "position_smoothing",
                "filter_accel_mps2", "filter_lat_accel_mps2", "filter_obs_m",
                "filter_gate_sigma" (frenet / line models),
                "line_offset_m", "line_speed_mps", "line_coverage": [P] (line model only)},
     "settings": {"dt_s", "horizon", "wheelbase_m", "max_steer_rad", "blend", "model",
                  "min_lookahead_m", "history", optional "estimator"},
     "line": {"waypoints_sha256", "waypoints"},   # line model only: what the line belongs to
     "uncertainty": null | {"frame": "track", "cov_m2": [H][2][2],   # along-, cross-track
                            optional, all or none: "state_scale": [H][2],
                            "model_var_m2": [H][2], "correlation": [H]},
     "provenance": {...}}
Version 1 read the same keys; with the Kalman estimator its rollouts ignored
position_smoothing (started at the filter's position), so such a config is read with 1.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

from fpe_jax.errors import InputError
from fpe_jax.spec import (
    LINE_KEYS,
    MAX_HORIZON,
    OPTIONAL_PARAM_KEYS,
    PARAM_KEYS,
    SCHEMA_VERSION,
    SETTING_KEYS,
    check_config,
)

# built-in presets (fpe_jax.model builds them) and their one-line docs: kept here, JAX-free,
# so that `fpe presets` answers without importing JAX
PRESET_DOCS = {
    "seed": "the original 2019 node exactly: 1 m/s, 2 m lookahead, reverse goal scan, 0.7^i",
    "seed-measured-speed": "the original node's rules with the measured speed",
    "linear": "constant speed along the current heading (thesis approach 2)",
    "pure-pursuit": "kinematic bicycle following the path, 2 m lookahead (approach 3)",
    "constant-velocity": "constant velocity vector from the recent history (approach 1)",
    "ctrv": "constant turn rate and velocity",
    "frenet": "along-track speed held from the newest position, lateral offset decaying to the "
    "centerline (tau 1 s)",
    "default": "the differentiable position blend; the fitter's starting point for --model blend",
}


def read_config(path) -> dict[str, Any]:
    """Read and check a config JSON (no JAX). Raises InputError naming what is wrong."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such config file", "a JSON config written by `fpe fit`")
    try:
        cfg = json.loads(path.read_bytes().decode("utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError(path, f"not valid JSON ({e})", "a JSON config") from None
    except RecursionError:
        raise InputError(path, "nested too deeply", "a JSON config written by `fpe fit`") from None
    return check_config(cfg, path)


def config_to_params(cfg: dict[str, Any]):
    """Params from a checked config dict."""
    from fpe_jax.model._params import Params, Settings

    settings = Settings(**{k: cfg["settings"][k] for k in SETTING_KEYS})
    keys = PARAM_KEYS + OPTIONAL_PARAM_KEYS + (LINE_KEYS if settings.model == "line" else ())
    return Params.create(settings, **{k: cfg["params"][k] for k in keys if k in cfg["params"]})


def check_waypoints(cfg: dict[str, Any], config_source, waypoints_xy_m, waypoints_source) -> None:
    """A line-model config is only valid on the waypoints its line was learned on (sha256 of
    their float64 values): InputError naming both files otherwise. Other models: no check."""
    if cfg["settings"]["model"] != "line":
        return
    from fpe_jax.geometry._path import waypoints_sha256

    line = cfg["line"]
    if waypoints_sha256(waypoints_xy_m) != line["waypoints_sha256"]:
        raise InputError(
            waypoints_source,
            f"not the waypoints the line of {config_source} was learned on "
            f"({line.get('waypoints') or 'sha256 ' + line['waypoints_sha256'][:12]})",
            "the waypoint file the config was fitted with",
        )


def params_to_config(params, *, uncertainty=None, provenance=None, line=None) -> dict[str, Any]:
    """A config dict from Params (+ optional uncertainty and provenance; `line`, the line
    model's {"waypoints_sha256", "waypoints"}, is required for it)."""
    cfg = {
        "schema_version": SCHEMA_VERSION,
        "params": params.physical(),
        "settings": dataclasses.asdict(params.settings),
        "uncertainty": uncertainty,
        "provenance": provenance or {},
    }
    if params.settings.model == "line":
        if not line or "waypoints_sha256" not in line:
            raise ValueError("params_to_config: the line model needs line.waypoints_sha256")
        cfg["line"] = dict(line)
    return cfg


def write_config(path, cfg: dict[str, Any], *, force: bool = False) -> None:
    """Write a config JSON; refuses to overwrite an existing file unless force."""
    from fpe_jax.io.writers import write_text

    write_text(path, json.dumps(cfg, indent=2) + "\n", force=force)


def load_params(
    *, preset: str | None = None, config: str | None = None, settings=None, waypoints=None
):
    """Params from a preset name or a config file (see `load_params_and_config`)."""
    return load_params_and_config(
        preset=preset, config=config, settings=settings, waypoints=waypoints
    )[0]


def load_params_and_config(
    *, preset: str | None = None, config: str | None = None, settings=None, waypoints=None
):
    """(Params, config dict or None) from a preset name or a config file (exactly one; default
    preset: 'default'), reading the config once.

    settings: {flag: (Settings field, value)} of user settings (`spec.USER_SETTINGS`) for a
    preset; a config carries the settings it was fitted with, so they are an error there.
    waypoints: optional (file name, (K, 2) array) the params will run on: a line-model config
    must have been fitted on exactly these (`check_waypoints`).
    """
    from fpe_jax.model._params import presets

    settings = {k: v for k, v in (settings or {}).items() if v[1] is not None}
    if config is not None:
        if settings:
            flags = ", ".join(settings)
            raise InputError(flags, "given with --config", "a config's own settings (or --preset)")
        cfg = read_config(config)
        if waypoints is not None:
            check_waypoints(cfg, config, waypoints[1], waypoints[0])
        return config_to_params(cfg), cfg
    name = preset or "default"
    if name not in presets:
        raise InputError("preset", f"unknown preset {name!r}", f"one of {', '.join(presets)}")
    return apply_settings(presets[name], settings), None


def apply_settings(params, settings: dict, source: str | None = None):
    """params with {name: (Settings field, value)} applied; a bad value is an InputError naming
    `source` or the flag."""
    from fpe_jax.model._params import with_settings

    for name, (field, value) in settings.items():
        ok = _is_number(value) and value > 0
        if field == "horizon":
            ok = ok and isinstance(value, int) and value <= MAX_HORIZON
        if not ok or (field == "max_steer_rad" and value >= 1.5707963):
            what = f"{source}: {name}" if source else name
            raise InputError(what, f"{value!r}", SETTING_EXPECTED[field])
    try:
        return with_settings(params, **{f: v for f, v in settings.values()})
    except ValueError as e:
        raise InputError(source or ", ".join(settings), str(e), "valid settings") from None


SETTING_EXPECTED = {
    "wheelbase_m": "a positive wheelbase in metres",
    "max_steer_rad": "a steering limit in radians, > 0 and < pi/2",
    "dt_s": "a positive step in seconds",
    "horizon": f"a whole number of steps, 1 to {MAX_HORIZON}",
}


def _is_number(x) -> bool:
    import math

    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)
