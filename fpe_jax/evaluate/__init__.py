"""Evaluation: targets from a drive (`make_targets`, `Dataset`), train/test splits,
the metrics (ADE/FDE, baselines: `_metrics`) and the uncertainty calibration. Names are
re-exported lazily from `_evaluate` and `_metrics`.
"""

import importlib

# public name -> the private module that defines it (imported on first use)
_LAZY = {
    "Dataset": "_evaluate",
    "Heldout": "_evaluate",
    "Targets": "_evaluate",
    "covariance_map": "_evaluate",
    "coverage": "_metrics",
    "cross_fold_lines": "_evaluate",
    "errors_m": "_metrics",
    "evaluate": "_evaluate",
    "fit_covariance": "_metrics",
    "fit_uncertainty": "_evaluate",
    "fit_variance_model": "_metrics",
    "heldout_predictions": "_evaluate",
    "make_datasets": "_evaluate",
    "make_targets": "_evaluate",
    "path_heading": "_evaluate",
    "predict_targets": "_evaluate",
    "prediction_covariance": "_evaluate",
    "row_covariance": "_metrics",
    "split_drive": "_evaluate",
    "summarize": "_metrics",
    "targets_before": "_evaluate",
    "track_frame_residuals": "_metrics",
}
__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name not in _LAZY:
        raise AttributeError(f"module 'fpe_jax.evaluate' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
