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
    "CAR_ID": "_view",
    "CdrCodec": "_cdr",
    "DEBIAN_DIST": "_ros1",
    "DEFAULT_PORT": "_view",
    "DISCOVERY_TOPIC": "_dds",
    "DdsTransport": "_dds",
    "ELLIPSE_POINTS": "_core",
    "FLAVOURS": "_types",
    "INPUT_DEFAULTS": "_cli",
    "INPUT_DEPTH": "_dds",
    "INPUT_FLAGS": "_cli",
    "IdlCodec": "_dds",
    "MARKER_LINE_LIST": "_core",
    "MARKER_LINE_STRIP": "_core",
    "MARKER_SPHERE_LIST": "_core",
    "MAX_DOMAIN_ID": "_dds",
    "MAX_PENDING": "_core",
    "Node": "_core",
    "NodeOptions": "_core",
    "OBSTACLES_TYPE": "_core",
    "OUTPUTS": "_types",
    "OUTPUT_DEPTH": "_dds",
    "OUTPUT_FLAGS": "_cli",
    "POSE_TYPES": "_core",
    "Predicted": "_view",
    "Ros1Transport": "_ros1",
    "Ros1Writer": "_cdr",
    "SPIN_PERIOD_S": "_dds",
    "STOP_TIMEOUT_S": "_foxglove",
    "SceneSink": "_foxglove",
    "TAG_TYPE": "_core",
    "TF_DEPTH": "_dds",
    "TF_KEEP_S": "_core",
    "TF_TYPE": "_core",
    "Transport": "_core",
    "WARN_PERIOD_S": "_dds",
    "add_arguments": "_view",
    "add_parser": "_cli",
    "check_args": "_view",
    "dds_topic_name": "_dds",
    "dds_type_name": "_dds",
    "ellipse_points": "_core",
    "feed": "_view",
    "frenet_to_map": "_core",
    "from_dict": "_ros1",
    "full_definition": "_types",
    "header": "_core",
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
    "time_dict": "_core",
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
