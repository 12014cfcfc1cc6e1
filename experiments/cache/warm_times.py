"""Warm command times with the compilation cache: the cache is read on every warm command's path.

Runs `fpe predict` and `fpe evaluate` on the sample drive (data/samples) once to fill a fresh
cache folder, then `--runs` more times each, and prints the median wall and CPU time (user +
system of the child) [s] of the warm runs as one JSON line.

    .venv/bin/python experiments/cache/warm_times.py --runs 5
"""

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "data" / "samples" / "drive.mcap"
TRACK = ROOT / "data" / "tracks" / "oval.csv"


def timed(argv: list[str], env: dict) -> tuple[float, float]:
    """Wall and CPU time [s] of one `fpe` command in a fresh process."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(argv, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)}: {proc.stderr[-300:]}")
    return wall, after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5)
    args = ap.parse_args()
    fpe = str(Path(sys.executable).parent / "fpe")
    tmp = Path(tempfile.mkdtemp(prefix="fpe-warm-"))
    env = {**os.environ, "FPE_CACHE_DIR": str(tmp / "cache")}
    env.pop("FPE_NO_CACHE", None)
    log = [str(SAMPLE), "--waypoints", str(TRACK), "--quiet"]
    commands = {
        "predict": [fpe, "predict", *log, "--out", str(tmp / "p.csv"), "--force"],
        "evaluate": [fpe, "evaluate", *log, "--preset", "default"],
    }
    result = {"runs": args.runs}
    for name, argv in commands.items():
        timed(argv, env)  # fills the cache
        times = [timed(argv, env) for _ in range(args.runs)]
        result[name] = {
            "warm_wall_s": round(float(np.median([w for w, _ in times])), 3),
            "warm_cpu_s": round(float(np.median([c for _, c in times])), 3),
            "wall_runs_s": [round(w, 3) for w, _ in times],
        }
    result["load_average"] = os.getloadavg()[0]
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
