"""Warm command times of two or more checkouts, interleaved: `make bench`'s `fpe predict`,
`fpe evaluate`, `fpe plot` (60 s drive, a config fitted on it) and `fpe fit` (the 1-minute drive;
`--fit-minutes 10,60` fits simulated drives of those lengths instead, as `make bench`'s "fit 10
min" and "fit 60 min"), each run in a fresh process with a compilation cache the checkout filled
before.

Each checkout's package is compiled to bytecode before each of its runs (`compileall`: a
no-op once done), as an installed wheel has it: where PYTHONDONTWRITEBYTECODE is set, an
editable install would otherwise compile every module it imports again in every command.
`--from-source LABEL,...` runs those checkouts without it (their package's `__pycache__`
removed before each run, with PYTHONDONTWRITEBYTECODE=1); one environment may be named twice:

    python experiments/benchmarks/warm_ab.py PYC=.venv SRC=.venv --from-source SRC

On a shared machine a load that drifts over minutes moves runs made minutes apart, so the
checkouts take turns (A B A B ... for each command) and each one's median is reported, with the
median CPU time (user + system of the child, all threads), which other processes' load moves
less than the wall time. `--parser` adds the CPU time of `fpe`'s start in a fresh process:
importing `fpe_jax.cli` and parsing a `fpe predict` line; `--imports MOD,...` the CPU time of
importing those modules in a fresh process (numpy first, apart, as every command imports it).

    python experiments/benchmarks/warm_ab.py OLD=../old/.venv NEW=.venv --runs 9
    python experiments/benchmarks/warm_ab.py OLD=../old/.venv NEW=.venv --commands fit \
        --fit-minutes 10,60

Each LABEL=VENV names a checkout by its virtual environment (its `bin/fpe` and `bin/python`).
The drive and config are made once with the first one; every checkout reads the same files.
Nothing is written outside a temporary folder, which is removed at the end.
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

PARSER_CODE = """
import time
t0 = time.process_time()
import fpe_jax.cli as cli
t1 = time.process_time()
argv = ["predict", "d.mcap", "--waypoints", "w.csv", "--config", "c.json", "--out", "p.csv"]
try:
    parser = cli._build_parser(argv[0])
except TypeError:  # a checkout whose parser is always whole
    parser = cli._build_parser()
parser.parse_args(argv)
print(t1 - t0, time.process_time() - t1)
"""
FOLDER_CODE = """
import importlib.util
folder = importlib.util.find_spec("fpe_jax").submodule_search_locations[0]
print(folder)
"""
COMPILE_CODE = """
import compileall, sys
sys.exit(0 if compileall.compile_dir(folder, quiet=1) else 1)
"""
IMPORTS_CODE = """
import importlib, sys, time
import numpy
t0 = time.process_time()
for name in sys.argv[1].split(","):
    importlib.import_module(name)
print(time.process_time() - t0)
"""


def run_fpe(
    venv: Path, argv: list[str], cache: Path, source: Path | None = None
) -> tuple[float, float]:
    """(wall [s], CPU [s]) of `fpe argv --quiet` in a fresh process with the cache folder; with
    `source` (the package's folder) without the package's bytecode, else with it."""
    env = {**os.environ, "FPE_CACHE_DIR": str(cache)}
    if source is None:
        compile_bytecode(venv)
    else:
        for folder in list(source.rglob("__pycache__")):
            shutil.rmtree(folder)
        env["PYTHONDONTWRITEBYTECODE"] = "1"
    env.pop("FPE_NO_CACHE", None)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(
        [str(venv / "bin" / "fpe"), *argv, "--quiet"], capture_output=True, text=True, env=env
    )
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise SystemExit(f"{venv}: fpe {' '.join(argv)}: {proc.stderr.strip()[-400:]}")
    return wall, after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime


def time_commands(
    venvs: dict[str, Path],
    names: list[str],
    runs: int,
    tmp: Path,
    sources: dict[str, Path],
    fit_minutes: list[float] | None = None,
) -> None:
    """Print the median warm wall and CPU times of the commands `names` of each checkout (those
    in `sources`, label -> package folder, without bytecode); "fit" on the 1-minute drive, or
    with `fit_minutes` on simulated drives of those lengths, one row each ("fit 10 min")."""
    first = next(iter(venvs.values()))
    fpe = str(first / "bin" / "fpe")
    env = {**os.environ, "FPE_CACHE_DIR": str(tmp / "prep")}

    def sim(minutes: float) -> list[str]:
        """A simulated drive of `minutes` (the first checkout's): its log and --waypoints."""
        drive = tmp / f"drive-{minutes:g}min"
        subprocess.run(
            [fpe, "simulate", "--duration", f"{60 * minutes:g}", "--out", str(drive)],
            check=True,
            capture_output=True,
            env=env,
        )
        return [str(drive / "drive.mcap"), "--waypoints", str(drive / "waypoints.csv")]

    log = sim(1)
    config = tmp / "config.json"
    subprocess.run(
        [fpe, "fit", *log, "--out", str(config)], check=True, capture_output=True, env=env
    )
    commands = {
        "predict": ["predict", *log, "--config", str(config), "--out", "{out}/p.csv", "--force"],
        "evaluate": ["evaluate", *log, "--config", str(config)],
        "plot": ["plot", *log, "--config", str(config), "--out", "{out}/p.png", "--force"],
        "fit": ["fit", *log, "--out", "{out}/c.json", "--force"],
    }
    if fit_minutes and "fit" in names:
        del commands["fit"]
        at = names.index("fit")
        fits = [f"fit {m:g} min" for m in fit_minutes]
        names = names[:at] + fits + names[at + 1 :]
        for m, name in zip(fit_minutes, fits):
            drive = log if m == 1 else sim(m)
            commands[name] = ["fit", *drive, "--out", f"{{out}}/c{m:g}.json", "--force"]
    times: dict[tuple[str, str], list[tuple[float, float]]] = {}
    for name in names:
        argvs = {}
        for label, venv in venvs.items():
            out = tmp / f"out-{label}"
            out.mkdir(exist_ok=True)
            argvs[label] = [a.replace("{out}", str(out)) for a in commands[name]]
            cache = tmp / f"cache-{label}-{name}"
            run_fpe(venv, argvs[label], cache, sources.get(label))  # fills the cache
        for _ in range(runs):
            for label, venv in venvs.items():
                cache = tmp / f"cache-{label}-{name}"
                t = run_fpe(venv, argvs[label], cache, sources.get(label))
                times.setdefault((name, label), []).append(t)
    print(f"load average {os.getloadavg()[0]:.1f}; medians of {runs} interleaved runs")
    print("| command | checkout | wall [s] | CPU [s] | wall runs [s] |")
    print("| --- | --- | --- | --- | --- |")
    for name in names:
        for label in venvs:
            t = times[name, label]
            wall = statistics.median(w for w, _ in t)
            cpu = statistics.median(c for _, c in t)
            walls = " ".join(f"{w:.2f}" for w, _ in t)
            print(f"| fpe {name} | {label} | {wall:.3f} | {cpu:.3f} | {walls} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("checkouts", nargs="+", metavar="LABEL=VENV")
    ap.add_argument("--runs", type=int, default=9, help="warm runs per command and checkout")
    ap.add_argument("--commands", default="predict,evaluate,plot,fit", help="comma list")
    ap.add_argument(
        "--fit-minutes",
        metavar="M,...",
        help="time fit on simulated drives of these minutes (default: the 1-minute drive)",
    )
    ap.add_argument("--parser", action="store_true", help="also time the CLI's start")
    ap.add_argument("--imports", metavar="MOD,...", help="also time importing these modules")
    ap.add_argument(
        "--from-source",
        default="",
        metavar="LABEL,...",
        help="time these checkouts' commands without their package's bytecode",
    )
    args = ap.parse_args()
    venvs = {}
    for item in args.checkouts:
        label, _, venv = item.partition("=")
        venvs[label] = Path(venv).resolve()
    tmp = Path(tempfile.mkdtemp(prefix="fpe-warm-ab-"))
    try:
        measure(args, venvs, tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def package_folder(venv: Path) -> Path:
    """The folder of the `fpe_jax` package that `venv` imports."""
    proc = subprocess.run(
        [str(venv / "bin" / "python"), "-c", FOLDER_CODE],
        check=True,
        capture_output=True,
        text=True,
        cwd=tempfile.gettempdir(),  # `python -c` imports from its folder first: not a checkout's
    )
    return Path(proc.stdout.strip())


def compile_bytecode(venv: Path) -> None:
    """Compile the `fpe_jax` package that `venv` imports to bytecode (`__pycache__` beside its
    sources, which git ignores)."""
    subprocess.run(
        [str(venv / "bin" / "python"), "-c", FOLDER_CODE + COMPILE_CODE],
        check=True,
        capture_output=True,
        cwd=tempfile.gettempdir(),
    )


def measure(args, venvs: dict[str, Path], tmp: Path) -> None:
    labels = [x for x in args.from_source.split(",") if x]
    if unknown := set(labels) - set(venvs):
        raise SystemExit(f"--from-source: no checkout labelled {', '.join(sorted(unknown))}")
    sources = {label: package_folder(venvs[label]) for label in labels}
    for label, venv in venvs.items():
        if label not in sources:
            compile_bytecode(venv)
    names = [n for n in args.commands.split(",") if n]
    fit_minutes = [float(m) for m in args.fit_minutes.split(",")] if args.fit_minutes else None
    if names:
        time_commands(venvs, names, args.runs, tmp, sources, fit_minutes)
    if args.parser:
        starts: dict[str, list[tuple[float, float]]] = {}
        for _ in range(max(args.runs, 11)):
            for label, venv in venvs.items():
                proc = subprocess.run(
                    [str(venv / "bin" / "python"), "-c", PARSER_CODE],
                    capture_output=True,
                    text=True,
                    check=True,
                    cwd=tmp,  # `python -c` imports from its folder first: not from a checkout
                )
                imp, parse = map(float, proc.stdout.split())
                starts.setdefault(label, []).append((imp, parse))
        print("\n| checkout | import fpe_jax.cli CPU [ms] | build parser + parse CPU [ms] |")
        print("| --- | --- | --- |")
        for label, t in starts.items():
            imp = statistics.median(i for i, _ in t) * 1e3
            parse = statistics.median(p for _, p in t) * 1e3
            print(f"| {label} | {imp:.1f} | {parse:.1f} |")
    if args.imports:
        spent: dict[str, list[float]] = {}
        for _ in range(max(args.runs, 11)):
            for label, venv in venvs.items():
                proc = subprocess.run(
                    [str(venv / "bin" / "python"), "-c", IMPORTS_CODE, args.imports],
                    capture_output=True,
                    text=True,
                    check=True,
                    cwd=tmp,
                )
                spent.setdefault(label, []).append(float(proc.stdout))
        print(f"\n| checkout | import {args.imports} CPU [ms] |")
        print("| --- | --- |")
        for label, t in spent.items():
            print(f"| {label} | {statistics.median(t) * 1e3:.1f} |")


if __name__ == "__main__":
    sys.exit(main())
