"""Simulated drives: `simulate` drives a car around a track (the embedded default data, the
demo's and the tests' drives). Names are re-exported lazily from `_sim`.
"""

import importlib

# public name -> the private module that defines it (imported on first use)
_LAZY = {
    "Camera": "_sim",
    "Driver": "_sim",
    "Sensor": "_sim",
    "SimResult": "_sim",
    "Vehicle": "_sim",
    "apriltag_layout": "_sim",
    "check_drivable": "_sim",
    "check_simulation_out": "_sim",
    "observe": "_sim",
    "simulate": "_sim",
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
