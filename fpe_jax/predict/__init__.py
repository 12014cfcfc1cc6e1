"""Prediction: one car, a batch of cars, sharded batches, a whole drive with its covariance."""

import importlib

# public name -> the private module that defines it (imported on first use)
_LAZY = {
    "AXIS": "_shard",
    "BLOCK_ROWS": "_predict",
    "BatchPredictor": "_batch",
    "ChunkPlan": "_batch",
    "DEFAULT_CHUNK": "_batch",
    "DTYPES": "_batch",
    "LATTICE_SIDE": "_batch",
    "MIN_BUCKET": "_predict",
    "PREDICT_CHUNK": "_predict",
    "ProjectionGrid": "_batch",
    "WINDOW_FIELDS": "_predict",
    "bucket": "_predict",
    "car_mesh": "_shard",
    "cast_floats": "_batch",
    "chunk_size": "_batch",
    "filtered": "_predict",
    "leading_size": "_shard",
    "model_states": "_predict",
    "no_arclength": "_predict",
    "pad_axis0": "_shard",
    "pad_rows": "_predict",
    "predict": "_predict",
    "predict_batch": "_predict",
    "predict_chunked": "_batch",
    "predict_drive": "_predict",
    "predict_poses": "_predict",
    "predict_rows": "_predict",
    "predict_sharded": "_shard",
    "predict_variance": "_predict",
    "replicate": "_shard",
    "row_blocks": "_predict",
    "shard_along_axis0": "_shard",
    "stack_params": "_predict",
    "states_both": "_predict",
    "states_from_array": "_batch",
    "states_from_drive": "_predict",
    "uses_filter": "_predict",
    "variance_rows": "_predict",
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
