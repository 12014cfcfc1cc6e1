"""Wall time and peak memory of a command with all its child processes (the test suite's).

    .venv/bin/python experiments/benchmarks/suite.py -- .venv/bin/pytest -q -n 2

`/usr/bin/time -v` reports the largest single process; pytest-xdist's workers and the commands
the tests start run side by side, so this samples the resident memory of the whole process tree
(every 0.2 s, from /proc) and prints the peak of its sum, with the load average before and after.
Linux only.
"""

from __future__ import annotations

import os
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


def tree_rss_bytes(root: int) -> int:
    """Summed resident memory [bytes] of `root` and its descendants."""
    tree, todo, total = _children(), [root], 0
    page = os.sysconf("SC_PAGE_SIZE")
    while todo:
        pid = todo.pop()
        try:
            total += int(Path(f"/proc/{pid}/statm").read_text().split()[1]) * page
        except OSError:
            pass
        todo += tree.get(pid, [])
    return total


def main() -> int:
    argv = sys.argv[1:]
    if argv[:1] == ["--"]:
        argv = argv[1:]
    if not argv:
        print(__doc__, file=sys.stderr)
        return 2
    load0 = os.getloadavg()
    t0 = time.perf_counter()
    proc = subprocess.Popen(argv)
    peak = 0
    while proc.poll() is None:
        peak = max(peak, tree_rss_bytes(proc.pid))
        time.sleep(0.2)
    wall_s = time.perf_counter() - t0
    load1 = os.getloadavg()
    print(
        f"exit {proc.returncode}; wall {wall_s:.0f} s; peak memory of the process tree "
        f"{peak / 2**30:.2f} GiB; load average {load0[0]:.1f} before, {load1[0]:.1f} after "
        f"(15 min: {load1[2]:.1f})",
        file=sys.stderr,
    )
    return proc.returncode


if __name__ == "__main__":
    sys.exit(main())
