"""`fpe run`'s stream: --rate stamps, header-less x,y,z refused without it, one bad line skipped
without poisoning the rest, restarted clocks, closed or full stdout, broken pipes and Ctrl-C."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import csv_lines, expected, fpe_run, oval_stream, stream_files

from fpe_jax import cli
from fpe_jax.io.stream import read_observations

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def oval():
    """(config dict, centerline (K, 2) [m], rows (N, 4) t [s], x, y [m], yaw [rad]) of a short
    simulated oval drive."""
    return oval_stream(6.0, seed=3)


@pytest.fixture()
def files(tmp_path, oval):
    return stream_files(tmp_path, *oval[:2])


@pytest.mark.parametrize(
    "k, cell, value, words",
    [
        (5, 0, "1.7e18", "not ns"),  # a nanosecond stamp among seconds
        (5, 0, "nan", "stamp is nan"),
        (5, 0, "0.01", "not after"),  # backwards
        (5, 0, "1e6", "jumps"),  # far ahead
        (5, 1, "1e308", "x is 1e+308"),
        (5, 2, "inf", "y is inf"),
        (5, 3, "1e308", "yaw is 1e+308"),
        (0, 0, "1.7e18", "not ns"),  # the very first line
    ],
)
def test_one_bad_line_is_skipped_and_does_not_poison_the_rest(
    monkeypatch, capsys, files, oval, k, cell, value, words
):
    cfg, wp, rows = oval
    lines = csv_lines(rows)
    cells = lines[k + 1].split(",")
    cells[cell] = value
    lines[k + 1] = ",".join(cells)
    rc, replies, err = fpe_run(monkeypatch, capsys, files, lines)
    assert rc == 0
    assert len(err) == 1 and err[0].startswith(f"fpe run: line {k + 2}: ") and words in err[0]
    assert replies == expected(cfg, wp, np.delete(rows, k, axis=0))


def test_a_restarted_clock_starts_a_new_history(monkeypatch, capsys, files, oval):
    cfg, wp, rows = oval
    first, second = rows[:20], rows[20:].copy()
    second[:, 0] -= second[0, 0]  # a new recording from t = 0
    rc, replies, err = fpe_run(monkeypatch, capsys, files, csv_lines(np.vstack([first, second])))
    assert rc == 0
    assert len(err) == 3 and "restart" in err[2] and "line 24" in err[2]
    # the two lines before the restart feed the new history, the third is the first reply
    want = expected(cfg, wp, first) + expected(cfg, wp, second)[2:]
    assert replies == want


def test_rate_stamps_the_originals_xyz_rows(monkeypatch, capsys, files, oval):
    cfg, wp, rows = oval
    lines = [f"{x!r},{y!r},0.0" for x, y in rows[:30, 1:3].tolist()]
    lines[4] = "oops,1,0"  # a malformed row keeps its sample time
    rc, replies, err = fpe_run(monkeypatch, capsys, [*files, "--rate", "10"], lines)
    assert rc == 0 and len(err) == 1 and "line 5" in err[0]
    t = np.arange(30) / 10.0
    want = expected(cfg, wp, np.delete(np.column_stack([t, rows[:30, 1:3], t * np.nan]), 4, 0))
    assert replies == want
    # a header without a time column, and JSON lines without t, are stamped the same way
    lines = ["x,y"] + [f"{x!r},{y!r}" for x, y in rows[:3, 1:3].tolist()]
    lines += [json.dumps({"x": 1.0, "y": 2.0})]
    rc, replies, err = fpe_run(monkeypatch, capsys, [*files, "--rate", "4"], lines)
    assert rc == 0 and [r["stamp"] for r in replies] == [0.0, 0.25, 0.5, 0.75] and not err


@pytest.mark.parametrize(
    "flags, lines, words",
    [
        ([], ["1.0,2.0,0.0", "1.1,2.0,0.0"], "x,y,z"),  # never read as t,x,y
        ([], ["x,y,yaw", "1,2,0"], "no t column"),
        (["--rate", "10"], ["t,x,y", "0,1,2"], "has a time column"),
        (["--rate", "10"], ['{"t": 0, "x": 1, "y": 2}'], "has a stamp"),
        (["--rate", "0"], ["1,2,0"], "--rate"),
        (["--rate", "1e-300"], ["1,2,0"], "absurd"),
        (["--rate", "nan"], ["1,2,0"], "--rate"),
        ([], ["t,x,y", "nan,1,2"], "none of its observations"),
    ],
)
def test_a_wrongly_laid_out_stream_is_one_line(monkeypatch, capsys, files, flags, lines, words):
    rc, replies, err = fpe_run(monkeypatch, capsys, [*files, *flags], lines)
    assert rc == 2 and not replies
    assert err[-1].startswith("fpe: error: ") and words in err[-1] and len(err) <= 2


def test_read_observations_counts_rate_rows_and_skips_comments():
    warned = []
    lines = ["\ufeff# a comment", "", "1,2,0", "# another", "3,4,0"]
    obs = list(read_observations(lines, warned.append, rate_hz=2.0))
    assert [(o.line, o.t_s, o.x_m) for o in obs] == [(3, 0.0, 1.0), (5, 0.5, 3.0)] and not warned


# ---- the process around the stream: closed and full stdout, broken pipes, Ctrl-C ------------


def _popen(files, **kw) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "fpe_jax.cli", "run", *files]
    return subprocess.Popen(cmd, stdin=subprocess.PIPE, text=True, cwd=ROOT, **kw)


def test_closed_or_full_stdout_ends_in_one_line(tmp_path, files, oval):
    stdin = "\n".join(csv_lines(oval[2])) + "\n"
    cmd = [sys.executable, "-m", "fpe_jax.cli", "run", *files]
    for how in ("closed", "/dev/full"):
        if how == "closed":  # stdout closed before the start: `fpe run ... >&-`
            proc = subprocess.run(
                ["bash", "-c", '"$@" >&-', "bash", *cmd], input=stdin.encode(), capture_output=True
            )
        else:
            with open(how, "w") as full:
                proc = subprocess.run(
                    cmd, input=stdin.encode(), stdout=full, stderr=subprocess.PIPE
                )
        err = proc.stderr.decode()
        assert proc.returncode == 1, err
        assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
        assert "cannot write the output" in err


def test_broken_pipe_and_ctrl_c(files, oval):
    stdin = "\n".join(csv_lines(oval[2])) + "\n"
    # the reader goes away after one reply (`fpe run | head -1`): a quiet exit 1
    with _popen(files, stdout=subprocess.PIPE, stderr=subprocess.PIPE) as proc:
        proc.stdin.write(stdin)
        proc.stdin.close()
        assert json.loads(proc.stdout.readline())["stamp"] == pytest.approx(oval[2][0, 0])
        proc.stdout.close()
        assert proc.wait(timeout=60) == 1
        assert proc.stderr.read() == ""
    # Ctrl-C while waiting for the next observation: exit 130, one line, no traceback
    with _popen(files, stdout=subprocess.PIPE, stderr=subprocess.PIPE) as proc:
        proc.stdin.write("\n".join(csv_lines(oval[2])[:3]) + "\n")
        proc.stdin.flush()
        proc.stdout.readline()
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=60) == 130
        assert proc.stderr.read().strip() == "fpe: interrupted"


def test_a_ctrl_c_lost_in_a_callback_is_sent_again(monkeypatch, capsys):
    """Python cannot raise from a __del__ or a gc callback (JAX has one): a KeyboardInterrupt
    landing there is only reported, and the work would go on. The CLI sends it again."""
    import time

    class Dies:
        def __del__(self):
            raise KeyboardInterrupt

    def work(args):
        Dies()  # its __del__ runs at once: the interrupt lands there
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:  # the resent interrupt stops this loop
            time.sleep(0.01)
        return 0

    monkeypatch.setattr(cli, "cmd_presets", work)
    monkeypatch.setattr(cli, "_build_parser", _parser_with(cli._build_parser, work))
    assert cli.main(["presets"]) == 130
    err = capsys.readouterr().err
    assert err.strip() == "fpe: interrupted" and "Traceback" not in err


def _parser_with(build, func):
    def patched(*only):
        parser = build(*only)
        parser._subparsers._group_actions[0].choices["presets"].set_defaults(func=func)
        return parser

    return patched
