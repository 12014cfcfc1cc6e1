"""Damaged MCAP chunks are reported, never decoded into different poses.

Single bits are flipped inside the chunk data of small MCAP files (zstd, lz4 and uncompressed
chunks, several chunks per file) and of the sample rosbag2 folder's storage file. Every flip must
either raise one InputError naming the file and the damaged chunk's byte offset, or decode to
exactly the same drive (a flip the format does not use). Flips elsewhere in the file may raise an
InputError naming the file, or decode to the same drive; none may change it silently.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from helpers import make_series, series_events

from fpe_jax import io
from fpe_jax.errors import InputError
from fpe_jax.io import ros_msgs as rm

ROSBAG2 = Path(__file__).resolve().parents[2] / "data" / "samples" / "drive_rosbag2"


def write_chunked_mcap(path: Path, compression: str, chunk_size: int = 2048) -> Path:
    """A ROS 2 MCAP with /car/pose (PoseStamped) and /car/odom (Odometry) in several chunks."""
    from mcap.writer import CompressionType
    from mcap_ros2.writer import Writer

    events = series_events("/car/pose", "geometry_msgs/PoseStamped", make_series(30, seed=1))
    events += series_events("/car/odom", "nav_msgs/Odometry", make_series(30, seed=2))
    events.sort(key=lambda e: e[0])
    kind = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "": CompressionType.NONE}
    with open(path, "wb") as f:
        w = Writer(f, chunk_size=chunk_size, compression=kind[compression])
        schemas = {}
        for log_ns, topic, msgtype, msg in events:
            if msgtype not in schemas:
                schemas[msgtype] = w.register_msgdef(rm.full_type(msgtype), rm.definition(msgtype))
            w.write_message(topic, schemas[msgtype], msg, log_time=log_ns, publish_time=log_ns)
        w.finish()
    return path


def chunk_data_ranges(path: Path) -> list[tuple[int, int, int]]:
    """(chunk record offset, first, end) byte ranges of each chunk's (compressed) records."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    out = []
    for c in summary.chunk_indexes:
        end = c.chunk_start_offset + c.chunk_length
        out.append((c.chunk_start_offset, end - c.compressed_size, end))
    return out


def drive_values(path) -> tuple[np.ndarray, ...]:
    d = io.load_drive(path, truth_topic=None)
    out = (d.t_s, d.xy_m, d.yaw_rad)
    if d.has_truth:
        out += (d.truth_t_s, d.truth_xy_m, d.truth_yaw_rad, d.truth_v_mps)
    return out


def same(a, b) -> bool:
    return len(a) == len(b) and all(np.array_equal(x, y, equal_nan=True) for x, y in zip(a, b))


def flip(path: Path, byte: int, bit: int) -> None:
    data = bytearray(path.read_bytes())
    data[byte] ^= 1 << bit
    path.write_bytes(bytes(data))


def check_flips(good: Path, target: Path, reported: Path, offsets, load) -> dict[str, int]:
    """Flip each (byte, bit) in a fresh copy of `good` at `target`, load, classify the outcome.

    Returns counts of "error" and "same"; raises AssertionError on a silent change, on an error
    that does not name `reported`, or (inside chunk data) one without the chunk's offset.
    """
    ref = load()
    ranges = chunk_data_ranges(target)
    counts = {"error": 0, "same": 0}
    for byte, bit in offsets:
        shutil.copyfile(good, target)
        flip(target, byte, bit)
        try:
            got = load()
        except InputError as e:
            msg = str(e)
            assert str(reported) in msg and "\n" not in msg, msg
            inside = [start for start, a, b in ranges if a <= byte < b]
            if inside:
                assert f"offset {inside[0]}" in msg, (byte, msg)
            counts["error"] += 1
        else:
            assert same(got, ref), f"flip at byte {byte} bit {bit} changed the drive silently"
            counts["same"] += 1
    shutil.copyfile(good, target)
    return counts


def _offsets(ranges, n: int, seed: int) -> list[tuple[int, int]]:
    rng = np.random.default_rng(seed)
    pool = np.concatenate([np.arange(a, b) for a, b in ranges])
    return [(int(b), int(rng.integers(8))) for b in rng.choice(pool, n, replace=False)]


@pytest.mark.parametrize("compression", ["zstd", "lz4", ""])
def test_flips_inside_mcap_chunks_are_reported(tmp_path, compression):
    good = write_chunked_mcap(tmp_path / "good.mcap", compression)
    target = tmp_path / "drive.mcap"
    shutil.copyfile(good, target)
    ranges = chunk_data_ranges(target)
    assert len(ranges) >= 3
    offsets = _offsets([(a, b) for _, a, b in ranges], 120, seed=len(compression))
    counts = check_flips(good, target, target, offsets, lambda: drive_values(target))
    # Inside chunk data nearly every flip changes what decodes; each one must be caught.
    assert counts["error"] >= 110, counts


def test_flips_anywhere_in_an_mcap_never_change_the_drive(tmp_path):
    good = write_chunked_mcap(tmp_path / "good.mcap", "zstd")
    target = tmp_path / "drive.mcap"
    shutil.copyfile(good, target)
    offsets = _offsets([(0, good.stat().st_size)], 200, seed=7)
    counts = check_flips(good, target, target, offsets, lambda: drive_values(target))
    assert counts["error"] > 0 and counts["same"] > 0, counts


def test_flips_inside_the_rosbag2_storage_chunks_are_reported(tmp_path):
    folder = tmp_path / "bag"
    shutil.copytree(ROSBAG2, folder)
    (inner,) = folder.glob("*.mcap")
    good = tmp_path / "good.mcap"
    shutil.copyfile(inner, good)
    ranges = chunk_data_ranges(inner)
    offsets = _offsets([(a, b) for _, a, b in ranges], 40, seed=3)
    counts = check_flips(good, inner, inner, offsets, lambda: drive_values(folder))
    assert counts["error"] >= 38, counts


def test_corrupt_chunk_is_one_line_from_the_cli(tmp_path, capsys):
    from fpe_jax import cli

    target = tmp_path / "drive.mcap"
    write_chunked_mcap(target, "zstd")
    start, a, b = chunk_data_ranges(target)[1]
    flip(target, (a + b) // 2, 3)
    assert cli.main(["info", str(target)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert err[0].startswith(f"fpe: error: {target}: ") and f"offset {start}" in err[0]


def test_damaged_summary_is_reported_before_decoding(tmp_path):
    """The summary holds the schemas the messages are decoded with: a flipped bit there (here in
    the middle of the section) is caught by the footer's CRC, naming the section's offset."""
    import struct

    target = write_chunked_mcap(tmp_path / "drive.mcap", "zstd")
    data = target.read_bytes()
    _, _, start, _, crc = struct.unpack("<BQQQI", data[-37:-8])
    assert crc != 0
    flip(target, (start + len(data) - 37) // 2, 0)
    with pytest.raises(
        InputError, match=f"corrupt: the summary section at byte offset {start} fails"
    ):
        io.load_drive(target)


def test_chunks_without_crcs_still_read(tmp_path):
    """rosbags' writer stores every chunk CRC as 0 ("not computed"): nothing to check, no error."""
    from helpers import write_rosbags

    s = make_series(12)
    folder = write_rosbags(tmp_path / "bag", series_events("/p", "geometry_msgs/PoseStamped", s))
    (inner,) = folder.glob("*.mcap")
    for path in (folder, inner):
        np.testing.assert_array_equal(io.load_drive(path).xy_m, s["xy"])
