"""The model: what a prediction is made of, for one car at a time.

`Params` (fitted values, arrays) and `Settings` (static choices), with `presets`,
`constrain` / `unconstrain`; `State` and `Poses`; the track-frame estimators (Theil-Sen in
`_estimate`, Kalman in `_kalman`); the rollouts and their blend (`_rollout`); the learned line
(`_line`); the observation history (`_history`, NumPy only). Single-sample pure functions;
`fpe_jax.predict` vmaps them over cars and drives. Names are re-exported lazily.
"""

import importlib

# public name -> the private module that defines it (imported on first use)
_LAZY = {
    "LineSamples": "_line",
    "Params": "_params",
    "Poses": "_state",
    "Settings": "_params",
    "State": "_state",
    "Value": "_state",
    "constrain": "_params",
    "distinct_mask": "_history",
    "drive_valid": "_history",
    "estimate_state": "_estimate",
    "estimate_variance": "_rollout",
    "history_valid": "_history",
    "history_windows": "_history",
    "kalman_params": "_kalman",
    "kalman_window": "_kalman",
    "learn_line": "_line",
    "limit_speed": "_line",
    "line_from_samples": "_line",
    "line_samples": "_line",
    "min_curvature_offset": "_line",
    "presets": "_params",
    "profile_at": "_rollout",
    "pure_pursuit_steer": "_rollout",
    "rollout": "_rollout",
    "rollout_blend": "_rollout",
    "rollout_ctrv": "_rollout",
    "rollout_cv": "_rollout",
    "rollout_frenet": "_rollout",
    "rollout_linear": "_rollout",
    "rollout_pure_pursuit": "_rollout",
    "rollout_seed": "_rollout",
    "track_frame_lines": "_estimate",
    "track_frame_window": "_estimate",
    "unconstrain": "_params",
    "with_settings": "_params",
}
__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name not in _LAZY:
        raise AttributeError(f"module 'fpe_jax.model' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
