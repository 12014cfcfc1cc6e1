"""Fit time and peak memory against hours of logs: `python experiments/benchmarks/fit_scale.py`.

Each size runs in a fresh process (peak resident memory from `resource.getrusage`, which a
process inherits from nothing it did not do itself): simulate the logs as 15-minute drives
on the built-in oval (10 Hz detector, as the fit benchmark in run.py; seeds 100, 101, ...),
then `fpe_jax.fit.fit` as `fpe fit` runs it (the line model, the last 30 % of each drive held
out; the held-out report and uncertainty included). The compilation cache is a fresh folder
per size, so every time includes compiling. `--block-rows 1000000000` fits every drive's loss
in one piece (no row blocks: the fit before `fpe_jax.fit.FIT_BLOCK_ROWS`) for comparison.
`--processes N` also fits every size as N processes on 127.0.0.1 (`fpe fit --num-processes`,
`fpe_jax.fit._processes`; one CPU device each, started together, each simulating the same
logs): the row gives the slowest process's time and each process's peak RSS. On a machine with
fewer cores than the processes need, their sums wait on the scheduler: such times say nothing
about the speed-up on separate hosts.

Writes fit_scale.json and fit_scale.md next to this file (or in --out-dir).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from subprocess import PIPE

HERE = Path(__file__).resolve().parent
DRIVE_MIN = 15.0
SENSOR = dict(rate_hz=10.0, jitter_frac=0.0, miss_prob=0.0, miss_per_radps=0.0)


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux


def _cpu_s() -> float:
    use = resource.getrusage(resource.RUSAGE_SELF)
    return use.ru_utime + use.ru_stime


def child(hours: float, block_rows: int | None, group=None) -> dict:
    """In a fresh process: simulate `hours` of logs, fit them; times [s] and peak RSS [MB].
    group: this process's `ProcessGroup` of a multi-process fit (None: one process)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    from fpe_jax.compile import _cache as cache
    from fpe_jax.fit import _fit as fit
    from fpe_jax.fit import _processes
    from fpe_jax.geometry._track import Track
    from fpe_jax.sim import _sim as sim

    if group is not None:  # before anything asks JAX for a device
        _processes.join(group)
    cache.enable()
    n_drives = max(1, round(hours * 60.0 / DRIVE_MIN))
    minutes = hours * 60.0 / n_drives
    t0 = time.perf_counter()
    runs = [
        sim.simulate("oval", duration_s=60.0 * minutes, seed=100 + k, sensor=sim.Sensor(**SENSOR))
        for k in range(n_drives)
    ]
    drives = [r.drive for r in runs]
    tracks = [Track.from_waypoints(runs[0].centerline_xy_m)] * n_drives
    simulate_s = time.perf_counter() - t0
    rss_before_mb = _peak_rss_mb()
    if block_rows is not None:  # the comparison: every dataset's loss in one piece
        fit.FIT_BLOCK_ROWS = block_rows
    t0, cpu0 = time.perf_counter(), _cpu_s()
    result = fit.fit(drives, tracks, devices=len(jax.devices()))
    fit_s = time.perf_counter() - t0
    info = result.info
    if group is not None:
        _processes.leave()
    return {
        "processes": 1 if group is None else group.num_processes,
        "process_id": 0 if group is None else group.process_id,
        "hours": hours,
        "drives": n_drives,
        "drive_min": minutes,
        "observations": int(sum(len(d.t_s) for d in drives)),
        "block_rows": block_rows or fit.FIT_BLOCK_ROWS,
        "simulate_s": simulate_s,
        "fit_s": fit_s,
        "cpu_s": _cpu_s() - cpu0,
        "solve_s": info["solve_s"],
        "compile_s": info["compile_s"],
        "steps": info["steps"],
        "presolve_steps": info["presolve_steps"],
        "loss": info["loss"],
        "converged": info["converged"],
        "peak_rss_before_fit_mb": rss_before_mb,
        "peak_rss_mb": _peak_rss_mb(),
        "fitted": result.params.physical(),
    }


def run_child(hours: float, block_rows: int | None, processes: int = 1) -> dict:
    """The row of one size: one child process, or `processes` children fitting together
    (the slowest one's times, every one's peak RSS in peak_rss_mb_each)."""
    argv = [sys.executable, str(Path(__file__).resolve()), "--child", str(hours)]
    if block_rows is not None:
        argv += ["--block-rows", str(block_rows)]
    if processes > 1:
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            argv += ["--coordinator", f"127.0.0.1:{s.getsockname()[1]}"]
        argv += ["--num-processes", str(processes)]
    with tempfile.TemporaryDirectory(prefix="fpe-fit-scale-") as cache_dir:
        env = {**os.environ, "FPE_CACHE_DIR": cache_dir}
        env.pop("XLA_FLAGS", None)  # one CPU device per process
        ids = range(processes) if processes > 1 else [None]
        extra = [[] if i is None else ["--process-id", str(i)] for i in ids]
        procs = [
            subprocess.Popen(argv + e, stdout=PIPE, stderr=PIPE, text=True, env=env) for e in extra
        ]
        try:
            outs = [p.communicate() for p in procs]
        finally:
            for p in procs:
                if p.poll() is None:
                    p.kill()
    for p, (_, err) in zip(procs, outs):
        if p.returncode != 0:
            raise RuntimeError(err.strip()[-2000:])
    rows = [json.loads(out.strip().splitlines()[-1]) for out, _ in outs]
    row = max(rows, key=lambda r: r["fit_s"])
    return row | {"peak_rss_mb_each": [r["peak_rss_mb"] for r in rows]}


def markdown(rows: list[dict], meta: dict) -> str:
    lines = [
        "# Fit time and peak memory against hours of logs",
        "",
        f"`{meta['command']}` on {meta['machine']} ({meta['when']}, load average"
        f" {meta['load_avg'][0]:.1f} at the start, {meta['load_avg'][1]:.1f} at the end;"
        f" {meta['done']} done).",
        "Each row is one fresh process with an empty compilation cache: simulate the hours as"
        f" {DRIVE_MIN:g}-minute 10 Hz drives on the oval, then `fpe_jax.fit.fit` (the line model,"
        " 30 % of each drive held out, report and uncertainty included). Time: `fit` alone,"
        " compilation included (the machine is shared: fit CPU is the process's user + system"
        " time); peak RSS: `resource.getrusage` of the whole process.",
        "",
        "| hours | drives | observations | row block | processes | fit [s] | solve [s]"
        " | steps (pre-solve) | loss | peak RSS [MB] | RSS before the fit [MB] | fit CPU [s] |",
        "| ---: | ---: | ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        block = "none" if r["block_rows"] >= 10**8 else str(r["block_rows"])
        rss = " / ".join(f"{m:.0f}" for m in r.get("peak_rss_mb_each", [r["peak_rss_mb"]]))
        lines.append(
            f"| {r['hours']:g} | {r['drives']} | {r['observations']} | {block} |"
            f" {r.get('processes', 1)} | {r['fit_s']:.1f} | {r['solve_s']:.1f} |"
            f" {r['steps']} ({r['presolve_steps']}) | {r['loss']:.6g} | {rss} |"
            f" {r['peak_rss_before_fit_mb']:.0f} | {r['cpu_s']:.1f} |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hours", default="1,3,10", help="comma list of logged hours (1,3,10)")
    ap.add_argument(
        "--unblocked-hours",
        default="",
        help="comma list of hours also fitted without row blocks, for comparison",
    )
    ap.add_argument(
        "--processes",
        type=int,
        default=1,
        help="also fit every size as this many processes on 127.0.0.1 (default 1: not)",
    )
    ap.add_argument("--out-dir", default=str(HERE), help="where fit_scale.{json,md} go")
    ap.add_argument("--child", type=float, help=argparse.SUPPRESS)
    ap.add_argument("--block-rows", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--coordinator", help=argparse.SUPPRESS)
    ap.add_argument("--num-processes", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--process-id", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child is not None:
        from fpe_jax.fit._processes import process_group

        group = process_group(args.coordinator, args.num_processes, args.process_id)
        print(json.dumps(child(args.child, args.block_rows, group)))
        return
    start = os.getloadavg()[0]
    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)  # before minutes of work, not after
    rows = []
    # per size the blocked fit, then (when asked) the one-piece fit of the same logs
    plan = [(float(h), None, 1) for h in args.hours.split(",") if h]
    plan += [(float(h), 10**9, 1) for h in args.unblocked_hours.split(",") if h]
    if args.processes > 1:
        plan += [(float(h), None, args.processes) for h in args.hours.split(",") if h]
    plan.sort(key=lambda p: (p[0], p[1] is not None, p[2]))
    for hours, block, processes in plan:
        row = run_child(hours, block, processes)
        rows.append(row)
        print(
            f"{hours:g} h ({'no blocks' if block else 'blocked'}, {processes} process(es)):"
            f" fit {row['fit_s']:.1f} s, peak RSS {row['peak_rss_mb_each']} MB,"
            f" loss {row['loss']:.6g}",
            flush=True,
        )
        meta = {
            "command": "python experiments/benchmarks/fit_scale.py " + " ".join(sys.argv[1:]),
            "machine": f"{platform.machine()} {os.cpu_count()} CPUs, {platform.python_version()}",
            "when": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            "load_avg": [start, os.getloadavg()[0]],
            "done": f"{len(rows)} of {len(plan)} sizes",
        }
        # written after every size: a long run stopped early keeps what it measured
        (out / "fit_scale.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=2))
        (out / "fit_scale.md").write_text(markdown(rows, meta))


if __name__ == "__main__":
    main()
