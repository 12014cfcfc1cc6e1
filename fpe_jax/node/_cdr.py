"""Message bytes of nested dicts, by code generated per type from the message definitions.

ROS 2 samples are plain CDR (XCDR1, little endian, final structs): the fields in definition order,
each primitive aligned to its size (up to 8) from the start of the payload, strings as uint32
length (with the NUL) + UTF-8 + NUL, sequences as uint32 count + elements, fixed arrays as their
elements. ROS 1 serializes the same way without any padding, strings without their NUL, and
times as {secs, nsecs}.

`CdrCodec` turns a rosbags `Typestore`'s field definitions into one writer (dict -> bytes) and
one reader (bytes -> dict) per ROS 2 type, `Ros1Writer` into one writer per ROS 1 type: Python
source with every nested type inlined and each run of primitives packed by one `struct.Struct`,
compiled once. They are the node's hot path: a 10-pose nav_msgs/Path encodes in a few tens of
microseconds, where cyclonedds' field-by-field serializer takes about ten times as long and
genpy's message objects about three times.

Values are checked as `IdlCodec` (fpe_jax.node._dds) checks them: the checks below are the
converters of both. A generated writer takes exactly what they take; for anything else it
raises, and the caller falls back to the field-by-field conversion, whose error names the field.

JAX-free and free of cyclonedds and genpy: the rules here are the wire formats.
"""

import numbers
import operator
import re
import struct
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
from rosbags.interfaces import Nodetype

ENCAPSULATION = b"\x00\x01\x00\x00"  # CDR_LE, no options
PLACEHOLDER = "structure_needs_at_least_one_member"  # rosidl's member of an empty message

# ---- value checks (shared with fpe_jax.node._dds.IdlCodec) ------------------------------------


class FieldError(ValueError):
    """A bad value deep in a message; `path` grows as the error passes each enclosing field."""

    def __init__(self, problem: str):
        super().__init__(problem)
        self.problem = problem
        self.path: list[str] = []


INT_RANGES = {
    "int8": (-(2**7), 2**7 - 1),
    "uint8": (0, 2**8 - 1),
    "byte": (0, 2**8 - 1),
    "char": (0, 2**8 - 1),
    "int16": (-(2**15), 2**15 - 1),
    "uint16": (0, 2**16 - 1),
    "int32": (-(2**31), 2**31 - 1),
    "uint32": (0, 2**32 - 1),
    "int64": (-(2**63), 2**63 - 1),
    "uint64": (0, 2**64 - 1),
}
# struct codes of the primitive types; ROS 2 maps `char` to uint8 and `byte` to octet (rosidl)
CODES = {"bool": "?", "float32": "f", "float64": "d"} | {
    k: c for k, c in zip(INT_RANGES, "bBBBhHiIqQ", strict=True)
}


def int_converter(kind: str) -> Callable[[Any], int]:
    lo, hi = INT_RANGES[kind]

    def convert(value: Any) -> int:
        if type(value) is int and lo <= value <= hi:  # the common case, without ABC checks
            return value
        if isinstance(value, bool | float | str) or not isinstance(value, numbers.Integral):
            raise FieldError(f"expected an integer ({kind}), got {value!r}")
        value = operator.index(value)
        if not lo <= value <= hi:
            raise FieldError(f"{value} is out of the range of {kind} [{lo}, {hi}]")
        return value

    return convert


def float_converter(kind: str) -> Callable[[Any], float]:
    def convert(value: Any) -> float:
        if type(value) is float:  # the common case, without ABC checks
            return value
        if isinstance(value, bool | str) or not isinstance(value, numbers.Real):
            raise FieldError(f"expected a number ({kind}), got {value!r}")
        return float(value)

    return convert


def to_bool(value: Any) -> bool:
    if isinstance(value, bool | np.bool_):
        return bool(value)
    raise FieldError(f"expected a bool, got {value!r}")


def string_converter(bound: int) -> Callable[[Any], str]:
    def convert(value: Any) -> str:
        if not isinstance(value, str):
            raise FieldError(f"expected a string, got {value!r}")
        if bound and len(value.encode()) > bound:
            raise FieldError(f"string of {len(value.encode())} bytes exceeds its bound {bound}")
        return value

    return convert


def array_converter(convert: Callable[[Any], Any], size: int, *, exact: bool):
    """A fixed array (`exact`: `size` elements) or sequence (at most `size`, 0: unbounded) of
    values each passed through `convert`, as a list."""

    def to_list(values: Any) -> list:
        if isinstance(values, str | Mapping) or not hasattr(values, "__len__"):
            raise FieldError(f"expected a list, got {type(values).__name__}")
        n = len(values)
        if exact and n != size:
            raise FieldError(f"expected {size} elements, got {n}")
        if not exact and size and n > size:
            raise FieldError(f"{n} elements exceed the sequence bound {size}")
        out = []
        for i, value in enumerate(values):
            try:
                out.append(convert(value))
            except FieldError as err:
                err.path.insert(0, f"[{i}]")
                raise
        return out

    return to_list


def converter(base: str, bound: int = 0) -> Callable[[Any], Any]:
    """The check and conversion of one value of a primitive ROS type (`bound`: of a string)."""
    if base in INT_RANGES:
        return int_converter(base)
    if base in ("float32", "float64"):
        return float_converter(base)
    if base == "bool":
        return to_bool
    if base == "string":
        return string_converter(bound)
    raise ValueError(f"field type {base} is not supported here")


def fielddefs(typestore, type_name: str, placeholder: bool = True) -> list:
    """The (name, node) fields of a type in a rosbags store; with `placeholder` an empty
    message has rosidl's one-byte member, as ROS 2 sends it, else none (ROS 1 sends nothing)."""
    try:
        _, fields = typestore.fielddefs[type_name]
    except KeyError:
        raise ValueError(
            f"message type {type_name!r} is not in the type store "
            "(register its definition, or check the spelling pkg/msg/Type)"
        ) from None
    fields = [f for f in fields if f[0] != PLACEHOLDER]  # rosbags' stores hold it for some
    if fields or not placeholder:
        return fields
    return [(PLACEHOLDER, (Nodetype.BASE, ("uint8", 0)))]


# ---- the generated code ----------------------------------------------------------------------


class _Unchecked(Exception):
    """Raised by generated code for a value it does not take (the caller's slow path explains)."""


def _mapping(value: Any) -> Any:
    if isinstance(value, Mapping):
        return value
    raise _Unchecked


def _sequence(value: Any) -> Any:
    if isinstance(value, str | Mapping) or not hasattr(value, "__len__"):
        raise _Unchecked
    return value


def _values(kind: type, convert: Callable[[Any], Any]) -> Callable[[Any], list]:
    """Elements of a primitive array as a list of `kind` (Python values taken as they are)."""

    def values(seq: Any) -> Any:
        if seq.__class__ is list or seq.__class__ is tuple:
            for v in seq:
                if v.__class__ is not kind:
                    break
            else:
                return seq
        if isinstance(seq, bytes | bytearray) and kind is int:
            return seq
        return [convert(v) for v in _sequence(seq)]

    return values


_KINDS = {"?": bool, "f": float, "d": float}
_PADS = tuple(bytes(n) for n in range(8))
_MISSING = object()
_EMPTY: Mapping = {}  # a missing nested message: every field zero (never written to)


class _Source:
    """Lines of one generated function and the constants its code names."""

    def __init__(self, stem: str):
        self.lines: list[str] = []
        self.consts: dict[str, Any] = {"_Z": _PADS, "_U": _Unchecked, "_M": _MISSING}
        self.n = 0
        self.stem = stem

    def var(self, stem: str = "v") -> str:
        self.n += 1
        return f"{stem}{self.n}"

    def const(self, value: Any, stem: str = "c") -> str:
        name = self.var(f"_{stem}")
        self.consts[name] = value
        return name

    def emit(self, indent: int, line: str) -> None:
        self.lines.append("    " * indent + line)

    def compile(self, header: str, footer: str, name: str) -> Callable:
        text = "\n".join([header, *self.lines, footer])
        scope = dict(self.consts)
        exec(compile(text, f"<cdr {self.stem}>", "exec"), scope)  # noqa: S102 - our own source
        return scope[name]


# ROS 1 spells times {secs, nsecs} (time: unsigned, duration: signed), where the type stores
# hold builtin_interfaces' {sec, nanosec}; its `byte` is a signed byte (genpy's int8)
_ROS1_TIMES = {
    "builtin_interfaces/msg/Time": [
        ("secs", (Nodetype.BASE, ("uint32", 0))),
        ("nsecs", (Nodetype.BASE, ("uint32", 0))),
    ],
    "builtin_interfaces/msg/Duration": [
        ("secs", (Nodetype.BASE, ("int32", 0))),
        ("nsecs", (Nodetype.BASE, ("int32", 0))),
    ],
}


class _WriterGen:
    """Emits the writer of one type: appends to the bytearray `b` from the dict `d0`.

    `known`, `off`: what the generator knows of the write position statically (position
    = off mod known); `fmt`, `vals`: the run of primitives not yet packed. `ros1`: ROS 1's
    serialization instead of CDR (no padding, strings without their NUL, times as above)."""

    def __init__(self, typestore, type_name: str, ros1: bool = False):
        self.store = typestore
        self.ros1 = ros1
        self.src = _Source(type_name)
        self.known, self.off = 8, 0
        self.fmt, self.vals = "", []
        self.ind = 1
        self.message("d0", type_name)
        self.flush()
        self.fn = self.src.compile("def write(d0, b):", "    return b", "write")

    def line(self, text: str) -> None:
        self.src.emit(self.ind, text)

    def flush(self) -> None:
        if self.vals:
            s = self.src.const(struct.Struct("<" + self.fmt), "s")
            self.line(f"b += {s}.pack({', '.join(self.vals)})")
        self.fmt, self.vals = "", []

    def align(self, size: int) -> str:
        """Padding before a primitive of `size` bytes: static ('x' codes) when the position is
        known well enough, else a dynamic pad emitted now (ROS 1: none)."""
        if self.ros1:
            return ""
        if size > self.known:
            self.flush()
            self.line(f"b += _Z[-len(b) & {size - 1}]")
            self.known, self.off = size, 0
        pad = -self.off % size
        self.off = (self.off + pad + size) % self.known
        return "x" * pad

    def prim(self, code: str, expr: str) -> None:
        pad = self.align(struct.calcsize(code))  # may flush the run so far: before reading fmt
        self.fmt += pad + code
        self.vals.append(expr)

    def base(self, base: str) -> str:
        """The primitive type `base` is on this wire."""
        return "int8" if self.ros1 and base == "byte" else base

    def checked(self, expr: str, base: str, bound: int = 0) -> str:
        """A variable holding `expr`, checked and converted as a value of `base`."""
        base = self.base(base)
        v = self.src.var()
        self.line(f"{v} = {expr}")
        kind = {"?": "bool", "f": "float", "d": "float"}.get(CODES.get(base), "int")
        if base == "string":
            kind = "str"
        conv = self.src.const(converter(base, bound), "k")
        self.line(f"if {v}.__class__ is not {kind}: {v} = {conv}({v})")
        return v

    def string(self, v: str, bound: int) -> None:
        e = self.src.var("e")
        self.line(f"{e} = {v}.encode()")
        if bound:
            self.line(f"if len({e}) > {bound}: raise _U")
        self.prim("I", f"len({e})" if self.ros1 else f"len({e}) + 1")
        self.flush()
        self.line(f"b += {e}")
        if not self.ros1:
            self.line("b.append(0)")
        self.known, self.off = 1, 0

    def message(self, d: str, type_name: str) -> None:
        """The fields of `type_name` read from the mapping variable `d`."""
        fields = (self.ros1 and _ROS1_TIMES.get(type_name)) or fielddefs(
            self.store, type_name, placeholder=not self.ros1
        )
        names = self.src.const(frozenset(name for name, _ in fields), "n")
        self.line(f"if {d}.__class__ is not dict: {d} = _m({d})")
        self.src.consts["_m"] = _mapping
        self.line(f"if not {d}.keys() <= {names}: raise _U")
        for name, node in fields:
            self.field(d, name, node)

    def field(self, d: str, name: str, node: tuple) -> None:
        kind, spec = node
        if kind == Nodetype.BASE:
            base, bound = spec
            if base == "string":
                self.string(self.checked(f"{d}.get({name!r}, '')", base, bound), bound)
            else:
                zero = {"bool": "False", "float32": "0.0", "float64": "0.0"}.get(base, "0")
                v = self.checked(f"{d}.get({name!r}, {zero})", base)
                self.prim(CODES[self.base(base)], v)
        elif kind == Nodetype.NAME:
            sub = self.src.var("d")
            self.line(f"{sub} = {d}.get({name!r}, _E)")
            self.src.consts["_E"] = _EMPTY
            self.message(sub, spec)
        else:
            self.array(f"{d}.get({name!r}, _M)", kind == Nodetype.ARRAY, *spec)

    def array(self, expr: str, fixed: bool, elem: tuple, size: int) -> None:
        seq = self.src.var("q")
        self.line(f"{seq} = {expr}")
        if fixed:
            zero = self.src.const(tuple(_zero(self.store, elem) for _ in range(size)), "z")
            self.line(f"if {seq} is _M: {seq} = {zero}")
        else:
            self.line(f"if {seq} is _M: {seq} = ()")
        ekind, espec = elem
        if ekind == Nodetype.BASE and espec[0] != "string":
            code = CODES[self.base(espec[0])]
            values = _values(_KINDS.get(code, int), converter(self.base(espec[0])))
            self.line(f"{seq} = {self.src.const(values, 'a')}({seq})")
        else:
            self.line(f"if {seq}.__class__ is not list: {seq} = _q({seq})")
            self.src.consts["_q"] = _sequence
        n = self.src.var("n")
        self.line(f"{n} = len({seq})")
        if fixed:
            self.line(f"if {n} != {size}: raise _U")
        elif size:
            self.line(f"if {n} > {size}: raise _U")
        if not fixed:
            self.prim("I", n)
        if ekind == Nodetype.BASE and espec[0] != "string":
            code = CODES[self.base(espec[0])]
            width = struct.calcsize(code)
            self.flush()
            if self.ros1:  # no padding
                pass
            elif width > self.known:  # the first element's padding (none without elements)
                self.line(f"if {n}: b += _Z[-len(b) & {width - 1}]")
            elif -self.off % width:
                self.line(f"if {n}: b += _Z[{-self.off % width}]")
            if code == "B":
                self.line(f"b += bytes({seq})")
            elif fixed:
                packer = self.src.const(struct.Struct(f"<{size}{code}"), "s")
                self.line(f"b += {packer}.pack(*{seq})")
            else:
                self.src.consts["_pack"] = struct.pack
                self.line(f"b += _pack('<%d{code}' % {n}, *{seq})")
            self.known, self.off = 1, 0
            return
        self.flush()
        e = self.src.var("e")
        self.line(f"for {e} in {seq}:")
        self.ind += 1
        self.known, self.off = 1, 0
        if ekind == Nodetype.BASE:
            self.string(self.checked(e, "string", espec[1]), espec[1])
        else:
            self.message(e, espec)
        self.flush()
        self.ind -= 1
        self.known, self.off = 1, 0


def _zero(typestore, node: tuple) -> Any:
    """The zero value of one field node as the writer takes it (a nested message: {})."""
    kind, spec = node
    if kind == Nodetype.BASE:
        return {"bool": False, "float32": 0.0, "float64": 0.0, "string": ""}.get(spec[0], 0)
    if kind == Nodetype.NAME:
        return _EMPTY
    if kind == Nodetype.ARRAY:
        return tuple(_zero(typestore, spec[0]) for _ in range(spec[1]))
    return ()


class _ReaderGen:
    """Emits the reader of one type: the dict of the payload `m` (a memoryview after the
    encapsulation) from position `p`."""

    def __init__(self, typestore, type_name: str):
        self.store = typestore
        self.src = _Source(type_name)
        self.known, self.off = 8, 0
        self.fmt, self.vals = "", []
        self.ind = 1
        self.line("L = len(m)")
        out = self.message(type_name)
        self.flush()
        self.fn = self.src.compile("def read(m, p):", f"    return {out}, p", "read")

    line = _WriterGen.line

    def flush(self) -> None:
        if self.vals:
            packer = struct.Struct("<" + self.fmt)
            s = self.src.const(packer, "s")
            self.line(f"{', '.join(self.vals)}, = {s}.unpack_from(m, p)")
            self.line(f"p += {packer.size}")
        self.fmt, self.vals = "", []

    def align(self, size: int) -> str:
        if size > self.known:
            self.flush()
            self.line(f"p += -p & {size - 1}")
            self.known, self.off = size, 0
        pad = -self.off % size
        self.off = (self.off + pad + size) % self.known
        return "x" * pad

    def prim(self, code: str) -> str:
        v = self.src.var()
        pad = self.align(struct.calcsize(code))
        self.fmt += pad + code
        self.vals.append(v)
        return v

    def string(self) -> str:
        n = self.prim("I")
        self.flush()
        v = self.src.var("s")
        self.line(f"if {n} < 1 or p + {n} > L: raise _U")
        self.line(f"{v} = str(m[p:p + {n} - 1], 'utf-8')")
        self.line(f"p += {n}")
        self.known, self.off = 1, 0
        return v

    def message(self, type_name: str) -> str:
        """Reads the fields of `type_name`; returns the variable of its dict."""
        items = []
        for name, node in fielddefs(self.store, type_name):
            items.append(f"{name!r}: {self.field(node)}")
        self.flush()
        d = self.src.var("d")
        self.line(f"{d} = {{{', '.join(items)}}}")
        return d

    def field(self, node: tuple) -> str:
        kind, spec = node
        if kind == Nodetype.BASE:
            return self.string() if spec[0] == "string" else self.prim(CODES[spec[0]])
        if kind == Nodetype.NAME:
            return self.message(spec)
        elem, size = spec
        if kind == Nodetype.ARRAY:
            self.flush()
            n = str(size)
        else:
            n = self.prim("I")
            self.flush()
        out = self.src.var("q")
        ekind, espec = elem
        if ekind == Nodetype.BASE and espec[0] != "string":
            code = CODES[espec[0]]
            width = struct.calcsize(code)
            if width > 1:
                if width > self.known:
                    self.line(f"if {n}: p += -p & {width - 1}")
                elif -self.off % width:
                    self.line(f"if {n}: p += {-self.off % width}")
            if code == "B":
                self.line(f"if p + {n} > L: raise _U")
                self.line(f"{out} = list(m[p:p + {n}])")
                self.line(f"p += {n}")
            else:
                self.src.consts["_unpack"] = struct.unpack_from
                self.line(f"{out} = list(_unpack('<%d{code}' % {n}, m, p))")
                self.line(f"p += {width} * {n}")
            self.known, self.off = 1, 0
            return out
        self.line(f"{out} = []")
        self.line(f"for _ in range({n}):")
        self.ind += 1
        self.known, self.off = 1, 0
        v = self.string() if ekind == Nodetype.BASE else self.message(espec)
        self.flush()
        self.line(f"{out}.append({v})")
        self.ind -= 1
        self.known, self.off = 1, 0
        return out


class Ros1Writer:
    """Generated ROS 1 serializers of the message types of a rosbags ROS 1 `Typestore`:
    `encode(type_name, msg)` is the ROS 1 bytes of a nested dict (times {secs, nsecs}, missing
    fields zero) as genpy serializes the same message; raises (any exception) for a message the
    checks above do not take."""

    def __init__(self, typestore):
        self._store = typestore
        self._writers: dict[str, Callable] = {}

    def writer(self, type_name: str) -> Callable:
        w = self._writers.get(type_name)
        if w is None:
            w = self._writers[type_name] = _WriterGen(self._store, type_name, ros1=True).fn
        return w

    def encode(self, type_name: str, msg: Mapping) -> bytes:
        return bytes(self.writer(type_name)(msg, bytearray()))


class CdrCodec:
    """Generated CDR writers and readers of the ROS 2 message types of a rosbags `Typestore`.

    `encode(type_name, msg)`: the CDR bytes (with the encapsulation header) of a nested dict,
    missing fields zero; raises (any exception) for a message the checks above do not take.
    `decode(type_name, data)`: the nested dict of CDR_LE bytes, every field, arrays as lists;
    raises (any exception) for bytes that do not hold a message of the type.
    """

    def __init__(self, typestore):
        self._store = typestore
        self._writers: dict[str, Callable] = {}
        self._readers: dict[str, Callable] = {}

    def writer(self, type_name: str) -> Callable:
        w = self._writers.get(type_name)
        if w is None:
            w = self._writers[type_name] = _WriterGen(self._store, type_name).fn
        return w

    def reader(self, type_name: str) -> Callable:
        r = self._readers.get(type_name)
        if r is None:
            r = self._readers[type_name] = _ReaderGen(self._store, type_name).fn
        return r

    def encode(self, type_name: str, msg: Mapping) -> bytes:
        return ENCAPSULATION + self.writer(type_name)(msg, bytearray())

    def decode(self, type_name: str, data: bytes | bytearray | memoryview) -> dict:
        view = memoryview(data)
        if view[:2] != b"\x00\x01":
            raise _Unchecked  # not CDR_LE: for the caller's general decoder
        return self.reader(type_name)(view[4:], 0)[0]


# ---- templates: the bytes of messages that differ only in a few numbers ----------------------


def _get(msg: Any, path: tuple) -> Any:
    for key in path:
        msg = msg[key]
    return msg


_PROBE_DTYPES = {"d": np.dtype("<f8"), "I": np.dtype("<u4"), "i": np.dtype("<i4")}
_STRING_CODE = re.compile(r"[1-9][0-9]*s")


def _probe_values(rng: np.random.Generator, code: str, n: int) -> tuple[list, list[bytes]]:
    """n distinct values of a leaf code, whose bytes are unlikely anywhere else in a message:
    (the values for the message dict, their bytes as packed)."""
    if code in _PROBE_DTYPES:
        vals = rng.uniform(1.0, 2.0, n) if code == "d" else rng.integers(2**24, 2**31, n)
        vals = vals.astype(_PROBE_DTYPES[code])
        return vals.tolist(), [v.tobytes() for v in vals]
    if not _STRING_CODE.fullmatch(code):
        raise ValueError(f"struct code {code!r} is not d, I, i or <length>s")
    letters = rng.integers(ord("a"), ord("z") + 1, (n, int(code[:-1]))).astype(np.uint8)
    raw = [row.tobytes() for row in letters]
    return [r.decode() for r in raw], raw


class Template:
    """Messages of one type that differ only in some leaves (stamps, coordinates, strings of a
    fixed length): the message is encoded once by the type's writer, and each new one is those
    bytes with the leaves written in by one `struct.Struct.pack` (the bytes between them passed
    as they are). Works for any wire format whose fixed-size primitives are their little-endian
    bytes and whose strings are their UTF-8 bytes after a length (CDR, ROS 1), as long as the
    leaves keep the message's length (never sequence lengths).

    Args:
        encode: msg dict -> its bytes (the transport's writer).
        msg: the message with every other field as it is to be sent.
        groups: {group name: (struct code, [leaf path, ...])}: code "d" (float64), "I"
            (uint32), "i" (int32) or "<n>s" (a string of n UTF-8 bytes, filled with bytes); a
            path is the keys and list indices from the message down to one field, e.g.
            ("header", "stamp", "sec"); `fill` takes each group's values in path order.

    Each leaf is found by encoding the message with every leaf set to a distinct probe value and
    locating its bytes; the template is then checked to reproduce both encodings byte for byte,
    so a leaf it cannot place raises ValueError here instead of sending wrong bytes later.
    """

    def __init__(self, encode: Callable[[Mapping], bytes], msg: Mapping,
                 groups: Mapping[str, tuple[str, list[tuple]]]):  # fmt: skip
        rng = np.random.default_rng(0)
        probe, probes, patterns = _copy(msg), {}, {}
        for name, (code, paths) in groups.items():
            try:
                probes[name], patterns[name] = _probe_values(rng, code, len(paths))
            except ValueError as e:
                raise ValueError(f"Template: group {name!r}: {e}") from None
            for path, v in zip(paths, probes[name], strict=True):
                _set(probe, path, v)
        base_bytes, probe_bytes = bytes(encode(msg)), bytes(encode(probe))
        if len(base_bytes) != len(probe_bytes):
            raise ValueError("Template: a leaf changes the message's length")
        leaves = []  # (offset, code, group, index in the group)
        for name, (code, paths) in groups.items():
            for k, (path, pattern) in enumerate(zip(paths, patterns[name])):
                at = probe_bytes.find(pattern)
                if at < 0 or probe_bytes.find(pattern, at + 1) >= 0:
                    raise ValueError(f"Template: cannot place the leaf {path} of group {name!r}")
                leaves.append((at, code, name, k))
        leaves.sort()
        fmt, args, pos = ["<"], [], 0
        self._slots: dict[str, list[int]] = {name: [0] * len(g[1]) for name, g in groups.items()}
        # a string group's byte length: struct would pad or cut other lengths silently
        self._lengths = {n: int(g[0][:-1]) for n, g in groups.items() if g[0].endswith("s")}
        for at, code, name, k in leaves:
            if at < pos:
                raise ValueError(f"Template: leaves of group {name!r} overlap")
            if at > pos:
                fmt.append(f"{at - pos}s")
                args.append(base_bytes[pos:at])
            fmt.append(code)
            self._slots[name][k] = len(args)
            args.append(0)
            pos = at + struct.calcsize(code)
        if pos < len(base_bytes):
            fmt.append(f"{len(base_bytes) - pos}s")
            args.append(base_bytes[pos:])
        self._struct = struct.Struct("".join(fmt))
        self._args = args
        filled = self.fill(**{n: [p if n in self._lengths else v for v, p in
                                  zip(probes[n], patterns[n])] for n in groups})  # fmt: skip
        base = {n: [_get(msg, p) for p in paths] for n, (_, paths) in groups.items()}
        base = {n: [v.encode() for v in b] if n in self._lengths else b for n, b in base.items()}
        if filled != probe_bytes or self.fill(**base) != base_bytes:
            raise ValueError("Template: the leaves do not account for the message's bytes")

    def fill(self, **values: Any) -> bytes:
        """One message's bytes: each group's values (Python numbers; a string group's bytes)
        in path order; raises struct.error for a number its field cannot hold, ValueError for
        a string of another length."""
        args = self._args.copy()
        for name, slots in self._slots.items():
            for slot, v in zip(slots, values[name], strict=True):
                args[slot] = v
        for name, n in self._lengths.items():
            if any(len(v) != n for v in values[name]):
                raise ValueError(f"Template: group {name!r} takes strings of {n} bytes")
        return self._struct.pack(*args)


def _copy(msg: Any) -> Any:
    """A copy of nested dicts and lists (leaves shared)."""
    if isinstance(msg, Mapping):
        return {k: _copy(v) for k, v in msg.items()}
    if isinstance(msg, list | tuple):
        return [_copy(v) for v in msg]
    return msg


def _set(msg: Any, path: tuple, value: Any) -> None:
    _get(msg, path[:-1])[path[-1]] = value
