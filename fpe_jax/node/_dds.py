"""ROS 2 on the wire without rclpy: a Transport over DDS through the `cyclonedds` wheel.

ROS 2 is DDS with naming and QoS conventions, which this module follows:

- topic `/a/b` is the DDS topic `rt/a/b`; type `pkg/msg/T` is the DDS type `pkg::msg::dds_::T_`;
- samples are plain CDR (XCDR1, little endian): every type is a final, keyless struct whose
  fields follow the message definition in order;
- outputs are reliable, volatile, keep-last 10 (the ROS 2 default profile); inputs are volatile,
  keep-last 10, reliable while every writer on the topic is reliable and best effort once a
  best-effort (sensor data) writer appears, which a reliable reader could not match;
- TF (tf2_msgs/TFMessage) takes tf2_ros' QoS: keep-last 100, and transient local on topics
  ending in `_static` (`/tf_static`), so static transforms published before the node started
  reach it;
- each endpoint carries `typehash=RIHS01_<sha256 hex>;` in its USER_DATA (ROS 2 Jazzy and later);
- the node announces its readers and writers on `ros_discovery_info`, so `ros2 node list` shows it.

The DDS types are generated at run time from the message definitions in a rosbags `Typestore`
(the same definitions that give the type hashes), never from hand-written layouts. Messages cross
the Transport boundary as nested dicts (see `IdlCodec`); their CDR bytes are written and read by
code generated from those definitions (`fpe_jax.node._cdr`) and go straight to and from Cyclone
DDS' C writers and readers.

No `from __future__ import annotations` here: cyclonedds reads the generated classes' field
annotations as objects.
"""

import logging
import os
import re
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

try:
    from cyclonedds._clayer import ddspy_take, ddspy_write
    from cyclonedds.builtin import BuiltinDataReader, BuiltinTopicDcpsPublication
    from cyclonedds.core import (
        DDSException,
        GuardCondition,
        InstanceState,
        Policy,
        Qos,
        ReadCondition,
        SampleState,
        ViewState,
        WaitSet,
    )
    from cyclonedds.domain import DomainParticipant
    from cyclonedds.idl import make_idl_struct
    from cyclonedds.idl import types as idl
    from cyclonedds.pub import DataWriter
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic
    from cyclonedds.util import duration
except ImportError as err:  # pragma: no cover - depends on the installation
    raise ImportError(
        "the ROS 2 transport needs the `cyclonedds` package: pip install 'fpe-jax[ros2]'"
    ) from err
from rosbags.interfaces import Nodetype
from rosbags.typesys.store import Typestore

from fpe_jax.node._cdr import (
    INT_RANGES,
    CdrCodec,
    FieldError,
    array_converter,
    fielddefs,
    float_converter,
    int_converter,
    string_converter,
    to_bool,
)

log = logging.getLogger(__name__)

OUTPUT_DEPTH = 10  # keep-last depth of every writer (ROS 2 default profile)
INPUT_DEPTH = 10  # keep-last depth of every reader
TF_TYPE = "tf2_msgs/msg/TFMessage"
TF_DEPTH = 100  # TF readers and writers, as tf2_ros' (transforms come in bursts)
SPIN_PERIOD_S = 0.02  # longest time spin() takes to notice that `stop` was set
WARN_PERIOD_S = 10.0  # one warning per topic and problem in this time
DISCOVERY_TOPIC = "ros_discovery_info"
MAX_DOMAIN_ID = 232  # the highest id whose RTPS ports fit in 16 bits

_TOPIC = re.compile(r"/?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*")
_TYPE = re.compile(r"([A-Za-z][A-Za-z0-9_]*)/msg/([A-Za-z][A-Za-z0-9_]*)")
_DDS_TYPE = re.compile(r"([A-Za-z][A-Za-z0-9_]*)::msg::dds_::([A-Za-z][A-Za-z0-9_]*)_")
_NODE_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


# ---------------------------------------------------------------------------------------------
# names


def dds_topic_name(topic: str) -> str:
    """The DDS topic of a ROS 2 topic: `/a/b` -> `rt/a/b` (a relative name is taken as absolute)."""
    if not isinstance(topic, str) or not _TOPIC.fullmatch(topic):
        raise ValueError(
            f"ROS 2 topic {topic!r}: not a valid topic name (expected e.g. /future_pose: "
            "letters, digits and _ in /-separated parts)"
        )
    return "rt/" + topic.lstrip("/")


def dds_type_name(type_name: str) -> str:
    """The DDS type of a ROS 2 message type: `pkg/msg/T` -> `pkg::msg::dds_::T_`."""
    match = _TYPE.fullmatch(type_name) if isinstance(type_name, str) else None
    if match is None:
        raise ValueError(
            f"message type {type_name!r}: expected a name of the form pkg/msg/Type "
            "(e.g. geometry_msgs/msg/PoseStamped)"
        )
    return f"{match[1]}::msg::dds_::{match[2]}_"


def ros_type_name(dds_type: str) -> str | None:
    """The ROS 2 message type of a DDS type name (`pkg::msg::dds_::T_` -> `pkg/msg/T`), or None
    when the name does not follow the ROS 2 convention."""
    match = _DDS_TYPE.fullmatch(dds_type)
    return None if match is None else f"{match[1]}/msg/{match[2]}"


def _ros_topic(topic: str) -> str:
    """The absolute spelling of a ROS 2 topic (checked), used as the key of every table here."""
    return "/" + dds_topic_name(topic)[3:]


def resolve_domain_id(domain_id: int | None) -> int:
    """`domain_id`, or `ROS_DOMAIN_ID` from the environment when it is None (unset or empty: 0)."""
    if domain_id is None:
        text = os.environ.get("ROS_DOMAIN_ID", "").strip()
        if not text:
            return 0
        try:
            domain_id = int(text)
        except ValueError:
            raise ValueError(
                f"ROS_DOMAIN_ID={text!r}: expected an integer 0..{MAX_DOMAIN_ID}"
            ) from None
        where = "ROS_DOMAIN_ID"
    else:
        where = "domain_id"
    if isinstance(domain_id, bool) or not 0 <= domain_id <= MAX_DOMAIN_ID:
        raise ValueError(f"{where}={domain_id!r}: expected an integer 0..{MAX_DOMAIN_ID}")
    return domain_id


def _durability(topic: str, type_name: str):
    """Transient local for static TF (as tf2_ros' static broadcasters and listeners), else
    volatile."""
    if type_name == TF_TYPE and topic.endswith("_static"):
        return Policy.Durability.TransientLocal
    return Policy.Durability.Volatile


def type_hash_user_data(typestore: Typestore, type_name: str) -> bytes:
    """The USER_DATA of a ROS 2 Jazzy endpoint: `typehash=RIHS01_<hex>;` of the type."""
    return f"typehash={typestore.hash_rihs01(type_name)};".encode()


# ---------------------------------------------------------------------------------------------
# message types: rosbags definitions -> cyclonedds IdlStruct classes, dict <-> sample


_IDL_INTS = {
    "int8": idl.int8,
    "uint8": idl.uint8,
    "byte": idl.byte,
    "char": idl.uint8,
    "int16": idl.int16,
    "uint16": idl.uint16,
    "int32": idl.int32,
    "uint32": idl.uint32,
    "int64": idl.int64,
    "uint64": idl.uint64,
}


_MISSING = object()


def _identity(value: Any) -> Any:
    return value


def _as_list(values: Any) -> list:
    return values if isinstance(values, list) else list(values)


def _list_of(convert: Callable[[Any], Any]) -> Callable[[Any], list]:
    return lambda values: [convert(v) for v in values]


class _Field:
    """How one field is declared, defaulted, built from a dict value and turned back into one."""

    __slots__ = ("name", "annotation", "default", "to_idl", "to_py")

    def __init__(self, name, annotation, default, to_idl, to_py):
        self.name = name
        self.annotation = annotation
        self.default = default  # () -> the field's zero value as an IDL value
        self.to_idl = to_idl  # dict value -> IDL value (raises FieldError)
        self.to_py = to_py  # IDL value -> dict value


class IdlCodec:
    """The cyclonedds IDL classes of a rosbags `Typestore`'s ROS 2 message types, and the
    conversion between nested dicts and their samples.

    Building a sample from a dict: a missing field takes its zero value (0, 0.0, False, "", [],
    nested zeros; a fixed array N zeros); an unknown field name or a value of the wrong kind raises
    ValueError naming the type and the field path. Fixed arrays and sequences accept lists, tuples
    or 1-D numpy arrays; numbers accept Python or numpy scalars. A dict read from a sample has
    every field; arrays and sequences are lists.
    """

    def __init__(self, typestore: Typestore):
        self._store = typestore
        self._cdr = CdrCodec(typestore)
        self._classes: dict[str, type] = {}
        self._fields: dict[str, tuple[_Field, ...]] = {}
        self._names: dict[str, frozenset[str]] = {}
        self._lock = threading.Lock()

    def idl_class(self, type_name: str) -> type:
        """The IdlStruct class of `type_name` (pkg/msg/Type), generated once and cached."""
        with self._lock:
            return self._class(type_name)

    def _class(self, type_name: str) -> type:
        cls = self._classes.get(type_name)
        if cls is not None:
            return cls
        dds_name = dds_type_name(type_name)
        defs = fielddefs(self._store, type_name)
        fields = tuple(self._field(type_name, name, node) for name, node in defs)
        cls = make_idl_struct(
            dds_name.rsplit("::", 1)[1], dds_name, {f.name: f.annotation for f in fields}
        )
        self._classes[type_name] = cls
        self._fields[type_name] = fields
        self._names[type_name] = frozenset(f.name for f in fields)
        return cls

    def _field(self, owner: str, name: str, node: tuple) -> _Field:
        kind, spec = node
        if kind == Nodetype.BASE:
            base, bound = spec
            if base in INT_RANGES:
                return _Field(name, _IDL_INTS[base], int, int_converter(base), _identity)
            if base in ("float32", "float64"):
                annotation = idl.float32 if base == "float32" else idl.float64
                return _Field(name, annotation, float, float_converter(base), _identity)
            if base == "bool":
                return _Field(name, bool, bool, to_bool, _identity)
            if base == "string":
                annotation = idl.bounded_str[bound] if bound else str
                return _Field(name, annotation, str, string_converter(bound), _identity)
            raise ValueError(f"{owner}.{name}: field type {base} is not supported on DDS here")
        if kind == Nodetype.NAME:
            sub = spec
            cls = self._class(sub)
            return _Field(
                name,
                cls,
                lambda: self._default(sub),
                lambda value: self._from_dict(sub, value),
                lambda sample: self._to_dict(sub, sample),
            )
        if kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
            subnode, size = spec
            elem = self._field(owner, name, subnode)
            # cyclonedds hands byte arrays and sequences over as bytes: lists, like the rest
            to_py = _as_list if subnode[0] == Nodetype.BASE else _list_of(elem.to_py)
            if kind == Nodetype.ARRAY:
                return _Field(
                    name,
                    idl.array[elem.annotation, size],
                    lambda: [elem.default() for _ in range(size)],
                    array_converter(elem.to_idl, size, exact=True),
                    to_py,
                )
            annotation = (
                idl.sequence[elem.annotation, size] if size else idl.sequence[elem.annotation]
            )
            return _Field(
                name, annotation, list, array_converter(elem.to_idl, size, exact=False), to_py
            )
        raise ValueError(f"{owner}.{name}: unsupported field kind {kind!r}")

    def _default(self, type_name: str) -> Any:
        cls = self._classes[type_name]
        return cls(**{f.name: f.default() for f in self._fields[type_name]})

    def _from_dict(self, type_name: str, msg: Any) -> Any:
        if not isinstance(msg, Mapping):
            raise FieldError(f"expected a dict for {type_name}, got {type(msg).__name__}")
        fields = self._fields[type_name]
        known = self._names[type_name]
        if not known.issuperset(msg):
            key = next(k for k in msg if k not in known)
            raise FieldError(
                f"unknown field {key!r} of {type_name} (fields: {', '.join(sorted(known))})"
            )
        values = {}
        for f in fields:
            value = msg.get(f.name, _MISSING)
            if value is _MISSING:
                values[f.name] = f.default()
                continue
            try:
                values[f.name] = f.to_idl(value)
            except FieldError as err:
                err.path.insert(0, f.name)
                raise
        return self._classes[type_name](**values)

    def _to_dict(self, type_name: str, sample: Any) -> dict:
        return {f.name: f.to_py(getattr(sample, f.name)) for f in self._fields[type_name]}

    def from_dict(self, type_name: str, msg: Mapping) -> Any:
        """A sample (an instance of `idl_class(type_name)`) built from a nested dict (see the
        class docstring)."""
        self.idl_class(type_name)
        try:
            return self._from_dict(type_name, msg)
        except FieldError as err:
            where = "".join(p if p.startswith("[") else "." + p for p in err.path)
            raise ValueError(f"{type_name}{where}: {err.problem}") from None

    def to_dict(self, type_name: str, sample: Any) -> dict:
        """The nested dict of a sample of `type_name`, every field included."""
        self.idl_class(type_name)
        return self._to_dict(type_name, sample)

    def encode(self, type_name: str, msg: Mapping) -> bytes:
        """The CDR bytes of a message, with the 4-byte encapsulation header (CDR_LE), as a writer
        sends them (the writer appends zero bytes up to a multiple of 4): by the type's
        generated writer (`fpe_jax.node._cdr`); a message it does not take goes through the
        IDL sample, which either encodes it or raises the ValueError naming the field."""
        self.idl_class(type_name)
        try:
            return self._cdr.encode(type_name, msg)
        except Exception:  # the checks below say what is wrong, or encode what is unusual
            return self.from_dict(type_name, msg).serialize(use_version_2=False)

    def decode(self, type_name: str, data: bytes | bytearray | memoryview) -> dict:
        """The nested dict of CDR bytes (with their encapsulation header) of `type_name`: by the
        type's generated reader; bytes it does not take (big endian, malformed) through
        cyclonedds' deserializer, which decodes them or raises."""
        self.idl_class(type_name)
        try:
            return self._cdr.decode(type_name, data)
        except Exception:
            return self.to_dict(type_name, self.idl_class(type_name).deserialize(bytes(data)))


def _as_list(values: Any) -> list:
    return values if isinstance(values, list) else list(values)


def _list_of(convert: Callable[[Any], Any]) -> Callable[[Any], list]:
    return lambda values: [convert(v) for v in values]


# ---------------------------------------------------------------------------------------------
# the transport


class _Reader:
    """One DDS reader and the callbacks of every subscription on its topic."""

    def __init__(self, topic: str, type_name: str):
        self.topic = topic
        self.type_name = type_name
        self.reader: DataReader | None = None
        self.condition: ReadCondition | None = None
        self.best_effort = False
        self.callbacks: list[Callable[[dict, str, int], None]] = []


class DdsTransport:
    """The ROS 2 Transport of the live node: DDS (Cyclone DDS) without rclpy.

    typestore: rosbags Typestore of the ROS 2 message types (type names pkg/msg/Type).
    domain_id: DDS domain; None takes ROS_DOMAIN_ID from the environment (unset: 0).
    node_name: the name `ros2 node list` shows (namespace /).

    Network interfaces, discovery peers and the like come from Cyclone DDS' own configuration
    (the CYCLONEDDS_URI environment variable), as for any ROS 2 node on Cyclone DDS.
    Callbacks run in the thread that calls `spin`; `publish` may be called from any thread.
    """

    flavour = "ros2"

    def __init__(
        self, typestore: Typestore, *, domain_id: int | None = None, node_name: str = "fpe_node"
    ):
        if not isinstance(node_name, str) or not _NODE_NAME.fullmatch(node_name):
            raise ValueError(
                f"node name {node_name!r}: expected letters, digits and _, not a leading digit"
            )
        self.domain_id = resolve_domain_id(domain_id)
        self.node_name = node_name
        self.codec = IdlCodec(typestore)
        self._store = typestore
        self._lock = threading.RLock()
        # ROS 2 participants name their security enclave in USER_DATA (the default one here)
        self._participant = DomainParticipant(
            self.domain_id, qos=Qos(Policy.Userdata(b"enclave=/;"))
        )
        self._waitset = WaitSet(self._participant)
        self._wake = GuardCondition(self._participant)
        self._waitset.attach(self._wake)
        self._entities: list = [self._wake]  # deleted in reverse order by close()
        self._topics: dict[str, tuple[Topic, str]] = {}  # DDS topic -> (Topic, type name)
        self._readers: dict[str, _Reader] = {}  # ROS topic -> reader
        self._writers: dict[str, tuple[DataWriter, str]] = {}  # ROS topic -> (writer, type name)
        self._pending: dict[str, list[Callable[[dict, str, int], None]]] = {}
        self._announced: dict[str, str] = {}  # DDS topic -> first DDS type name seen on it
        self._best_effort: set[str] = set()  # DDS topics with a best-effort writer
        self._publications: BuiltinDataReader | None = None
        self._warned: dict[tuple[str, str], float] = {}
        self._closed = False
        self._spinning = threading.Event()  # set while no spin() runs
        self._spinning.set()
        self._spin_thread: int | None = None
        self._discovery = self._make_discovery_writer()

    # -- the Transport protocol --------------------------------------------------------------

    def subscribe(
        self,
        topic: str,
        type_name: str | None,
        callback: Callable[[dict, str, int], None],
    ) -> None:
        """Deliver each message on `topic` as callback(msg_dict, type_name, receive_time_ns)
        from `spin`. type_name None: the type the topic's writers announce in DDS discovery
        (the reader is created once a writer of a known type is seen). The reader is reliable
        while every writer seen on the topic is, and is replaced by a best-effort one as soon as
        a best-effort (sensor data) writer appears, which a reliable reader could not match
        (as rosbag2 adapts its subscriptions): reliable writers lose nothing, best-effort ones
        are accepted. receive_time_ns: time.time_ns() when the sample was taken."""
        topic = _ros_topic(topic)
        if not callable(callback):
            raise ValueError(f"ROS 2 topic {topic}: callback {callback!r} is not callable")
        with self._lock:
            self._check_open()
            if self._publications is None:
                self._publications = BuiltinDataReader(
                    self._participant, BuiltinTopicDcpsPublication
                )
                condition = ReadCondition(
                    self._publications, SampleState.NotRead | ViewState.Any | InstanceState.Any
                )
                self._waitset.attach(condition)
                self._entities += [self._publications, condition]
            if type_name is None:
                self._pending.setdefault(topic, []).append(callback)
            else:
                self.codec.idl_class(type_name)
                self._add_reader(topic, type_name, callback)
            self._wake.set(True)  # spin() reads discovery and resolves the type

    def encode(self, type_name: str, msg: Mapping) -> bytes:
        """The CDR bytes (with the encapsulation header) `advertise`'s publish sends for a
        message dict; raises ValueError for one that does not fit the type."""
        return self.codec.encode(type_name, msg)

    def advertise(self, topic: str, type_name: str) -> Callable[[Any], None]:
        """Return publish(msg) for `topic`: a reliable, volatile, keep-last 10 writer
        (TF: keep-last 100, transient local on `*_static`). msg: a dict, or the bytes of one
        made by `encode` (sent as they are).
        publish raises ValueError for a message that does not fit the type (unknown field,
        wrong kind of value, out of range)."""
        topic = _ros_topic(topic)
        dds_topic = dds_topic_name(topic)
        self.codec.idl_class(type_name)
        with self._lock:
            self._check_open()
            if topic in self._writers:
                writer, known = self._writers[topic]
                if known != type_name:
                    raise ValueError(
                        f"ROS 2 topic {topic}: already advertised as {known}, not {type_name}"
                    )
            else:
                qos = Qos(
                    Policy.Reliability.Reliable(max_blocking_time=duration(milliseconds=100)),
                    _durability(topic, type_name),
                    Policy.History.KeepLast(TF_DEPTH if type_name == TF_TYPE else OUTPUT_DEPTH),
                    Policy.DataRepresentation(use_cdrv0_representation=True),
                    Policy.Userdata(type_hash_user_data(self._store, type_name)),
                )
                writer = DataWriter(self._participant, self._topic(dds_topic, type_name), qos=qos)
                self._entities.append(writer)
                self._writers[topic] = (writer, type_name)
                self._announce()
        encode = self.codec.encode
        ref = writer._ref

        def publish(msg: Any) -> None:
            # the CDR bytes straight to the C writer (DataWriter.write would build an IDL
            # sample and serialize it in Python first); padded as DataWriter.write pads them
            data = msg if msg.__class__ is bytes else encode(type_name, msg)
            ret = ddspy_write(ref, data + bytes(-len(data) & 3))
            if ret < 0:
                raise DDSException(ret, f"writing a sample on ROS 2 topic {topic}")

        return publish

    def spin(self, stop: threading.Event) -> None:
        """Deliver callbacks until `stop` is set (noticed within SPIN_PERIOD_S) or the transport
        is closed. An exception raised by a callback propagates."""
        timeout = duration(seconds=SPIN_PERIOD_S)
        with self._lock:
            self._check_open()
            self._spinning.clear()
            self._spin_thread = threading.get_ident()
        try:
            while not stop.is_set() and not self._closed:
                with self._lock:
                    if self._publications is not None:
                        self._discover()
                    readers = list(self._readers.values())
                for reader in readers:
                    self._drain(reader)
                if stop.is_set() or self._closed:
                    break
                self._waitset.wait(timeout)
                self._wake.take()
        finally:
            self._spin_thread = None
            self._spinning.set()

    def close(self) -> None:
        """Delete every DDS entity of this node (idempotent). Called while another thread
        spins, it ends that spin first (waiting at most 1 s)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._wake.set(True)
        if self._spin_thread not in (None, threading.get_ident()):
            self._spinning.wait(timeout=1.0)
        with self._lock:
            self._waitset.__del__()
            for entity in reversed(self._entities):
                entity.__del__()
            self._participant.__del__()
            self._entities.clear()
            self._readers.clear()
            self._writers.clear()
            self._topics.clear()

    # -- more than the protocol --------------------------------------------------------------

    def subscriber_count(self, topic: str) -> int:
        """How many DDS readers match this node's writer on `topic` (0 if not advertised)."""
        topic = _ros_topic(topic)
        with self._lock:
            entry = self._writers.get(topic)
            return 0 if entry is None else entry[0].get_publication_matched_status().current_count

    def publisher_count(self, topic: str) -> int:
        """How many DDS writers match this node's reader on `topic` (0 if none yet)."""
        topic = _ros_topic(topic)
        with self._lock:
            entry = self._readers.get(topic)
            if entry is None:
                return 0
            return entry.reader.get_subscription_matched_status().current_count

    def topic_type(self, topic: str) -> str | None:
        """The message type this node uses on `topic` (None while a subscription with
        type_name None has not yet seen a writer)."""
        topic = _ros_topic(topic)
        with self._lock:
            if topic in self._writers:
                return self._writers[topic][1]
            if topic in self._readers:
                return self._readers[topic].type_name
            return None

    def __enter__(self) -> "DdsTransport":
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    # -- internals ---------------------------------------------------------------------------

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError("DdsTransport: used after close()")

    def _topic(self, dds_topic: str, type_name: str) -> Topic:
        entry = self._topics.get(dds_topic)
        if entry is not None:
            if entry[1] != type_name:
                raise ValueError(
                    f"ROS 2 topic /{dds_topic[3:]}: already used here with type {entry[1]}, "
                    f"not {type_name}"
                )
            return entry[0]
        topic = Topic(self._participant, dds_topic, self.codec.idl_class(type_name))
        self._entities.append(topic)
        self._topics[dds_topic] = (topic, type_name)
        return topic

    def _add_reader(
        self, topic: str, type_name: str, callback: Callable[[dict, str, int], None]
    ) -> None:
        entry = self._readers.get(topic)
        if entry is None:
            entry = self._readers[topic] = _Reader(topic, type_name)
            self._open_reader(entry, dds_topic_name(topic) in self._best_effort)
        elif entry.type_name != type_name:
            raise ValueError(
                f"ROS 2 topic {topic}: already subscribed as {entry.type_name}, not {type_name}"
            )
        entry.callbacks.append(callback)

    def _open_reader(self, entry: _Reader, best_effort: bool) -> None:
        """Give `entry` a new DDS reader (reliable or best effort), replacing its old one after
        delivering what the old one holds."""
        old = (entry.reader, entry.condition)
        if entry.reader is not None:
            self._drain(entry)
        qos = Qos(
            Policy.Reliability.BestEffort
            if best_effort
            else Policy.Reliability.Reliable(max_blocking_time=duration(milliseconds=100)),
            Policy.Durability.Volatile
            if best_effort
            else _durability(entry.topic, entry.type_name),
            Policy.History.KeepLast(TF_DEPTH if entry.type_name == TF_TYPE else INPUT_DEPTH),
            Policy.Userdata(type_hash_user_data(self._store, entry.type_name)),
        )
        topic = self._topic(dds_topic_name(entry.topic), entry.type_name)
        entry.reader = DataReader(self._participant, topic, qos=qos)
        entry.condition = ReadCondition(
            entry.reader, SampleState.NotRead | ViewState.Any | InstanceState.Any
        )
        entry.best_effort = best_effort
        self._waitset.attach(entry.condition)
        self._entities += [entry.reader, entry.condition]
        if old[0] is not None:
            self._waitset.detach(old[1])
            for entity in reversed(old):
                self._entities.remove(entity)
                entity.__del__()
        self._announce()

    def _discover(self) -> None:
        """Read DDS discovery: the type each topic's first writer announces (subscriptions
        without a type), and best-effort writers (their topic's reader turns best effort)."""
        while True:
            samples = self._publications.take(N=64)
            if not samples:
                break
            for endpoint in samples:
                name = getattr(endpoint, "topic_name", None)
                if not name or not endpoint.type_name:
                    continue  # a writer that went away
                self._announced.setdefault(name, endpoint.type_name)
                qos = endpoint.qos
                if Policy.Reliability in qos and qos[Policy.Reliability] == (
                    Policy.Reliability.BestEffort
                ):
                    self._best_effort.add(name)
        for entry in list(self._readers.values()):
            if not entry.best_effort and dds_topic_name(entry.topic) in self._best_effort:
                self._open_reader(entry, best_effort=True)
        for topic in list(self._pending):
            dds_type = self._announced.get(dds_topic_name(topic))
            if dds_type is None:
                continue
            type_name = ros_type_name(dds_type)
            if type_name is None or type_name not in self._store.fielddefs:
                self._warn(
                    topic,
                    "unknown type",
                    f"ROS 2 topic {topic}: writers announce type {dds_type}, which is not a "
                    "known ROS 2 message type here; waiting for another writer",
                )
                del self._announced[dds_topic_name(topic)]
                continue
            for callback in self._pending.pop(topic):
                self._add_reader(topic, type_name, callback)

    def _drain(self, entry: _Reader) -> None:
        """Take every waiting sample of one reader and deliver it; a sample that does not
        decode is dropped with a rate-limited warning."""
        mask = SampleState.Any | ViewState.Any | InstanceState.Any
        while not self._closed:
            taken = ddspy_take(entry.reader._ref, mask, 1)  # (CDR bytes, SampleInfo) pairs
            if isinstance(taken, int):
                raise DDSException(taken, f"taking a sample of ROS 2 topic {entry.topic}")
            if not taken:
                return
            receive_ns = time.time_ns()
            data, info = taken[0]
            if not info.valid_data:
                continue  # a writer went away (dispose / unregister), not a message
            try:
                msg = self.codec.decode(entry.type_name, data)
            except Exception as err:  # a sample that does not decode is taken all the same
                self._warn(
                    entry.topic,
                    "malformed",
                    f"ROS 2 topic {entry.topic}: dropped a sample that is not a valid "
                    f"{entry.type_name} ({type(err).__name__}: {err})",
                )
                continue
            for callback in entry.callbacks:
                callback(msg, entry.type_name, receive_ns)

    def _warn(self, topic: str, problem: str, text: str) -> None:
        now = time.monotonic()
        last = self._warned.get((topic, problem))
        if last is None or now - last >= WARN_PERIOD_S:
            self._warned[(topic, problem)] = now
            log.warning(text)

    # -- ros_discovery_info: how ROS 2 tools learn which node owns which endpoints ------------

    def _make_discovery_writer(self) -> DataWriter | None:
        type_name = "rmw_dds_common/msg/ParticipantEntitiesInfo"
        if type_name not in self._store.fielddefs:
            return None
        qos = Qos(
            Policy.Reliability.Reliable(max_blocking_time=duration(milliseconds=100)),
            Policy.Durability.TransientLocal,
            Policy.History.KeepLast(1),
            Policy.DataRepresentation(use_cdrv0_representation=True),
            Policy.Userdata(type_hash_user_data(self._store, type_name)),
        )
        writer = DataWriter(self._participant, self._topic(DISCOVERY_TOPIC, type_name), qos=qos)
        self._entities.append(writer)
        self._announce(writer)
        return writer

    def _announce(self, writer: DataWriter | None = None) -> None:
        writer = writer or getattr(self, "_discovery", None)
        if writer is None:
            return

        # a GID is the 16-byte DDS GUID, zero-padded where the store's Gid is longer (Humble: 24)
        size = self._store.fielddefs["rmw_dds_common/msg/Gid"][1][0][1][1][1]

        def gid(entity) -> dict:
            return {"data": list(entity.guid.bytes.ljust(size, b"\0"))}

        info = {
            "gid": gid(self._participant),
            "node_entities_info_seq": [
                {
                    "node_namespace": "/",
                    "node_name": self.node_name,
                    "reader_gid_seq": [gid(r.reader) for r in self._readers.values()],
                    "writer_gid_seq": [gid(w) for w, _ in self._writers.values()],
                }
            ],
        }
        writer.write(self.codec.from_dict("rmw_dds_common/msg/ParticipantEntitiesInfo", info))
