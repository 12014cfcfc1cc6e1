"""ROS 1 transport of the live node: rospy from Debian, messages as nested dicts.

Debian's ROS 1 Python packages (python3-rospy, python3-genpy, the message packages) live in
/usr/lib/python3/dist-packages, which a virtual environment does not see: importing this module
appends that folder to sys.path (after the environment's own packages, so its NumPy wins).
Message classes Debian does not ship (apriltag_ros, f110_msgs) are generated at run time with
genpy from the type store's full definitions (`fpe_jax.node.typestore("ros1")`), no catkin.
"""

from __future__ import annotations

import copy
import functools
import importlib
import io
import shutil
import struct
import sys
import threading
import time
import types
import warnings
from collections.abc import Callable

from fpe_jax.errors import InputError
from fpe_jax.node._cdr import Ros1Writer
from fpe_jax.node._types import full_definition, typestore

DEBIAN_DIST = "/usr/lib/python3/dist-packages"
if DEBIAN_DIST not in sys.path:
    sys.path.append(DEBIAN_DIST)

try:
    import genpy
    import genpy.dynamic
    import rospy
except ImportError as e:  # pragma: no cover - depends on the machine
    raise InputError(
        "--ros1",
        f"rospy / genpy cannot be imported ({e})",
        "Debian's ROS 1 packages: apt-get install python3-rospy python3-genpy ros-core "
        "python3-geometry-msgs python3-nav-msgs python3-visualization-msgs python3-tf2-msgs",
    ) from None

# messages each output connection holds for rospy's writer thread: a prediction's per-step
# covariances come as a burst of H (10) messages, which a queue of 10 would shed whenever the
# writer thread waits for the CPU through one input period; publishing never blocks either way
OUTPUT_QUEUE = 100

_CLASSES: dict[str, type] = {}
_LOCK = threading.Lock()


def ros1_name(type_name: str) -> str:
    """ "pkg/msg/Type" -> "pkg/Type"."""
    return type_name.replace("/msg/", "/")


def message_class(type_name: str) -> type:
    """The genpy class of a type ("pkg/msg/Type" or "pkg/Type"): the installed package's, else
    one generated from the type store's definition (same md5 as a catkin build's)."""
    key = ros1_name(type_name)
    with _LOCK:
        if key in _CLASSES:
            return _CLASSES[key]
        pkg, name = key.split("/")
        try:
            cls = getattr(importlib.import_module(f"{pkg}.msg"), name)
        except (ImportError, AttributeError):
            full = f"{pkg}/msg/{name}"
            if full not in typestore("ros1").types:
                raise ValueError(f"unknown ROS 1 message type {key!r}") from None
            cls = _generate(key, full_definition("ros1", full))
        _CLASSES[key] = cls
        return cls


def _generate(key: str, definition: str) -> type:
    """genpy's class of type `key` generated from its full definition.

    genpy writes the class's code into a new folder /tmp/genpy_* and leaves its removal to the
    interpreter's exit, which `fpe` skips (`fpe_jax.cli.entry` ends with os._exit): every node
    would leave one behind. The folder is removed here, once its module is imported."""
    folders: list[str] = []
    real = genpy.dynamic.atexit
    genpy.dynamic.atexit = types.SimpleNamespace(register=lambda _rmtree, f: folders.append(f))
    try:
        return genpy.dynamic.generate_dynamic(key, definition)[key]
    finally:
        genpy.dynamic.atexit = real
        for folder in folders:
            shutil.rmtree(folder, ignore_errors=True)
            if folder in sys.path:
                sys.path.remove(folder)


def to_dict(msg) -> dict:
    """A genpy message as nested dicts (times as {secs, nsecs}, arrays as lists)."""
    out = {}
    for slot in msg.__slots__:
        out[slot] = _value_to_py(getattr(msg, slot))
    return out


def _value_to_py(v):
    if isinstance(v, genpy.Message):
        return to_dict(v)
    if isinstance(v, genpy.TVal):
        return {"secs": v.secs, "nsecs": v.nsecs}
    if isinstance(v, list | tuple):
        return [_value_to_py(x) for x in v]
    return v


def from_dict(cls: type, d: dict):
    """A genpy message of class `cls` from nested dicts; missing fields take their defaults, an
    unknown field is a ValueError naming the type and the field."""
    slots, convert, zero = _plan(cls)
    if not d.keys() <= convert.keys():
        k = next(k for k in d if k not in convert)
        raise ValueError(f"{cls._type} has no field {k!r} (fields: {', '.join(slots)})")
    msg = cls.__new__(cls)  # every slot is set below: no default objects built to be replaced
    for k in slots:
        v = d.get(k, _MISSING)
        if v is _MISSING:
            setattr(msg, k, zero[k]())
        else:
            c = convert[k]
            setattr(msg, k, v if c is None else c(v))
    return msg


_MISSING = object()


@functools.cache
def _plan(cls: type) -> tuple[tuple[str, ...], dict, dict]:
    """(slots, {slot: converter or None for a value taken as is}, {slot: () -> its default})."""
    convert, zero = {}, {}
    proto = cls()
    for slot, slot_type in zip(cls.__slots__, cls._slot_types):
        base, array = slot_type.split("[", 1)[0], "[" in slot_type
        value = getattr(proto, slot)
        if isinstance(value, int | float | str | bytes | tuple):  # immutable: shared
            zero[slot] = lambda value=value: value
        else:
            zero[slot] = lambda value=value: copy.deepcopy(value)
        if base in ("time", "duration"):
            make = genpy.Time if base == "time" else genpy.Duration
            one = lambda x, make=make: make(x["secs"], x["nsecs"]) if isinstance(x, dict) else x  # noqa: E731
        elif "/" in base or base == "Header":
            sub = message_class("std_msgs/Header" if base == "Header" else base)
            one = lambda x, sub=sub: from_dict(sub, x) if isinstance(x, dict) else x  # noqa: E731
        else:
            convert[slot] = list if array and base not in ("uint8", "char") else None
            continue
        convert[slot] = (lambda v, one=one: [one(x) for x in v]) if array else one
    return tuple(cls.__slots__), convert, zero


@functools.cache
def _writer() -> Ros1Writer:
    return Ros1Writer(typestore("ros1"))


@functools.cache
def _generated(full_type: str, cls: type) -> bool:
    """Whether the generated writer of `full_type` ("pkg/msg/Type") writes `cls`'s messages:
    the type store holds the type with the class's md5."""
    store = typestore("ros1")
    return full_type in store.fielddefs and store.generate_msgdef(full_type, 1)[1] == cls._md5sum


class _Seq:
    """The header rospy stamps its sequence number into before serializing a message."""

    __slots__ = ("seq", "frame_id")

    def __init__(self):
        self.seq, self.frame_id = 0, ""


@functools.cache
def _raw_class(cls: type) -> type:
    """A subclass of the genpy class `cls` whose instances carry their serialized bytes: rospy
    publishes it as a `cls` (same type and md5) and writes the bytes, with its sequence number
    in the header's first 4 bytes as it would have set `header.seq`."""
    has_header = cls._has_header

    class Raw(cls):
        __slots__ = ("_raw",)

        @classmethod
        def of(klass, data: bytes):
            msg = klass.__new__(klass)
            msg._raw = data
            if has_header:
                msg.header = _Seq()
            return msg

        def serialize(self, buff) -> None:
            if has_header:
                buff.write(_SEQ.pack(self.header.seq & 0xFFFFFFFF))
                buff.write(memoryview(self._raw)[4:])
            else:
                buff.write(self._raw)

    Raw.__name__ = Raw.__qualname__ = f"Raw{cls.__name__}"
    return Raw


_SEQ = struct.Struct("<I")


class Ros1Transport:
    """The `Transport` of the node over rospy (one ROS 1 node per process).

    Args:
        name: the node's name (`rospy.init_node`; the master must be reachable).
        queue_size: per input subscription; older messages are dropped under a flood.
    """

    flavour = "ros1"

    def __init__(self, name: str = "future_pose_estimator", queue_size: int = 100):
        rospy.init_node(name, anonymous=False, disable_signals=True)
        self.queue_size = queue_size
        self._subs: list = []
        self._pubs: dict = {}  # topic -> rospy.Publisher

    @staticmethod
    def param(name: str, default=None):
        """The private ROS parameter ~name, or `default` when it is not set."""
        return rospy.get_param(f"~{name}", default)

    def subscribe(self, topic: str, type_name: str | None, callback) -> None:
        if type_name is None:

            def raw(msg, topic=topic):
                t = msg._connection_header["type"]
                try:
                    cls = message_class(t)
                    decoded = cls().deserialize(msg._buff)
                except Exception as e:  # an undecodable message reaches the node as one
                    callback({"_undecodable": str(e)}, f"{t.replace('/', '/msg/', 1)}", 0)
                    return
                callback(to_dict(decoded), t.replace("/", "/msg/", 1), time.time_ns())

            sub = rospy.Subscriber(topic, rospy.AnyMsg, raw, queue_size=self.queue_size,
                                   tcp_nodelay=True)  # fmt: skip
        else:
            cls = message_class(type_name)
            sub = rospy.Subscriber(
                topic,
                cls,
                lambda m: callback(to_dict(m), type_name, time.time_ns()),
                queue_size=self.queue_size,
                tcp_nodelay=True,
            )
        self._subs.append(sub)

    def encode(self, type_name: str, msg: dict) -> bytes:
        """The ROS 1 bytes `advertise`'s publish sends for a message dict (header seq 0: rospy
        writes its own): by the type's generated writer (`fpe_jax.node._cdr.Ros1Writer`) when
        the type store's definition is the class's (same md5), else, and for a message that
        writer does not take, by genpy from `from_dict` (ValueError naming a field it refuses)."""
        full = ros1_name(type_name).replace("/", "/msg/", 1)
        cls = message_class(type_name)
        if _generated(full, cls):
            try:
                return _writer().encode(full, msg)
            except Exception:  # genpy's conversion takes it or says what is wrong
                pass
        buff = io.BytesIO()
        from_dict(cls, msg).serialize(buff)
        return buff.getvalue()

    def advertise(self, topic: str, type_name: str) -> Callable[[dict | bytes], None]:
        """publish(msg) for `topic`: msg a dict, or the bytes of one made by `encode`, sent as
        they are (rospy stamps its sequence number into the header)."""
        cls = message_class(type_name)
        pub = rospy.Publisher(topic, cls, queue_size=OUTPUT_QUEUE, tcp_nodelay=True)
        self._pubs[topic] = pub
        raw = _raw_class(cls)

        def publish(msg: dict | bytes) -> None:
            data = msg if msg.__class__ is bytes else self.encode(type_name, msg)
            pub.publish(raw.of(data))

        return publish

    def subscriber_count(self, topic: str) -> int:
        """How many subscribers are connected to this node's publisher on `topic` (0 if not
        advertised)."""
        pub = self._pubs.get(topic)
        return 0 if pub is None else pub.get_num_connections()

    def spin(self, stop: threading.Event) -> None:
        while not stop.is_set() and not rospy.is_shutdown():
            stop.wait(0.05)

    def close(self) -> None:
        for s in self._subs:
            s.unregister()
        for p in self._pubs.values():
            p.unregister()
        with warnings.catch_warnings():  # rospy's shutdown calls deprecated threading APIs
            warnings.simplefilter("ignore", DeprecationWarning)
            rospy.signal_shutdown("fpe node stopped")
