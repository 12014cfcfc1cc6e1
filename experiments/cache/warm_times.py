"""Warm command times with the compilation cache: the cache is read on every warm command's path.

Runs `fpe predict` and `fpe evaluate` on the sample drive and `fpe batch` on the sample cars
(data/samples) once to fill a fresh cache folder, then `--runs` more times each, and prints the
median wall and CPU time (user + system of the child) [s] of the warm runs as one JSON line;
then (unless --no-loads), in this process, the median time [ms] of loading each stored
executable (`aot._load`: checks, unpickling, XLA's loading) and of its checks alone (reading it
as a bounded regular file and its HMAC), over 20 loads.

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


def load_times_ms(cache_dir: Path, n: int = 20) -> list[dict]:
    """Per stored executable: its size, the median full load and the median of its checks [ms]."""
    import hmac

    import jax

    jax.config.update("jax_enable_x64", True)
    os.environ["FPE_CACHE_DIR"] = str(cache_dir)
    from fpe_jax import aot, cache

    secret = cache.secret_key()
    rows = []
    for path in sorted(cache_dir.rglob("aot/*.exe")):
        full, checks = [], []
        for _ in range(n):
            t0 = time.perf_counter()
            blob = cache.read_regular(path, cache.MAX_ENTRY_BYTES)
            k = len(cache.MAGIC)
            assert hmac.compare_digest(
                blob[k : k + 32], cache._mac(secret, path.name, blob[k + 32 :])
            )
            t1 = time.perf_counter()
            assert aot._load(path, secret, []) is not None
            t2 = time.perf_counter()
            checks.append(t1 - t0)
            full.append(t2 - t1)
        rows.append(
            {
                "bytes": path.stat().st_size,
                "load_ms": round(1e3 * float(np.median(full)), 2),
                "checks_ms": round(1e3 * float(np.median(checks)), 3),
            }
        )
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--no-loads", action="store_true", help="only the commands' times")
    args = ap.parse_args()
    fpe = str(Path(sys.executable).parent / "fpe")
    tmp = Path(tempfile.mkdtemp(prefix="fpe-warm-"))
    env = {**os.environ, "FPE_CACHE_DIR": str(tmp / "cache")}
    env.pop("FPE_NO_CACHE", None)
    log = [str(SAMPLE), "--waypoints", str(TRACK), "--quiet"]
    commands = {
        "predict": [fpe, "predict", *log, "--out", str(tmp / "p.csv"), "--force"],
        "evaluate": [fpe, "evaluate", *log, "--preset", "default"],
        "batch": [
            fpe,
            "batch",
            str(SAMPLE.parent / "cars.csv"),
            *log[1:],
            "--preset",
            "default",
            "--out",
            str(tmp / "b.npy"),
            "--force",
        ],  # fmt: skip
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
    if not args.no_loads:
        result["loads_ms"] = load_times_ms(tmp / "cache")
    result["load_average"] = os.getloadavg()[0]
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
