"""A fit run as several cooperating processes (one per host, or per socket) with JAX's own
multi-process support, `jax.distributed`.

Every process runs the same fit on the same logs. After `join`, `jax.devices()` lists the
devices of every process, and the fit's loss spreads its row blocks over all of them
(`fit_params(devices=...)`, a `jax.shard_map` whose partial sums are added across processes);
everything else (states, the line, the solver's steps, the report) each process computes
itself, on the same values, so every process ends with the same fit (`check_same` verifies
it). On the CPU the processes add their sums with Gloo over TCP (jaxlib's default CPU
collectives).

`join` first meets the other processes on the coordinator's port with a small handshake of its
own, then starts JAX's coordination service there. The handshake turns what JAX reports only by
aborting the process after its timeout (a coordinator that never answers, a process that never
comes, a port in use, two processes with one id) into an `InputError` naming the problem,
within `timeout_s`.

Usage (what `fpe fit --coordinator --num-processes --process-id` does):

    group = process_group("10.0.0.1:6789", num_processes=2, process_id=0)
    join(group)                    # before anything else runs on JAX's devices
    result = fit(drives, tracks, devices=len(jax.devices()))
    check_same(group, digest_of(result))
    leave()
"""

from __future__ import annotations

import dataclasses
import errno
import ipaddress
import math
import os
import socket
import sys
import time

from fpe_jax.errors import InputError

DEFAULT_TIMEOUT_S = 120.0
COORDINATOR_ENV = "JAX_COORDINATOR_ADDRESS"  # read by jax.distributed.initialize too
BIND_ENV = "JAX_COORDINATOR_BIND_ADDRESS"
_HELLO = "fpe-fit-join 1"  # the handshake's first words: protocol and its version
_LINE_BYTES = 256
_RETRY_S = 0.2


@dataclasses.dataclass(frozen=True)
class ProcessGroup:
    """The processes of one fit: the coordinator's address (process 0's host and a free port
    there), how many processes, this one's id (0 .. num_processes - 1), and how long to wait
    for the others to join [s]."""

    host: str
    port: int
    num_processes: int
    process_id: int
    timeout_s: float = DEFAULT_TIMEOUT_S

    @property
    def address(self) -> str:
        return f"{self.host}:{self.port}"

    @property
    def primary(self) -> bool:
        """Whether this process writes the fit's files and reports (process 0)."""
        return self.process_id == 0


def _whole(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def parse_address(value: str, source: str = "coordinator") -> tuple[str, int]:
    """(host, port) of "HOST:PORT" (an IPv6 host in brackets: "[::1]:6789")."""
    host, sep, port = str(value).rpartition(":")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    if not sep or not host or not port.isdigit() or not 1 <= int(port) <= 65535:
        raise InputError(source, f"{value!r} is not HOST:PORT", "e.g. 10.0.0.1:6789")
    return host, int(port)


def process_group(
    coordinator: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
    timeout_s: float | None = None,
) -> ProcessGroup | None:
    """The checked process group of a fit, or None for a fit in this one process.

    num_processes None or 1 is one process (then the other arguments must be unset or agree).
    coordinator defaults to $JAX_COORDINATOR_ADDRESS. Raises InputError naming the argument
    (coordinator, num_processes, process_id, coordinator_timeout_s) for a value it cannot use.
    """
    if num_processes is not None and (not _whole(num_processes) or num_processes < 1):
        raise InputError("num_processes", repr(num_processes), "a whole number >= 1")
    if timeout_s is not None and not (
        isinstance(timeout_s, int | float) and math.isfinite(timeout_s) and timeout_s > 0
    ):
        raise InputError("coordinator_timeout_s", repr(timeout_s), "seconds > 0")
    if num_processes in (None, 1):
        if coordinator is not None:
            raise InputError("coordinator", "given for a fit in one process", "--num-processes N")
        if process_id not in (None, 0):
            raise InputError(
                "process_id", f"{process_id!r} in a fit of one process", "0, or --num-processes"
            )
        return None
    if process_id is None:
        raise InputError("process_id", "missing", f"this process's id, 0 to {num_processes - 1}")
    if not _whole(process_id) or not 0 <= process_id < num_processes:
        raise InputError(
            "process_id", f"{process_id!r} is out of range", f"0 to {num_processes - 1}"
        )
    coordinator = coordinator or os.environ.get(COORDINATOR_ENV)
    if not coordinator:
        raise InputError("coordinator", "missing", f"process 0's HOST:PORT (or ${COORDINATOR_ENV})")
    host, port = parse_address(coordinator)
    timeout = DEFAULT_TIMEOUT_S if timeout_s is None else float(timeout_s)
    return ProcessGroup(host, port, num_processes, process_id, timeout)


def _is_loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return host == "localhost"


def _bind_address(group: ProcessGroup) -> tuple[str, int] | None:
    """Where process 0 listens: $JAX_COORDINATOR_BIND_ADDRESS, else the coordinator's own
    loopback address (a fit on one host stays off the network), else None: every interface."""
    if os.environ.get(BIND_ENV):
        return parse_address(os.environ[BIND_ENV], BIND_ENV)
    return (group.host, group.port) if _is_loopback(group.host) else None


def _listen(group: ProcessGroup) -> socket.socket:
    bind = _bind_address(group)
    try:
        if bind is None:
            dual = socket.has_dualstack_ipv6()
            family = socket.AF_INET6 if dual else socket.AF_INET
            return socket.create_server(
                ("", group.port), family=family, dualstack_ipv6=dual, reuse_port=False
            )
        return socket.create_server(bind)
    except OSError as e:
        if e.errno == errno.EADDRINUSE:
            raise InputError(
                "coordinator",
                f"port {group.port} is already in use on this host",
                "a free port for process 0 (another program, or another fit, listens there)",
            ) from None
        raise InputError(
            "coordinator", f"cannot listen on {group.address}: {e.strerror}", "this host's address"
        ) from None


def _read_line(conn: socket.socket, deadline: float) -> str | None:
    """One line from conn before the deadline; None on end of stream or timeout."""
    data = b""
    while not data.endswith(b"\n") and len(data) < _LINE_BYTES:
        left = deadline - time.monotonic()
        if left <= 0:
            return None
        conn.settimeout(left)
        try:
            chunk = conn.recv(_LINE_BYTES - len(data))
        except (TimeoutError, OSError):
            return None
        if not chunk:
            return None
        data += chunk
    return data.decode("ascii", "replace").strip()


def _refusal(group: ProcessGroup, words: list[str], joined: dict) -> str | None:
    """Why process 0 turns a joining process away (None: it may join)."""
    if len(words) != 4 or " ".join(words[:2]) != _HELLO or not all(w.isdigit() for w in words[2:]):
        return "it is not a process of fpe fit"
    n, i = int(words[2]), int(words[3])
    if n != group.num_processes:
        return f"it was started with {n} processes, process 0 with {group.num_processes}"
    if not 1 <= i < n:
        return f"process id {i} is out of range (1 to {n - 1} join process 0)"
    if i in joined:
        return f"two processes were started with process id {i}"
    return None


def _gather(group: ProcessGroup, deadline: float) -> None:
    """Process 0: wait until every other process has joined, then tell them all to go on."""
    joined: dict[int, socket.socket] = {}
    server = _listen(group)
    try:
        while len(joined) < group.num_processes - 1:
            left = deadline - time.monotonic()
            if left <= 0:
                missing = [i for i in range(1, group.num_processes) if i not in joined]
                raise InputError(
                    "coordinator",
                    f"{len(joined) + 1} of {group.num_processes} processes joined "
                    f"{group.address} within {group.timeout_s:g} s; missing process id(s) "
                    + ", ".join(map(str, missing)),
                    "every process started with the same --coordinator and --num-processes, "
                    "or a longer --coordinator-timeout",
                )
            server.settimeout(left)
            try:
                conn, _ = server.accept()
            except TimeoutError:
                continue
            line = _read_line(conn, min(deadline, time.monotonic() + 5.0)) or ""
            why = _refusal(group, line.split(), joined)
            if why is None:
                joined[int(line.split()[3])] = conn
                continue
            try:
                conn.sendall(f"refused {why}\n".encode())
            except OSError:
                pass
            conn.close()
        for i, conn in joined.items():
            try:
                conn.sendall(b"go\n")
            except OSError:
                raise InputError(
                    "coordinator", f"process {i} left before the fit started", "it to run on"
                ) from None
        for conn in joined.values():  # the peer closes first: no lingering socket on the port
            _read_line(conn, time.monotonic() + 5.0)
    finally:
        for conn in joined.values():
            conn.close()
        server.close()


def _meet(group: ProcessGroup, deadline: float) -> None:
    """Process 1 and on: join process 0 (retrying until it listens), wait for its go."""
    hello = f"{_HELLO} {group.num_processes} {group.process_id}\n".encode()
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            raise InputError(
                "coordinator",
                f"process 0 at {group.address} did not answer within {group.timeout_s:g} s",
                "process 0 started with this --coordinator and reachable from this host, or "
                "a longer --coordinator-timeout",
            )
        try:
            conn = socket.create_connection((group.host, group.port), timeout=min(left, 5.0))
        except socket.gaierror as e:
            raise InputError("coordinator", f"unknown host {group.host!r}: {e.strerror}") from None
        except OSError:  # not listening yet, or not reachable yet
            time.sleep(min(_RETRY_S, max(left, 0.0)))
            continue
        with conn:
            try:
                conn.sendall(hello)
            except OSError:
                continue
            answer = _read_line(conn, deadline)
        if answer == "go":
            return
        if answer and answer.startswith("refused "):
            raise InputError("coordinator", f"process 0 refused this process: {answer[8:]}")
        if answer is not None:
            raise InputError(
                "coordinator",
                f"{group.address} answered {answer[:40]!r}",
                "the address of process 0 of this fit",
            )
        # no answer: process 0 went away (its own timeout or error); try again until ours


def join(group: ProcessGroup) -> None:
    """Meet the other processes (`_gather` / `_meet`), start `jax.distributed` and connect
    the collectives once, so that `jax.devices()` lists every process's devices.

    Call before anything has run on JAX's devices. Raises InputError (source "coordinator")
    when the processes do not all join within group.timeout_s.
    """
    deadline = time.monotonic() + group.timeout_s
    if group.primary:
        _gather(group, deadline)
    else:
        _meet(group, deadline)
    import jax

    bind = _bind_address(group)
    jax.distributed.initialize(
        coordinator_address=group.address,
        num_processes=group.num_processes,
        process_id=group.process_id,
        initialization_timeout=max(1, math.ceil(deadline - time.monotonic())) + 10,
        coordinator_bind_address=None if bind is None else f"{bind[0]}:{bind[1]}",
    )
    _connect_collectives()


def _connect_collectives() -> None:
    """One sum over every device of every process: the CPU collectives (Gloo) connect on their
    first use and say so on stdout, which belongs to the fit's report; here they say it to
    /dev/null. Raises InputError when the sum is wrong."""
    import jax
    import numpy as np
    from jax.sharding import Mesh, NamedSharding
    from jax.sharding import PartitionSpec as P

    devices = jax.devices()
    mesh = Mesh(np.array(devices), ("processes",))
    ones = np.ones(len(devices), np.int32)
    x = jax.make_array_from_callback(
        ones.shape, NamedSharding(mesh, P("processes")), ones.__getitem__
    )
    count = jax.jit(
        jax.shard_map(
            lambda v: jax.lax.psum(v.sum(), "processes"),
            mesh=mesh,
            in_specs=P("processes"),
            out_specs=P(),
        )
    )
    sys.stdout.flush()
    saved, null = os.dup(1), os.open(os.devnull, os.O_WRONLY)
    os.dup2(null, 1)
    try:
        total = int(jax.block_until_ready(count(x)).addressable_data(0))
    finally:
        os.dup2(saved, 1)
        os.close(saved)
        os.close(null)
    if total != len(devices):
        raise InputError("coordinator", f"a sum over {len(devices)} devices gave {total}")


def check_same(group: ProcessGroup, payload: bytes, what: str = "fit") -> None:
    """Raise InputError unless every process passed the same payload (their fits' digests):
    the processes computed the same values from what each read."""
    import hashlib

    import numpy as np
    from jax.experimental import multihost_utils

    digest = np.frombuffer(hashlib.sha256(payload).digest(), np.uint8)
    every = np.asarray(multihost_utils.process_allgather(digest))
    differ = [i for i in range(every.shape[0]) if not np.array_equal(every[i], every[0])]
    if differ:
        raise InputError(
            "coordinator",
            f"the {what} of process(es) {', '.join(map(str, differ))} differs from process 0's",
            "the same logs and options, jaxlib build and CPU type on every process",
        )


def lost_process(group: ProcessGroup, error: BaseException) -> InputError | None:
    """The InputError to report for `error` when it says that a collective lost another
    process (it stopped or its host went away); None for any other error."""
    text = str(error)
    if "Gloo" not in text and "Connection closed by peer" not in text:
        return None
    first = text.strip().splitlines()[0] if text.strip() else type(error).__name__
    return InputError(
        "coordinator",
        f"another process of the fit ({group.num_processes} processes at {group.address}) "
        f"stopped: {first[:200]}",
        "every process running to the end; see the other processes' errors",
    )


def leave() -> None:
    """Stop `jax.distributed` once every process has got here (JAX's shutdown barrier)."""
    import jax

    if jax.distributed.is_initialized():
        jax.distributed.shutdown()
