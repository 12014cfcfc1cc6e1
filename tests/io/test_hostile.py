"""Hostile input to the readers: TF dropouts, constant stamps, epoch stamps, deep TF trees, long
output names, floods of bad stream lines, number syntax, disagreeing static transforms, absurd
mounts and a tag seen twice in one image.

Exactness: epoch and zero-based stamps that differ by whole seconds must give the same predictions
to 1e-9 m (the integer nanoseconds are kept until the time origin is subtracted, so the two runs
see the same float64 relative stamps; measured differences are 0).
"""

from __future__ import annotations

import io as pyio
import json
import subprocess
import sys
import tracemalloc

import numpy as np
import pytest

from fpe_jax import cli, io, spec
from fpe_jax.errors import InputError
from fpe_jax.io import apriltag as at
from fpe_jax.io import tables
from fpe_jax.io.stream import read_observations
from fpe_jax.io.tf import TfBuffer
from fpe_jax.io.writers import _odom_events, _pose_msg, _write_ros2_mcap
from fpe_jax.sim import _sim as sim

S = 1_000_000_000  # ns per second
EPOCH_NS = 1_700_000_000 * S


def _tf(parent, child, ns, t=(0.0, 0.0, 0.0), yaw=0.0, static=False):
    q = (0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2))
    return (parent, child, ns, t, q, static, "/tf_static" if static else "/tf")


def _ten_hz_with_gap(gap_from_s: float, gap_to_s: float, end_s: float = 6.0):
    """map -> base_link at 10 Hz on [0, end], none strictly inside (gap_from, gap_to); x = t m."""
    t = np.arange(0, round(end_s * 10) + 1) / 10
    t = t[(t <= gap_from_s + 1e-9) | (t >= gap_to_s - 1e-9)]
    return [_tf("map", "base_link", int(round(k * S)), (k, 0.0, 0.0)) for k in t]


# --------------------------------------------------------------------- 3: TF dropouts


def test_lookup_across_a_long_tf_gap_is_refused_with_the_edge_and_the_gap():
    buf = TfBuffer(_ten_hz_with_gap(2.0, 5.0), source="drive.bag")
    # within the samples and at the gap's own samples: fine
    got = buf.lookup("map", "base_link", [int(1.05 * S), 2 * S, 5 * S])
    np.testing.assert_allclose(got.t_m[:, 0], [1.05, 2.0, 5.0], atol=1e-12)
    with pytest.raises(InputError) as e:
        buf.lookup("map", "base_link", [1 * S, int(3.5 * S)], "detections on /tag")
    msg = str(e.value)
    for words in ("map -> base_link", "gap of 3.000 s", "2.000 s", "5.000 s", "3.500 s",
                  "1 of 2 detections on /tag", "0.400 s", "--max-tf-gap"):  # fmt: skip
        assert words in msg, (words, msg)
    assert list(buf.covers("map", "base_link", [1 * S, int(3.5 * S), 5 * S])) == [1, 0, 1]
    # the default limit: 4 sample periods (0.4 s at 10 Hz); a 0.3 s gap is interpolated
    short = TfBuffer(_ten_hz_with_gap(2.0, 2.3))
    assert short.covers("map", "base_link", [int(2.15 * S)]).all()
    # a limit set by the caller
    loose = TfBuffer(_ten_hz_with_gap(2.0, 5.0), max_gap_s=3.5)
    np.testing.assert_allclose(loose.lookup("map", "base_link", [int(3.5 * S)]).t_m[0, 0], 3.5)
    with pytest.raises(InputError, match="max_gap_s"):
        TfBuffer([], max_gap_s=-1.0)


def test_default_gap_limit_is_four_periods_but_at_least_0_2_s():
    fast = [_tf("map", "base_link", k * S // 100, (k / 100, 0, 0)) for k in range(300)]
    fast = [f for f in fast if not (100 < f[2] * 100 // S < 115)]  # a 0.15 s dropout at 100 Hz
    buf = TfBuffer(fast)
    assert buf.edges[("map", "base_link")].max_gap_ns == int(0.2 * S)
    assert buf.covers("map", "base_link", [int(1.07 * S)]).all()
    rows = {(r["parent"], r["child"]): r for r in buf.describe()}
    assert rows[("map", "base_link")]["max_gap_s"] == pytest.approx(0.15)


@pytest.fixture(scope="module")
def hairpin():
    return sim.simulate("hairpin", duration_s=20.0, seed=2, camera=sim.Camera())


def _layout_events(res, ego_gap_s=None, det_stamp=None):
    """The simulator's AprilTag events plus truth; the ego TF removed inside `ego_gap_s`; the
    detections' header stamps replaced by `det_stamp(ns)`."""
    events = at.apriltag_events("test", **sim.apriltag_layout(res))
    if ego_gap_s is not None:
        lo, hi = (int(v * S) for v in ego_gap_s)
        events = [e for e in events if e[1] != "/tf" or not lo < e[0] < hi]
    if det_stamp is not None:
        for ns, topic, _, msg in events:
            if topic == at.DETECTION_TOPIC:
                msg["header"]["stamp"] = {"sec": 0, "nanosec": 0} | det_stamp(ns)
                for d in msg["detections"]:
                    d["pose"]["header"]["stamp"] = msg["header"]["stamp"]
    d = res.drive
    truth = dict(t_s=d.truth_t_s, xy_m=d.truth_xy_m, yaw_rad=d.truth_yaw_rad, v_mps=d.truth_v_mps)
    return events + _odom_events("test", truth | {"yaw_rate_rps": res.truth_yaw_rate_rps})


def test_detections_across_an_ego_tf_dropout_are_refused_or_dropped(hairpin, tmp_path, capsys):
    path = _write_ros2_mcap(tmp_path / "gap.mcap", _layout_events(hairpin, ego_gap_s=(8.0, 11.0)))
    with pytest.raises(InputError, match=r"gap of 3\.000 s in the TF of map -> base_link"):
        io.load_drive(path)
    got = io.load_drive(path, drop_outside_tf=True)
    t = hairpin.drive.t_s
    ego = hairpin.ego_t_s
    lo, hi = ego[ego <= 8.0][-1], ego[ego >= 11.0][0]
    n_in_gap = int(np.sum((t > lo) & (t < hi)))
    assert got.meta["detection"]["n_dropped_tf_gap"] == n_in_gap > 0
    assert got.meta["detection"]["n_dropped_outside_tf"] == n_in_gap
    assert len(got.t_s) == len(t) - n_in_gap
    assert not np.any((got.t_s > lo) & (got.t_s < hi))
    # a limit longer than the dropout accepts it
    assert len(io.load_drive(path, max_tf_gap_s=4.0).t_s) == len(t)
    # the command line: refused in one line, or dropped with a note that counts them
    out = tmp_path / "c.csv"
    rc = cli.main(["convert", str(path), "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "gap of 3.0" in err and not out.exists()
    rc = cli.main(["convert", str(path), "--out", str(out), "--drop-outside-tf"])
    err = capsys.readouterr().err
    assert rc == 0 and f"dropped {n_in_gap} detections" in err
    rc = cli.main(["convert", str(path), "--out", str(out), "--max-tf-gap", "4", "--force"])
    assert rc == 0, capsys.readouterr().err
    rc = cli.main(["convert", str(path), "--out", str(out), "--max-tf-gap", "-1", "--force"])
    assert rc == 2 and "--max-tf-gap" in capsys.readouterr().err
    # a recipe's drive takes the limit too
    from fpe_jax.fit._recipe import load_recipe

    np.savetxt(tmp_path / "wp.csv", hairpin.centerline_xy_m, delimiter=",", header="x,y",
               comments="")  # fmt: skip
    recipe = tmp_path / "r.toml"
    recipe.write_text(f'waypoints = "wp.csv"\n[[drives]]\npath = "{path}"\nmax_tf_gap_s = 4\n')
    ((d, _, _),) = load_recipe(recipe).drives
    assert len(d.t_s) == len(t)
    recipe.write_text(recipe.read_text().replace("= 4", "= -1"))
    with pytest.raises(InputError, match="max_tf_gap_s"):
        load_recipe(recipe)


# --------------------------------------------------------------------- 4: constant stamps


def test_zero_or_constant_detection_stamps_are_an_error_naming_the_topic(hairpin, tmp_path):
    for name, stamp in (("zero", lambda ns: {}), ("const", lambda ns: {"sec": 1700000000})):
        events = _layout_events(hairpin, det_stamp=stamp)
        path = _write_ros2_mcap(tmp_path / f"{name}.mcap", events)
        with pytest.raises(InputError) as e:
            io.load_drive(path)
        msg = str(e.value)
        assert at.DETECTION_TOPIC in msg and "header stamps" in msg and "--log-time" in msg, msg
    # with --log-time the TF is looked up at the log time too: the drive of the intact log
    path = _write_ros2_mcap(tmp_path / "z.mcap", _layout_events(hairpin, det_stamp=lambda n: {}))
    got = io.load_drive(path, log_time=True)
    want = io.load_drive(
        _write_ros2_mcap(tmp_path / "ok.mcap", _layout_events(hairpin)), log_time=True
    )
    np.testing.assert_array_equal(got.t_s, want.t_s)
    np.testing.assert_allclose(got.xy_m, want.xy_m, rtol=0, atol=1e-9)


def test_constant_stamps_on_a_pose_topic_are_an_error(tmp_path):
    events = [
        (k * S // 10 + S, "/opp/pose", "geometry_msgs/PoseStamped", _pose_msg(0, "map", k, 0, 0))
        for k in range(20)
    ]
    path = _write_ros2_mcap(tmp_path / "p.mcap", events)
    with pytest.raises(InputError, match="/opp/pose.*all 20 .*header stamps.*--log-time"):
        io.load_drive(path)
    assert len(io.load_drive(path, log_time=True).t_s) == 20


# --------------------------------------------------------------------- 7: epoch stamps


@pytest.fixture(scope="module")
def oval():
    res = sim.simulate("oval", duration_s=8.0, seed=3)
    d = res.drive
    n = len(d.t_s)
    # stamps off every binary grid: 123.456789 ms + k * 87.654321 ms
    t_ns = 123_456_789 + np.arange(n, dtype=np.int64) * 87_654_321
    return res.centerline_xy_m, t_ns, d.xy_m, d.yaw_rad


def _stamp_text(ns: int) -> str:
    return f"{ns // S}.{ns % S:09d}"


def _predict(drive, wp):
    from fpe_jax.drive import local_frame
    from fpe_jax.geometry._track import Track
    from fpe_jax.model._params import presets
    from fpe_jax.predict._predict import predict_rows, states_from_drive

    params = presets["default"]
    local, wp, _, origin = local_frame(drive, wp)
    track = Track.from_waypoints(wp)
    poses = np.asarray(
        predict_rows(params, states_from_drive(params, local, track), track).packed()
    )
    return local.t_s, poses


def test_epoch_and_zero_based_stamps_predict_the_same(oval, tmp_path):
    wp, t_ns, xy, yaw = oval
    got = {}
    for name, off in (("zero", 0), ("epoch", EPOCH_NS)):
        csv = tmp_path / f"{name}.csv"
        rows = [f"{_stamp_text(int(n) + off)},{x!r},{y!r},{a!r}" for n, (x, y), a in
                zip(t_ns, xy.tolist(), yaw.tolist())]  # fmt: skip
        csv.write_text("t,x,y,yaw\n" + "\n".join(rows) + "\n")
        events = [
            (int(n) + off, "/opp/pose", "geometry_msgs/PoseStamped",
             _pose_msg(int(n) + off, "map", x, y, a))
            for n, (x, y), a in zip(t_ns, xy.tolist(), yaw.tolist())
        ]  # fmt: skip
        mcap = _write_ros2_mcap(tmp_path / f"{name}.mcap", events)
        for fmt, path in (("csv", csv), ("mcap", mcap)):
            drive = io.load_drive(path)
            assert drive.meta["t0_ns"] == int(t_ns[0]) + off
            got[name, fmt] = _predict(drive, wp)
    for fmt in ("csv", "mcap"):
        (tz, pz), (te, pe) = got["zero", fmt], got["epoch", fmt]
        np.testing.assert_array_equal(te, tz)
        assert np.max(np.abs(pe - pz)) <= 1e-9, (fmt, np.max(np.abs(pe - pz)))
    # `fpe convert` writes the stamps back exactly
    drive = io.load_drive(tmp_path / "epoch.csv")
    io.write_drive_csv(tmp_path / "back.csv", drive)
    col = [r.split(",")[0] for r in (tmp_path / "back.csv").read_text().splitlines()[1:]]
    assert col == [_stamp_text(int(n) + EPOCH_NS) for n in t_ns]
    # the MCAP's yaw went through a quaternion: the two formats agree to rounding
    np.testing.assert_allclose(got["zero", "csv"][1], got["zero", "mcap"][1], rtol=0, atol=1e-12)


def test_stream_epoch_and_zero_based_stamps_predict_the_same(oval):
    from fpe_jax.io.config import params_to_config
    from fpe_jax.model._params import presets
    from fpe_jax.runner._runner import Runner, run_stream

    wp, t_ns, xy, yaw = oval
    replies = {}
    for name, off in (("zero", 0), ("epoch", EPOCH_NS)):
        lines = ["t,x,y,yaw\n"] + [
            f"{_stamp_text(int(n) + off)},{x!r},{y!r},{a!r}\n"
            for n, (x, y), a in zip(t_ns, xy.tolist(), yaw.tolist())
        ]
        out, err = pyio.StringIO(), pyio.StringIO()
        runner = Runner(params_to_config(presets["default"]), wp)
        assert run_stream(runner, lines, out, err) == 0 and not err.getvalue()
        replies[name] = [json.loads(r) for r in out.getvalue().splitlines()]
    z, e = replies["zero"], replies["epoch"]
    assert len(z) == len(e) == len(t_ns)
    diff = max(np.max(np.abs(np.array(a["poses"]) - b["poses"])) for a, b in zip(z, e))
    assert diff <= 1e-9, diff
    assert abs(e[5]["stamp"] - z[5]["stamp"] - 1.7e9) < 1e-6  # the stamp as the line gave it


def test_stamps_parse_exactly_to_nanoseconds():
    assert tables.stamp_ns("1700000000.123456789") == 1_700_000_000_123_456_789
    assert tables.stamp_ns("-0.5") == -500_000_000
    assert tables.stamp_ns("1.7e9") == 1_700_000_000 * S
    assert tables.stamp_ns("12") == 12 * S
    assert tables.stamp_ns("0.0000000015") == 2  # half to even at the nanosecond
    assert tables.stamp_ns("nan") is None and tables.stamp_ns("inf") is None


# --------------------------------------------------------------------- 13: deep trees, names


def test_a_tf_tree_3000_frames_deep_is_described_and_looked_up(tmp_path, capsys):
    chain = [_tf(f"f{k}", f"f{k + 1}", 0, (0.001, 0, 0), static=True) for k in range(3000)]
    buf = TfBuffer(chain)
    rows = buf.describe()
    assert len(rows) == 3000 and rows[-1]["depth"] == 2999
    np.testing.assert_allclose(buf.lookup("f0", "f3000", [0]).t_m[0, 0], 3.0, atol=1e-9)
    events = [
        (S, "/tf_static", "tf2_msgs/TFMessage", {"transforms": [
            {"header": {"stamp": {"sec": 0, "nanosec": 0}, "frame_id": p}, "child_frame_id": c,
             "transform": {"translation": {"x": 0.001, "y": 0.0, "z": 0.0},
                           "rotation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}}
            for p, c, *_ in chain]})
    ]  # fmt: skip
    path = _write_ros2_mcap(tmp_path / "deep.mcap", events)
    rc = cli.main(["info", str(path), "--json"])
    out, err = capsys.readouterr()
    assert rc == 0 and "Traceback" not in err, err
    assert len(json.loads(out)["tf_tree"]) == 3000


@pytest.mark.parametrize("name", ["a" * 251 + ".csv", "é" * 125 + ".csv", "\u20ac" * 83 + ".c"])
def test_output_names_up_to_the_file_system_limit_are_written(tmp_path, name):
    assert 250 <= len(name.encode()) <= 255
    out = tmp_path / name
    io.write_text(out, "x\n")
    assert out.read_text() == "x\n" and [p.name for p in tmp_path.iterdir()] == [name]
    with pytest.raises(InputError, match="cannot be used as an output path"):
        io.check_output_path(tmp_path / ("b" * 256), False)


def test_a_second_interrupt_during_cleanup_exits_130_without_a_traceback(tmp_path):
    """The second Ctrl-C lands while the first one's message is being written: exit 130, quiet."""
    code = """
import sys
from fpe_jax import cli

class Stderr:  # the second Ctrl-C arrives during the first write after the first one
    armed = False
    def write(self, text):
        if self.armed:
            self.armed = False
            raise KeyboardInterrupt
        return sys.__stderr__.write(text)
    def flush(self):
        sys.__stderr__.flush()

def command(args):
    sys.stderr = Stderr()
    sys.stderr.armed = True
    raise KeyboardInterrupt

args = cli._build_parser().parse_args(["presets"])
args.func = command
cli._build_parser = lambda *only: type("P", (), {"parse_args": lambda self, argv: args})()
cli.entry()
"""
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path)
    assert p.returncode == 130 and "Traceback" not in p.stderr, (p.returncode, p.stderr)


@pytest.mark.parametrize("interrupted", [False, True])
def test_a_ctrl_c_as_the_console_script_stops_listening_exits_130_quietly(tmp_path, interrupted):
    """A Ctrl-C that lands after `main` restored the SIGINT handler, as `entry` sets it aside
    (after a finished command, or the second one after an interrupted one): exit 130, quiet."""
    code = f"""
import signal, sys
from fpe_jax import cli

real, calls = signal.signal, []
def set_handler(sig, handler):  # a Ctrl-C lands as entry's own SIG_IGN call starts
    if sig == signal.SIGINT and handler is signal.SIG_IGN:
        calls.append(1)
        if len(calls) == {2 if interrupted else 1}:
            raise KeyboardInterrupt
    return real(sig, handler)
signal.signal = set_handler

def command(args):
    if {interrupted}:
        raise KeyboardInterrupt
    return 0

args = cli._build_parser().parse_args(["presets"])
args.func = command
cli._build_parser = lambda *only: type("P", (), {{"parse_args": lambda self, argv: args}})()
cli.entry()
"""
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path)
    assert p.returncode == 130 and "Traceback" not in p.stderr, (p.returncode, p.stderr)


@pytest.mark.parametrize("at_line", [0, 2, 5, 12])
def test_a_ctrl_c_in_a_callback_is_resent_even_when_another_lands_in_the_hook(tmp_path, at_line):
    """A Ctrl-C that lands in a callback Python cannot raise from (an unraisable
    KeyboardInterrupt, as in JAX's garbage-collection callback) still ends the command with 130,
    and a second one landing while the interpreter reports the first (at any line the main
    thread runs in cli.py or threading.py from then on) prints no traceback. The command is
    blocked in a system call (as `fpe run` waits on stdin): the interrupt sent again ends it."""
    code = f"""
import sys, time
from fpe_jax import cli

count = [0]
def tracer(frame, event, arg):  # a second Ctrl-C lands at the {at_line}th line run in the hook
    if frame.f_code.co_filename.endswith(("cli.py", "threading.py")):
        def local(frame, event, arg):
            if event == "line":
                count[0] += 1
                if count[0] == {at_line + 1}:
                    raise KeyboardInterrupt
            return local
        return local
    return None

class Callback:
    def __del__(self):
        raise KeyboardInterrupt  # the first Ctrl-C, where Python cannot raise it

def command(args):
    sys.settrace(tracer)
    Callback()
    sys.settrace(None)
    time.sleep(60)  # the interrupt sent again ends this
    return 0

args = cli._build_parser().parse_args(["presets"])
args.func = command
cli._build_parser = lambda *only: type("P", (), {{"parse_args": lambda self, argv: args}})()
cli.entry()
"""
    p = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=30
    )
    assert p.returncode == 130 and "Traceback" not in p.stderr, (p.returncode, p.stderr)
    assert p.stderr.strip() == "fpe: interrupted", p.stderr


# --------------------------------------------------------------------- 14: floods of bad lines


def _flood(n_bad: int):
    """Two observations on the 10 m circle with n_bad malformed lines between them."""
    yield "t,x,y\n"
    yield "0.0,10.0,0.0\n"
    for _ in range(n_bad):
        yield "oops,1,2\n"
    yield "0.1,10.0,0.1\n"


def test_run_counts_skipped_lines_in_flat_memory_and_rate_limits_messages(monkeypatch):
    monkeypatch.setattr(spec, "STREAM_MESSAGE_EVERY_S", 1e9)  # no timed message in the test
    from fpe_jax.io.config import params_to_config
    from fpe_jax.model._params import presets
    from fpe_jax.runner._runner import Runner, run_stream

    a = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    wp = np.column_stack([10 * np.cos(a), 10 * np.sin(a)])
    peaks = []
    for n_bad in (200, 2_000, 20_000):  # the first pass makes the one-time allocations
        runner = Runner(params_to_config(presets["default"]), wp)
        out, err = pyio.StringIO(), pyio.StringIO()
        tracemalloc.start()
        assert run_stream(runner, _flood(n_bad), out, err) == 0
        peaks.append(tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
        lines = err.getvalue().splitlines()
        assert len(out.getvalue().splitlines()) == 2
        assert len(lines) <= spec.STREAM_MESSAGES + 3, len(lines)
        assert lines[0].startswith("fpe run: line 3: ")
        assert f"skipped {n_bad} of {n_bad + 2} lines" in lines[-1], lines[-1]
    # no per-line memory: one pointer kept per line would add 18,000 x 8 B = 141 KiB
    assert peaks[2] < peaks[1] + 32 * 1024, peaks


# --------------------------------------------------------------------- 15: syntax and ranges


def test_a_stream_line_cut_short_at_the_end_is_reported_not_read():
    warned = []
    lines = ["t,x,y\n", "0.0,1.0,2.0\n", "0.1,1.1,3."]
    obs = list(read_observations(lines, warned.append))
    assert [o.line for o in obs] == [2]
    assert len(warned) == 1 and "line 3" in warned[0] and "no newline" in warned[0]
    # lines given without their newlines are whole lines
    obs = list(read_observations([s.rstrip("\n") for s in lines], warned.append))
    assert [o.y_m for o in obs] == [2.0, 3.0]


@pytest.mark.parametrize("cell", ["1_0", "\u0663", "\uff11", "0x10", "1e5_0"])
def test_numbers_are_plain_ascii(cell, tmp_path):
    warned = []
    lines = [
        "t,x,y\n",
        "0.0,1.0,2.0\n",
        f"0.1,{cell},2.0\n",
        f'{{"t": 0.2, "x": "{cell}", "y": 2}}\n',
    ]
    obs = list(read_observations(lines, warned.append))
    assert [o.line for o in obs] == [2] and len(warned) == 2, warned
    assert all("expected a number" in w for w in warned)
    f = tmp_path / "d.csv"
    f.write_text(f"t,x,y\n0,1,2\n0.1,{cell},2\n", encoding="utf-8")
    with pytest.raises(InputError, match="line 3: non-numeric cell"):
        tables.read_table(f)


def test_plain_numbers_still_read():
    for cell, v in (("1.5", 1.5), ("-2", -2.0), ("+3.", 3.0), (".5e-1", 0.05), ("1E3", 1000.0)):
        assert tables.plain_number(cell) == v
    for cell in ("nan", "NaN", "-inf", "Infinity"):
        assert not np.isfinite(tables.plain_number(cell))


def test_static_transforms_that_disagree_are_an_error():
    rng = np.random.default_rng(0)
    many = [_tf("base_link", "laser", 0, tuple(rng.normal(0, 10, 3)), static=True)
            for _ in range(1501)]  # fmt: skip
    with pytest.raises(InputError) as e:
        TfBuffer(many + [_tf("map", "base_link", S)], source="x.bag")
    msg = str(e.value)
    assert "base_link -> laser" in msg and "1501" in msg and "/tf_static" in msg, msg
    # repeats of one mount (a latched topic) and last-bit differences are one mount
    same = [_tf("base_link", "laser", 0, (0.5, 0, 0.1 + k * 1e-12), static=True) for k in range(9)]
    assert len(TfBuffer(same).edges[("base_link", "laser")].stamps_ns) == 1


@pytest.mark.parametrize("value", ["0,0,0,1e20", "1e6,0,0,3.14", "0,0,-50,0", "0,0,0,7"])
def test_absurd_tag_mounts_are_refused_with_the_range(value):
    with pytest.raises(InputError) as e:
        at.parse_tag_to_base(value)
    msg = str(e.value)
    assert msg.startswith("--tag-to-base: ") and f"{spec.MAX_TAG_OFFSET_M:g} m" in msg, msg
    assert at.parse_tag_to_base("-0.2,0,0.2,3.14159") == (-0.2, 0.0, 0.2, 3.14159)


def test_tf_quaternions_far_from_unit_and_absurd_translations_are_refused():
    bad_q = ("map", "base_link", S, (0, 0, 0), (0, 0, 0, 1e20), False, "/tf")
    with pytest.raises(InputError, match="not a unit quaternion"):
        TfBuffer([bad_q])
    far = _tf("map", "base_link", S, (1e20, 0, 0))
    with pytest.raises(InputError, match="translation"):
        TfBuffer([far])
    near = ("map", "base_link", S, (0, 0, 0), (0, 0, 0, 1.001), False, "/tf")
    TfBuffer([near])  # rounding in a recorder: normalized, as tf2 accepts it


def test_half_width_out_of_range_is_refused(tmp_path, capsys):
    for hw in (1e6, 0.0, float("nan")):
        with pytest.raises(InputError, match=f"{spec.MAX_HALF_WIDTH_M:g}"):
            spec.check_half_width(hw, "--half-width")
    rc = cli.main(["simulate", "--half-width", "1e6", "--out", str(tmp_path / "s")])
    err = capsys.readouterr().err
    assert rc == 2 and "--half-width" in err and f"{spec.MAX_HALF_WIDTH_M:g}] m" in err, err
    assert not (tmp_path / "s").exists()


def test_a_tag_seen_twice_in_one_image_has_its_own_message(hairpin, tmp_path):
    events = _layout_events(hairpin)
    for _, topic, _, msg in events:
        if topic == at.DETECTION_TOPIC and msg["detections"]:
            msg["detections"] = msg["detections"] * 2
    path = _write_ros2_mcap(tmp_path / "twice.mcap", events)
    with pytest.raises(InputError) as e:
        io.load_drive(path)
    msg = str(e.value)
    assert "no detection of tag 0" not in msg and "more than once" in msg, msg
