"""fpe-jax: differentiable near-future pose prediction for autonomous race cars.

import fpe_jax as fpe
track = fpe.Track.from_waypoints(waypoints_xy_m)
params = fpe.presets["default"]
poses = fpe.predict(params, fpe.State(x_m=..., y_m=..., yaw_rad=..., v_mps=...), track)

The public names are imported lazily (module-level `__getattr__`), so that JAX-free modules such as
`fpe_jax.runner`, `fpe_jax.io` and `fpe_jax.spec` can be imported on a car that has no JAX.
"""

from __future__ import annotations

import importlib
import sys
import types
from typing import TYPE_CHECKING

# public name -> the module that defines it
_LAZY = {
    "Drive": "fpe_jax.drive",
    "InputError": "fpe_jax.errors",
    "Params": "fpe_jax.model",
    "Settings": "fpe_jax.model",
    "constrain": "fpe_jax.model",
    "presets": "fpe_jax.model",
    "unconstrain": "fpe_jax.model",
    "predict": "fpe_jax.predict",
    "predict_batch": "fpe_jax.predict",
    "predict_drive": "fpe_jax.predict",
    "stack_params": "fpe_jax.predict",
    "State": "fpe_jax.model",
    "Track": "fpe_jax.geometry",
}

__all__ = [
    "Drive",
    "InputError",
    "Params",
    "Settings",
    "State",
    "Track",
    "constrain",
    "predict",
    "predict_batch",
    "predict_drive",
    "presets",
    "stack_params",
    "unconstrain",
]
__version__ = "0.1.0"

if TYPE_CHECKING:  # static analysers and IDEs see the real imports
    from fpe_jax.drive import Drive
    from fpe_jax.errors import InputError
    from fpe_jax.geometry._track import Track
    from fpe_jax.model._params import Params, Settings, constrain, presets, unconstrain
    from fpe_jax.model._state import State
    from fpe_jax.predict._predict import predict, predict_batch, predict_drive, stack_params


def __getattr__(name: str):
    if name not in _LAZY:
        # AttributeError (not ImportError) lets `from fpe_jax import io` import the subpackage
        raise AttributeError(f"module 'fpe_jax' has no attribute {name!r}")
    value = getattr(importlib.import_module(_LAZY[name]), name)
    globals()[name] = value  # cache: later lookups skip __getattr__
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))


class _Package(types.ModuleType):
    # The submodule `fpe_jax.predict` shares its name with the public function `predict`;
    # importing the submodule makes the import system bind the package attribute to the module,
    # so `from fpe_jax import predict` would give a module (tests/predict/test_predict.py).
    # Keep the public name: skip that binding (the submodule stays in sys.modules).
    def __setattr__(self, name, value):
        if isinstance(value, types.ModuleType) and name in _LAZY:
            return
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package
