"""fpe-jax: differentiable near-future pose prediction for autonomous race cars.

import fpe_jax as fpe
track = fpe.Track.from_waypoints(waypoints_xy_m)
params = fpe.presets["default"]
poses = fpe.predict(params, fpe.State(x_m=..., y_m=..., yaw_rad=..., v_mps=...), track)
"""

from fpe_jax.drive import Drive
from fpe_jax.errors import InputError
from fpe_jax.params import Params, Settings, constrain, presets, unconstrain
from fpe_jax.predict import predict, predict_batch, predict_drive, stack_params
from fpe_jax.rollout import State
from fpe_jax.track import Track

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
