"""Track geometry: the layer every model and reader builds on.

`build_path` cleans and resamples waypoints (NumPy, no JAX: the runner and the readers use it);
`Track` is the arc-length track as device arrays, with projection of points onto it
(`project_rollout`, `arclength_along`); `builtin_track` reads the shipped tracks (oval, hairpin,
random:SEED); `resample_loop` and `loop_curvature` work on closed loops. Names are re-exported
lazily from the private modules `_path`, `_track`, `_tracks`, so importing this package costs
nothing until a name is used.
"""

import importlib

# public name -> the private module that defines it (imported on first use)
_LAZY = {
    "BRANCH_COS": "_path",
    "MIN_ON_TRACK_SHARE": "_path",
    "NearPath": "_path",
    "ON_TRACK_M": "_path",
    "Track": "_track",
    "arclength_along": "_track",
    "arclength_along_heading": "_track",
    "build_path": "_path",
    "builtin_track": "_tracks",
    "check_on_track": "_path",
    "check_share_near": "_path",
    "covariance_map": "_path",
    "is_builtin": "_tracks",
    "left_normals": "_path",
    "loop_arclength": "_tracks",
    "loop_curvature": "_tracks",
    "map_origin": "_path",
    "near_path": "_path",
    "nearest_index": "_path",
    "nearest_vertex": "_path",
    "off_track": "_path",
    "off_track_judge": "_path",
    "on_track_m": "_path",
    "profile_values": "_path",
    "project_rollout": "_track",
    "resample_loop": "_tracks",
    "track_agreement": "_path",
    "waypoints_sha256": "_path",
    "wrap_angle": "_path",
    "wrap_to": "_track",
}
__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name not in _LAZY:
        raise AttributeError(f"module 'fpe_jax.geometry' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
