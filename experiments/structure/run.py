"""Structure of the package: modules per package, the longest module, import arrows, and the
walk of one pose from a log to a CSV row, for this checkout and (optionally) another commit.

    .venv/bin/python experiments/structure/run.py [--before COMMIT]

The walk profiles the work of `fpe predict data/samples/drive.mcap --waypoints
data/tracks/oval.csv --out OUT.csv` (`cmd_predict`, default preset) in a child process and
records every call whose callee lives in the package: `files` is the number of the package's
files the command executes, `hops` the number of distinct file-to-file call sites (a call site
counted once however often it runs), `CLI re-entries` the hops that lead back into cli.py from
another file. `--before` measures COMMIT the same way from a temporary git worktree.
Writes experiments/results/structure.md.
"""

from __future__ import annotations

import argparse
import ast
import json
import subprocess
import sys
import tempfile
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
OUT = ROOT / "experiments" / "results" / "structure.md"

# run inside the child: profile `fpe predict` on the sample drive, print the call edges as JSON
_WALK = r"""
import json, sys
from pathlib import Path
pkg = str(Path(sys.argv[1]) / "fpe_jax")
edges = set()
depth = [0]
def prof(frame, event, arg):
    name = frame.f_code.co_name
    if name == "cmd_predict":  # only the command's own work: parsing and imports are left out
        depth[0] += 1 if event == "call" else -1 if event == "return" else 0
    if event != "call" or not depth[0] or not frame.f_code.co_filename.startswith(pkg):
        return
    callee = frame.f_code.co_filename
    back = frame.f_back
    while back is not None and not back.f_code.co_filename.startswith(pkg):
        back = back.f_back
    if back is not None and back.f_code.co_filename != callee:
        edges.add((back.f_code.co_filename, back.f_lineno, callee))
from fpe_jax import cli
root = Path(sys.argv[1])
argv = ["predict", str(root / "data/samples/drive.mcap"), "--waypoints",
        str(root / "data/tracks/oval.csv"), "--out", sys.argv[2]]
sys.setprofile(prof)
rc = cli.main(argv)
sys.setprofile(None)
files = sorted({e[0] for e in edges} | {e[2] for e in edges})
print(json.dumps({"rc": rc, "files": [f[len(pkg) + 1:] for f in files],
                  "edges": [[a[len(pkg) + 1:], n, b[len(pkg) + 1:]] for a, n, b in edges]}))
"""


def modules(tree: Path) -> dict[str, int]:
    """{module path relative to fpe_jax/: lines} of every Python file of the package."""
    pkg = tree / "fpe_jax"
    return {
        str(p.relative_to(pkg)): len(p.read_text().splitlines())
        for p in sorted(pkg.rglob("*.py"))
        if "msgs" not in p.parts
    }


def unit(module: str) -> str:
    """The top-level unit a dotted module name belongs to: `fpe_jax.io.logs` -> `io`."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def import_arrows(tree: Path) -> int:
    """Distinct (importing unit, imported unit) pairs between the package's top-level units
    (sub-packages and top-level modules), imports inside functions included."""
    pkg = tree / "fpe_jax"
    arrows = set()
    for p in pkg.rglob("*.py"):
        if "msgs" in p.parts:
            continue
        rel = p.relative_to(tree).with_suffix("")
        name = ".".join(rel.parts[:-1] if rel.name == "__init__" else rel.parts)
        src = unit(name)
        for node in ast.walk(ast.parse(p.read_text())):
            targets = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = name.split(".")[
                        : len(name.split(".")) - node.level + (rel.name == "__init__")
                    ]
                    mod = ".".join(base + ([node.module] if node.module else []))
                else:
                    mod = node.module or ""
                targets = [mod] + [f"{mod}.{a.name}" for a in node.names]
            for t in targets:
                if (
                    t.startswith("fpe_jax.")
                    and (pkg / t.split(".")[1]).exists()
                    or (t.startswith("fpe_jax.") and (pkg / f"{t.split('.')[1]}.py").exists())
                ):
                    dst = unit(t)
                    if dst != src:
                        arrows.add((src, dst))
    return len(arrows)


def walk(tree: Path) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        out = subprocess.run(
            [sys.executable, "-c", _WALK, str(tree), str(Path(tmp) / "pred.csv")],
            cwd=tmp,
            env={"PYTHONPATH": str(tree), "PATH": "/usr/bin:/bin", "FPE_CACHE_DIR": tmp},
            capture_output=True,
            text=True,
            check=True,
        )
    res = json.loads(out.stdout.splitlines()[-1])
    edges = res["edges"]
    cli = "cli.py"
    assert res["rc"] == 0, res
    logic = [e for e in edges if not e[2].endswith("__init__.py")]
    return {
        "files": len(res["files"]),
        "files_logic": len({f for f in res["files"] if not f.endswith("__init__.py")}),
        "hops": len(edges),
        "hops_logic": len(logic),
        "pairs": len({(a, b) for a, _, b in logic}),
        "cli_reentries": sum(1 for a, _, b in edges if b == cli and a != cli),
        "cli_calls": sum(1 for a, _, b in logic if a == cli),
    }


def measure(tree: Path) -> dict:
    mods = modules(tree)
    per_pkg = Counter(Path(m).parts[0] if len(Path(m).parts) > 1 else "(top level)" for m in mods)
    longest = max(mods, key=mods.get)
    return {
        "modules": len(mods),
        "per_package": dict(sorted(per_pkg.items())),
        "longest": f"{longest} ({mods[longest]} lines)",
        "cli_lines": mods.get("cli.py", 0),
        "import_arrows": import_arrows(tree),
        **walk(tree),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", help="a commit to measure the same way (default: none)")
    args = ap.parse_args()
    rows = {"this checkout": measure(ROOT)}
    if args.before:
        with tempfile.TemporaryDirectory() as tmp:
            wt = Path(tmp) / "before"
            subprocess.run(
                ["git", "worktree", "add", "-q", "--detach", str(wt), args.before],
                cwd=ROOT,
                check=True,
            )
            try:
                rows[f"commit {args.before}"] = measure(wt)
            finally:
                subprocess.run(
                    ["git", "worktree", "remove", "--force", str(wt)], cwd=ROOT, check=True
                )
    cmd = "`.venv/bin/python experiments/structure/run.py" + (
        f" --before {args.before}`" if args.before else "`"
    )
    lines = [
        "# Structure of the package",
        "",
        f"Regenerate: {cmd}.",
        "",
        "Modules: the package's Python files (generated message classes excluded).",
        "Import arrows: distinct pairs of top-level units (a sub-package or a top-level module)",
        "where one imports the other, imports inside functions included.",
        "Walk: the work of `fpe predict data/samples/drive.mcap --waypoints data/tracks/oval.csv",
        "--out OUT.csv` (`cmd_predict`) under a profiler; files = the package's files it runs,",
        "hops = distinct file-to-file call sites, CLI re-entries = hops back into cli.py from",
        "another file; call sites in cli.py = the command module's own calls into the package.",
        "",
        "| measure | " + " | ".join(rows) + " |",
        "|---|" + "---|" * len(rows),
    ]
    for key, label in [
        ("modules", "modules"),
        ("per_package", "modules per package"),
        ("longest", "longest module"),
        ("cli_lines", "cli.py lines"),
        ("import_arrows", "import arrows between units"),
        ("files", "walk: files"),
        ("files_logic", "walk: files, package __init__ dispatch left out"),
        ("hops", "walk: hops"),
        ("hops_logic", "walk: hops, package __init__ dispatch left out"),
        ("pairs", "walk: distinct (file, file) pairs, dispatch left out"),
        ("cli_reentries", "walk: CLI re-entries"),
        ("cli_calls", "walk: call sites in cli.py into other files (dispatch left out)"),
    ]:
        vals = []
        for r in rows.values():
            v = r[key]
            vals.append(
                ", ".join(f"{k} {n}" for k, n in v.items()) if isinstance(v, dict) else str(v)
            )
        lines.append(f"| {label} | " + " | ".join(vals) + " |")
    OUT.write_text("\n".join(lines) + "\n")
    print(OUT.read_text())


if __name__ == "__main__":
    main()
