"""Reading ROS logs without ROS: plain MCAP files, rosbag2 folders and ROS 1 bags.

`open_log` returns a `Log`: an index of its topics (message type, count, log-time span) and a way
to iterate decoded messages of chosen topics. Two back ends hide behind it:

- plain `.mcap` files: the `mcap` reader, decoding with mcap_ros2's decoder factory, which builds
  CDR decoders from the schemas embedded in the file (a channel whose schema is empty -- rosbag2
  writes that when it lacks a type's definition -- is decoded with the definition `ros_msgs`
  holds for that type, if it holds one);
- rosbag2 folders (any storage plugin) and ROS 1 `.bag` files: rosbags' `AnyReader`, whose
  fallback typestore (for recordings without definitions) also has the shipped message types.

Decoded messages from both expose the same attribute names (`msg.header.stamp.sec`, ...), so the
extraction code (`pose_rows`) is shared. Every error the libraries raise on a broken file -- which
varies wildly and includes MemoryError for truncated MCAP -- becomes an `InputError`.

MCAP chunks are read with their CRCs checked (the `mcap` reader skips that by default; rosbags
checks them itself), so a damaged chunk is an error, not different poses: `corrupt_chunk` then
finds which one, and the error names the file and the chunk's byte offset. The summary section
(schemas, channels, chunk index) is checked against the footer's CRC before reading
(`damaged_summary`). A chunk or summary written without a CRC (stored as 0) cannot be checked.
"""

from __future__ import annotations

import contextlib
import dataclasses
import struct
import zlib
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from fpe_jax.errors import InputError
from fpe_jax.io import ros_msgs as rm

STAMPED_POSE_TYPES = ("geometry_msgs/PoseStamped", "geometry_msgs/PoseWithCovarianceStamped")
ODOMETRY_TYPES = ("nav_msgs/Odometry",)
TF_TYPES = ("tf2_msgs/TFMessage", "tf/tfMessage")  # the second: old ROS 1 `tf` package
POSE_TYPES = STAMPED_POSE_TYPES + ODOMETRY_TYPES + TF_TYPES
PATH_TYPES = ("nav_msgs/Path",)


@dataclasses.dataclass(frozen=True)
class TopicInfo:
    """One topic of a log. msgtype is short (`pkg/Type`); times are log (recording) times [ns]."""

    name: str
    msgtype: str
    count: int
    first_ns: int | None
    last_ns: int | None

    @property
    def rate_hz(self) -> float | None:
        """Mean message rate over the topic's span, or None with fewer than 2 distinct times."""
        if self.count < 2 or self.last_ns == self.first_ns:
            return None
        return (self.count - 1) / ((self.last_ns - self.first_ns) * 1e-9)


_MCAP_MAGIC = b"\x89MCAP0\r\n"
_OP_FOOTER, _OP_CHUNK = 0x02, 0x06


def _decompress(data: bytes, compression: str, size: int) -> bytes:
    if compression == "":
        return data
    if compression == "zstd":
        import zstandard

        return zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
    if compression == "lz4":
        import lz4.frame

        return lz4.frame.decompress(data)
    raise ValueError(f"unknown chunk compression {compression!r}")


def corrupt_chunk(path) -> str | None:
    """What is wrong with the first damaged chunk of an MCAP file, found by walking its records.

    Returns a description naming the byte offset of the first chunk that cannot be decompressed,
    has the wrong size or fails its CRC, or of a record that runs past the end of the file; None
    when every chunk is intact (or the file is not an MCAP at all).
    """
    with open(path, "rb") as f:
        if f.read(8) != _MCAP_MAGIC:
            return None
        end = f.seek(0, 2)
        offset = f.seek(8)
        while offset + 9 <= end:
            opcode, length = struct.unpack("<BQ", f.read(9))
            if offset + 9 + length > end:
                return (
                    f"the record at byte offset {offset} runs past the end of the file "
                    f"({length} bytes, {end - offset - 9} left: truncated?)"
                )
            if opcode == _OP_FOOTER:
                return None
            if opcode != _OP_CHUNK:
                offset = f.seek(length, 1)
                continue
            # chunk: start, end time (2 x u64), records size (u64), CRC (u32), compression
            # (u32-prefixed string), compressed records (u64-prefixed)
            body = f.read(length)
            size, crc, n = struct.unpack_from("<QII", body, 16)
            compression = body[32 : 32 + n].decode("utf-8", "replace")
            (n_data,) = struct.unpack_from("<Q", body, 32 + n)
            chunk = f"the chunk at byte offset {offset}"
            try:
                records = _decompress(body[40 + n : 40 + n + n_data], compression, size)
            except Exception as e:  # noqa: BLE001 -- any failure means the chunk is damaged
                return f"{chunk} cannot be decompressed ({compression}: {type(e).__name__})"
            if len(records) != size:
                return f"{chunk} holds {len(records)} bytes, its header says {size}"
            computed = zlib.crc32(records)
            if crc != 0 and computed != crc:
                return f"{chunk} fails its CRC (stored {crc:#010x}, computed {computed:#010x})"
            offset += 9 + length
    return None


def damaged_summary(path) -> str | None:
    """What the footer's CRC says is wrong with an MCAP file's summary section, or None.

    The summary holds the schemas and channels the reader decodes with and the index of the
    chunks; readers do not check its CRC, and one flipped bit in a schema can rename a field.
    None also when the file has no summary or no summary CRC (stored as 0).
    """
    with open(path, "rb") as f:
        size = f.seek(0, 2)
        footer_at = size - 8 - 29  # the footer record (29 bytes) sits before the closing magic
        if footer_at < 8:
            return None
        f.seek(footer_at)
        opcode, length, start, _, crc = struct.unpack("<BQQQI", f.read(29))
        if opcode != _OP_FOOTER or length != 20 or start == 0 or crc == 0:
            return None
        if start >= footer_at:
            return f"is corrupt: its footer points to a summary at byte {start}, past the footer"
        f.seek(start)
        # The CRC covers the summary and the footer up to (not including) the CRC field.
        computed = zlib.crc32(f.read(size - 8 - 4 - start))
    if computed != crc:
        return (
            f"is corrupt: the summary section at byte offset {start} fails its CRC "
            f"(stored {crc:#010x}, computed {computed:#010x})"
        )
    return None


@contextlib.contextmanager
def _library_errors(source: Path, fmt: str, mcap_files: tuple[Path, ...] = ()):
    """Turn whatever a reader library raises on a broken file into one clear InputError; when an
    MCAP file behind it has a damaged chunk, name that file and the chunk's byte offset."""
    try:
        yield
    except InputError:
        raise
    except Exception as e:  # the libraries raise anything, MemoryError included
        for f in mcap_files:
            try:
                found = corrupt_chunk(f)
            except Exception:  # noqa: BLE001 -- a file too broken to walk: report the original
                found = None
            if found is not None:
                raise InputError(f, f"is corrupt: {found}", "an intact copy") from e
        detail = f"{type(e).__name__}: {e}"
        if len(detail) > 200:
            detail = detail[:200] + "..."
        raise InputError(
            source, f"cannot read it as {fmt} (corrupt or truncated?): {detail}", f"a valid {fmt}"
        ) from e


class Log:
    """A ROS log opened for reading; see `open_log`."""

    def __init__(self, source: Path, fmt: str, target: Path):
        self.source = source  # what the user named
        self.format = fmt  # "mcap", "rosbag2" or "rosbag1"
        self._target = target  # the file or folder the back end opens
        self._mcap_files: tuple[Path, ...] = ()  # checked for damaged chunks when reading fails
        if fmt == "mcap":
            self._mcap_files = (target,)
        elif fmt == "rosbag2":
            self._mcap_files = tuple(sorted(target.glob("*.mcap")))
        for f in self._mcap_files:
            problem = damaged_summary(f)
            if problem is not None:
                raise InputError(f, problem, "an intact copy")
        with _library_errors(source, fmt, self._mcap_files):
            self.topics: dict[str, TopicInfo] = self._index()

    def _index(self) -> dict[str, TopicInfo]:
        types: dict[str, str] = {}
        counts: dict[str, int] = {}
        first: dict[str, int] = {}
        last: dict[str, int] = {}
        for topic, msgtype, log_ns, _ in self._raw(None, decode=False):
            types.setdefault(topic, msgtype)
            counts[topic] = counts.get(topic, 0) + 1
            first[topic] = min(first.get(topic, log_ns), log_ns)
            last[topic] = max(last.get(topic, log_ns), log_ns)
        for topic, msgtype in self._declared_topics():  # topics with no messages still count
            types.setdefault(topic, msgtype)
        return {
            t: TopicInfo(t, types[t], counts.get(t, 0), first.get(t), last.get(t))
            for t in sorted(types)
        }

    def messages(self, topics: Iterable[str]) -> Iterator[tuple[str, str, int, Any]]:
        """Decoded (topic, short msgtype, log time [ns], message) of `topics`, in log-time order."""
        with _library_errors(self.source, self.format, self._mcap_files):
            yield from self._raw(list(topics), decode=True)

    def _declared_topics(self) -> list[tuple[str, str]]:
        if self.format == "mcap":
            from mcap.reader import make_reader

            with open(self._target, "rb") as f:
                summary = make_reader(f, validate_crcs=True).get_summary()
            if summary is None:
                return []
            return [
                (c.topic, rm.short_type(summary.schemas[c.schema_id].name) if c.schema_id else "")
                for c in summary.channels.values()
            ]
        with self._anyreader() as reader:
            return [(c.topic, rm.short_type(c.msgtype)) for c in reader.connections]

    def _raw(self, topics, decode: bool) -> Iterator[tuple[str, str, int, Any]]:
        if self.format == "mcap":
            from mcap.reader import make_reader
            from mcap_ros2.decoder import DecoderFactory

            factory, decoders = DecoderFactory(), {}
            with open(self._target, "rb") as f:
                reader = make_reader(f, validate_crcs=True)
                for schema, channel, message in reader.iter_messages(topics):
                    name = rm.short_type(schema.name) if schema is not None else ""
                    msg = None
                    if decode:
                        if channel.id not in decoders:
                            decoders[channel.id] = factory.decoder_for(
                                channel.message_encoding, _with_definition(schema)
                            )
                        if decoders[channel.id] is None:  # e.g. protobuf, JSON or ROS 1 MCAP
                            raise InputError(
                                self.source,
                                f"topic {channel.topic!r} is encoded as "
                                f"{channel.message_encoding!r} with schema {name or 'none'}",
                                "ROS 2 CDR messages with a ros2msg schema",
                            )
                        msg = decoders[channel.id](message.data)
                    yield channel.topic, name, message.log_time, msg
            return
        with self._anyreader() as reader:
            conns = [c for c in reader.connections if topics is None or c.topic in topics]
            for conn, log_ns, raw in reader.messages(connections=conns):
                msg = reader.deserialize(raw, conn.msgtype) if decode else None
                yield conn.topic, rm.short_type(conn.msgtype), log_ns, msg

    def _anyreader(self):
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        # Fallback types for (old) recordings that embed no message definitions.
        store = get_typestore(
            Stores.ROS1_NOETIC if self.format == "rosbag1" else Stores.ROS2_HUMBLE
        )
        shipped = {}
        for name, fields in rm.shipped_definitions().items():
            shipped.update(get_types_from_msg(fields, rm.full_type(name)))
        store.register(shipped)
        return AnyReader([self._target], default_typestore=store)


def _with_definition(schema):
    """`schema`, or a copy holding our definition of its type when the file's is empty."""
    if schema is None or schema.data.strip() or not rm.known_type(schema.name):
        return schema
    from mcap.records import Schema

    text = rm.definition(schema.name).encode()
    return Schema(id=schema.id, name=schema.name, encoding="ros2msg", data=text)


def open_log(path) -> Log:
    """Open a ROS log: `.mcap`, `.bag`, a rosbag2 folder, or its `metadata.yaml` / storage file.

    A `.mcap` file is read on its own even inside a rosbag2 folder (it is self-contained); a
    `metadata.yaml` or `.db3` stands for its folder. Raises InputError if it cannot be read.
    """
    p = Path(path)
    if not p.exists():
        raise InputError(p, "does not exist")
    if p.is_dir():
        if not (p / "metadata.yaml").is_file():
            raise InputError(p, "is a folder without metadata.yaml", "a rosbag2 recording folder")
        return Log(p, "rosbag2", p)
    if p.stat().st_size == 0:
        raise InputError(p, "is empty")
    if p.name == "metadata.yaml" or (p.suffix == ".db3" and (p.parent / "metadata.yaml").is_file()):
        return Log(p, "rosbag2", p.parent)
    if p.suffix == ".mcap":
        return Log(p, "mcap", p)
    if p.suffix == ".bag":
        return Log(p, "rosbag1", p)
    raise InputError(
        p, f"unknown log format {p.suffix or '(no suffix)'!r}", "a .mcap, .bag or rosbag2 folder"
    )


def is_log_path(path) -> bool:
    """Whether `path` names a ROS log (rather than a CSV table), judged by its name only."""
    p = Path(path)
    return p.is_dir() or p.name == "metadata.yaml" or p.suffix in (".mcap", ".bag", ".db3")


def _same_frame(a: str, b: str) -> bool:
    # ROS 1 frames often carry a leading slash ("/map"); tf2 dropped it.
    return a.lstrip("/") == b.lstrip("/")


def pose_rows(msgtype: str, msg: Any, log_ns: int, tf_pair: tuple[str, str]) -> list[tuple]:
    """Rows (stamp_ns, log_ns, x, y, qx, qy, qz, qw, v) of one decoded message.

    v [m/s] is the planar speed hypot(linear.x, linear.y) of an Odometry twist, NaN otherwise.
    A TFMessage gives one row per transform from tf_pair[0] to tf_pair[1] (often none).
    """
    if msgtype in TF_TYPES:
        out = []
        for tr in msg.transforms:
            if _same_frame(tr.header.frame_id, tf_pair[0]) and _same_frame(
                tr.child_frame_id, tf_pair[1]
            ):
                out.append(
                    _row(tr.header.stamp, log_ns, tr.transform.translation, tr.transform.rotation)
                )
        return out
    if msgtype == "geometry_msgs/PoseStamped":
        pose, v = msg.pose, np.nan
    elif msgtype == "geometry_msgs/PoseWithCovarianceStamped":
        pose, v = msg.pose.pose, np.nan
    elif msgtype == "nav_msgs/Odometry":
        pose = msg.pose.pose
        v = float(np.hypot(msg.twist.twist.linear.x, msg.twist.twist.linear.y))
    else:
        raise ValueError(f"pose_rows: unsupported type {msgtype}")
    return [_row(msg.header.stamp, log_ns, pose.position, pose.orientation, v)]


def _row(stamp, log_ns: int, p, q, v: float = np.nan) -> tuple:
    stamp_ns = int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
    return (stamp_ns, int(log_ns), p.x, p.y, q.x, q.y, q.z, q.w, v)
