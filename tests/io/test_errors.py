"""Bad input through the CLI: exit status 2, one line on stderr naming the file, nothing written."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from helpers import PS, TF, cli_runner, make_series, series_events, write_mcap

from fpe_jax import cli, io
from fpe_jax.errors import InputError
from fpe_jax.io import ros_msgs as rm


def _good_waypoints(tmp_path: Path) -> Path:
    f = tmp_path / "wp.csv"
    a = np.linspace(0, 2 * np.pi, 60, endpoint=False)
    np.savetxt(f, np.column_stack([10 * np.cos(a), 10 * np.sin(a), a]), delimiter=",")
    return f


def _good_drive(tmp_path: Path) -> Path:
    f = tmp_path / "drive.csv"
    f.write_text("t,x,y\n0,10,0\n0.1,10,0.1\n0.2,10,0.2\n")
    return f


def _pose_log(tmp_path: Path, topics=("/p",), msgtype=PS) -> Path:
    s = make_series(6)
    return write_mcap(
        tmp_path / "log.mcap", [e for t in topics for e in series_events(t, msgtype, s)]
    )


def _string_log(tmp_path: Path) -> Path:
    from mcap_ros2.writer import Writer

    f = tmp_path / "chatter.mcap"
    with open(f, "wb") as fh, Writer(fh) as w:
        schema = w.register_msgdef("std_msgs/msg/String", "string data\n")
        w.write_message("/chatter", schema, {"data": "hello"}, log_time=1)
    return f


def _silent_topic_log(tmp_path: Path) -> Path:
    """A channel that is declared but never carries a message."""
    from mcap.writer import Writer

    f = tmp_path / "silent.mcap"
    with open(f, "wb") as fh:
        w = Writer(fh)
        w.start(profile="ros2", library="test")
        sid = w.register_schema(rm.full_type(PS), "ros2msg", rm.definition(PS).encode())
        w.register_channel("/p", "cdr", sid)
        w.finish()
    return f


def _json_log(tmp_path: Path) -> Path:
    """A channel that claims PoseStamped but holds JSON, not CDR."""
    from mcap.writer import Writer

    f = tmp_path / "json.mcap"
    with open(f, "wb") as fh:
        w = Writer(fh)
        w.start(profile="", library="test")
        sid = w.register_schema(rm.full_type(PS), "jsonschema", b"{}")
        cid = w.register_channel("/p", "json", sid)
        w.add_message(cid, log_time=1, data=b"{}", publish_time=1)
        w.finish()
    return f


def _truncated_log(tmp_path: Path) -> Path:
    good = write_mcap(tmp_path / "good.mcap", series_events("/p", PS, make_series(300)))
    f = tmp_path / "cut.mcap"
    f.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    return f


def _file(name: str, content: bytes):
    def make(tmp_path: Path) -> Path:
        f = tmp_path / name
        f.write_bytes(content)
        return f

    return make


def _all_nan_log(tmp_path: Path) -> Path:
    s = make_series(4)
    s["xy"][:] = np.nan
    return write_mcap(tmp_path / "nan.mcap", series_events("/p", PS, s))


# (id, make the bad drive file, extra flags, words the message must contain)
DRIVE_CASES = [
    ("missing-mcap", lambda p: p / "nope.mcap", [], "does not exist"),
    ("missing-csv", lambda p: p / "nope.csv", [], "does not exist"),
    ("empty-mcap", _file("e.mcap", b""), [], "is empty"),
    ("empty-csv", _file("e.csv", b""), [], "no data rows"),
    ("unknown-format", _file("d.xyz", b"1,2,3\n"), [], "unknown drive format"),
    ("garbage-mcap", _file("g.mcap", bytes(range(256)) * 8), [], "corrupt"),
    ("magic-only-mcap", _file("m.mcap", b"\x89MCAP0\r\n"), [], "corrupt"),
    ("truncated-mcap", _truncated_log, [], "corrupt"),
    ("garbage-bag", _file("g.bag", b"#ROSBAG V2.0\n" + b"\x00" * 64), [], "corrupt"),
    ("folder-not-a-bag", lambda p: p, [], "metadata.yaml"),
    ("pose-topic-absent", _pose_log, ["--pose-topic", "/nope"], "no pose topic '/nope'"),
    ("unsupported-type", _string_log, ["--pose-topic", "/chatter"], "std_msgs/String"),
    ("no-pose-topic", _string_log, [], "no pose topic among /chatter"),
    (
        "several-pose-topics",
        lambda p: _pose_log(p, ("/a", "/b")),
        [],
        "several pose topics: /a, /b",
    ),
    ("json-encoded", _json_log, [], "encoded as 'json'"),
    ("no-messages", _silent_topic_log, ["--pose-topic", "/p"], "has no messages"),
    ("tf-pair-absent", lambda p: _pose_log(p, ("/tf",), TF), ["--tf-child", "x"], "map -> x"),
    (
        "tf-topic-lacks-pair",
        lambda p: _pose_log(p, ("/tf",), TF),
        ["--pose-topic", "/tf", "--tf-child", "x"],
        "other_base_link",
    ),
    ("truth-topic-absent", _pose_log, ["--truth-topic", "/odom"], "no truth topic '/odom'"),
    ("all-nan", _all_nan_log, [], "NaN or infinite"),
    ("rate-on-log", _pose_log, ["--rate", "10"], "--rate"),
    ("csv-needs-rate", _file("a.csv", b"1,2,0\n3,4,0\n"), [], "--rate HZ is required"),
    ("csv-bad-rate", _file("a.csv", b"1,2,0\n3,4,0\n"), ["--rate", "-1"], "--rate is -1.0"),
    ("csv-rate-and-t", _file("a.csv", b"t,x,y\n0,1,2\n"), ["--rate", "5"], "time column"),
    (
        "csv-non-numeric",
        _file("a.csv", b"t,x,y\n0,1,2\n1,one,2\n"),
        [],
        "line 3: non-numeric cell 'one'",
    ),
    ("csv-ragged", _file("a.csv", b"t,x,y\n0,1\n"), [], "line 2 has 2 cells"),
    ("csv-no-x", _file("a.csv", b"t,east,y\n0,1,2\n"), [], "no x column"),
    ("csv-header-only", _file("a.csv", b"t,x,y\n"), [], "no data rows"),
    ("csv-4-col-headerless", _file("a.csv", b"0,1,2,3\n"), ["--rate", "1"], "4 columns"),
    ("csv-pose-topic", _file("a.csv", b"t,x,y\n0,1,2\n"), ["--pose-topic", "/p"], "ROS logs"),
    ("csv-binary", _file("a.csv", b"\xff\xfe\x00garbage"), [], "not a text file"),
]


def _run(argv, capsys) -> str:
    err = cli_runner(capsys, argv, expect=2)[2]
    assert err.count("\n") == 1 and err.startswith("fpe: error: "), err
    return err


def _assert_nothing_written(tmp_path: Path, out: Path) -> None:
    assert not out.exists()
    assert not list(tmp_path.glob(".*.part"))


@pytest.mark.parametrize(
    "make, flags, words", [c[1:] for c in DRIVE_CASES], ids=[c[0] for c in DRIVE_CASES]
)
def test_bad_drive_through_predict(tmp_path, capsys, make, flags, words):
    bad = make(tmp_path)
    out = tmp_path / "pred.csv"
    err = _run(
        ["predict", bad, "--waypoints", _good_waypoints(tmp_path), "--out", out, *flags], capsys
    )
    assert str(bad) in err and words in err, err
    _assert_nothing_written(tmp_path, out)
    with pytest.raises(InputError, match=words.replace("(", r"\(")):
        io.load_drive(
            bad,
            pose_topic=flags[flags.index("--pose-topic") + 1] if "--pose-topic" in flags else None,
            truth_topic=flags[flags.index("--truth-topic") + 1]
            if "--truth-topic" in flags
            else None,
            rate_hz=float(flags[flags.index("--rate") + 1]) if "--rate" in flags else None,
            tf_child=flags[flags.index("--tf-child") + 1]
            if "--tf-child" in flags
            else "other_base_link",
        )


@pytest.mark.parametrize(
    "case", ["missing-mcap", "garbage-mcap", "truncated-mcap", "pose-topic-absent"]
)
def test_bad_log_through_info(tmp_path, capsys, case):
    _, make, flags, words = next(c for c in DRIVE_CASES if c[0] == case)
    bad = make(tmp_path)
    err = _run(["info", bad, *flags], capsys)
    assert str(bad) in err and words in err


# (id, waypoint file content or maker, words)
WAYPOINT_CASES = [
    ("two-distinct", b"0,0,0\n1,1,0\n0,0,0\n1,1,0\n", "only 2 distinct waypoints"),
    ("non-numeric", b"# x_m, y_m, w_tr_right_m, w_tr_left_m\n0,0,1,1\n1,x,1,1\n", "line 3"),
    ("no-x-column", b"a,y\n0,0\n1,0\n2,2\n", "no x column"),
    ("four-col-headerless", b"0,0,1,1\n1,0,1,1\n2,2,1,1\n", "4 columns"),
    ("nan-point", b"0,0\n1,0\nnan,1\n2,2\n", "data row 3"),
    ("missing", None, "does not exist"),
    ("no-path-topic", "log", "no nav_msgs/Path topics"),
]


@pytest.mark.parametrize(
    "content, words", [c[1:] for c in WAYPOINT_CASES], ids=[c[0] for c in WAYPOINT_CASES]
)
def test_bad_waypoints_through_predict(tmp_path, capsys, content, words):
    wp = tmp_path / "wp.csv"
    if content == "log":
        wp = _pose_log(tmp_path)
    elif content is not None:
        wp.write_bytes(content)
    out = tmp_path / "pred.mcap"
    err = _run(["predict", _good_drive(tmp_path), "--waypoints", wp, "--out", out], capsys)
    assert str(wp) in err and words in err, err
    _assert_nothing_written(tmp_path, out)


def test_output_path_errors(tmp_path, capsys):
    drive, wp = _good_drive(tmp_path), _good_waypoints(tmp_path)
    out = tmp_path / "pred.csv"
    out.write_text("precious")
    err = _run(["predict", drive, "--waypoints", wp, "--out", out], capsys)
    assert str(out) in err and "--force" in err and out.read_text() == "precious"
    nowhere = tmp_path / "no" / "such" / "pred.csv"
    err = _run(["predict", drive, "--waypoints", wp, "--out", nowhere], capsys)
    assert str(nowhere) in err and "does not exist" in err
    with pytest.raises(InputError, match="unknown output format '.txt'"):
        io.write_predictions(tmp_path / "p.txt", np.zeros(1), np.zeros((1, 2, 3)), 0.1)
    with pytest.raises(InputError, match="is a folder"):
        io.check_output_path(tmp_path, force=True)
    _assert_nothing_written(tmp_path, tmp_path / "p.txt")


def test_failed_write_leaves_nothing(tmp_path):
    """A writer that fails half-way (a stamp that cannot be a ROS time) leaves no file."""
    out = tmp_path / "sim.mcap"
    with pytest.raises(InputError, match="stamps must be finite"):
        io.write_drive_mcap(
            out, pose=dict(t_s=[0.0, np.nan], xy_m=np.zeros((2, 2)), yaw_rad=[0, 0])
        )
    with pytest.raises(InputError, match="xy_m has shape"):
        io.write_drive_mcap(out, pose=dict(t_s=[0.0, 1.0], xy_m=np.zeros((3, 2)), yaw_rad=[0, 0]))
    with pytest.raises(InputError, match="missing v_mps"):
        io.write_drive_mcap(out, odom=dict(t_s=[0.0], xy_m=[[0, 0]], yaw_rad=[0], yaw_rate_rps=[0]))
    _assert_nothing_written(tmp_path, out)


def test_bad_path_topic_in_waypoint_log(tmp_path):
    log = _pose_log(tmp_path)
    with pytest.raises(InputError, match="no nav_msgs/Path topic '/plan'"):
        io.load_waypoints(log, topic="/plan")
    with pytest.raises(InputError, match="not a ROS log"):
        io.load_waypoints(_good_waypoints(tmp_path), topic="/plan")


def test_library_errors_name_the_argument_and_the_cli_its_flag(tmp_path, capsys):
    """The library names its own argument (a Python caller has no flags); the CLI maps it to the
    flag that sets it (argparse itself refuses a --format or --dtype outside its choices)."""
    from fpe_jax import spec
    from fpe_jax.evaluate._evaluate import split_drive
    from fpe_jax.geometry._track import Track
    from fpe_jax.io.config import load_params, params_to_config, write_config
    from fpe_jax.io.export import export_config
    from fpe_jax.model._params import presets
    from fpe_jax.predict._batch import BatchPredictor
    from fpe_jax.sim._sim import simulate

    drive = simulate("oval", duration_s=5.0).drive
    cfg = tmp_path / "c.json"
    write_config(cfg, params_to_config(presets["default"]))
    wp = _good_waypoints(tmp_path)
    track = Track.from_waypoints(np.loadtxt(wp, delimiter=",")[:, :2])
    library = [
        ("holdout", lambda: split_drive(drive, 1.5)),
        ("preset", lambda: load_params(preset="nope")),
        ("chunk", lambda: spec.check_chunk(0)),
        ("dtype", lambda: BatchPredictor(presets["default"], track, dtype="int8")),
        ("fmt", lambda: export_config(cfg, "xml", tmp_path / "o")),
        ("node", lambda: export_config(cfg, "ros2", tmp_path / "o.yaml", node="a b")),
        ("waypoints", lambda: export_config(cfg, "stablehlo", tmp_path / "o.shlo")),
    ]
    for name, call in library:
        with pytest.raises(InputError) as e:
            call()
        assert e.value.source == name, (name, str(e.value))
    drive_csv = _good_drive(tmp_path)
    through_cli = [
        ("--holdout", f"fit {drive_csv} --waypoints {wp} --out {tmp_path}/f.json --holdout 1.5"),
        ("--preset", f"evaluate {drive_csv} --waypoints {wp} --preset nope"),
        ("--node", f"export {cfg} --format ros2 --out {tmp_path}/o.yaml --node a.b"),
        ("--waypoints", f"export {cfg} --format stablehlo --out {tmp_path}/o.shlo"),
    ]
    for flag, argv in through_cli:
        assert cli.main(argv.split()) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith(f"fpe: error: {flag}: "), (argv, err)
