"""What several test files share: the in-process CLI runner, tree closeness, finite-difference
checks, and the catalogue of tracks x predictors that parity tests run over."""

from __future__ import annotations

import functools
import io
import json
import sys
from pathlib import Path

import jax
import numpy as np
import pytest
from rosbags.interfaces import Nodetype
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from fpe_jax import Drive, Params, Settings, presets
from fpe_jax.io import ros_msgs as rm
from fpe_jax.io.writers import _write_ros2_mcap
from fpe_jax.runner._runner import Runner
from fpe_jax.sim._sim import simulate

LEVINE = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "levine"


# ---- the CLI ----------------------------------------------------------------------------------


def cli_runner(
    capsys, argv, stdin: str | None = None, monkeypatch=None, *, expect=(0, 2)
) -> tuple[int, str, str]:
    """In-process `fpe ARGV` (items turned into str): (exit status, stdout, stderr). The status
    must be one of `expect` (an int for exactly one) and stderr must hold no traceback; `stdin`
    (with monkeypatch) is what the command reads."""
    from fpe_jax import cli

    if stdin is not None:
        monkeypatch.setattr(sys, "stdin", io.StringIO(stdin))
    capsys.readouterr()
    rc = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    assert "Traceback" not in err, err
    expect = (expect,) if isinstance(expect, int) else tuple(expect)
    assert rc in expect, (rc, expect, err)
    return rc, out, err


def csv_lines(rows) -> list[str]:
    return ["t,x,y,yaw"] + [",".join(repr(float(v)) for v in r) for r in rows]


def oval_stream(duration_s: float, seed: int) -> tuple[dict, np.ndarray, np.ndarray]:
    """(default preset's config dict, centerline (K, 2) [m], rows (N, 4) t [s], x, y [m],
    yaw [rad]) of a simulated oval drive: what `fpe run` tests stream."""
    from fpe_jax.io.config import params_to_config

    res = simulate("oval", duration_s=duration_s, seed=seed)
    d = res.drive
    rows = np.column_stack([d.t_s, d.xy_m, d.yaw_rad])
    return params_to_config(presets["default"]), res.centerline_xy_m, rows


def stream_files(folder: Path, cfg: dict, wp) -> list[str]:
    """Write the config and waypoints into `folder`; `fpe run`'s flags naming them."""
    from fpe_jax.io.config import write_config

    write_config(folder / "cfg.json", cfg)
    np.savetxt(folder / "wp.csv", wp, delimiter=",", fmt="%.17g")
    return ["--config", str(folder / "cfg.json"), "--waypoints", str(folder / "wp.csv")]


def fpe_run(monkeypatch, capsys, argv, lines) -> tuple[int, list[dict], list[str]]:
    """In-process `fpe run ARGV` on the stdin `lines`: (exit status, replies, stderr lines)."""
    monkeypatch.setattr(sys, "stdin", io.StringIO("".join(f"{line}\n" for line in lines)))
    capsys.readouterr()
    from fpe_jax import cli

    rc = cli.main(["run", *argv])
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    return rc, [json.loads(line) for line in out.splitlines()], err.strip().splitlines()


def expected(cfg, wp, rows) -> list[dict]:
    """What a fresh runner replies for the rows (t, x, y, yaw) in order."""
    r = Runner(cfg, wp)
    replies = []
    for t, x, y, yaw in rows:
        poses = r.update(t, x, y, yaw).tolist()
        replies.append({"stamp": float(t), "poses": poses, "valid": r.valid})
    return replies


# ---- trees -------------------------------------------------------------------------------------


def assert_trees_close(a, b, *, rtol: float = 0.0, atol: float = 0.0, err_msg: str = "") -> None:
    """a and b have one pytree structure (static fields such as Settings included) and every
    leaf of a is within atol + rtol |b| of b's."""
    leaves_a, tree_a = jax.tree.flatten(a)
    leaves_b, tree_b = jax.tree.flatten(b)
    assert tree_a == tree_b, f"{err_msg}: {tree_a} != {tree_b}"
    for x, y in zip(leaves_a, leaves_b):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol, atol, err_msg=err_msg)


# ---- finite differences ------------------------------------------------------------------------


def fd_jvp(f, x, tangent, eps: float):
    """Central difference (f(x + eps t) - f(x - eps t)) / (2 eps) of f at the pytree x along the
    pytree tangent t, leaf by leaf of f's output (NumPy)."""
    up = f(jax.tree.map(lambda a, t: a + eps * t, x, tangent))
    down = f(jax.tree.map(lambda a, t: a - eps * t, x, tangent))
    return jax.tree.map(lambda u, d: (np.asarray(u) - np.asarray(d)) / (2 * eps), up, down)


def assert_jvp_matches_fd(f, x, tangent, eps: float, *, rtol: float, atol: float) -> None:
    """jax.jvp of f at x along tangent equals its central difference."""
    _, auto = jax.jvp(f, (x,), (tangent,))
    assert_trees_close(auto, fd_jvp(f, x, tangent, eps), rtol=rtol, atol=atol)


def fd_gradient(f, x, eps: float) -> np.ndarray:
    """Central-difference gradient of a scalar f at the array x, one basis direction (a JVP) at a
    time: same shape as x."""
    x = np.asarray(x, dtype=float)
    out = np.zeros(x.size)
    for i in range(x.size):
        e = np.zeros(x.size)
        e[i] = 1.0
        out[i] = float(fd_jvp(f, x, e.reshape(x.shape), eps))
    return out.reshape(x.shape)


# ---- the catalogue: tracks x predictors --------------------------------------------------------

CUSTOM = {  # non-trivial weights, delay, gain and speed shrinkage; both blend modes
    "heading-blend": lambda: Params.create(
        Settings(blend="heading"),
        lookahead_m=1.3,
        lookahead_gain_s=0.3,
        weights=np.linspace(0.95, 0.1, 10),
        delay_s=0.15,
    ),
    "shrunk-speed": lambda: Params.create(
        Settings(),
        lookahead_m=0.8,
        lookahead_gain_s=0.1,
        weights=np.linspace(0.2, 0.9, 10),
        delay_s=0.05,
        speed_weight=0.3,
        speed_mps=2.5,
    ),
}
# every preset and the two fitted-looking blends
PREDICTORS = (*presets, *CUSTOM)


def predictor(name: str) -> Params:
    """A preset by name, or one of CUSTOM's."""
    return CUSTOM[name]() if name in CUSTOM else presets[name]


@functools.cache
def _oval() -> tuple[np.ndarray, Drive]:
    res = simulate("oval", duration_s=20.0, seed=3)
    return res.centerline_xy_m, res.drive


@functools.cache
def _levine() -> tuple[np.ndarray, Drive]:
    wp = np.loadtxt(LEVINE / "levine-waypoints.csv", delimiter=",")[:, :2]
    poses = np.loadtxt(LEVINE / "actual-poses.csv", delimiter=",")
    n = len(poses)
    drive = Drive(t_s=np.arange(n) * 0.1, xy_m=poses[:, :2], yaw_rad=np.full(n, np.nan))
    return wp, drive


TRACKS = {
    # a 20 s simulated drive on the oval: noisy detections with yaw, outliers, repeats-free
    "oval": _oval,
    # the real 2019 drive: 10 Hz, no yaw, ~48 % repeated rows, stops and outlier jumps
    "levine": _levine,
}
# (track, predictor) pairs: every predictor on the oval; the 2720-point real lap (slow to run
# through the JAX predictor) with the seed and one of each blend mode
CASES = [("oval", p) for p in PREDICTORS] + [
    ("levine", p) for p in ("seed", "default", "heading-blend")
]


def track_drive(name: str) -> tuple[np.ndarray, Drive]:
    """(K, 2) waypoints [m] and a drive on them; skips when the real data is absent."""
    if name == "levine" and not LEVINE.is_dir():
        pytest.skip(f"real data not found at {LEVINE} (../shared/data beside the checkout)")
    return TRACKS[name]()


# ---- logs in every container (the io, io_errors, crc and apriltag tests) ----------------------

PS = "geometry_msgs/PoseStamped"
PWCS = "geometry_msgs/PoseWithCovarianceStamped"
ODOM = "nav_msgs/Odometry"
TF = "tf2_msgs/TFMessage"
POSE_TYPES = (PS, PWCS, ODOM, TF)
EPOCH_NS = 1_700_000_000_123_456_789  # absolute stamps exercise nanosecond-exact time handling


def make_series(n: int = 30, seed: int = 0) -> dict[str, np.ndarray]:
    """A random pose series: ns (N,) int stamps, xy (N, 2) [m], yaw (N,) [rad], v (N,) [m/s]."""
    rng = np.random.default_rng(seed)
    return {
        "ns": EPOCH_NS + np.arange(n, dtype=np.int64) * 100_000_000 + rng.integers(0, 999, n),
        "xy": rng.uniform(-50, 50, (n, 2)),
        "yaw": rng.uniform(-3.1, 3.1, n),
        "v": rng.uniform(0, 8, n),
    }


def pose_message(msgtype: str, ns: int, x: float, y: float, yaw: float, v: float = 0.0) -> dict:
    """A message dict (mcap_ros2 form) of one of the four pose types, map -> other_base_link."""
    header = {"stamp": rm.stamp_dict(ns), "frame_id": "map"}
    pose = {"position": {"x": x, "y": y, "z": 0.0}, "orientation": rm.yaw_to_quaternion(yaw)}
    if msgtype == PS:
        return {"header": header, "pose": pose}
    if msgtype == PWCS:
        return {"header": header, "pose": {"pose": pose, "covariance": [0.0] * 36}}
    if msgtype == ODOM:
        # Split the speed over x and y so the reader's hypot() is tested, not just linear.x.
        lin = {"x": 0.6 * v, "y": 0.8 * v, "z": 0.0}
        twist = {"linear": lin, "angular": {"x": 0.0, "y": 0.0, "z": 0.3}}
        return {
            "header": header,
            "child_frame_id": "other_base_link",
            "pose": {"pose": pose, "covariance": [0.0] * 36},
            "twist": {"twist": twist, "covariance": [0.0] * 36},
        }
    assert msgtype == TF
    decoy = {  # another frame pair in the same message: must be ignored
        "header": {"stamp": rm.stamp_dict(ns), "frame_id": "map"},
        "child_frame_id": "ego_base_link",
        "transform": {
            "translation": {"x": -1.0, "y": -2.0, "z": 0.0},
            "rotation": pose["orientation"],
        },
    }
    mine = {
        "header": header,
        "child_frame_id": "other_base_link",
        "transform": {"translation": pose["position"], "rotation": pose["orientation"]},
    }
    return {"transforms": [decoy, mine]}


def series_events(topic: str, msgtype: str, s: dict, log_ns=None) -> list[tuple]:
    """(log_ns, topic, msgtype, message) events of a series; log time = stamp unless given."""
    log_ns = s["ns"] if log_ns is None else log_ns
    return [
        (int(lg), topic, msgtype, pose_message(msgtype, int(n), *p, a, v))
        for lg, n, p, a, v in zip(log_ns, s["ns"], s["xy"].tolist(), s["yaw"], s["v"])
    ]


def write_mcap(path: Path, events: list[tuple]) -> Path:
    """A plain ROS 2 MCAP written by mcap_ros2 (events: (log_ns, topic, short type, dict))."""
    _write_ros2_mcap(path, events)
    return path


def _to_rosbags(store, msgtype: str, d: dict):
    """Build a rosbags message object of `msgtype` from an mcap_ros2-style dict."""
    _, fields = store.fielddefs[msgtype]
    kw = {}
    for name, (node, spec) in fields:
        val = d.get(name)
        if node == Nodetype.BASE:
            kw[name] = val if val is not None else ("" if spec[0] == "string" else 0)
        elif node == Nodetype.NAME:
            kw[name] = _to_rosbags(store, spec, val or {})
        elif node == Nodetype.ARRAY and spec[0][0] == Nodetype.NAME:  # e.g. Point[4]
            kw[name] = [_to_rosbags(store, spec[0][1], v) for v in val or [{}] * spec[1]]
        elif node == Nodetype.ARRAY:
            kw[name] = np.asarray(val if val is not None else [0] * spec[1], dtype=spec[0][1][0])
        elif spec[0][0] == Nodetype.BASE:  # a sequence of numbers: an array, as rosbags wants
            assert node == Nodetype.SEQUENCE
            kw[name] = np.asarray(val or [], dtype=spec[0][1][0])
        else:
            assert node == Nodetype.SEQUENCE and spec[0][0] == Nodetype.NAME
            kw[name] = [_to_rosbags(store, spec[0][1], v) for v in val or []]
    return store.types[msgtype](**kw)


def shipped_typestore(distro):
    """A rosbags typestore of `distro` plus the message types the package ships as .msg files."""
    store = get_typestore(distro)
    for name, fields in rm.shipped_definitions().items():
        store.register(get_types_from_msg(fields, rm.full_type(name)))
    return store


def write_rosbags(path: Path, events: list[tuple], storage: str = "mcap") -> Path:
    """A rosbag2 folder (format version 9, storage "mcap" or "sqlite3") or, with storage "ros1",
    a ROS 1 bag, written by rosbags (typestore: the distro's plus the shipped types)."""
    if storage == "ros1":
        from rosbags.rosbag1 import Writer

        store = shipped_typestore(Stores.ROS1_NOETIC)
        # Noetic's store lacks tf2_msgs; the type is one line over a known one.
        store.register(
            get_types_from_msg("geometry_msgs/TransformStamped[] transforms", rm.full_type(TF))
        )
        writer, serialize = Writer(path), store.serialize_ros1
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        store = shipped_typestore(Stores.ROS2_HUMBLE)
        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        writer = Writer(path, version=9, storage_plugin=plugin)
        serialize = store.serialize_cdr
    conns = {}
    with writer:
        for log_ns, topic, msgtype, msg in events:
            full = rm.full_type(msgtype)
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, full, typestore=store)
            writer.write(conns[topic], log_ns, serialize(_to_rosbags(store, full, msg), full))
    return path


def write_log(tmp_path: Path, container: str, events: list[tuple]) -> Path:
    """Write events in `container`; return the path a user would pass to load_drive."""
    if container == "mcap":
        return write_mcap(tmp_path / "drive.mcap", events)
    if container == "rosbag1":
        return write_rosbags(tmp_path / "drive.bag", events, storage="ros1")
    if container == "rosbag2-db3":  # sqlite3 storage, named by its .db3 file
        (db3,) = write_rosbags(tmp_path / "drive_bag", events, storage="sqlite3").glob("*.db3")
        return db3
    folder = write_rosbags(tmp_path / "drive_bag", events)
    if container == "rosbag2-metadata":
        return folder / "metadata.yaml"
    if container == "rosbag2-inner-mcap":
        (inner,) = folder.glob("*.mcap")
        return inner
    return folder


def assert_series(t_s, xy, yaw, s: dict, keep=slice(None)) -> None:
    np.testing.assert_array_equal(t_s, rm.ns_to_seconds(s["ns"][keep]))
    np.testing.assert_array_equal(xy, s["xy"][keep])
    np.testing.assert_allclose(yaw, s["yaw"][keep], rtol=0, atol=1e-12)


# ---- fresh processes (the runner, export and fit tests) ----------------------------------------

# Run in a subprocess before anything else: importing JAX (or what needs it) fails there.
NO_JAX = """
import sys
class NoJax:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in ("jax", "jaxlib", "equinox", "optimistix"):
            raise ImportError(f"{name} is blocked: this process has no JAX")
sys.meta_path.insert(0, NoJax())
"""
# appended to a NO_JAX program: fails when any JAX package got imported anyway
CHECK_NO_JAX = """
leaked = [m for m in ("jax", "jaxlib", "equinox", "optimistix") if m in sys.modules]
assert not leaked, leaked
"""

# loads a StableHLO export in a new process and predicts for 1, 7 and 1000 cars
FRESH = """
import sys
import jax
import numpy as np
from fpe_jax.io.export import load

f = load(sys.argv[1])
with np.load(sys.argv[2]) as npz:
    inputs = dict(npz)
out = {}
for b in (1, 7, 1000):
    out[f"b{b}"] = f(**{k: inputs[k][:b] for k in inputs})
# omitted optional inputs: the State defaults, s_m NaN (a global projection on the track)
out["defaults"] = f(*(inputs[k][:7] for k in ("x_m", "y_m", "yaw_rad", "v_mps")))
assert not jax.config.jax_enable_x64  # the loader's float64 does not leak into the process
np.savez(sys.argv[3], **out)
"""


# ---- the NumPy runner's parity with the JAX predictor ------------------------------------------

TOL_M = 1e-6


def run_drive(r: Runner, drive: Drive) -> np.ndarray:
    """(N, H, 3) runner predictions for every observation of a drive."""
    return np.stack(
        [r.update(t, x, y, yaw) for t, (x, y), yaw in zip(drive.t_s, drive.xy_m, drive.yaw_rad)]
    )


def assert_parity(pred_runner: np.ndarray, pred_jax: np.ndarray) -> None:
    assert pred_runner.shape == pred_jax.shape
    assert np.all(np.isfinite(pred_runner))
    assert np.max(np.abs(pred_runner[..., :2] - pred_jax[..., :2])) <= TOL_M
    dyaw = np.angle(np.exp(1j * (pred_runner[..., 2] - pred_jax[..., 2])))
    assert np.max(np.abs(dyaw)) <= TOL_M
