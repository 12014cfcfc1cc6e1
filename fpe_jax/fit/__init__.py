"""Fitting: the loss and its solve (`fit`, `_fit`), the package's BFGS (`_bfgs`), fit recipes
(`_recipe`: TOML files in fit/), the fit report (`_report`) and the study cases the demo and
the experiments fit (`_cases`: simulate, split, fit, evaluate). Names are re-exported lazily.
"""

import importlib

# public name -> the private module that defines it (imported on first use)
_LAZY = {
    "Case": "_cases",
    "DEFAULT_MODEL": "_fit",
    "FILTER_PRIOR_M2": "_fit",
    "FIT_BLOCK_ROWS": "_fit",
    "FitResult": "_fit",
    "MODEL_FIT": "_fit",
    "PRESOLVE_ROWS": "_fit",
    "Recipe": "_recipe",
    "allowed_groups": "_fit",
    "baseline": "_fit",
    "default_groups": "_fit",
    "default_solver": "_fit",
    "f1tenth_cases": "_cases",
    "fde_ratio": "_cases",
    "fit": "_fit",
    "fit_case": "_cases",
    "fit_params": "_fit",
    "format_fitted": "_report",
    "format_table": "_report",
    "levine_case": "_cases",
    "line_section": "_report",
    "load_recipe": "_recipe",
    "md_table": "_report",
    "presets_beating_fitted": "_cases",
    "provenance": "_report",
    "real_cases": "_cases",
    "robust_residuals": "_fit",
    "simulated_case": "_cases",
    "solver_named": "_recipe",
    "study_cases": "_cases",
}
__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name not in _LAZY:
        raise AttributeError(f"module 'fpe_jax.fit' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
