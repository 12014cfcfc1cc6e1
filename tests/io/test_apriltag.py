"""AprilTag recordings: TF math and buffer, detection decoding, composition into the map frame,
the simulator's AprilTag layout, files from an independent writer (rosbags), and bad input.

Exactness: composing a simulated detection back into the map goes through float64 quaternion
products only, so it must reproduce the simulator's map-frame detection to 1e-9 m / 1e-9 rad
(measured ~1e-14); files written by other writers hold the same float64 values, so the drives
read from them are compared exactly.
"""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path

import numpy as np
import pytest
from helpers import _to_rosbags, cli_runner, shipped_typestore, write_rosbags
from rosbags.typesys import Stores

from fpe_jax import io
from fpe_jax.errors import InputError
from fpe_jax.io import apriltag as at
from fpe_jax.io import ros_msgs as rm
from fpe_jax.io.tf import Rigid, TfBuffer, quat_from_matrix, quat_rotate, slerp
from fpe_jax.io.writers import _odom_events, _write_ros2_mcap
from fpe_jax.sim import _sim as sim

DET = "/tag_detections"


def _wrap(a):
    return np.angle(np.exp(1j * np.asarray(a)))


def _rot(axis: str, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    r = np.eye(3)
    r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
    return r


def _quat_to_matrix(q: np.ndarray) -> np.ndarray:
    return np.stack([quat_rotate(q, e) for e in np.eye(3)], axis=-1)


# --------------------------------------------------------------------- message definitions


UPSTREAM_FIELDS = {  # (type, name) as in the upstream .msg files (comments dropped)
    "apriltag_msgs/AprilTagDetection": [
        ("string", "family"),
        ("int32", "id"),
        ("int32", "hamming"),
        ("float32", "goodness"),
        ("float32", "decision_margin"),
        ("apriltag_msgs/Point", "centre"),
        ("apriltag_msgs/Point[4]", "corners"),
        ("float64[9]", "homography"),
    ],
    "apriltag_msgs/AprilTagDetectionArray": [
        ("std_msgs/Header", "header"),
        ("apriltag_msgs/AprilTagDetection[]", "detections"),
    ],
    "apriltag_msgs/Point": [("float64", "x"), ("float64", "y")],
    "apriltag_ros/AprilTagDetection": [
        ("int32[]", "id"),
        ("float64[]", "size"),
        ("geometry_msgs/PoseWithCovarianceStamped", "pose"),
    ],
    "apriltag_ros/AprilTagDetectionArray": [
        ("std_msgs/Header", "header"),
        ("apriltag_ros/AprilTagDetection[]", "detections"),
    ],
}


def test_shipped_definitions_match_the_upstream_messages():
    defs = rm.shipped_definitions()
    assert set(defs) == set(UPSTREAM_FIELDS) | {
        "apriltags2_ros/AprilTagDetection",
        "apriltags2_ros/AprilTagDetectionArray",
    }
    for name, fields in UPSTREAM_FIELDS.items():
        assert [tuple(line.split()) for line in defs[name].splitlines()] == fields, name
    # The old package name has the same fields.
    for t in ("AprilTagDetection", "AprilTagDetectionArray"):
        old = defs[f"apriltags2_ros/{t}"].replace("apriltags2_ros/", "apriltag_ros/")
        assert old == defs[f"apriltag_ros/{t}"]
    # Both decoders accept them: rosbags builds types, mcap_ros2 parses the full definitions.
    from mcap_ros2._dynamic import generate_dynamic

    store = shipped_typestore(Stores.ROS2_HUMBLE)
    for name in defs:
        assert rm.full_type(name) in store.fielddefs
        assert rm.full_type(name) in generate_dynamic(rm.full_type(name), rm.definition(name))


# --------------------------------------------------------------------- transform math


def test_quaternion_math_against_rotation_matrices():
    rng = np.random.default_rng(0)
    q = rng.normal(size=(50, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    v = rng.normal(size=(50, 3))
    r = _quat_to_matrix(q)
    # quat_rotate is a proper rotation (orthonormal, det +1) and quat_from_matrix inverts it.
    np.testing.assert_allclose(
        np.einsum("nji,njk->nik", r, r), np.tile(np.eye(3), (50, 1, 1)), atol=1e-12
    )
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-12)
    back = np.array([quat_from_matrix(m) for m in r])
    np.testing.assert_allclose(np.abs(np.sum(back * q, axis=1)), 1.0, atol=1e-12)
    # Composition is matrix product; inversion undoes it.
    a = Rigid.make(rng.normal(size=(50, 3)), q)
    b = Rigid.make(v, q[::-1])
    ab = a @ b
    np.testing.assert_allclose(_quat_to_matrix(ab.q), r @ _quat_to_matrix(b.q), atol=1e-12)
    np.testing.assert_allclose(ab.t_m, a.t_m + np.einsum("nij,nj->ni", r, b.t_m), atol=1e-12)
    ident = a @ a.inv()
    np.testing.assert_allclose(ident.t_m, 0.0, atol=1e-12)
    np.testing.assert_allclose(np.abs(ident.q[:, 3]), 1.0, atol=1e-12)
    # Known rotations: the camera's optical frame and an upright tag facing backwards.
    np.testing.assert_allclose(
        _quat_to_matrix(at.OPTICAL_IN_BODY.q)[0], [[0, 0, 1], [-1, 0, 0], [0, -1, 0]], atol=1e-15
    )
    np.testing.assert_allclose(
        _quat_to_matrix(at.tag_mount(0, 0, 0, np.pi).q)[0],
        [[0, 0, -1], [-1, 0, 0], [0, 1, 0]],
        atol=1e-15,
    )
    np.testing.assert_allclose(Rigid.planar([1.0], [2.0], [0.7]).yaw_rad(), [0.7], atol=1e-15)


def test_slerp_is_uniform_in_angle_and_takes_the_short_way():
    q0 = np.array([[0.0, 0.0, 0.0, 1.0]] * 5)
    q1 = Rigid.planar(np.zeros(5), np.zeros(5), np.full(5, 2.0)).q
    u = np.array([0.0, 0.25, 0.5, 0.75, 1.0])
    np.testing.assert_allclose(
        Rigid(np.zeros((5, 3)), slerp(q0, q1, u)).yaw_rad(), 2.0 * u, atol=1e-14
    )
    # -q1 is the same rotation: the result must not go the long way round.
    np.testing.assert_allclose(
        Rigid(np.zeros((5, 3)), slerp(q0, -q1, u)).yaw_rad(), 2.0 * u, atol=1e-14
    )
    # Rotations about a tilted axis stay on that axis at every fraction.
    axis = np.array([1.0, 2.0, 2.0]) / 3.0
    qa = np.concatenate([axis * np.sin(0.6), [np.cos(0.6)]])[None].repeat(5, 0)
    mid = slerp(q0, qa, u)
    angles = 2 * np.arctan2(np.linalg.norm(mid[:, :3], axis=1), mid[:, 3])
    np.testing.assert_allclose(angles, 1.2 * u, atol=1e-12)
    np.testing.assert_allclose(
        mid[1:, :3] / np.linalg.norm(mid[1:, :3], axis=1)[:, None],
        np.tile(axis, (4, 1)),
        atol=1e-12,
    )


# --------------------------------------------------------------------- the buffer


def _tf(parent, child, ns, t=(0.0, 0.0, 0.0), yaw=0.0, static=False, topic=None):
    q = (0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2))
    return (parent, child, ns, t, q, static, topic or ("/tf_static" if static else "/tf"))


def test_buffer_interpolates_and_chains():
    s = 1_000_000_000
    buf = TfBuffer(
        [
            _tf("/map", "base_link", 3 * s, (2.0, 0.0, 0.0), 1.0),  # out of order, leading '/'
            _tf("map", "base_link", 1 * s, (0.0, 0.0, 0.0), 0.0),
            _tf("map", "base_link", 2 * s, (9.0, 9.0, 9.0), 0.0),  # repeated stamp: last wins
            _tf("map", "base_link", 2 * s, (1.0, 0.0, 0.0), 0.5),
            _tf("base_link", "laser", 0, (0.5, 0.0, 0.0), np.pi / 2, static=True),
            _tf("laser", "camera", 0, (0.0, 1.0, 0.0), 0.0, static=True),
        ]
    )
    stamps = np.array([1, 1.5, 2, 2.5, 3]) * s
    base = buf.lookup("map", "base_link", stamps.astype(np.int64))
    np.testing.assert_allclose(base.t_m[:, 0], [0.0, 0.5, 1.0, 1.5, 2.0], atol=1e-15)
    np.testing.assert_allclose(base.yaw_rad(), [0.0, 0.25, 0.5, 0.75, 1.0], atol=1e-14)
    # A chain equals the product of its edges; the reverse lookup is its inverse.
    cam = buf.lookup("map", "camera", stamps.astype(np.int64))
    laser = Rigid.make([0.5, 0, 0], [0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)])
    want = base @ laser @ Rigid.make([0, 1.0, 0], [0, 0, 0, 1])
    np.testing.assert_allclose(cam.t_m, want.t_m, atol=1e-14)
    np.testing.assert_allclose(np.abs(np.sum(cam.q * want.q, axis=1)), 1.0, atol=1e-14)
    back = buf.lookup("camera", "map", stamps.astype(np.int64))
    np.testing.assert_allclose((cam @ back).t_m, 0.0, atol=1e-14)
    assert buf.chain_frames("map", "camera") == ["map", "base_link", "laser", "camera"]
    assert buf.chain_frames("camera", "laser") == ["camera", "laser"]
    # Static edges hold at any time, even far outside the dynamic span.
    assert buf.covers("base_link", "camera", [0, 10**12]).all()
    assert list(buf.covers("map", "camera", [s - 1, s, 3 * s, 3 * s + 1])) == [0, 1, 1, 0]
    rows = {(e["parent"], e["child"]): e for e in buf.describe()}
    assert rows[("map", "base_link")]["count"] == 3 and rows[("map", "base_link")]["rate_hz"] == 1.0
    assert rows[("laser", "camera")]["static"] and rows[("laser", "camera")]["depth"] == 2


@pytest.mark.parametrize(
    "transforms, a, b, stamp_s, words",
    [
        (
            [_tf("map", "base_link", 10**9)],
            "map",
            "camera",
            1,
            ["'camera'", "not in the log's TF tree", "base_link, map"],
        ),
        (
            [_tf("map", "base_link", 10**9), _tf("laser", "camera", 0, static=True)],
            "map",
            "camera",
            1,
            ["no TF chain joins map and camera", "base_link, map", "camera, laser"],
        ),
        (
            [_tf("map", "base_link", 10**9), _tf("map", "base_link", 2 * 10**9)],
            "map",
            "base_link",
            0.5,
            [
                "outside the TF buffer of map -> base_link",
                "0.500 s before its first transform",
                "[1.000 s, 2.000 s]",
            ],
        ),
        (
            [_tf("map", "base_link", 10**9), _tf("map", "base_link", 2 * 10**9)],
            "map",
            "base_link",
            2.25,
            ["0.250 s after its last transform"],
        ),
        (
            [_tf("map", "car", 10**9), _tf("tag", "car", 0, static=True)],
            "map",
            "car",
            1,
            ["'car' has several parents (map, tag)"],
        ),
        (
            [_tf("map", "odom", 10**9), _tf("map", "odom", 0, static=True)],
            "map",
            "odom",
            1,
            ["map -> odom is published both as static and as dynamic"],
        ),
    ],
)
def test_buffer_errors_name_frames_and_gaps(transforms, a, b, stamp_s, words):
    buf = TfBuffer(transforms, source="drive.bag")
    with pytest.raises(InputError) as e:
        buf.lookup(a, b, [int(stamp_s * 1e9)], "detections")
    for w in words:
        assert w in str(e.value), (w, str(e.value))
    assert str(e.value).startswith("drive.bag: ")


def test_buffer_rejects_zero_quaternions():
    bad = ("map", "base_link", 10**9, (0, 0, 0), (0, 0, 0, 0), False, "/tf")
    with pytest.raises(InputError, match="zero or non-finite rotation"):
        TfBuffer([bad])


# --------------------------------------------------------------------- the simulated layout


@pytest.fixture(scope="module")
def drive_sim():
    """A 20 s hairpin drive seen through the camera (the hairpin's turns take the tag out of
    view), written in both layouts: the AprilTag recording and the equivalent map-frame log."""
    res = sim.simulate("hairpin", duration_s=20.0, seed=2, camera=sim.Camera())
    return res


@pytest.fixture(scope="module")
def written(drive_sim, tmp_path_factory):
    root = tmp_path_factory.mktemp("apriltag")
    sim.write_simulation(drive_sim, root / "tag")
    sim.write_simulation(drive_sim, root / "map", layout="map")
    return root


@pytest.fixture(scope="module")
def tag_drive(written):
    """The simulator's own AprilTag recording, read: what every other file of it must give."""
    return io.load_drive(written / "tag" / "drive.mcap")


@pytest.fixture(scope="module")
def no_mount_log(drive_sim, tmp_path_factory) -> Path:
    """The recording without its tag -> base transform (the mount then comes from a flag)."""
    path = tmp_path_factory.mktemp("no_mount") / "no_mount.mcap"
    return _write_mcap(path, _events(drive_sim, drop_static=("other_base_link",)))


LATE_EGO_S = 5.0  # late_log's localisation starts here


@pytest.fixture(scope="module")
def late_log(drive_sim, tmp_path_factory) -> Path:
    """The recording with the ego TF only from LATE_EGO_S: the first detections are outside it."""
    path = tmp_path_factory.mktemp("late") / "late.mcap"
    return _write_mcap(path, _events(drive_sim, ego_from_s=LATE_EGO_S))


@pytest.fixture(scope="module")
def rosbag2_mcap(drive_sim, tmp_path_factory):
    """style -> the rosbag2 folder (MCAP storage) rosbags writes of that detector's layout, written
    once: one case reads the folder, another its storage file."""
    folders = {}

    def folder(style: str) -> Path:
        if style not in folders:
            bag = tmp_path_factory.mktemp("rosbag2") / "bag"
            folders[style] = write_rosbags(bag, _events(drive_sim, style=style), storage="mcap")
        return folders[style]

    return folder


def _events(res, style="apriltag_ros", drop_static=(), ego_from_s=None):
    """The layout's events (as the simulator writes them) plus truth odometry; optionally
    without some static transforms (by child frame) or the ego TF before `ego_from_s`."""
    events = at.apriltag_events("test", style=style, **sim.apriltag_layout(res))
    if ego_from_s is not None:  # a recording whose localisation starts late
        start_ns = int(ego_from_s * 1e9)
        events = [e for e in events if e[1] != "/tf" or e[0] >= start_ns]
    d = res.drive
    events += _odom_events(
        "test",
        dict(
            t_s=d.truth_t_s,
            xy_m=d.truth_xy_m,
            yaw_rad=d.truth_yaw_rad,
            v_mps=d.truth_v_mps,
            yaw_rate_rps=res.truth_yaw_rate_rps,
        ),
    )
    for _, topic, _, msg in events:
        if topic == "/tf_static":
            msg["transforms"] = [
                t for t in msg["transforms"] if t["child_frame_id"] not in drop_static
            ]
    return events


def _write_mcap(path: Path, events) -> Path:
    _write_ros2_mcap(path, events)
    return path


def _same_drive(a, b, exact=True):
    np.testing.assert_array_equal(a.t_s, b.t_s)
    if exact:
        np.testing.assert_array_equal(a.xy_m, b.xy_m)
        np.testing.assert_array_equal(a.yaw_rad, b.yaw_rad)
    else:
        np.testing.assert_allclose(a.xy_m, b.xy_m, rtol=0, atol=1e-9)
        np.testing.assert_allclose(_wrap(a.yaw_rad - b.yaw_rad), 0.0, atol=1e-9)
    np.testing.assert_array_equal(a.truth_t_s, b.truth_t_s)
    np.testing.assert_array_equal(a.truth_xy_m, b.truth_xy_m)


def test_layout_composes_to_the_map_frame_log(drive_sim, written, tag_drive):
    tag = tag_drive
    flat = io.load_drive(written / "map" / "drive.mcap")
    assert tag.meta["pose_topic"] == DET and tag.meta["truth_topic"] == "/opp/odom"
    _same_drive(tag, flat, exact=False)
    err = np.abs(tag.xy_m - flat.xy_m).max()
    assert err < 1e-12, err  # float64 products only
    det = tag.meta["detection"]
    assert det["chain"] == ["map", "base_link", "laser", "camera", "tag_0", "other_base_link"]
    assert det["n_tag_detections"] == len(drive_sim.drive.t_s)
    assert det["n_empty_arrays"] == drive_sim.drive.meta["n_dropped"] > 0
    assert drive_sim.drive.meta["n_out_of_view"] > 0  # the hairpin's turns
    scenario = json.loads((written / "tag" / "scenario.json").read_text())
    assert scenario["topics"]["frames"] == det["chain"] and "camera" in scenario


def test_camera_only_removes_detections():
    """The default sensor's drive is untouched by the camera: same seed, same numbers, and a
    camera that sees everything gives back exactly the drive without one."""
    kw = dict(duration_s=20.0, seed=5)
    plain = sim.simulate("hairpin", **kw)
    seen = sim.simulate("hairpin", camera=sim.Camera(), **kw)
    wide = sim.simulate(
        "hairpin", camera=sim.Camera(hfov_rad=7.0, max_range_m=1e9, max_incidence_rad=4.0), **kw
    )
    assert "camera" not in plain.scenario and plain.ego_t_s is None and plain.missed_t_s is None
    for name in ("t_s", "xy_m", "yaw_rad", "truth_xy_m", "truth_v_mps"):
        np.testing.assert_array_equal(getattr(wide.drive, name), getattr(plain.drive, name))
    idx = np.searchsorted(plain.drive.t_s, seen.drive.t_s)
    np.testing.assert_array_equal(plain.drive.t_s[idx], seen.drive.t_s)
    np.testing.assert_array_equal(plain.drive.xy_m[idx], seen.drive.xy_m)
    n_lost = len(plain.drive.t_s) - len(seen.drive.t_s)
    assert n_lost == seen.drive.meta["n_out_of_view"] > 0
    assert len(seen.missed_t_s) == seen.drive.meta["n_dropped"]
    blind = sim.simulate("hairpin", camera=sim.Camera(hfov_rad=1e-6), **kw)
    assert len(blind.drive.t_s) == 0 or len(blind.drive.t_s) < 0.05 * len(plain.drive.t_s)


def test_ego_follows_at_the_sensor_gap(drive_sim):
    """The trailing car's TF is its own motion: on the centerline, 2-4 m behind, moving with
    the leading car, heading along the track."""
    r = drive_sim
    n = len(r.drive.truth_t_s)
    gap = np.linalg.norm(r.ego_xy_m - r.drive.truth_xy_m, axis=1)
    assert 1.8 < gap.min() and gap.max() < 4.2
    v = np.linalg.norm(np.diff(r.ego_xy_m, axis=0), axis=1) / np.diff(r.ego_t_s)
    assert abs(np.median(v) - np.median(r.drive.truth_v_mps)) < 0.5
    step = r.ego_xy_m[1:] - r.ego_xy_m[:-1]
    heading = np.arctan2(step[:, 1], step[:, 0])
    assert np.percentile(np.abs(_wrap(heading - r.ego_yaw_rad[:-1])), 95) < 0.1
    assert len(r.ego_t_s) == n and r.ego_t_s[-1] >= r.drive.t_s[-1]


def test_composition_matches_truth_within_the_noise(tmp_path):
    """Clean sensor: the composed poses are the truth (to the 50 Hz truth's interpolation
    error). Noisy sensor over 2 minutes: mean error (bias) < 1 cm; outliers left out."""
    kw = dict(seed=3, camera=sim.Camera())
    clean = sim.simulate("oval", duration_s=20.0, sensor=sim.Sensor.clean(), **kw)
    noisy = sim.simulate("oval", duration_s=120.0, **kw)
    for res, check in ((clean, "clean"), (noisy, "noisy")):
        sim.write_simulation(res, tmp_path / check)
        got = io.load_drive(tmp_path / check / "drive.mcap")
        d = res.drive
        np.testing.assert_allclose(got.t_s, d.t_s, rtol=0, atol=1e-9)  # stamps: whole ns
        np.testing.assert_allclose(got.xy_m, d.xy_m, rtol=0, atol=1e-9)  # exactly the sim's noise
        np.testing.assert_allclose(_wrap(got.yaw_rad - d.yaw_rad), 0, atol=1e-9)
        tx = np.interp(res.capture_t_s, d.truth_t_s, d.truth_xy_m[:, 0])
        ty = np.interp(res.capture_t_s, d.truth_t_s, d.truth_xy_m[:, 1])
        err = got.xy_m - np.stack([tx, ty], 1)
        if check == "clean":
            assert np.abs(err).max() < 2e-3  # linear interpolation of 50 Hz truth
        else:
            # ~1350 detections, sigma ~0.15 m per axis: the mean's spread is ~4 mm per axis.
            good = ~res.outlier
            bias = np.abs(err[good].mean(axis=0))
            assert (bias < 0.01).all(), bias
            assert 0.02 < np.std(err[good]) < 0.3  # the noise is there, of the modelled size


# --------------------------------------------------------------------- files from rosbags


@pytest.mark.parametrize(
    "style, container",
    [
        ("apriltag_ros", "rosbag1"),
        ("apriltags2_ros", "rosbag1"),
        ("apriltag_ros", "rosbag2-mcap"),
        ("apriltag_ros", "inner-mcap"),
        ("apriltag_msgs", "rosbag2-mcap"),
        ("apriltag_msgs", "inner-mcap"),
        ("apriltag_msgs", "rosbag2-db3"),
    ],
)
def test_rosbags_written_variants_read_back_the_same(
    drive_sim, tag_drive, rosbag2_mcap, tmp_path, style, container
):
    """ROS 1 bags and rosbag2 (MCAP / sqlite3 storage) written by rosbags, in each detector's
    message layout, compose to the very drive the simulator's own MCAP gives; "inner-mcap"
    reads the rosbag2 storage file through mcap + mcap_ros2 (rosbags' embedded schemas)."""
    events = _events(drive_sim, style=style)
    if container == "rosbag1":
        path = write_rosbags(tmp_path / "drive.bag", events, storage="ros1")
    elif container == "rosbag2-db3":
        path = write_rosbags(tmp_path / "bag", events, storage="sqlite3")
    else:
        path = rosbag2_mcap(style)
        if container == "inner-mcap":
            (path,) = path.glob("*.mcap")
    got = io.load_drive(path)
    _same_drive(got, tag_drive)
    det = got.meta["detection"]
    if style == "apriltag_msgs":
        assert det["tag_frame"] == "tag36h11:0"
        assert det["links"][1]["from"] == "TF camera -> tag36h11:0 at each detection's stamp"
    else:
        assert det["tag_frame"] == "tag_0" and det["links"][1]["from"] == "the detection's pose"
    assert got.meta["pose_type"] == rm.full_type(
        f"{'apriltag_msgs' if style == 'apriltag_msgs' else style}/AprilTagDetectionArray"
    )


def test_fork_layouts_read_from_their_embedded_definitions(drive_sim, tag_drive, tmp_path):
    """ROS 2 forks reuse names with other fields: e.g. an `apriltag_msgs` whose detection holds
    a scalar id and size and the ROS 1 pose. The file's own schema decides how it decodes."""
    from mcap_ros2.writer import Writer

    fork = rm.definition("apriltag_ros/AprilTagDetectionArray").replace(
        "apriltag_ros/AprilTagDetection", "apriltag_msgs/AprilTagDetection"
    )
    fork = fork.replace("int32[] id", "int32 id").replace("float64[] size", "float64 size")
    path = tmp_path / "fork.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        schemas = {}
        for ns, topic, msgtype, msg in sorted(_events(drive_sim), key=lambda e: e[0]):
            if topic == DET:
                msgtype = "apriltag_msgs/AprilTagDetectionArray"
                for det in msg["detections"]:
                    det["id"], det["size"] = det["id"][0], det["size"][0]
            if msgtype not in schemas:
                text = fork if topic == DET else rm.definition(msgtype)
                schemas[msgtype] = w.register_msgdef(rm.full_type(msgtype), text)
            w.write_message(topic, schemas[msgtype], msg, log_time=ns, publish_time=ns)
        w.finish()
    got = io.load_drive(path)
    assert got.meta["pose_type"] == "apriltag_msgs/msg/AprilTagDetectionArray"
    _same_drive(got, tag_drive)


def test_recordings_without_definitions_use_the_shipped_ones(drive_sim, tag_drive, tmp_path):
    """An MCAP channel with an empty schema (what rosbag2 writes for a type it has no definition
    of) and a rosbag2 sqlite3 recording without definitions both decode."""
    events = _events(drive_sim)
    want = tag_drive
    # MCAP: the mcap writer with empty ros2msg schemas, CDR from rosbags.
    from mcap.writer import Writer

    store = shipped_typestore(Stores.ROS2_HUMBLE)
    path = tmp_path / "bare.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="ros2")
        schemas, channels = {}, {}
        for ns, topic, msgtype, msg in sorted(events, key=lambda e: e[0]):
            full = rm.full_type(msgtype)
            if full not in schemas:
                schemas[full] = w.register_schema(full, "ros2msg", b"")
            if topic not in channels:
                channels[topic] = w.register_channel(topic, "cdr", schemas[full])
            data = store.serialize_cdr(_to_rosbags(store, full, msg), full)
            w.add_message(channels[topic], log_time=ns, data=data, publish_time=ns)
        w.finish()
    _same_drive(io.load_drive(path), want)
    # rosbag2 sqlite3 with its definitions removed (an older recorder's bag).
    folder = write_rosbags(tmp_path / "old", events, storage="sqlite3")
    (db3,) = folder.glob("*.db3")
    with sqlite3.connect(db3) as con:
        con.execute("DELETE FROM message_definitions")
    _same_drive(io.load_drive(folder), want)


def test_tag_to_base_flag_equals_the_static_transform(no_mount_log, tag_drive):
    path = no_mount_log
    cam = sim.Camera()
    mount = ",".join(f"{v!r}" for v in (*cam.tag_xyz_m, cam.tag_yaw_rad))
    got = io.load_drive(path, tag_to_base=mount)
    _same_drive(got, tag_drive, exact=False)
    assert got.meta["detection"]["links"][2]["from"].startswith("--tag-to-base -0.2,0,0.2,3.14159")
    with pytest.raises(InputError, match="--tag-to-base X,Y,Z,YAW"):
        io.load_drive(path)
    # A wrong mount moves the car: the flag is used, not ignored.
    off = io.load_drive(path, tag_to_base=[-0.5, 0.0, 0.2, np.pi])
    assert np.median(np.linalg.norm(off.xy_m - got.xy_m, axis=1)) == pytest.approx(0.3, abs=1e-9)


def test_tag_frame_found_under_another_name(drive_sim, tag_drive, tmp_path):
    """A tag frame not called tag_<id>: the car frame's parent in a tree of its own."""
    events = _events(drive_sim)
    for _, topic, _, msg in events:
        for t in msg.get("transforms", []) if topic == "/tf_static" else []:
            if t["header"]["frame_id"] == "tag_0":
                t["header"]["frame_id"] = "rear_tag"
    got = io.load_drive(_write_mcap(tmp_path / "renamed.mcap", events))
    assert got.meta["detection"]["tag_frame"] == "rear_tag"
    _same_drive(got, tag_drive)


def test_detector_tf_beside_pose_carrying_detections(drive_sim, tag_drive, tmp_path):
    """apriltag_ros can also publish camera -> tag_0 on /tf: the tree then hangs the tag under
    the camera; the detections' own poses are still what is composed."""
    events = _events(drive_sim)
    for ns, topic, msgtype, msg in _events(drive_sim, style="apriltag_msgs"):
        if topic == "/tf" and msg["transforms"][0]["child_frame_id"] == "tag36h11:0":
            msg["transforms"][0]["child_frame_id"] = "tag_0"
            events.append((ns, topic, msgtype, msg))
    got = io.load_drive(_write_mcap(tmp_path / "both.mcap", events))
    _same_drive(got, tag_drive)
    assert got.meta["detection"]["links"][1]["from"] == "the detection's pose"


def test_drop_outside_tf_drops_and_counts(drive_sim, late_log):
    start, path = LATE_EGO_S, late_log
    with pytest.raises(
        InputError, match="before its first transform.*drop-outside-tf|before its first"
    ):
        io.load_drive(path)
    got = io.load_drive(path, drop_outside_tf=True)
    first_tf = drive_sim.ego_t_s[drive_sim.ego_t_s >= start][0]
    n_early = int(np.sum(drive_sim.drive.t_s < first_tf - 1e-9))
    assert got.meta["detection"]["n_dropped_outside_tf"] == n_early > 0
    assert len(got.t_s) == len(drive_sim.drive.t_s) - n_early and got.t_s[0] >= first_tf - 1e-9


# --------------------------------------------------------------------- the CLI


def _fpe(capsys, *args) -> tuple[int, str, str]:
    return cli_runner(capsys, args)


def _bad(tmp_path, name, events):
    return _write_mcap(tmp_path / f"{name}.mcap", events)


def test_cli_errors_are_one_line_and_exit_2(
    drive_sim, written, no_mount_log, late_log, tmp_path, capsys
):
    ev = _events(drive_sim)
    empty = [e for e in ev if e[1] != DET] + [
        (e[0], e[1], e[2], dict(e[3], detections=[])) for e in ev if e[1] == DET
    ]
    cases = {
        "missing-link": (
            _bad(tmp_path, "nolink", _events(drive_sim, drop_static=("laser",))),
            [],
            ["no TF chain joins map and camera", "{base_link, map}", "{camera, laser}"],
        ),
        "missing-frame": (
            _bad(tmp_path, "nocam", _events(drive_sim, drop_static=("camera",))),
            [],
            ["TF frame 'camera' is not in the log's TF tree", "frames: base_link, laser, map"],
        ),
        "too-old": (
            late_log,
            [],
            ["outside the TF buffer of map -> base_link", "s before its first transform"],
        ),
        "wrong-id": (
            written / "tag" / "drive.mcap",
            ["--tag-id", 3],
            ["no detection of tag 3", "tag ids seen: 0 (", "--tag-id one of 0"],
        ),
        "empty": (_bad(tmp_path, "empty", empty), [], ["detection arrays are empty"]),
        "bad-mount": (
            written / "tag" / "drive.mcap",
            ["--tag-to-base", "1,2,3"],
            ["--tag-to-base", "not four finite numbers"],
        ),
        "tag-flag-on-pose-log": (
            written / "map" / "drive.mcap",
            ["--tag-id", 0],
            ["--tag-id applies to AprilTag detection topics"],
        ),
    }
    for name, (log, flags, words) in cases.items():
        out_csv = tmp_path / f"{name}.csv"
        rc, out, err = _fpe(capsys, "convert", log, "--out", out_csv, *flags)
        assert rc == 2, (name, err)
        assert err.count("\n") == 1 and err.startswith("fpe: error: "), (name, err)
        for w in words:
            assert w in err, (name, w, err)
        assert not out_csv.exists()
    # The mount as a user types it (a negative X needs the `=` form).
    rc, _, err = _fpe(
        capsys,
        "convert",
        no_mount_log,
        "--out",
        tmp_path / "m.csv",
        "--tag-to-base=-0.2,0,0.2,3.14159265",
    )
    assert rc == 0 and "wrote" in err
    # The same through a command that predicts (the error comes before any JAX work).
    wp = written / "tag" / "waypoints.csv"
    pred = tmp_path / "p.csv"
    rc, _, err = _fpe(capsys, "predict", cases["missing-link"][0], "--waypoints", wp, "--out", pred)
    assert rc == 2 and "no TF chain joins map and camera" in err and not pred.exists()


def test_cli_info_prints_the_tf_tree_and_the_chain(written, capsys):
    rc, out, _ = _fpe(capsys, "info", written / "tag" / "drive.mcap")
    assert rc == 0
    lines = out.splitlines()
    assert "TF tree:" in lines
    dyn = next(line for line in lines if "map -> base_link" in line and "dynamic" in line)
    assert "50.00 Hz" in dyn and "transforms" in dyn
    assert any(
        line.strip().startswith("base_link -> laser") and line.endswith("static") for line in lines
    )
    assert any("laser -> camera" in line and "static" in line for line in lines)
    assert "  chain: map -> base_link -> laser -> camera -> tag_0 -> other_base_link" in lines
    assert any("camera -> tag_0" in line and "the detection's pose" in line for line in lines)
    assert "pose:  /tag_detections" in lines
    rc, out, _ = _fpe(capsys, "info", written / "tag" / "drive.mcap", "--json")
    info = json.loads(out)
    assert [(e["parent"], e["child"], e["static"]) for e in info["tf_tree"]] == [
        ("map", "base_link", False),
        ("base_link", "laser", True),
        ("laser", "camera", True),
        ("tag_0", "other_base_link", True),
    ]
    assert info["detections"][0]["chain"][-2:] == ["tag_0", "other_base_link"]
    # A chain that cannot be composed is reported, not fatal, in info.
    rc, out, _ = _fpe(capsys, "info", written / "tag" / "drive.mcap", "--tag-id", "7")
    assert (
        rc == 0
        and "cannot be composed: detection topic '/tag_detections' has no detection of tag 7" in out
    )


def test_cli_simulate_apriltag_and_convert_for_run(tmp_path, capsys):
    out = tmp_path / "sim"
    rc, _, err = _fpe(
        capsys,
        "simulate",
        "--track",
        "hairpin",
        "--duration",
        "8",
        "--sensor",
        "apriltag",
        "--out",
        out,
    )
    assert rc == 0 and "detections" in err
    info = io.describe_log(out / "drive.mcap")
    assert {t["name"] for t in info["topics"]} == {"/opp/odom", DET, "/tf", "/tf_static"}
    csv = tmp_path / "obs.csv"
    assert _fpe(capsys, "convert", out / "drive.mcap", "--out", csv)[0] == 0
    assert csv.read_text().startswith("t,x,y,yaw\n")
    drive = io.load_drive(out / "drive.mcap")
    back = io.load_drive(csv)
    np.testing.assert_allclose(back.t_s, drive.t_s, rtol=0, atol=1e-9)
    np.testing.assert_allclose(back.xy_m, drive.xy_m, rtol=0, atol=1e-9)
    # `fpe run` reads that file on stdin: one prediction per row.
    import io as pyio

    from fpe_jax.runner._runner import BENCH_CONFIG, Runner, run_stream

    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps(BENCH_CONFIG))
    runner = Runner.from_config(cfg, out / "waypoints.csv")
    sink, errs = pyio.StringIO(), pyio.StringIO()
    assert run_stream(runner, pyio.StringIO(csv.read_text()), sink, errs) == 0
    assert errs.getvalue() == "" and len(sink.getvalue().splitlines()) == len(drive.t_s)
    assert _fpe(capsys, "convert", out / "drive.mcap", "--out", csv)[0] == 2  # no overwrite


def test_recipe_takes_tag_keys(written, tag_drive, tmp_path):
    from fpe_jax.fit._recipe import load_recipe

    cam = sim.Camera()
    recipe = tmp_path / "r.toml"
    recipe.write_text(
        f'waypoints = "{written / "tag" / "waypoints.csv"}"\n'
        f'[[drives]]\npath = "{written / "tag" / "drive.mcap"}"\ntag_id = 0\n'
        f"tag_to_base = {[*cam.tag_xyz_m, cam.tag_yaw_rad]}\n"
    )
    ((d, _, _),) = load_recipe(recipe).drives
    _same_drive(d, tag_drive, exact=False)
    recipe.write_text(recipe.read_text().replace("tag_to_base = [", "tag_to_base = [1, "))
    with pytest.raises(InputError, match="tag_to_base"):
        load_recipe(recipe)


def test_fit_and_predict_equal_the_map_frame_log(written, tmp_path, capsys):
    """`fpe fit` / `fpe predict` on the AprilTag recording give what they give on the map-frame
    log of the same simulated drive (within 1e-6 m; measured ~1e-14)."""
    wp = written / "tag" / "waypoints.csv"
    params, preds = {}, {}
    for k in ("tag", "map"):
        log, cfg, pred = written / k / "drive.mcap", tmp_path / f"{k}.json", tmp_path / f"{k}.csv"
        assert (
            _fpe(capsys, "fit", log, "--waypoints", wp, "--out", cfg, "--blend", "position")[0] == 0
        )
        assert (
            _fpe(capsys, "predict", log, "--waypoints", wp, "--config", cfg, "--out", pred)[0] == 0
        )
        params[k] = json.loads(cfg.read_text())["params"]
        preds[k] = np.genfromtxt(pred, delimiter=",", names=True)
    for name, value in params["map"].items():
        np.testing.assert_allclose(params["tag"][name], value, rtol=0, atol=1e-6, err_msg=name)
    for col in ("stamp", "x", "y"):
        np.testing.assert_allclose(preds["tag"][col], preds["map"][col], rtol=0, atol=1e-6)
    np.testing.assert_allclose(_wrap(preds["tag"]["yaw"] - preds["map"]["yaw"]), 0, atol=1e-6)
