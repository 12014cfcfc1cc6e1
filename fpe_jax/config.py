"""Tuned configs: versioned JSON holding physical parameter values, settings, uncertainty and the
fit's provenance. Readable without JAX (`read_config` is plain JSON + checks) so the NumPy runner
can load the same files.

Schema (version 1):
    {"schema_version": 1,
     "params": {"lookahead_m", "lookahead_gain_s", "weights": [H], "delay_s", "speed_weight",
                "speed_mps"},
     "settings": {"dt_s", "horizon", "wheelbase_m", "max_steer_rad", "blend", "model",
                  "min_lookahead_m", "history"},
     "uncertainty": null | {"frame": "track", "cov_m2": [H][2][2]},   # along-, cross-track
     "provenance": {...}}
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

from fpe_jax.errors import InputError
from fpe_jax.spec import PARAM_KEYS, SCHEMA_VERSION, SETTING_KEYS, check_config


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
    from fpe_jax.params import Params, Settings

    settings = Settings(**{k: cfg["settings"][k] for k in SETTING_KEYS})
    return Params.create(settings, **{k: cfg["params"][k] for k in PARAM_KEYS})


def params_to_config(params, *, uncertainty=None, provenance=None) -> dict[str, Any]:
    """A config dict from Params (+ optional uncertainty and provenance)."""
    return {
        "schema_version": SCHEMA_VERSION,
        "params": params.physical(),
        "settings": dataclasses.asdict(params.settings),
        "uncertainty": uncertainty,
        "provenance": provenance or {},
    }


def write_config(path, cfg: dict[str, Any], *, force: bool = False) -> None:
    """Write a config JSON; refuses to overwrite an existing file unless force."""
    from fpe_jax.io.writers import write_text

    write_text(path, json.dumps(cfg, indent=2) + "\n", force=force)


def load_params(*, preset: str | None = None, config: str | None = None):
    """Params from a preset name or a config file (exactly one; default preset: 'default')."""
    from fpe_jax.params import presets

    if config is not None:
        return config_to_params(read_config(config))
    name = preset or "default"
    if name not in presets:
        raise InputError("--preset", f"unknown preset {name!r}", f"one of {', '.join(presets)}")
    return presets[name]
