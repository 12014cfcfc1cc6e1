"""Property-based hostile input (hypothesis) over recipes, CSVs (drives, waypoints, batch cars),
`fpe run` streams and output paths: every command ends in exit 2 with at most 3 stderr lines and
no traceback (or exit 0 with correct output), and no file the user had changes.

Fixed example counts, derandomized and without an example database, so CI runs the same cases
every time; in-process CLI calls throughout (the subprocess checks are in test_stream.py and at
the end here: SIGINT mid-fit and mid-simulate).
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import cli_runner, expected
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fpe_jax import spec
from fpe_jax.fit._recipe import DRIVE_KEYS, SIMULATE_KEYS
from fpe_jax.io.config import params_to_config, write_config
from fpe_jax.model._params import presets

ROOT = Path(__file__).resolve().parents[1]
SQUARE_WP = "x,y\n0,0\n10,0\n10,10\n0,10\n"

hostile = settings(
    max_examples=int(os.environ.get("FPE_HOSTILE_EXAMPLES", "100")),
    derandomize=True,
    database=None,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)


@contextlib.contextmanager
def user_folder(files: dict[str, str | bytes]):
    """A fresh folder holding the user's files; yields (folder, snapshot of it). The folder
    sits inside a temporary one of its own, so what a target of ".." writes is removed too."""
    with tempfile.TemporaryDirectory() as d:
        folder = Path(d) / "user"
        folder.mkdir()
        for name, content in files.items():
            p = folder / name
            p.parent.mkdir(parents=True, exist_ok=True)
            p.write_bytes(content if isinstance(content, bytes) else content.encode())
        yield folder, snapshot(folder)


def snapshot(folder: Path) -> dict[str, bytes | None]:
    """Every path under folder with its bytes (None for folders)."""
    return {
        str(p.relative_to(folder)): (p.read_bytes() if p.is_file() else None)
        for p in sorted(folder.rglob("*"))
    }


def assert_error_line(err: str) -> None:
    lines = err.strip().splitlines()
    assert 1 <= len(lines) <= 3 and lines[-1].startswith("fpe: error: "), err


# ---- values as hostile files hold them ---------------------------------------------------------

NUMBER_TEXT = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-(10**30), 10**30).map(str),
    st.sampled_from(["1e308", "-1e308", "1.7e18", "1.7e9", "0", "-0.0", "5e-324", "1_0", "0x10"]),
)
CELL = st.one_of(
    NUMBER_TEXT,
    st.text(alphabet=" abc#;\"'\t-.e+", max_size=4),
    st.just(""),
)


def table_text(header: str | None, rows: list[list[str]], sep: str) -> str:
    lines = [] if header is None else [header]
    return "\n".join(lines + [sep.join(r) for r in rows]) + "\n"


TABLE = st.builds(
    table_text,
    st.sampled_from(
        [
            None,
            "t,x,y,yaw",
            "t,x,y",
            "x,y",
            "\ufefft,x,y",
            "t;x;y",
            "time,x_m,y_m,v",
            "t,t,x,y",
            "# x_m, y_m, z",
            "x,y,yaw,v",
            "x,y,yaw,v,yaw_rate",
            "x [m],y [m]",
        ]
    ),
    st.lists(st.lists(CELL, min_size=1, max_size=5), max_size=6),
    st.sampled_from([",", ";", " "]),
)
FILE_BYTES = st.one_of(TABLE.map(str.encode), st.binary(max_size=40))


# ---- drive CSVs: `fpe convert` reads them exactly as every command does ------------------------


@hostile
@given(content=FILE_BYTES, rate=st.sampled_from([None, "10", "0", "nan", "1e-300", "1e9"]))
def test_drive_csv(capsys, content, rate):
    with user_folder({"drive.csv": content}) as (folder, before):
        argv = ["convert", folder / "drive.csv", "--out", folder / "out.csv"]
        rc, _, err = cli_runner(capsys, argv + (["--rate", rate] if rate else []))
        if rc == 2:
            assert_error_line(err)
            assert snapshot(folder) == before
            return
        out = np.loadtxt(folder / "out.csv", delimiter=",", skiprows=1, ndmin=2)
        assert len(out) >= 1 and np.all(np.isfinite(out[:, :3]))
        assert np.all(np.diff(out[:, 0]) > 0)  # strictly increasing stamps
        cells = content.decode("utf-8-sig").replace(";", ",").replace(" ", ",").split()
        given_x = {float(c) for line in cells for c in line.split(",") if _is_float(c)}
        assert all(any(abs(x - g) <= 1e-6 * max(1.0, abs(g)) for g in given_x) for x in out[:, 1])


def _is_float(c: str) -> bool:
    try:
        return math.isfinite(float(c))
    except ValueError:
        return False


# ---- waypoint CSVs: `fpe info --waypoints` builds the path every predictor builds --------------


@hostile
@given(content=FILE_BYTES)
def test_waypoint_csv(capsys, content):
    with user_folder({"wp.csv": content}) as (folder, before):
        rc, out, err = cli_runner(capsys, ["info", "--waypoints", folder / "wp.csv", "--json"])
        assert snapshot(folder) == before
        if rc == 2:
            assert_error_line(err)
            return
        w = json.loads(out)["waypoints"]
        assert spec.MIN_TRACK_LENGTH_M <= w["length_m"] <= spec.MAX_TRACK_LENGTH_M
        assert w["n_points"] >= 3 and w["ds_m"] > 0


# ---- batch cars: CSV or .npy ----------------------------------------------------------------

CARS_NPY = st.one_of(
    st.builds(
        lambda n, c, v: np.full((n, c), v),
        st.integers(0, 4),
        st.sampled_from([0, 3, 4, 5, 6]),
        st.sampled_from([0.5, np.nan, np.inf, 1e308, -1e9, 0.0]),
    ),
    st.lists(st.floats(-20, 20), min_size=4, max_size=4).map(lambda r: np.array([r])),
    st.sampled_from([np.zeros(3), np.float64(1.0), np.ones((2, 4), dtype=complex)]),
)


def _npy_bytes(arr) -> bytes:
    buf = io.BytesIO()
    np.save(buf, arr)
    return buf.getvalue()


@pytest.fixture(scope="module")
def square_grid_once():
    """Every example predicts on SQUARE_WP: its projection grid (NumPy, a function of the track
    alone, tests/predict/test_batch.py) is built by the first example that reaches it and
    reused, as the examples differ only in their cars (its build was most of each example)."""
    from fpe_jax.predict._batch import ProjectionGrid

    build, grids = ProjectionGrid.build, {}

    def once(track, **kwargs):
        xy = np.asarray(track.xy_m)
        key = (xy.dtype.str, xy.shape, xy.tobytes(), bool(track.closed), *sorted(kwargs.items()))
        if key not in grids:
            grids[key] = build(track, **kwargs)
        return grids[key]

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(ProjectionGrid, "build", once)
        yield grids


@hostile
@given(
    cars=st.one_of(
        TABLE.map(lambda t: ("cars.csv", t.encode())),
        CARS_NPY.map(lambda a: ("cars.npy", _npy_bytes(a))),
        st.binary(max_size=200).map(lambda b: ("cars.npy", _npy_bytes(np.ones((1, 4)))[:8] + b)),
    )
)
def test_batch_cars(capsys, square_grid_once, cars):
    name, content = cars
    with user_folder({name: content, "wp.csv": SQUARE_WP}) as (folder, before):
        argv = ["batch", folder / name, "--waypoints", folder / "wp.csv", "--preset", "default"]
        rc, _, err = cli_runner(capsys, [*argv, "--out", folder / "out.npy", "--quiet"])
        if rc == 2:
            assert_error_line(err)
            assert snapshot(folder) == before
            return
        poses = np.load(folder / "out.npy")
        assert poses.ndim == 3 and poses.shape[1:] == (10, 3) and np.all(np.isfinite(poses))


# ---- recipes ---------------------------------------------------------------------------------

TOML_SCALAR = st.one_of(
    st.text(alphabet="abc./_-", max_size=6),
    st.integers(-(2**63), 2**63 - 1),
    st.floats(allow_nan=True, allow_infinity=True),
    st.booleans(),
)
TOML_VALUE = st.recursive(
    TOML_SCALAR,
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.sampled_from("abt"), inner),
    max_leaves=5,
)


def toml(v) -> str:
    """A TOML value (inline tables and arrays) for a Python value."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return (
            "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
        )
    if isinstance(v, int):
        return str(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(toml(x) for x in v) + "]"
    return "{" + ", ".join(f"{json.dumps(k)} = {toml(x)}" for k, x in v.items()) + "}"


def one_of_or_value(*options):
    return st.one_of(st.sampled_from(options), TOML_VALUE)


DRIVE_ENTRY = st.dictionaries(
    st.sampled_from(sorted(DRIVE_KEYS | {"speed"})),
    st.one_of(
        st.sampled_from(["missing.csv", "bad.csv", "wp.csv", "", "../out.csv"]),
        st.dictionaries(
            st.sampled_from(sorted(SIMULATE_KEYS | {"speed"})),
            one_of_or_value("oval", "hairpin", "random:-1", 1.0, 0.5, -1, 1e12, 0),
            max_size=3,
        ),
        one_of_or_value(10, 0, True, [0.1, 0, 0.2, 3.1]),
    ),
    max_size=4,
)
RECIPE = st.fixed_dictionaries(
    {},
    optional={
        "out": one_of_or_value("c.json", "../x.json", "sub/c.json", "", "wp.csv"),
        "waypoints": one_of_or_value("wp.csv", "missing.csv", "bad.csv", ""),
        "holdout": one_of_or_value(0.3, 0, 1, -0.5, "abc"),
        "fit": one_of_or_value(["delay"], [], ["nonsense"], "delay"),
        "model": one_of_or_value(*spec.FIT_MODELS, "magic"),
        "blend": one_of_or_value(*spec.FIT_BLENDS, "magic"),
        "solver": one_of_or_value(*spec.SOLVERS, "adam"),
        "settings": st.dictionaries(
            st.sampled_from([*spec.USER_SETTINGS, "history"]),
            one_of_or_value(0.1, 10, -1, 0, 1e9),
            max_size=2,
        ),
        "drives": st.one_of(st.lists(DRIVE_ENTRY, max_size=2), TOML_VALUE),
        "test_drives": st.lists(DRIVE_ENTRY, max_size=1),
        "extra": TOML_VALUE,
    },
)


class Reached(Exception):
    """Every check passed and the recipe reached the slow part (simulation or fitting)."""


@hostile
@given(recipe=RECIPE.map(lambda r: "\n".join(f"{k} = {toml(v)}" for k, v in r.items())))
def test_recipe(capsys, monkeypatch, recipe):
    from fpe_jax.fit import _fit as fit
    from fpe_jax.sim import _sim as sim

    def reached(*args, **kwargs):
        raise Reached

    monkeypatch.setattr(sim, "simulate", reached)
    monkeypatch.setattr(fit, "fit", reached)
    files = {"r/r.toml": recipe + "\n", "r/wp.csv": SQUARE_WP, "r/bad.csv": b"\x00\xff,1\n"}
    files["r/c.json"] = "a user's file"  # never replaced without --force
    with user_folder(files) as (folder, before):
        try:
            rc, _, err = cli_runner(capsys, ["fit", folder / "r" / "r.toml"])
        except Reached:
            return  # a valid recipe: nothing written yet
        assert rc == 2
        assert_error_line(err)
        assert snapshot(folder) == before


# ---- `fpe run` streams -------------------------------------------------------------------------


@pytest.fixture(scope="module")
def stream_case(tmp_path_factory):
    """(argv, config, waypoints (K, 2), rows (N, 4) t, x, y, yaw) of a 3 s simulated drive."""
    from fpe_jax.sim._sim import simulate

    res = simulate("oval", duration_s=3.0, seed=5)
    d = res.drive
    folder = tmp_path_factory.mktemp("stream")
    cfg = params_to_config(presets["default"])
    write_config(folder / "cfg.json", cfg)
    np.savetxt(folder / "wp.csv", res.centerline_xy_m, delimiter=",", fmt="%.17g")
    argv = ["run", "--config", folder / "cfg.json", "--waypoints", folder / "wp.csv"]
    rows = np.column_stack([d.t_s, d.xy_m, d.yaw_rad])[:15]
    return argv, cfg, res.centerline_xy_m, rows


def csv_row(r) -> str:
    return ",".join(repr(float(v)) for v in r)


BAD_CELL = {  # per column: values that make a row unusable wherever it stands (after line 1)
    0: ["nan", "inf", "1.7e18", "-1e12", "-5", "1e4", "abc", ""],
    1: ["nan", "-inf", "1e308", "abc", "", "1e9"],
    2: ["inf", "-1e308", "x", ""],
    3: ["1e308", "inf", "-inf", "x", "1e7"],
}


def bad_line(draw, rows) -> str:
    kind = draw(st.sampled_from(["cell", "columns", "json", "text"]))
    r = rows[draw(st.integers(0, len(rows) - 1))]
    if kind == "cell":
        col = draw(st.integers(0, 3))
        cells = csv_row(r).split(",")
        cells[col] = draw(st.sampled_from(BAD_CELL[col]))
        return ",".join(cells)
    if kind == "columns":
        return draw(st.sampled_from([csv_row(r) + ",1", ",".join(csv_row(r).split(",")[:2])]))
    if kind == "json":
        return draw(
            st.sampled_from(
                [
                    json.dumps({"t": float(r[0]), "x": float(r[1])}),
                    json.dumps({"t": float(r[0]), "x": True, "y": 1.0}),
                    json.dumps({"t": None, "x": 1.0, "y": 1.0}),
                    "{" + '"t": ' + "[" * 5000 + "]" * 5000 + "}",
                    "{not json",
                    "[1, 2, 3]",
                ]
            )
        )
    return draw(st.text(alphabet="abc;{}[]\"' \t", min_size=1).filter(_is_garbage))


def _is_garbage(s: str) -> bool:
    t = s.strip()
    return bool(t) and not t.startswith("#")


@st.composite
def streams_with_bad_lines(draw, rows):
    lines = ["t,x,y,yaw"] + [csv_row(r) for r in rows]
    # after the first observation (line 2): a first stamp has nothing to be judged against
    bad_at = sorted(draw(st.sets(st.integers(3, len(lines)), min_size=1, max_size=2)))
    for at in bad_at:  # line numbers in the final stream, 1-based, inserted in order
        lines.insert(at - 1, bad_line(draw, rows))
    return lines, bad_at


@pytest.fixture(scope="module")
def stream_replies(stream_case) -> list[dict]:
    """What a fresh runner replies to the good rows of stream_case, in order: every example's
    stream holds these rows, and bad lines must change none of the replies."""
    _, cfg, wp, rows = stream_case
    return expected(cfg, wp, rows)


@hostile
@given(data=st.data())
def test_stream_bad_lines_are_skipped_and_poison_nothing(
    capsys, monkeypatch, stream_case, stream_replies, data
):
    argv, _, _, rows = stream_case
    lines, bad_at = data.draw(streams_with_bad_lines(rows))
    rc, out, err = cli_runner(capsys, argv, "\n".join(lines) + "\n", monkeypatch)
    assert rc == 0, err
    warned = [int(line.split()[3].rstrip(":")) for line in err.strip().splitlines()]
    assert warned == bad_at, err
    assert [json.loads(line) for line in out.splitlines()] == stream_replies


@hostile
@given(
    lines=st.lists(
        st.one_of(
            st.builds(",".join, st.lists(CELL, min_size=1, max_size=5)),
            st.text(max_size=12),
            st.builds(json.dumps, st.dictionaries(st.sampled_from("txy"), TOML_SCALAR)),
        ),
        max_size=6,
    ),
    rate=st.sampled_from([None, "10", "0", "1e-300"]),
)
def test_stream_anything(capsys, monkeypatch, stream_case, lines, rate):
    argv = stream_case[0] + (["--rate", rate] if rate else [])
    stdin = "\n".join(line.replace("\n", " ").replace("\r", " ") for line in lines) + "\n"
    rc, out, err = cli_runner(capsys, argv, stdin, monkeypatch)
    for line in err.strip().splitlines():
        assert line.startswith(("fpe run: line ", "fpe: error: ")), err
    if rc == 2:
        assert err.strip().splitlines()[-1].startswith("fpe: error: ")
    stamps = []
    for line in out.splitlines():
        reply = json.loads(line)  # strict JSON: no NaN
        assert np.all(np.isfinite(reply["poses"])) and len(reply["poses"]) == 10
        stamps.append(reply["stamp"])
    assert all(b > a for a, b in zip(stamps, stamps[1:])) or "restart" in err


# ---- output paths --------------------------------------------------------------------------

OUT_PATHS = [
    "new.json",
    "existing.json",
    "folder",
    "folder/",
    "missing/x.json",
    "file.txt/x.json",
    "x" * 300 + ".json",
    "bad\nname.json",
    "ünï cödé.json",
    "",
    ".",
    "..",
    "folder/../new2.json",
    "/proc/self/fpe-test.json",
    ".existing.json.tmp",
]


@hostile
@given(
    target=st.sampled_from(OUT_PATHS),
    command=st.sampled_from(["export", "convert", "simulate"]),
    force=st.booleans(),
)
def test_output_paths(capsys, command, target, force):
    cfg = json.dumps(params_to_config(presets["default"]))
    drive = "t,x,y\n0,0,0\n0.1,0.2,0\n0.2,0.4,0\n"
    files = {"c.json": cfg, "drive.csv": drive, "existing.json": "mine", "file.txt": "mine"}
    files |= {"folder/keep.txt": "mine", ".existing.json.tmp": "mine"}
    cwd_before = sorted(os.listdir())  # an empty --out must not mean the current folder
    with user_folder(files) as (folder, before):
        out = target if target.startswith("/") else str(folder / target) if target else ""
        argv = {
            "export": ["export", folder / "c.json", "--format", "json", "--out", out],
            "convert": ["convert", folder / "drive.csv", "--out", out],
            "simulate": ["simulate", "--duration", "1", "--out", out],
        }[command]
        rc, _, err = cli_runner(capsys, argv + (["--force"] if force else []))
        after = snapshot(folder)
        assert sorted(os.listdir()) == cwd_before
        if rc == 2:
            assert_error_line(err)
            assert after == before
            return
        changed = {k for k in set(before) | set(after) if before.get(k, 0) != after.get(k, 0)}
        # only the target (and, for simulate, the files inside it) is new or replaced
        rel = os.path.relpath(os.path.normpath(out), folder)
        inside = (lambda k: True) if rel == "." else (lambda k: k.startswith(rel + os.sep))
        assert all(k == rel or inside(k) for k in changed), (changed, rel)
        if rel in before and command != "simulate":
            assert force  # a user's file is replaced only with --force
        assert not any(".part" in k for k in after)


# ---- Ctrl-C in the slow commands: exit 130, no traceback, nothing left behind ----------------


def _interrupt_after_start(
    cmd: list[str], cwd: Path, wait_for: str | None, cpu_s: float = 0.0, env: dict | None = None
):
    """(exit status, stderr, seconds from the signal to the exit) of `fpe CMD` sent SIGINT as
    soon as a progress line contains `wait_for`, or once the command has used cpu_s seconds of
    CPU (its imports take about 0.3 s: then it is at work, whatever the machine's load)."""
    with subprocess.Popen(
        [sys.executable, "-m", "fpe_jax.cli", *map(str, cmd)],
        cwd=cwd,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    ) as proc:
        try:
            seen = []
            if wait_for is not None:  # the progress lines come on stderr as the work goes on
                for line in proc.stderr:
                    seen.append(line)
                    if wait_for in line:
                        break
            else:
                _wait_for_cpu(proc.pid, cpu_s)
            proc.send_signal(signal.SIGINT)
            t0 = time.perf_counter()
            rc = proc.wait(timeout=60)
            return rc, "".join(seen) + proc.stderr.read(), time.perf_counter() - t0
        finally:
            proc.kill()


def _wait_for_cpu(pid: int, cpu_s: float) -> None:
    """Until process `pid` has used cpu_s seconds of CPU (Linux's /proc; elsewhere 4 s of wall
    time, which covers its imports)."""
    stat = Path(f"/proc/{pid}/stat")
    if not stat.exists():
        time.sleep(4.0)
        return
    tick = os.sysconf("SC_CLK_TCK")
    while True:
        # utime and stime: fields 14 and 15, counted after the ")" that ends the command name
        fields = stat.read_text().rsplit(")", 1)[1].split()
        if (int(fields[11]) + int(fields[12])) / tick >= cpu_s:
            return
        time.sleep(0.02)


def test_ctrl_c_mid_fit_and_mid_simulate(tmp_path, tmp_path_factory):
    from fpe_jax.sim._sim import simulate, write_simulation

    write_simulation(simulate("oval", duration_s=20.0, seed=1), tmp_path / "sim")
    before = snapshot(tmp_path)
    sim = tmp_path / "sim"
    # a cache of its own: the fit compiles its solver whatever the session has stored, so the
    # signal lands while the solver's executable is being made on the fit's second thread
    env = os.environ | {"FPE_CACHE_DIR": str(tmp_path_factory.mktemp("cold-cache"))}
    rc, err, took_s = _interrupt_after_start(
        ["fit", sim / "drive.mcap", "--waypoints", sim / "waypoints.csv", "--out", "c.json"],
        tmp_path,
        wait_for="fitting",
        env=env,
    )
    assert rc == 130 and "Traceback" not in err and err.strip().endswith("fpe: interrupted"), err
    # at once: the compile still under way (5-30 s) is not waited for
    assert took_s < 3.0, took_s
    assert snapshot(tmp_path) == before
    rc, err, _ = _interrupt_after_start(
        ["simulate", "--duration", str(spec.MAX_DURATION_S), "--out", "long"],
        tmp_path,
        wait_for=None,
        cpu_s=1.0,
    )
    assert rc == 130 and "Traceback" not in err and err.strip() == "fpe: interrupted", err
    assert snapshot(tmp_path) == before
