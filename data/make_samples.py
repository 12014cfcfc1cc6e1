"""Write the small data fpe-jax ships: the built-in tracks and one simulated drive in every format.

    .venv/bin/python data/make_samples.py            # rewrite data/ and the package's track copies
    .venv/bin/python data/make_samples.py --check    # exit 1 unless data/ is what it would write
                                                     # (values within TOLERANCE, see below)
    .venv/bin/python data/make_samples.py --out DIR  # write the same tree into DIR instead

What each file is, with its columns, units, frames and rates: data/README.md. Running it again
gives byte-identical files (with the same versions of numpy, mcap, mcap-ros2-support, rosbags
and zstandard: the binary logs embed compressed chunks). On another CPU NumPy's vectorised
sin/cos may round the last bits differently, so files are compared by what they say: every
number within TOLERANCE (1e-8 in the file's own units: m, rad, s, m/s), all else equal. --check
passes on such a machine, and a rewrite keeps every file that is the same in that sense (it
changes no tracked file unless a value really moved).

The built-in tracks `oval` and `hairpin` are designed here as straights and arcs and shipped as
CSV files; `fpe_jax.tracks.builtin_track` reads the copies in fpe_jax/builtin_tracks/ (a test
checks they equal data/tracks/). The simulator reads those files, so the sample drive below
depends on the shipped tracks, never on this script's arithmetic.
"""

from __future__ import annotations

import argparse
import io as stdio
import math
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

from fpe_jax import sim
from fpe_jax.io import ros_msgs as rm
from fpe_jax.tracks import SPACING_M, builtin_track, loop_arclength, resample_loop

DATA = Path(__file__).resolve().parent
PACKAGE_TRACKS = DATA.parent / "fpe_jax" / "builtin_tracks"

TOLERANCE = 1e-8  # absolute, in each file's units (m, rad, s, m/s): last-bit rounding, and
# the 9th decimal of a CSV value that rounding moved across a boundary
HALF_WIDTH_M = {"oval": 1.1, "hairpin": 0.9}
# The sample drive: `fpe simulate --track oval --duration 30 --latency 0.3 --seed 0`.
SAMPLE = dict(track="oval", duration_s=30.0, latency_s=0.3, seed=0)
XYZ_RATE_HZ = 10.0  # the 2019 project saved the observed pose at 10 Hz
CARS_EVERY_M = 8.0  # spacing of the batch example's cars along the oval
CARS_SPEED_MPS = 4.0


# ---- track designs -------------------------------------------------------------------------------


def _turtle(segments: list[tuple[float, float]], step_m: float = 0.01) -> np.ndarray:
    """Trace straight/arc segments (length [m], curvature [1/m]) from the origin heading +x.

    Positions are exact per arc (no integration drift), so a closed design closes exactly.
    Returns (N, 2) points every `step_m`, closing point dropped.
    """
    x = y = th = 0.0
    pts = []
    for length_m, kappa in segments:
        n = max(int(round(length_m / step_m)), 1)
        s = np.arange(n) * (length_m / n)
        if kappa == 0.0:
            px, py = x + s * math.cos(th), y + s * math.sin(th)
        else:
            px = x + (np.sin(th + kappa * s) - math.sin(th)) / kappa
            py = y - (np.cos(th + kappa * s) - math.cos(th)) / kappa
        pts.append(np.stack([px, py], axis=1))
        if kappa == 0.0:
            x, y = x + length_m * math.cos(th), y + length_m * math.sin(th)
        else:
            x += (math.sin(th + kappa * length_m) - math.sin(th)) / kappa
            y -= (math.cos(th + kappa * length_m) - math.cos(th)) / kappa
        th += kappa * length_m
    if math.hypot(x, y) > 1e-9:
        raise RuntimeError("track design does not close")
    return np.concatenate(pts)


def _arc(radius_m: float, angle_rad: float) -> tuple[float, float]:
    """A turn as a turtle segment: positive angle turns left, negative turns right."""
    return radius_m * abs(angle_rad), math.copysign(1.0 / radius_m, angle_rad)


def _smooth_loop(xy_m: np.ndarray, window_m: float, step_m: float = 0.01) -> np.ndarray:
    """Moving average over `window_m` of a closed loop sampled every `step_m`: turns in and out
    of arcs get gradual curvature (as on real tracks) instead of a jump."""
    n = int(round(window_m / step_m))
    pad = np.concatenate([xy_m[-n:], xy_m, xy_m[:n]])
    kernel = np.ones(n) / n
    smooth = [np.convolve(pad[:, c], kernel, mode="same")[n:-n] for c in (0, 1)]
    return np.stack(smooth, axis=1)


def oval_xy() -> np.ndarray:
    """A 30 m x 12 m stadium: two 18 m straights, two 6 m radius turns (K, 2) [m]."""
    pi = math.pi
    dense = _turtle([(18.0, 0.0), _arc(6.0, pi), (18.0, 0.0), _arc(6.0, pi)])
    return resample_loop(_smooth_loop(dense, 2.0), SPACING_M)[0]


def hairpin_xy() -> np.ndarray:
    """A ~71 m loop with a right-hand 1.5 m radius hairpin between two 2 m turns (K, 2) [m]."""
    # East 20 m, wide left turn, then a left-right-left "S" whose middle is a 1.5 m radius
    # hairpin (its two legs 3 m apart: 1.2 m of wall between the track edges), back west, and
    # a wide left turn home. The x-displacements sum to zero, so the loop closes exactly.
    pi = math.pi
    design = [
        (20.0, 0.0),
        _arc(4.0, pi),
        (5.0, 0.0),
        _arc(2.0, pi / 2),
        (1.0, 0.0),
        _arc(1.5, -pi),
        (1.0, 0.0),
        _arc(2.0, pi / 2),
        (8.0, 0.0),
        _arc(4.0, pi),
    ]
    return resample_loop(_smooth_loop(_turtle(design), 1.0), SPACING_M)[0]


def track_csv(xy_m: np.ndarray, half_width_m: float) -> str:
    """The F1TENTH centerline format; values as Python's shortest exact repr, so the file gives
    back the very floats that were written."""
    lines = ["# x_m, y_m, w_tr_right_m, w_tr_left_m"]
    w = repr(float(half_width_m))
    lines += [f"{float(x)!r}, {float(y)!r}, {w}, {w}" for x, y in xy_m]
    return "\n".join(lines) + "\n"


# ---- the sample drive ---------------------------------------------------------------------------


def _stamp_text(ns: int) -> str:
    """An int stamp [ns] as exact decimal seconds."""
    sec, nanosec = divmod(int(ns), 1_000_000_000)
    return f"{sec}.{nanosec:09d}"


def drive_csv(res: sim.SimResult) -> str:
    """Detections as `t,x,y,yaw`: t [s] to the nanosecond (the logs' stamps), the rest to 1 nm /
    1 nrad."""
    d = res.drive
    rows = ["t,x,y,yaw"]
    for ns, (x, y), yaw in zip(rm.seconds_to_ns(d.t_s), d.xy_m, d.yaw_rad):
        rows.append(f"{_stamp_text(ns)},{x:.9f},{y:.9f},{yaw:.9f}")
    return "\n".join(rows) + "\n"


def xyz_rows(res: sim.SimResult, rate_hz: float = XYZ_RATE_HZ) -> np.ndarray:
    """(R, 3) the original's pose file: the newest detection at t_first + k / rate_hz, held when
    none arrived since (as the 2019 node logged), z = 0."""
    t = res.drive.t_s
    n = int(math.floor((t[-1] - t[0]) * rate_hz + 1e-9)) + 1
    newest = np.searchsorted(t, t[0] + np.arange(n) / rate_hz + 1e-9, side="right") - 1
    return np.column_stack([res.drive.xy_m[newest], np.zeros(n)])


def xyz_csv(res: sim.SimResult) -> str:
    """Header-less `x, y, z` rows with 6 decimals, as the 2019 project wrote them."""
    return "".join(f"{x:.6f}, {y:.6f}, {z:.6f}\n" for x, y, z in xyz_rows(res))


def cars_csv() -> str:
    """Cars for `fpe batch`: on the oval's centerline every CARS_EVERY_M, heading along it."""
    xy, _ = builtin_track("oval")
    s = loop_arclength(xy)
    idx = np.searchsorted(s[:-1], np.arange(0.0, s[-1], CARS_EVERY_M))
    nxt = (idx + 1) % len(xy)
    yaw = np.arctan2(xy[nxt, 1] - xy[idx, 1], xy[nxt, 0] - xy[idx, 0])
    rows = ["x,y,yaw,v"]
    rows += [f"{x:.6f},{y:.6f},{a:.6f},{CARS_SPEED_MPS:.1f}" for (x, y), a in zip(xy[idx], yaw)]
    return "\n".join(rows) + "\n"


def _convert(src: Path, dst: Path, compress: str | None, mode: str = "") -> None:
    """rosbags' own converter: a rosbag2 folder for a suffix-less dst, a ROS 1 bag for .bag."""
    from rosbags.convert import convert

    convert(
        srcs=[src],
        dst=dst,
        dst_storage="mcap",
        dst_version=9,
        compress=compress,
        compress_mode=mode,
        default_typestore=None,
        typestore=None,
        exclude_topics=[],
        include_topics=[],
        exclude_msgtypes=[],
        include_msgtypes=[],
    )


def _rewrite_with_chunk_crcs(path: Path) -> None:
    """Rewrite an MCAP's records into zstd chunks with CRCs, keeping schemas, channels (with
    their metadata, e.g. QoS), messages in file order and metadata records.

    rosbags' writer leaves every chunk CRC zero, so nothing could tell a damaged chunk from a
    good one; ROS 2's recorder (the C++ MCAP writer) computes them by default.
    """
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer

    with open(path, "rb") as f:
        reader = make_reader(f)
        header, summary = reader.get_header(), reader.get_summary()
        records = list(reader.iter_messages(log_time_order=False))
        metadata = list(reader.iter_metadata())
    out = stdio.BytesIO()
    w = Writer(out, compression=CompressionType.ZSTD, enable_crcs=True)
    w.start(profile=header.profile, library=f"{header.library}; chunks rewritten by mcap")
    schemas = {
        sid: w.register_schema(s.name, s.encoding, s.data) for sid, s in summary.schemas.items()
    }
    channels = {
        cid: w.register_channel(c.topic, c.message_encoding, schemas[c.schema_id], c.metadata)
        for cid, c in summary.channels.items()
    }
    for _, channel, m in records:
        w.add_message(channels[channel.id], m.log_time, m.data, m.publish_time, m.sequence)
    for m in metadata:
        w.add_metadata(m.name, m.metadata)
    w.finish()
    path.write_bytes(out.getvalue())


def write_samples(out: Path) -> list[Path]:
    """The sample drive in every format under out/ (which must not exist yet)."""
    res = sim.simulate(
        SAMPLE["track"],
        duration_s=SAMPLE["duration_s"],
        latency_s=SAMPLE["latency_s"],
        seed=SAMPLE["seed"],
    )
    out.mkdir(parents=True)
    with tempfile.TemporaryDirectory() as tmp:
        sim.write_simulation(res, Path(tmp) / "sim")  # what `fpe simulate` writes
        for name in ("drive.mcap", "scenario.json"):
            shutil.move(Path(tmp) / "sim" / name, out / name)
    _convert(out / "drive.mcap", out / "drive_rosbag2", compress=None)
    (inner,) = (out / "drive_rosbag2").glob("*.mcap")
    _rewrite_with_chunk_crcs(inner)
    _convert(out / "drive.mcap", out / "drive.bag", compress="bz2")
    (out / "drive.csv").write_text(drive_csv(res))
    (out / "poses_xyz.csv").write_text(xyz_csv(res))
    (out / "cars.csv").write_text(cars_csv())
    return sorted(p for p in out.rglob("*") if p.is_file())


def write_tracks(out: Path) -> list[Path]:
    out.mkdir(parents=True, exist_ok=True)
    files = []
    for name, xy in (("oval", oval_xy()), ("hairpin", hairpin_xy())):
        files.append(out / f"{name}.csv")
        files[-1].write_text(track_csv(xy, HALF_WIDTH_M[name]))
    return files


def write_all(root: Path) -> list[Path]:
    """tracks/ and samples/ under root; returns every written file."""
    tracks = write_tracks(root / "tracks")
    return tracks + write_samples(root / "samples")


def _files(root: Path, names: tuple[str, ...] = ("tracks", "samples")) -> list[str]:
    return [
        str(p.relative_to(root))
        for name in names
        for p in sorted((root / name).rglob("*"))
        if p.is_file() and "__pycache__" not in p.parts
    ]


def _values(path: Path):
    """What a file says, as numbers and structures (a log: its drive's arrays)."""
    import json

    import yaml

    from fpe_jax import io
    from fpe_jax.io.tables import read_table

    if path.suffix == ".csv":
        t = read_table(path)
        return t.header, t.data
    if path.suffix == ".json":
        return json.loads(path.read_text())
    if path.suffix == ".yaml":
        return yaml.safe_load(path.read_text())
    d = io.load_drive(path)
    return d.t_s, d.xy_m, d.yaw_rad, d.truth_t_s, d.truth_xy_m, d.truth_yaw_rad, d.truth_v_mps


def _close(a, b) -> bool:
    """Equal structures whose numbers agree within TOLERANCE (NaN equals NaN)."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a, b = np.asarray(a), np.asarray(b)
        if a.shape != b.shape or a.dtype.kind != b.dtype.kind:
            return False
        if a.dtype.kind not in "fc":
            return bool(np.array_equal(a, b))
        return bool(np.allclose(a, b, rtol=0.0, atol=TOLERANCE, equal_nan=True))
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_close(a[k], b[k]) for k in a)
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        return len(a) == len(b) and all(_close(x, y) for x, y in zip(a, b))
    if isinstance(a, float) and isinstance(b, float):
        return abs(a - b) <= TOLERANCE or (math.isnan(a) and math.isnan(b))
    return type(a) is type(b) and a == b


def same_file(a: Path, b: Path) -> bool:
    """Whether two written files are the same: equal bytes, or equal values (`_close`)."""
    if a.read_bytes() == b.read_bytes():
        return True
    try:
        return _close(_values(a), _values(b))
    except Exception:  # unreadable as a value file: the bytes decided
        return False


def compare_trees(fresh: Path, data: Path) -> list[str]:
    """The relative paths (under tracks/ and samples/) where `data` differs from `fresh`."""
    new, old = _files(fresh), _files(data)
    bad = sorted(set(new) ^ set(old))
    bad += [k for k in new if k in old and not same_file(fresh / k, data / k)]
    return sorted(bad)


def _sync(fresh: Path, data: Path) -> list[Path]:
    """Make data/ say what fresh/ says: copy each file that differs (`same_file`), remove those
    fresh/ lacks; a file equal within TOLERANCE is left as it is. Returns the files changed."""
    changed = []
    for k in _files(fresh.parent, (fresh.name,)):
        src, dst = fresh.parent / k, data.parent / k
        if not dst.is_file() or not same_file(src, dst):
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src, dst)
            changed.append(dst)
    for k in _files(data.parent, (data.name,)):
        if not (fresh.parent / k).exists():
            (data.parent / k).unlink()
            changed.append(data.parent / k)
    return changed


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    group = ap.add_mutually_exclusive_group()
    group.add_argument("--out", type=Path, help="write tracks/ and samples/ here (new folder)")
    group.add_argument("--check", action="store_true", help="compare with data/, write nothing")
    args = ap.parse_args(argv)
    if args.out is not None:
        if args.out.exists():
            print(f"make_samples: {args.out} exists; choose a new folder", file=sys.stderr)
            return 2
        for p in write_all(args.out):
            print(f"wrote {p}")
        return 0
    if args.check:
        with tempfile.TemporaryDirectory() as tmp:
            fresh = Path(tmp) / "data"
            write_all(fresh)
            bad = compare_trees(fresh, DATA)
            for k in sorted(k for k in _files(fresh) if k.startswith("tracks/")):
                copy = PACKAGE_TRACKS / Path(k).name
                if not copy.is_file() or copy.read_bytes() != (DATA / k).read_bytes():
                    bad.append(str(copy.relative_to(DATA.parent)))
        for k in bad:
            print(f"differs: {k}")
        print(
            f"data/ is up to date (values within {TOLERANCE:g})"
            if not bad
            else f"{len(bad)} file(s) differ by more than {TOLERANCE:g}"
        )
        return 1 if bad else 0
    # Tracks first, copied into the package: the simulator reads the built-in tracks from there.
    # Files that say the same within TOLERANCE are kept, so no tracked file changes for nothing.
    with tempfile.TemporaryDirectory() as tmp:
        fresh = Path(tmp) / "data"
        write_tracks(fresh / "tracks")
        written = _sync(fresh / "tracks", DATA / "tracks")
        for track in (DATA / "tracks").glob("*.csv"):
            copy = PACKAGE_TRACKS / track.name
            if not copy.is_file() or copy.read_bytes() != track.read_bytes():
                PACKAGE_TRACKS.mkdir(exist_ok=True)
                shutil.copyfile(track, copy)
                written.append(copy)
        write_samples(fresh / "samples")
        written += _sync(fresh / "samples", DATA / "samples")
    for p in written:
        print(f"wrote {p.relative_to(DATA.parent)}")
    print(f"{len(written)} file(s) changed; data/ says what this script writes")
    return 0


if __name__ == "__main__":
    sys.exit(main())
