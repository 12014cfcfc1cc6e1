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
    "BadMessage": "_core",
    "CdrCodec": "_cdr",
    "DdsTransport": "_dds",
    "IdlCodec": "_dds",
    "Node": "_core",
    "NodeOptions": "_core",
    "Predicted": "_view",
    "Ros1Transport": "_ros1",
    "Ros1Writer": "_cdr",
    "SceneSink": "_foxglove",
    "Template": "_cdr",
    "Transport": "_core",
    "Wire": "_wire",
    "add_arguments": "_view",
    "add_parser": "_cli",
    "check_args": "_view",
    "dds_topic_name": "_dds",
    "dds_type_name": "_dds",
    "ellipse_points": "_wire",
    "feed": "_view",
    "frenet_to_map": "_core",
    "from_dict": "_ros1",
    "full_definition": "_types",
    "header": "_wire",
    "log": "_dds",
    "message_class": "_ros1",
    "msg_files": "_types",
    "options_from_args": "_cli",
    "predicted": "_view",
    "resolve_domain_id": "_dds",
    "ros1_name": "_ros1",
    "ros_type_name": "_dds",
    "run": "_cli",
    "show": "_view",
    "stamp_ns": "_core",
    "time_dict": "_wire",
    "to_dict": "_ros1",
    "type_hash_user_data": "_dds",
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
