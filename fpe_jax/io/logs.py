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
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from fpe_jax.errors import InputError
from fpe_jax.io import ros_msgs as rm

STAMPED_POSE_TYPES = ("geometry_msgs/PoseStamped", "geometry_msgs/PoseWithCovarianceStamped")
ODOMETRY_TYPES = ("nav_msgs/Odometry",)
TF_TYPES = ("tf2_msgs/TFMessage", "tf/tfMessage")  # the second: old ROS 1 `tf` package
POSE_TYPES = STAMPED_POSE_TYPES + ODOMETRY_TYPES + TF_TYPES
PATH_TYPES = ("nav_msgs/Path",)
DETECTION_TYPES = (  # AprilTag detections (`fpe_jax.io.apriltag`)
    "apriltag_ros/AprilTagDetectionArray",
    "apriltags2_ros/AprilTagDetectionArray",
    "apriltag_msgs/AprilTagDetectionArray",
)


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


class PoseRows(NamedTuple):
    """A pose-like topic's poses (`Log.pose_tables`): stamp_ns (N,) int64 header stamps,
    log_ns (N,) int64 recording times, values (N, 7) float64: x, y [m], the orientation
    quaternion qx, qy, qz, qw, and v [m/s], an Odometry twist's planar speed (NaN otherwise)."""

    stamp_ns: np.ndarray
    log_ns: np.ndarray
    values: np.ndarray

    @classmethod
    def of(cls, rows: Sequence[tuple]) -> PoseRows:
        """From `pose_rows` rows (stamp_ns, log_ns, x, y, qx, qy, qz, qw, v)."""
        return cls(
            np.array([r[0] for r in rows], np.int64),
            np.array([r[1] for r in rows], np.int64),
            np.array([r[2:] for r in rows], np.float64).reshape(len(rows), 7),
        )

    @classmethod
    def joined(cls, parts: Sequence[PoseRows]) -> PoseRows:
        if not parts:
            return cls(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 7)))
        return cls(*(np.concatenate(a) for a in zip(*parts)))

    def take(self, rows: np.ndarray) -> PoseRows:
        return PoseRows(self.stamp_ns[rows], self.log_ns[rows], self.values[rows])


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


def _chunk_records(body: bytes, chunk: str) -> bytes:
    """The records in a chunk's body (start, end time 2 x u64, records size u64, CRC u32,
    u32-prefixed compression, u64-prefixed records); ValueError naming `chunk` if damaged."""
    size, crc, n = struct.unpack_from("<QII", body, 16)
    compression = body[32 : 32 + n].decode("utf-8", "replace")
    (n_data,) = struct.unpack_from("<Q", body, 32 + n)
    try:
        records = _decompress(body[40 + n : 40 + n + n_data], compression, size)
    except Exception as e:  # noqa: BLE001 -- any failure means the chunk is damaged
        why = f"{compression}: {type(e).__name__}"
        raise ValueError(f"{chunk} cannot be decompressed ({why})") from e
    if len(records) != size:
        raise ValueError(f"{chunk} holds {len(records)} bytes, its header says {size}")
    computed = zlib.crc32(records)
    if crc != 0 and computed != crc:
        raise ValueError(f"{chunk} fails its CRC (stored {crc:#010x}, computed {computed:#010x})")
    return records


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
            try:
                _chunk_records(f.read(length), f"the chunk at byte offset {offset}")
            except ValueError as e:
                return str(e)
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


_OP_MESSAGE, _OP_DATA_END = 0x05, 0x0F
_RECORD = struct.Struct("<BQ")  # opcode, length
_MESSAGE = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time


def _records_messages(buf: bytes, channels, with_data: bool, seen: list[int]):
    """(channel id, log time [ns], data or None) of the message records in `buf`; counts every
    message record in seen[0]."""
    at, end = 0, len(buf)
    while at < end:
        if at + 9 > end:
            raise ValueError(f"a record header at byte {at} of a chunk is cut off")
        opcode, n = _RECORD.unpack_from(buf, at)
        body = at + 9
        at = body + n
        if at > end:
            raise ValueError(f"the record at byte {body - 9} of a chunk runs past its end")
        if opcode == _OP_MESSAGE:
            seen[0] += 1
            channel, _, log_ns, _ = _MESSAGE.unpack_from(buf, body)
            if channels is None or channel in channels:
                yield channel, log_ns, buf[body + 22 : at] if with_data else None


def scan_mcap(path, summary, channels=None, with_data: bool = True):
    """(channel id, log time [ns], data) of the messages of an MCAP file, in file order, of the
    channel ids in `channels` (None: all; data None unless with_data).

    Walks the records itself, chunks decompressed and CRC-checked: the mcap reader spent ~25 us
    of Python on each message, ~2 s on a 10-minute drive's three topics. What it walked must
    match the file's `summary` (the chunks of its index, its message count), so a damaged
    record header cannot silently hide messages. Raises ValueError on a damaged or truncated
    file (`corrupt_chunk` then says where).
    """
    chunks, seen = [], [0]
    with open(path, "rb") as f:
        if f.read(8) != _MCAP_MAGIC:
            raise ValueError("no MCAP magic at the start")
        end = f.seek(0, 2)
        at = f.seek(8)
        while at + 9 <= end:
            opcode, n = _RECORD.unpack(f.read(9))
            if at + 9 + n > end:
                raise ValueError(f"the record at byte offset {at} runs past the end of the file")
            if opcode == _OP_DATA_END or (opcode == _OP_FOOTER and at == end - 8 - 29):
                break
            if opcode == _OP_FOOTER:
                raise ValueError(f"a footer at byte offset {at}, before the end of the file")
            if opcode == _OP_CHUNK:
                chunks.append(at)
                records = _chunk_records(f.read(n), f"the chunk at byte offset {at}")
                yield from _records_messages(records, channels, with_data, seen)
            elif opcode == _OP_MESSAGE:
                record = _RECORD.pack(opcode, n) + f.read(n)
                yield from _records_messages(record, channels, with_data, seen)
            else:
                f.seek(n, 1)
            at += 9 + n
    if summary.chunk_indexes and chunks != sorted(
        c.chunk_start_offset for c in summary.chunk_indexes
    ):
        raise ValueError("its chunks differ from the chunk index in its summary")
    if summary.statistics is not None and seen[0] != summary.statistics.message_count:
        raise ValueError(
            f"it holds {seen[0]} messages, its summary says {summary.statistics.message_count}"
        )


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
        self._summary = None  # an MCAP file's summary (channels, schemas), when it has one
        with _library_errors(source, fmt, self._mcap_files):
            if fmt == "mcap":
                from mcap.reader import make_reader

                with open(self._target, "rb") as f:
                    self._summary = make_reader(f, validate_crcs=True).get_summary()
            self.topics: dict[str, TopicInfo] = self._index()

    def _schema_name(self, channel) -> str:
        schema = self._summary.schemas.get(channel.schema_id) if channel.schema_id else None
        return rm.short_type(schema.name) if schema is not None else ""

    def _index(self) -> dict[str, TopicInfo]:
        types: dict[str, str] = {}
        counts: dict[str, int] = {}
        first: dict[str, int] = {}
        last: dict[str, int] = {}

        def add(topic, msgtype, n, t0, t1):
            types.setdefault(topic, msgtype)
            counts[topic] = counts.get(topic, 0) + n
            first[topic] = min(first.get(topic, t0), t0)
            last[topic] = max(last.get(topic, t1), t1)

        if self._summary is not None:  # per channel, from one walk over the records
            found = [(c, t) for c, t, _ in scan_mcap(self._target, self._summary, with_data=False)]
            ids = np.array([c for c, _ in found], dtype=np.int64)
            times = np.array([t for _, t in found], dtype=np.int64)
            for channel in np.unique(ids).tolist():
                if channel not in self._summary.channels:
                    raise ValueError(f"messages of channel {channel}, which the summary lacks")
                c, t = self._summary.channels[channel], times[ids == channel]
                add(c.topic, self._schema_name(c), len(t), int(t.min()), int(t.max()))
        else:
            for topic, msgtype, log_ns, _ in self._raw(None, decode=False):
                add(topic, msgtype, 1, log_ns, log_ns)
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
            if self._summary is None:
                return []
            return [(c.topic, self._schema_name(c)) for c in self._summary.channels.values()]
        with self._anyreader() as reader:
            return [(c.topic, rm.short_type(c.msgtype)) for c in reader.connections]

    def pose_tables(self, topics: Sequence[str], tf_pair: tuple[str, str]) -> dict[str, PoseRows]:
        """The `PoseRows` of each of `topics` (pose-like), in log-time order.

        In MCAP files the fixed-layout types (`CDR_POSE_TYPES`) are read straight from their
        CDR bytes (`cdr_pose_table`), all such topics in one walk over the file, POSE_BATCH
        messages of a channel at a time: decoding a message with mcap_ros2 took ~50x longer,
        and a 10-minute drive holds 37,000 of them.
        """
        fast = self.format == "mcap" and self._summary is not None
        quick = [t for t in topics if fast and self.topics[t].msgtype in CDR_POSE_TYPES]
        out = self._cdr_pose_tables(quick, tf_pair) if quick else {}
        for topic in topics:
            if topic not in out:
                decoded = self.messages([topic])
                rows = [
                    r for _, name, ns, msg in decoded for r in pose_rows(name, msg, ns, tf_pair)
                ]
                out[topic] = PoseRows.of(rows)
        return {t: out[t] for t in topics}

    def _cdr_pose_tables(self, topics: list[str], tf_pair) -> dict[str, PoseRows]:
        channels = {i: c for i, c in self._summary.channels.items() if c.topic in topics}
        pending: dict[int, list] = {i: [] for i in channels}  # (order, log_ns, data) to decode
        parts: dict[str, list] = {t: [] for t in topics}  # (order, PoseRows) per batch
        decoders: dict = {}

        def decode(channel: int) -> None:
            order, log_ns, data = zip(*pending[channel])
            pending[channel] = []
            c = channels[channel]
            rows = self._channel_rows(c, data, np.array(log_ns, np.int64), decoders, tf_pair)
            parts[c.topic].append((np.array(order, np.int64), rows))

        with _library_errors(self.source, self.format, self._mcap_files):
            found = scan_mcap(self._target, self._summary, set(channels))
            for k, (channel, log_ns, data) in enumerate(found):
                pending[channel].append((k, log_ns, data))
                if len(pending[channel]) == POSE_BATCH:
                    decode(channel)
            for channel in channels:
                if pending[channel]:
                    decode(channel)
        out = {}
        for topic, batches in parts.items():
            order = np.concatenate([o for o, _ in batches]) if batches else np.zeros(0, np.int64)
            rows = PoseRows.joined([r for _, r in batches])
            # log-time order; equal times in file order, as a stable sort of the walk gives
            out[topic] = rows.take(np.lexsort((order, rows.log_ns)))
        return out

    def _channel_rows(self, c, data, log_ns, decoders: dict, tf_pair) -> PoseRows:
        """The rows of messages `data` (bytes) of MCAP channel `c`, received at log_ns."""
        name = self._schema_name(c)
        n = len(data)
        if c.message_encoding == "cdr":
            stamp_ns, values, ok = cdr_pose_table(name, data)
        else:
            stamp_ns, values, ok = np.zeros(n, np.int64), np.zeros((n, 7)), np.zeros(n, bool)
        for k in np.flatnonzero(~ok).tolist():  # another encoding or unexpected bytes
            schema = self._summary.schemas.get(c.schema_id)
            msg = self._decoder(decoders, schema, c)(data[k])
            (row,) = pose_rows(name, msg, int(log_ns[k]), tf_pair)  # one per pose message
            stamp_ns[k], values[k] = row[0], row[2:]
        return PoseRows(stamp_ns, log_ns, values)

    def _decoder(self, decoders: dict, schema, channel):
        """The decoder of an MCAP channel's messages, made once per channel id (in `decoders`);
        InputError when there is none (e.g. protobuf, JSON or ROS 1 MCAP)."""
        from mcap_ros2.decoder import DecoderFactory

        if channel.id not in decoders:
            decoders[channel.id] = DecoderFactory().decoder_for(
                channel.message_encoding, _with_definition(schema)
            )
        if decoders[channel.id] is None:
            name = rm.short_type(schema.name) if schema is not None else ""
            raise InputError(
                self.source,
                f"topic {channel.topic!r} is encoded as {channel.message_encoding!r} with "
                f"schema {name or 'none'}",
                "ROS 2 CDR messages with a ros2msg schema",
            )
        return decoders[channel.id]

    def _mcap_messages(self, topics):
        """(schema, channel, message, decode) of an MCAP file's messages; decode() -> message."""
        from mcap.reader import make_reader

        decoders: dict = {}
        with open(self._target, "rb") as f:
            reader = make_reader(f, validate_crcs=True)
            for schema, channel, message in reader.iter_messages(topics):

                def decode(s=schema, c=channel, m=message):
                    return self._decoder(decoders, s, c)(m.data)

                yield schema, channel, message, decode

    def _raw(self, topics, decode: bool) -> Iterator[tuple[str, str, int, Any]]:
        if self.format == "mcap":
            for schema, channel, message, decoded in self._mcap_messages(topics):
                name = rm.short_type(schema.name) if schema is not None else ""
                yield channel.topic, name, message.log_time, decoded() if decode else None
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
        parent, child = tf_pair
        return [
            _row(tr.header.stamp, log_ns, tr.transform.translation, tr.transform.rotation)
            for tr in msg.transforms
            if _same_frame(tr.header.frame_id, parent) and _same_frame(tr.child_frame_id, child)
        ]
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


# types whose CDR layout is fixed up to their frame id strings: read without a decoder
CDR_POSE_TYPES = STAMPED_POSE_TYPES + ODOMETRY_TYPES
POSE_BATCH = 4096  # messages of a channel read as one array: memory bounded in the log's length
# Odometry: from the pose to twist.twist.linear: 7 pose values and a 6 x 6 covariance
_ODOM_TWIST_OFFSET = 8 * (7 + 36)


def cdr_pose_table(
    msgtype: str, data: Sequence[bytes]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The `PoseRows` stamp_ns (N,) and values (N, 7) of N PoseStamped,
    PoseWithCovarianceStamped or Odometry messages read from their little-endian CDR bytes
    (ROS 2's encoding: a 4-byte encapsulation header, then fields aligned to their size counted
    from its end), and ok (N,): False where the bytes are not that (big-endian, or too short),
    and that message must go through the full decoder.

    Messages of one layout (size and frame id lengths; in a recording, nearly always all of
    them) are read as one array.
    """
    n = len(data)
    stamp_ns, values, ok = np.zeros(n, np.int64), np.full((n, 7), np.nan), np.zeros(n, bool)
    size = np.fromiter(map(len, data), np.int64, n)
    for length in np.unique(size).tolist():
        rows = np.flatnonzero(size == length)
        raw = np.frombuffer(b"".join([data[k] for k in rows.tolist()]), np.uint8)
        _cdr_pose_layouts(msgtype, raw.reshape(len(rows), length), rows, stamp_ns, values, ok)
    return stamp_ns, values, ok


def _cdr_field(raw: np.ndarray, at: int, dtype: str, count: int = 1) -> np.ndarray:
    """(N, count) values of `dtype` at byte `at` of each row of raw (N, L) uint8."""
    width = np.dtype(dtype).itemsize * count
    return np.ascontiguousarray(raw[:, at : at + width]).view(dtype)


def _cdr_pose_layouts(msgtype, raw, rows, stamp_ns, values, ok) -> None:
    """`cdr_pose_table` of messages of one size, raw (N, L) uint8, rows (N,) their indices into
    stamp_ns, values and ok (written where readable)."""
    length = raw.shape[1]
    if length < 16:  # no room for the header
        return
    odom = msgtype in ODOMETRY_TYPES  # a second string (child_frame_id) and the twist after
    pose_bytes = _ODOM_TWIST_OFFSET + 16 if odom else 56  # what is read from the pose on
    little = (raw[:, 0] == 0) & (raw[:, 1] == 1)  # the encapsulation id of little-endian CDR
    frame = _cdr_field(raw, 12, "<u4")[:, 0].astype(np.int64)  # header.frame_id's length
    child = np.zeros(len(raw), np.int64)  # child_frame_id's length field, with its 4 bytes
    for n_frame in np.unique(frame[little]).tolist():
        at = 12 + n_frame  # after header.frame_id (its length counts the terminating NUL)
        same = little & (frame == n_frame)
        if odom:
            at = (at + 3) & ~3
            if 4 + at + 4 > length:
                continue
            child = _cdr_field(raw, 4 + at, "<u4")[:, 0].astype(np.int64) + 4
        for n_child in np.unique(child[same]).tolist():
            pose_at = 4 + ((at + n_child + 7) & ~7)
            if pose_at + pose_bytes > length:
                continue
            these = same & (child == n_child)
            r, k = raw[these], rows[these]
            sec = _cdr_field(r, 4, "<i4")[:, 0].astype(np.int64)
            stamp_ns[k] = sec * 1_000_000_000 + _cdr_field(r, 8, "<u4")[:, 0].astype(np.int64)
            pose = _cdr_field(r, pose_at, "<f8", 7)  # position x, y, z, orientation x, y, z, w
            values[k, :6] = pose[:, [0, 1, 3, 4, 5, 6]]
            if odom:  # twist.twist.linear x, y: the planar speed
                xy = _cdr_field(r, pose_at + _ODOM_TWIST_OFFSET, "<f8", 2)
                values[k, 6] = np.hypot(xy[:, 0], xy[:, 1])
            ok[k] = True


def _row(stamp, log_ns: int, p, q, v: float = np.nan) -> tuple:
    stamp_ns = int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
    return (stamp_ns, int(log_ns), p.x, p.y, q.x, q.y, q.z, q.w, v)


def check_stamps_vary(source, topic: str, stamps_ns: np.ndarray, what="messages") -> None:
    """InputError when all (two or more) header stamps of a topic are equal (zero: unset), which
    would collapse the drive into one pose."""
    if len(stamps_ns) > 1 and np.all(stamps_ns == stamps_ns[0]):
        value = (
            "zero (unset)" if stamps_ns[0] == 0 else f"{rm.ns_to_seconds(stamps_ns[:1])[0]:.9f} s"
        )
        raise InputError(
            source,
            f"{topic}: the header stamps of all {len(stamps_ns)} {what} are {value}",
            "header stamps of the time each was measured, or --log-time to stamp by recording time",
        )
