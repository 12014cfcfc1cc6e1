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
    "BLEND_MODES": "_params",
    "ESTIMATORS": "_params",
    "FALLBACK_TAU_S": "_constants",
    "GATE_SHARPNESS": "_constants",
    "INIT_LAT_RATE_SIGMA_MPS": "_constants",
    "INIT_POS_SIGMA_M": "_constants",
    "INIT_SPEED_SIGMA_MPS": "_constants",
    "LIMIT_ACCEL_RATIOS": "_line",
    "LIMIT_BRAKE_RATIOS": "_line",
    "LIMIT_SMOOTH_M": "_line",
    "LIMIT_TOP_RADII_M": "_line",
    "LINE_KEYS": "_params",
    "LineSamples": "_line",
    "MAX_GAP_S": "_line",
    "MAX_SPAN_S": "_history",
    "MAX_SPEED_RATIO": "_constants",
    "MIN_CURV_ITERS": "_line",
    "MIN_CURV_RHO": "_line",
    "MIN_CURV_RIDGE": "_line",
    "MIN_PAIR_DT_S": "_history",
    "MIN_PROFILE_SPEED_MPS": "_constants",
    "MIN_SAMPLES": "_line",
    "MIN_TAU_S": "_params",
    "MIN_VALID_OBS": "_history",
    "MIN_VALID_SPAN_S": "_history",
    "MODELS": "_params",
    "OUTLIER_M": "_history",
    "PRIOR_FOLDS": "_line",
    "PRIOR_LAG_M": "_line",
    "PRIOR_MIN_COVERED_M": "_line",
    "PRIOR_RIDGE": "_line",
    "PRIOR_SHIFTS_M": "_line",
    "PRIOR_SMOOTH_M": "_line",
    "PROFILE_DS_M": "_line",
    "PROFILE_SMOOTH_M": "_line",
    "Params": "_params",
    "Poses": "_state",
    "SLOPE_DS_M": "_constants",
    "Settings": "_params",
    "State": "_state",
    "USER_SETTINGS": "_params",
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
