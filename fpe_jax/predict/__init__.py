"""Prediction: one car (`predict`), a batch of cars (`predict_batch`, `BatchPredictor`),
cars sharded over devices (`predict_sharded`), a whole drive (`predict_drive`,
`states_from_drive`) with the prediction's variance (`predict_variance`, `variance_rows`).

`fpe_jax.predict` is the function for users (`fpe_jax/__init__.py`); this package is reached by
`from fpe_jax.predict import ...` or `importlib.import_module("fpe_jax.predict")`. Names are
re-exported lazily from `_predict`, `_batch`, `_shard`.
"""

import importlib

# public name -> the private module that defines it (imported on first use)
_LAZY = {
    "BatchPredictor": "_batch",
    "CarBlocks": "_batch",
    "ChunkPlan": "_batch",
    "ProjectionGrid": "_batch",
    "car_mesh": "_shard",
    "cast_floats": "_batch",
    "chunk_size": "_batch",
    "filtered": "_predict",
    "leading_size": "_shard",
    "model_states": "_predict",
    "off_track_cars": "_batch",
    "off_track_judge": "_batch",
    "origin_dtype": "_batch",
    "off_track_summary": "_batch",
    "pad_axis0": "_shard",
    "predict": "_predict",
    "predict_batch": "_predict",
    "predict_chunked": "_batch",
    "predict_drive": "_predict",
    "predict_poses": "_predict",
    "predict_rows": "_predict",
    "predict_sharded": "_shard",
    "predict_variance": "_predict",
    "replicate": "_shard",
    "shard_along_axis0": "_shard",
    "stack_params": "_predict",
    "states_both": "_predict",
    "states_from_array": "_batch",
    "states_from_drive": "_predict",
    "uses_filter": "_predict",
    "variance_rows": "_predict",
    "with_origin": "_batch",
}
__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name not in _LAZY:
        raise AttributeError(f"module 'fpe_jax.predict' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
