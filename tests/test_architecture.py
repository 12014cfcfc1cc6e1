"""The layer rules (import-linter contracts in pyproject.toml) hold, and a wrong import breaks
them: each case adds one import to a copy of the package and `lint-imports` must fail on it."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LINT = Path(sys.executable).with_name("lint-imports")


def lint(root: Path) -> subprocess.CompletedProcess:
    """`lint-imports` over the package in `root` (its pyproject's contracts)."""
    if not LINT.exists():
        if os.environ.get("CI"):
            pytest.fail(f"{LINT} is missing: install the dev extra (import-linter)")
        pytest.skip("import-linter is not installed (pip install -e '.[dev]')")
    env = {**os.environ, "PYTHONPATH": str(root)}
    return subprocess.run(
        [str(LINT), "--no-cache"], cwd=root, env=env, capture_output=True, text=True, timeout=300
    )


@pytest.fixture
def copy(tmp_path) -> Path:
    """The package and its contracts in a temporary folder."""
    shutil.copytree(ROOT / "fpe_jax", tmp_path / "fpe_jax", ignore=shutil.ignore_patterns("*.pyc"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path)
    return tmp_path


def test_the_contracts_hold(copy):
    r = lint(copy)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "0 broken" in r.stdout


@pytest.mark.parametrize(
    ("module", "line", "contract"),
    [
        ("runner/_runner.py", "import jax", "runner, spec, errors, io and the node import no JAX"),
        ("io/tables.py", "import equinox", "runner, spec, errors, io and the node import no JAX"),
        ("node/_core.py", "import jax", "runner, spec, errors, io and the node import no JAX"),
        ("plots.py", "from fpe_jax import evaluate", "plots only draw"),
        ("predict/_predict.py", "from fpe_jax import pipeline", "layers"),
        ("geometry/_track.py", "import matplotlib", "the model reads no files"),
        ("geometry/_path.py", "from fpe_jax import drive", "no import cycles"),
    ],
)
def test_a_wrong_import_breaks_a_contract(copy, module, line, contract):
    target = copy / "fpe_jax" / module
    # inside a function, as most lazy imports are: the contracts see those too
    target.write_text(target.read_text() + f"\n\ndef _wrong():\n    {line}\n")
    r = lint(copy)
    assert r.returncode != 0, r.stdout
    broken = r.stdout.split("Broken contracts")[-1]
    assert contract in broken, r.stdout


def test_every_file_the_suite_starts_first_exists(request):
    """conftest's LONGEST_FIRST names existing test files, each once: a renamed file would
    quietly go back to its place in the collection order."""
    plugins = request.config.pluginmanager.get_plugins()
    [first] = [p.LONGEST_FIRST for p in plugins if hasattr(p, "LONGEST_FIRST")]
    assert len(set(first)) == len(first)
    for name in first:
        assert (ROOT / name).is_file(), name


def test_a_test_run_leaves_no_compilation_cache_behind(tmp_path):
    """The suite's compilation cache is a temporary folder of one run (tests/conftest.py): the
    run removes it at its end, so `make test` does not fill the temporary folder run by run."""
    test = "tests/test_architecture.py::test_every_file_the_suite_starts_first_exists"
    env = {k: v for k, v in os.environ.items() if not k.startswith(("FPE_", "PYTEST_"))}
    r = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", test],
        cwd=ROOT,
        env={**env, "TMPDIR": str(tmp_path)},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    assert not list(tmp_path.glob("fpe-test-cache-*"))
