"""`fpe batch` end to end: `python experiments/benchmarks/batch_io.py`.

The command as a user runs it, each run a fresh process: N = 1e5, 1e6, 2e6, 1e7 cars on the
Levine track (`run.py`'s `make_cars`: within 0.5 m of the centre line, (N, 5) float64 `.npy`)
predicted with the default preset into an (N, 10, 3) float32 `.npy`. Each round runs every N
once, in turn (a load that drifts over minutes moves every N alike); a first, unmeasured round
fills the compilation cache, which every later run shares; then `--runs` measured rounds:
wall time of the whole process, its CPU time and its peak resident memory (`os.wait4`'s
ru_maxrss of that child; the cars are made in another process, so this one stays small and
adds nothing to it). Reported: the medians, and the marginal rate
(N2 - N1) / (t2 - t1) between N1 = 1e5 and N2 = 2e6, which leaves out the fixed start-up
(importing JAX, loading compiled code). For scale, the library's own rate
(`BatchPredictor` called on an (N, 5) array in memory, the `batch` section of `run.py`) is
measured at N = 2e6 in a fresh process after each round. `--compare FPE` measures another
`fpe` executable (say, an older checkout's) on the same files, run for run alternating with
this one.

The machine's load average is recorded at the start and the end: on a shared host the wall
times move with it; the CPU times less so.

Writes batch_io.json and batch_io.md next to this file (or in --out-dir).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
sys.path.insert(0, str(HERE))

from run import LEVINE, load_levine, make_cars  # noqa: E402

SIZES = (100_000, 1_000_000, 2_000_000, 10_000_000)
MARGINAL = (100_000, 2_000_000)
LIBRARY_N = 2_000_000


def fpe_here() -> str:
    return str(Path(sys.executable).with_name("fpe"))


def timed(argv: list[str], env: dict) -> dict:
    """Run argv to completion: wall [s], CPU (user + system) [s], peak RSS [MB] of the child."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(argv, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    err = proc.stderr.read()
    _, status, use = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    proc.stderr.close()
    if proc.returncode != 0:
        raise SystemExit(f"bench: {' '.join(argv)} failed:\n{err.decode()}")
    return {"wall_s": wall, "cpu_s": use.ru_utime + use.ru_stime, "peak_mb": use.ru_maxrss / 1024}


def batch_argv(fpe: str, cars: Path, out: Path) -> list[str]:
    return [
        fpe, "batch", str(cars), "--waypoints", str(LEVINE), "--preset", "default",
        "--out", str(out), "--force", "--quiet",
    ]  # fmt: skip


def library_child(cars_path: str, runs: int) -> dict:
    """In a fresh process: `BatchPredictor` on the cars in memory, `runs` timed calls after a
    first (compiling) one; the median rate [predictions/s]."""
    import jax

    jax.config.update("jax_enable_x64", False)
    from fpe_jax.compile import _cache as cache
    from fpe_jax.drive import map_origin
    from fpe_jax.geometry._track import Track
    from fpe_jax.model._params import presets
    from fpe_jax.predict._batch import BatchPredictor

    cache.enable(False)
    wp = load_levine()
    origin = map_origin(wp)
    cars = np.load(cars_path)
    cars[:, :2] -= origin
    predictor = BatchPredictor(presets["default"], Track.from_waypoints(wp - origin))
    predictor(cars)
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        predictor(cars)
        times.append(time.perf_counter() - t0)
    res = {"n_cars": len(cars), "wall_s": statistics.median(times), "runs": runs}
    print(json.dumps(res))


def cars_child(path: str, n: int) -> None:
    """In a fresh process: write `make_cars`' n cars on the Levine track to path (.npy)."""
    from fpe_jax.geometry._track import Track

    np.save(path, make_cars(Track.from_waypoints(load_levine()), n))


def in_child(call: str, env: dict) -> str:
    """Run `batch_io.<call>` in a fresh Python; its stdout. This process stays small: Linux
    counts a parent's peak memory at the time it starts a command into that command's peak
    (`ru_maxrss` survives the exec), so the cars are made, and JAX imported, elsewhere."""
    code = f"import sys; sys.path.insert(0, {str(HERE)!r}); import batch_io; batch_io.{call}"
    res = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    if res.returncode != 0:
        raise SystemExit(f"bench: batch_io.{call} failed:\n{res.stderr}")
    return res.stdout


def measure(sizes, runs: int, compare: str | None, work: Path, env: dict) -> dict:
    """Every size (and executable) once per round, `runs` rounds after a warm-up round: a load
    that drifts over minutes then moves all sizes alike, not the last ones only. The library's
    rate is measured once per round too."""
    executables = {"this": fpe_here()} | ({"compare": compare} if compare else {})
    cars = {n: work / f"cars_{n}.npy" for n in sizes}
    for n, path in cars.items():
        in_child(f"cars_child({str(path)!r}, {n})", env)
    out = work / "poses.npy"
    per = {(name, n): [] for name in executables for n in sizes}
    library = []
    for k in range(runs + 1):  # round 0 fills the compilation cache and is not counted
        for n in sizes:
            for name, fpe in executables.items():
                res = timed(batch_argv(fpe, cars[n], out), env)
                if k:
                    per[name, n].append(res)
        if k and LIBRARY_N in cars:
            line = in_child(f"library_child({str(cars[LIBRARY_N])!r}, 3)", env)
            library.append(json.loads(line.strip().splitlines()[-1]))
        print(f"  round {k}/{runs} done", flush=True)
    rows = {name: [] for name in executables}
    for (name, n), runs_n in per.items():
        row = {"n_cars": n, "runs": runs_n}
        for key in ("wall_s", "cpu_s", "peak_mb"):
            row[key] = statistics.median(r[key] for r in runs_n)
        rows[name].append(row)
        print(
            f"  {name:8s} N={n:>9d}: {row['wall_s']:6.2f} s wall, {row['cpu_s']:6.2f} s CPU, "
            f"{row['peak_mb']:6.0f} MB peak",
            flush=True,
        )
    lib = None
    if library:
        lib = {"n_cars": LIBRARY_N, "runs": len(library), "per_round": library}
        lib["wall_s"] = statistics.median(r["wall_s"] for r in library)
        lib["rate_per_s"] = LIBRARY_N / lib["wall_s"]
        print(f"  library  N={LIBRARY_N}: {lib['rate_per_s']:.3g} predictions/s", flush=True)
    parent_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return {"rows": rows, "library": lib, "parent_peak_mb": parent_mb}


def marginal_sizes(sizes) -> tuple[int, int]:
    """N1, N2 of the marginal rate: 1e5 and 2e6, or the smallest and largest size measured."""
    return MARGINAL if set(MARGINAL) <= set(sizes) else (min(sizes), max(sizes))


def marginal(rows: list[dict], key: str = "wall_s") -> float | None:
    """(N2 - N1) / (t2 - t1) [predictions/s] of the medians `key` (None if t2 <= t1)."""
    return _rate(rows, *marginal_sizes([r["n_cars"] for r in rows]), key)


def _rate(rows: list[dict], n1: int, n2: int, key: str = "wall_s") -> float | None:
    by_n = {r["n_cars"]: r[key] for r in rows}
    return (n2 - n1) / (by_n[n2] - by_n[n1]) if by_n[n2] > by_n[n1] else None


def _n(n: int) -> str:
    """1e5, 2e6, 1.5e4: a car count as the tables show it."""
    return f"{n:.1e}".replace(".0e", "e").replace("e+0", "e").replace("e+", "e")


def write_report(results: dict, out_dir: Path) -> None:
    (out_dir / "batch_io.json").write_text(json.dumps(results, indent=1) + "\n")
    lines = [
        "# `fpe batch` end to end",
        "",
        "Written by `python experiments/benchmarks/batch_io.py` (`make bench`); see its docstring.",
        f"Machine: {results['machine']}. Load average (1 min) {results['load_start']:.2f} at the "
        f"start, {results['load_end']:.2f} at the end. Medians of {results['runs']} runs per N, "
        "each a fresh `fpe batch` process; every size runs once per round, after a first round "
        "that fills the compilation cache. "
        f"Peak memory is each process's own (`ru_maxrss`; the benchmark process that starts "
        f"them peaked at {results['parent_peak_mb']:.0f} MB, a floor under these).",
        "",
        "| fpe | N cars | wall [s] | CPU [s] | peak memory [MB] | cars/s (wall) |",
        "| --- | ---: | ---: | ---: | ---: | ---: |",
    ]
    for name, rows in results["rows"].items():
        for r in rows:
            lines.append(
                f"| {name} | {_n(r['n_cars'])} | {r['wall_s']:.2f} | {r['cpu_s']:.2f} | "
                f"{r['peak_mb']:.0f} | {r['n_cars'] / r['wall_s']:.3g} |"
            )
    n1, n2 = marginal_sizes(results["sizes"])
    lines += [
        "",
        f"| fpe | marginal rate {_n(n1)} -> {_n(n2)} [predictions/s] | per CPU-s | target |",
    ]
    lines += ["| --- | ---: | ---: | --- |"]
    for name, rows in results["rows"].items():
        wall, cpu = marginal(rows), marginal(rows, "cpu_s")
        ok = "met" if wall and wall >= 2e6 else "not met"
        lines.append(
            f"| {name} | {wall or float('nan'):.3g} | {cpu or float('nan'):.3g} | >= 2e6 ({ok}) |"
        )
    sizes = sorted(results["sizes"])
    if len(sizes) > 2 and (sizes[-2], sizes[-1]) != (n1, n2):
        steady = {name: _rate(rows, sizes[-2], sizes[-1]) for name, rows in results["rows"].items()}
        lines += [
            "",
            f"Marginal rate {_n(sizes[-2])} -> {_n(sizes[-1])} (wall): "
            + ", ".join(f"{name} {r or float('nan'):.3g}/s" for name, r in steady.items())
            + ".",
        ]
    big = [r for r in results["rows"]["this"] if r["n_cars"] == 10_000_000]
    if big:
        ok = "met" if big[0]["peak_mb"] < 1000 else "not met"
        lines += [
            "",
            f"Peak memory at N = 1e7: {big[0]['peak_mb']:.0f} MB (target < 1000 MB, {ok}).",
        ]
    if results["library"]:
        lib = results["library"]
        lines += [
            "",
            f"The library alone (`BatchPredictor` on the cars in memory, N = {_n(lib['n_cars'])}, "
            f"in a fresh process once per round, median over the rounds) in the same session: "
            f"{lib['rate_per_s']:.3g} predictions/s.",
        ]
    if max(results["load_start"], results["load_end"]) > results["cpus"]:
        lines += [
            "",
            "The load average exceeded the CPU count: other work shared the cores, so the wall "
            "times, and the marginal rate from them, moved with it; the CPU times are steadier.",
        ]
    if results.get("compare"):
        lines += ["", f"`compare` is `{results['compare']}`, run alternating with `this`."]
    (out_dir / "batch_io.md").write_text("\n".join(lines) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=float, nargs="+", default=SIZES, help="N cars per size")
    ap.add_argument("--runs", type=int, default=3, help="measured runs per size (median)")
    ap.add_argument("--compare", metavar="FPE", help="another fpe executable to measure too")
    ap.add_argument("--out-dir", type=Path, default=HERE)
    ap.add_argument("--quick", action="store_true", help="N = 1e4, 1e5, 1 run: a smoke test")
    args = ap.parse_args()
    if not LEVINE.is_file():
        raise SystemExit(f"bench: Levine waypoints not found at {LEVINE} (../shared/data)")
    sizes = (10_000, 100_000) if args.quick else tuple(int(n) for n in args.sizes)
    runs = 1 if args.quick else args.runs
    load_start = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="fpe-batch-io-") as tmp:
        env = dict(os.environ, FPE_CACHE_DIR=str(Path(tmp) / "cache"))
        res = measure(sizes, runs, args.compare, Path(tmp), env)
    results = {
        "machine": f"{platform.node()}, {os.cpu_count()} CPUs, {platform.python_version()}",
        "cpus": os.cpu_count(),
        "load_start": load_start,
        "load_end": os.getloadavg()[0],
        "runs": runs,
        "sizes": list(sizes),
        "compare": args.compare,
        "measured_at": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        **res,
    }
    args.out_dir.mkdir(parents=True, exist_ok=True)
    write_report(results, args.out_dir)
    for name, rows in res["rows"].items():
        rate = marginal(rows)
        print(f"{name}: marginal rate {rate or float('nan'):.3g} predictions/s")
    print(f"wrote {args.out_dir / 'batch_io.md'}")


if __name__ == "__main__":
    main()
