"""The JAX-free on-car runner: a NumPy mirror of the model (`Runner`, `_runner`) and
in-race learning (`AdaptiveRunner`, `_adapt`) with its ellipses calibrated online
(`EllipseCalibration`, `_calibrate`). Importing this package, and using it, imports no
JAX (tests/runner/test_adapt.py and tests/runner/test_runner.py check it in a process where
JAX is blocked).
`python -m fpe_jax.runner WAYPOINTS` prints the runner's step-time benchmark.
"""

import importlib

# public name -> the private module that defines it (imported on first use)
_LAZY = {
    "AdaptiveRunner": "_adapt",
    "BLEND_MODES": "_runner",
    "EllipseCalibration": "_calibrate",
    "FloatN": "_runner",
    "GoalScan": "_runner",
    "MODELS": "_runner",
    "Runner": "_runner",
    "RunnerPath": "_runner",
    "benchmark_update": "_runner",
    "kernel": "_adapt",
    "load_waypoints_xy": "_runner",
    "predict_drive_adaptive": "_adapt",
    "profile_points": "_adapt",
    "run_stream": "_runner",
    "seed_rollout": "_runner",
    "start_config": "_adapt",
}
__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name not in _LAZY:
        raise AttributeError(f"module 'fpe_jax.runner' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
