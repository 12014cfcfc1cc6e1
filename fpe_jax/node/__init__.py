"""The live prediction node (`fpe node`) and the Foxglove view (`fpe view`): front ends that run on
the car or beside it.

JAX-free: the car may have no JAX. The middleware-neutral core (`Node`) talks to a `Transport`
(ROS 1 through rospy, ROS 2 through DDS) with messages as nested dicts, one type store per
flavour (`typestore`); `SceneSink` streams the scene of live or replayed predictions to Foxglove
(WebSocket and MCAP). Names are imported on first use, so registering the subcommands keeps
`fpe --help` fast.
"""

import importlib

# public name -> the private module that defines it
_LAZY = {
    "FLAVOURS": "_types",
    "OUTPUTS": "_core",
    "Node": "_core",
    "NodeOptions": "_core",
    "SceneSink": "_foxglove",
    "Transport": "_core",
    "full_definition": "_types",
    "typestore": "_types",
}
__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name not in _LAZY:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
