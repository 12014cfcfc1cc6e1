"""A fit run as several processes (`fpe fit --num-processes`, `fpe_jax.fit._processes`): real
processes on 127.0.0.1, each with one CPU device, against the fit in one process; and the
errors of a group that cannot form, each within its timeout."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import cli_runner

from fpe_jax.errors import InputError
from fpe_jax.fit import _processes as P

DATA = Path(__file__).resolve().parents[2] / "data"
LOG, WAYPOINTS = DATA / "samples" / "drive.csv", DATA / "tracks" / "oval.csv"
# the blend in one mode compiles fastest; blocks of 32 rows split the sample drive's 227
# training rows into 8 blocks, 4 on each process's device
FIT = ["--model", "blend", "--blend", "position", "--block-rows", "32", "--no-cache"]
LIMIT_S = 240  # no process of these tests may run longer


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def child_env() -> dict:
    """The environment of a started process: one CPU device, no coordinator of the caller's."""
    env = {k: v for k, v in os.environ.items() if k != P.COORDINATOR_ENV}
    flags = [f for f in env.pop("XLA_FLAGS", "").split() if "device_count" not in f]
    return env | {"XLA_FLAGS": " ".join(flags), "JAX_PLATFORMS": "cpu", "PYTHONUNBUFFERED": "1"}


def start(args: list[str]) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=child_env(),
    )


def finish(procs: list[subprocess.Popen]) -> list[tuple[int, str, str]]:
    """(status, stdout, stderr) of every process, each given until LIMIT_S after the first was
    waited for; every one still running then (or after a failure here) is killed."""
    deadline = time.monotonic() + LIMIT_S
    out = []
    try:
        for p in procs:
            o, e = p.communicate(timeout=max(deadline - time.monotonic(), 1))
            out.append((p.returncode, o, e))
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.communicate()
    return out


# process 1 runs the CLI in Python to show what the pipeline returned it: its fitted values
# (which the CLI does not print there) and whether it was told it is not process 0
SPY = r"""
import contextlib, io, json, sys
from fpe_jax import cli, pipeline
seen = {}
fit_logs = pipeline.fit_logs
def spy(*args, **kwargs):
    seen["outcome"] = fit_logs(*args, **kwargs)
    return seen["outcome"]
pipeline.fit_logs = spy
printed = io.StringIO()
with contextlib.redirect_stdout(printed):
    rc = cli.main(sys.argv[1:])
o = seen["outcome"]
print(json.dumps({"rc": rc, "printed": printed.getvalue(), "primary": o.primary,
                  "params": o.config["params"], "solver": o.config["provenance"]["solver"]}))
"""


def test_two_processes_fit_as_one_and_agree_bit_for_bit(tmp_path):
    """Two `fpe fit` processes on 127.0.0.1 (one CPU device each) split the loss's row blocks
    and add their sums over Gloo: both end with bit for bit the same fitted values, process 0
    alone reports and writes its --out, process 1 prints and writes nothing; and the values
    equal the fit in one process to 1e-6 (absolute, on values of order 0.01-2): the two fits
    add the same block sums in another order (one device's scan of 8 blocks against two scans
    of 4 and an all-reduce), last-bit differences in each loss and gradient that the solver's
    steps carry into the values (~1e-8 measured)."""
    port = free_port()
    group = ["--coordinator", f"127.0.0.1:{port}", "--num-processes", "2"]
    argv = ["fit", str(LOG), "--waypoints", str(WAYPOINTS), *FIT]
    out = {name: tmp_path / f"{name}.json" for name in ("p0", "p1", "one")}
    cli = ["-m", "fpe_jax.cli"]
    pair = [
        start([*cli, *argv, *group, "--process-id", "0", "--out", str(out["p0"])]),
        start(["-c", SPY, *argv, *group, "--process-id", "1", "--out", str(out["p1"])]),
    ]
    (rc0, out0, err0), (rc1, out1, err1) = finish(pair)
    # the one-process fit after the pair, not beside it: three JAX processes at once would
    # hold the suite's peak memory
    ((rc, _, err),) = finish([start([*cli, *argv, "--out", str(out["one"])])])
    assert rc0 == 0, err0[-3000:]
    assert rc1 == 0, err1[-3000:]
    assert rc == 0, err[-3000:]
    p1 = json.loads(out1.strip().splitlines()[-1])
    assert p1["rc"] == 0 and p1["primary"] is False
    assert p1["printed"] == "" and err1 == "", (p1["printed"], err1)  # process 1 is quiet
    assert not out["p1"].exists()
    assert out0.startswith("fitted (position blend") and f"wrote {out['p0']}" in out0
    cfg0, cfg = json.loads(out["p0"].read_text()), json.loads(out["one"].read_text())
    solver = cfg0["provenance"]["solver"]
    assert solver["devices"] == 2 and solver["processes"] == 2, solver
    assert "devices" not in cfg["provenance"]["solver"]  # the fit in one process is as before
    assert cfg0["params"] == p1["params"]  # bit for bit: JSON keeps every float's digits
    assert p1["solver"]["loss"] == solver["loss"]
    assert solver["loss"] == pytest.approx(cfg["provenance"]["solver"]["loss"], rel=1e-10)
    for name, value in cfg["params"].items():
        np.testing.assert_allclose(cfg0["params"][name], value, rtol=0, atol=1e-6, err_msg=name)


JOIN_AND_COMPARE = r"""
import sys
import jax
from fpe_jax.errors import InputError
from fpe_jax.fit import _processes as P
group = P.process_group(sys.argv[1], 2, int(sys.argv[2]), timeout_s=60)
P.join(group)
print("devices", len(jax.devices()), "local", len(jax.local_devices()), flush=True)
P.check_same(group, b"same")
try:
    P.check_same(group, sys.argv[2].encode())
except InputError as e:
    print("error", e)
P.leave()
"""


def test_joined_processes_see_every_device_and_notice_different_results():
    """After `join` each process sees both devices (one its own); `check_same` passes equal
    payloads and names the process whose payload differs from process 0's."""
    address = f"127.0.0.1:{free_port()}"
    procs = [start(["-c", JOIN_AND_COMPARE, address, str(i)]) for i in (0, 1)]
    for rc, out, err in finish(procs):
        assert rc == 0, err[-3000:]
        lines = out.strip().splitlines()
        assert lines[0] == "devices 2 local 1"
        assert lines[1] == (
            "error coordinator: the fit of process(es) 1 differs from process 0's (expected the "
            "same logs and options, jaxlib build and CPU type on every process)"
        )


def fit_argv(tmp_path, *flags) -> list:
    return ["fit", LOG, "--waypoints", WAYPOINTS, "--out", tmp_path / "c.json", *flags]


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--num-processes", "2", "--process-id", "2"], "--process-id: 2 is out of range"),
        (["--num-processes", "2", "--process-id", "-1"], "--process-id: -1 is out of range"),
        (["--num-processes", "2"], "--process-id: missing"),
        (["--num-processes", "0"], "--num-processes: 0 (expected a whole number >= 1)"),
        (["--coordinator", "127.0.0.1:1"], "--coordinator: given for a fit in one process"),
        (["--num-processes", "2", "--process-id", "1"], "--coordinator: missing"),
        (
            ["--num-processes", "2", "--process-id", "1", "--coordinator", "host"],
            "--coordinator: 'host' is not HOST:PORT",
        ),
        (["--num-processes", "2", "--process-id", "1", "--coordinator", "h:99999"], "HOST:PORT"),
        (["--num-processes", "2", "--coordinator-timeout", "0"], "--coordinator-timeout: 0.0"),
    ],
)
def test_bad_process_flags_are_refused_before_anything_is_read(
    tmp_path, capsys, monkeypatch, flags, message
):
    monkeypatch.delenv(P.COORDINATOR_ENV, raising=False)
    rc, out, err = cli_runner(capsys, fit_argv(tmp_path, *flags), expect=2)
    assert message in err and out == ""
    assert err.count("\n") == 1 and not (tmp_path / "c.json").exists()


def test_the_coordinator_defaults_to_jax_coordinator_address(monkeypatch):
    monkeypatch.setenv(P.COORDINATOR_ENV, "10.0.0.1:6789")
    group = P.process_group(None, 3, 2)
    assert (group.host, group.port, group.address) == ("10.0.0.1", 6789, "10.0.0.1:6789")
    assert not group.primary and group.timeout_s == P.DEFAULT_TIMEOUT_S
    assert P.process_group(None, 1, None) is None  # one process: the variable plays no part
    assert P.process_group("[::1]:7", 2, 0).host == "::1"


def timed_error(tmp_path, capsys, flags) -> tuple[str, float]:
    t0 = time.monotonic()
    _, _, err = cli_runner(capsys, fit_argv(tmp_path, *flags), expect=2)
    return err.strip(), time.monotonic() - t0


def test_an_unreachable_coordinator_is_an_error_after_the_timeout(tmp_path, capsys):
    address = f"127.0.0.1:{free_port()}"  # nobody listens there
    flags = ["--num-processes", "2", "--process-id", "1", "--coordinator", address]
    err, took = timed_error(tmp_path, capsys, [*flags, "--coordinator-timeout", "1.5"])
    assert err == (
        f"fpe: error: --coordinator: process 0 at {address} did not answer within 1.5 s "
        "(expected process 0 started with this --coordinator and reachable from this host, "
        "or a longer --coordinator-timeout)"
    )
    assert 1.5 <= took < 30


def test_process_0_alone_names_the_missing_processes_after_the_timeout(tmp_path, capsys):
    address = f"127.0.0.1:{free_port()}"
    flags = ["--num-processes", "3", "--process-id", "0", "--coordinator", address]
    err, took = timed_error(tmp_path, capsys, [*flags, "--coordinator-timeout", "1"])
    assert f"--coordinator: 1 of 3 processes joined {address} within 1 s" in err
    assert "missing process id(s) 1, 2" in err
    assert 1 <= took < 30


def test_a_port_in_use_is_refused_at_once(tmp_path, capsys):
    with socket.create_server(("127.0.0.1", 0)) as taken:
        address = f"127.0.0.1:{taken.getsockname()[1]}"
        flags = ["--num-processes", "2", "--process-id", "0", "--coordinator", address]
        err, took = timed_error(tmp_path, capsys, flags)
    assert f"--coordinator: port {address.split(':')[1]} is already in use on this host" in err
    assert took < 30


def handshake(group: P.ProcessGroup, errors: dict, index: int) -> None:
    """One process's side of the handshake (`join` without JAX); its InputError into
    errors[index]."""
    deadline = time.monotonic() + group.timeout_s
    try:
        (P._gather if group.primary else P._meet)(group, deadline)
    except InputError as e:
        errors[index] = str(e)


def run_handshakes(groups: list[P.ProcessGroup]) -> dict:
    """{index in groups: error} of the groups' handshakes, run at once on threads."""
    errors: dict = {}
    threads = [
        threading.Thread(target=handshake, args=(g, errors, i)) for i, g in enumerate(groups)
    ]
    for t in threads:
        t.start()
        time.sleep(0.05)  # process 0 first, usually
    for t in threads:
        t.join(60)
    assert not any(t.is_alive() for t in threads)
    return errors


def test_the_handshake_lets_a_whole_group_go_on():
    port = free_port()
    groups = [P.ProcessGroup("127.0.0.1", port, 3, i, 20.0) for i in (2, 0, 1)]
    assert run_handshakes(groups) == {}


def test_the_handshake_refuses_a_second_process_with_one_id_or_another_count():
    port = free_port()
    groups = [
        P.ProcessGroup("127.0.0.1", port, 2, 0, 2.0),
        P.ProcessGroup("127.0.0.1", port, 3, 1, 2.0),
    ]
    errors = run_handshakes(groups)
    assert errors[1] == (
        "coordinator: process 0 refused this process: it was started with 3 processes, "
        "process 0 with 2"
    )
    assert "1 of 2 processes joined" in errors[0] and "missing process id(s) 1" in errors[0]
    port = free_port()
    groups = [P.ProcessGroup("127.0.0.1", port, 3, i, 2.0) for i in (0, 1, 1)]
    errors = run_handshakes(groups)  # the later of the two with id 1 is refused
    assert "missing process id(s) 2" in errors[0]
    refused, waited = sorted([errors[1], errors[2]], key=lambda e: "refused" not in e)
    assert refused == (
        "coordinator: process 0 refused this process: two processes were started with process id 1"
    )
    assert "did not answer within 2 s" in waited
