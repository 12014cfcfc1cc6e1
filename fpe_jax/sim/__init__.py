"""Simulated drives: `simulate` drives a car around a track (the embedded default data, the
demo's and the tests' drives); `_cases` holds the study cases the experiments run. Names are
re-exported lazily from `_sim` and `_cases`.
"""

import importlib

# public name -> the private module that defines it (imported on first use)
_LAZY = {
    "Camera": "_sim",
    "Case": "_cases",
    "DELAY_TOLERANCE_S": "_cases",
    "DT_S": "_sim",
    "Driver": "_sim",
    "F1TENTH_TRACKS": "_cases",
    "G_MPS2": "_sim",
    "LATENCY_S": "_cases",
    "MAX_DURATION_S": "_sim",
    "REF_SPACING_M": "_sim",
    "SIM_VERSION": "_sim",
    "Sensor": "_sim",
    "SimResult": "_sim",
    "TRUTH_EVERY": "_sim",
    "Vehicle": "_sim",
    "apriltag_layout": "_sim",
    "f1tenth_cases": "_cases",
    "fde_ratio": "_cases",
    "fit_case": "_cases",
    "levine_case": "_cases",
    "observe": "_sim",
    "presets_beating_fitted": "_cases",
    "real_cases": "_cases",
    "simulate": "_sim",
    "simulated_case": "_cases",
    "study_cases": "_cases",
    "write_simulation": "_sim",
}
__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name not in _LAZY:
        raise AttributeError(f"module 'fpe_jax.sim' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
