"""Compiled programs and the arrays they take, below the model.

`jit` / `executable` keep ahead-of-time executables on disk (`_aot`, `_cache`: `fpe cache`);
`device_array` puts host values on the device without a compiled program per shape (`_arrays`);
`bucket`, `pad_rows` and `row_blocks` cut rows into the few padded shapes every command shares
(`_rows`, NumPy only). Names are re-exported lazily.
"""

import importlib

# public name -> the private module that defines it (imported on first use)
_LAZY = {
    "Executable": "_aot",
    "MARKER": "_cache",
    "Refused": "_cache",
    "active_dir": "_cache",
    "bucket": "_rows",
    "clear": "_cache",
    "cpu_features": "_cache",
    "device_array": "_arrays",
    "disable": "_cache",
    "disabled": "_cache",
    "enable": "_cache",
    "entry_name": "_cache",
    "executable": "_aot",
    "fusion_emitters": "_aot",
    "info": "_cache",
    "jit": "_aot",
    "load_signed": "_cache",
    "no_arclength": "_rows",
    "pad_rows": "_rows",
    "read_regular": "_cache",
    "root_dir": "_cache",
    "row_blocks": "_rows",
    "secret_key": "_cache",
    "store_signed": "_cache",
    "subfolder_name": "_cache",
    "user_key": "_cache",
    "warn": "_cache",
}
__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name not in _LAZY:
        raise AttributeError(f"module 'fpe_jax.compile' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
