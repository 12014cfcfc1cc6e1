"""Wall time and peak memory of a command with all its child processes (the test suite's).

    CI=true .venv/bin/python experiments/benchmarks/suite.py -- make test

`/usr/bin/time -v` reports the largest single process; pytest-xdist's workers and the commands
the tests start run side by side, so this samples the memory of the whole process tree every
0.5 s from /proc and prints the peak of two sums, with the load average before and after:
resident memory (RSS: a page that several processes map, as the JAX library's code, counts once
per process) and proportional memory (PSS: each shared page split among the processes that map
it, so the sum is what the tree holds of the machine's memory). RSS comes from `statm`, which
costs next to nothing; PSS needs each process's whole memory map (`smaps_rollup`, long for a
JAX process, and taken from the cores the suite runs on), so it is read only
while the RSS sum exceeds the PSS peak so far: PSS never exceeds RSS, so no other moment can
hold a higher PSS. It also prints the CPU seconds (user + system) of every descendant the
command waited for: a shared host's own speed varies, and the same work then takes more CPU
seconds, so compare wall times only beside them; and the sampler's own. The host's speed is
also probed before and after the command (`host_loop_s`): on a quiet machine a slower loop means
the host itself gave the machine less. Linux only.
"""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import time
from pathlib import Path


def _children() -> dict[int, list[int]]:
    tree: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:  # the process ended meanwhile
            continue
        tree.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    return tree


_PAGE_BYTES = os.sysconf("SC_PAGE_SIZE")


def _tree(root: int) -> list[int]:
    """`root` and its descendants' process ids."""
    tree, todo, pids = _children(), [root], []
    while todo:
        pid = todo.pop()
        pids.append(pid)
        todo += tree.get(pid, [])
    return pids


def rss_bytes(pids: list[int]) -> int:
    """Summed resident memory [bytes] of `pids`, from `statm`."""
    total = 0
    for pid in pids:
        try:
            total += int(Path(f"/proc/{pid}/statm").read_text().split()[1]) * _PAGE_BYTES
        except (OSError, ValueError, IndexError):  # the process ended meanwhile
            pass
    return total


def pss_bytes(pids: list[int]) -> int:
    """Summed proportional memory [bytes] of `pids`, from `smaps_rollup`."""
    total = 0
    for pid in pids:
        try:
            for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
                if line.startswith("Pss:"):
                    total += int(line.split()[1]) * 1024
                    break
        except (OSError, ValueError):  # the process ended meanwhile
            pass
    return total


def host_loop_s(n: int = 10**7, tries: int = 3) -> float:
    """Seconds a Python loop summing n integers takes, the best of `tries` runs: one core's speed
    as this machine gets it now."""
    best = float("inf")
    for _ in range(tries):
        t0 = time.perf_counter()
        total = 0
        for i in range(n):
            total += i
        best = min(best, time.perf_counter() - t0)
    return best


def main() -> int:
    argv = sys.argv[1:]
    if argv[:1] == ["--"]:
        argv = argv[1:]
    if not argv:
        print(__doc__, file=sys.stderr)
        return 2
    load0 = os.getloadavg()
    loop0_s = host_loop_s()
    before = resource.getrusage(resource.RUSAGE_SELF)
    t0 = time.perf_counter()
    proc = subprocess.Popen(argv)
    peak_rss = peak_pss = 0
    while proc.poll() is None:
        pids = _tree(proc.pid)
        rss = rss_bytes(pids)
        peak_rss = max(peak_rss, rss)
        if rss > peak_pss:
            peak_pss = max(peak_pss, pss_bytes(pids))
        time.sleep(0.5)
    wall_s = time.perf_counter() - t0
    load1 = os.getloadavg()
    own = resource.getrusage(resource.RUSAGE_SELF)
    sampling_s = own.ru_utime + own.ru_stime - before.ru_utime - before.ru_stime
    loop1_s = host_loop_s()
    used = resource.getrusage(resource.RUSAGE_CHILDREN)
    print(
        f"exit {proc.returncode}; wall {wall_s:.0f} s; CPU {used.ru_utime + used.ru_stime:.0f} s "
        f"(sampling: {sampling_s:.1f} s); "
        "peak memory of the process tree: "
        f"RSS {peak_rss / 1e9:.2f} GB, PSS {peak_pss / 1e9:.2f} GB; "
        f"load average {load0[0]:.1f} before, {load1[0]:.1f} after "
        f"(15 min: {load1[2]:.1f}); host loop {loop0_s:.2f} s before, {loop1_s:.2f} s after",
        file=sys.stderr,
    )
    return proc.returncode


if __name__ == "__main__":
    sys.exit(main())
