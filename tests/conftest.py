"""Strict JAX settings for every test: float64, no implicit rank or dtype promotion."""

import ctypes
import ctypes.util
import gc
import os
import signal
import tempfile
from pathlib import Path

# the compilation cache of the tests and of the commands they start is a temporary folder: never
# the user's, and each session starts cold (subprocesses inherit the environment). The workers
# of one parallel run (pytest-xdist) share it, so each executable is compiled once per run; its
# writes are atomic renames, so a worker reads an executable whole or compiles it itself.
_RUN = os.environ.get("PYTEST_XDIST_TESTRUNUID")
if _RUN:
    _CACHE = Path(tempfile.gettempdir()) / f"fpe-test-cache-{_RUN}"
    _CACHE.mkdir(exist_ok=True)
    os.environ["FPE_CACHE_DIR"] = str(_CACHE)
else:
    os.environ["FPE_CACHE_DIR"] = tempfile.mkdtemp(prefix="fpe-test-cache-")

# The suite compiles a few thousand programs and runs each on little data, so XLA's compiler is
# most of its time. Its programs (and the commands it starts) compile as a debug build would:
# without LLVM's optimisation passes and with the loop emitters the stored executables already
# use, so the largest (the fit's loss and gradient) compile several times faster. Every test
# passes either way; FPE_TEST_XLA_OPTIMIZE=1 runs the suite with XLA's own defaults, and the
# benchmarks and experiments always compile as a user's command does.
if os.environ.get("FPE_TEST_XLA_OPTIMIZE") != "1":
    os.environ["XLA_FLAGS"] = (
        "--xla_cpu_use_fusion_emitters=false --xla_backend_optimization_level=0"
        " --xla_llvm_disable_expensive_passes=true " + os.environ.get("XLA_FLAGS", "")
    ).strip()

# a suite started in the background (`make test &`, nohup) inherits SIGINT ignored, and so would
# every command it starts: the Ctrl-C tests need the interactive default, in here and in children
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

import ast  # noqa: E402

import jax  # noqa: E402
import pytest  # noqa: E402
from jaxtyping import _import_hook  # noqa: E402


# The run-time checks (`--jaxtyping-packages` in pyproject.toml) decorate every function of
# fpe_jax as its module loads, and so every function nested in another: a nested function is
# defined anew on each call of its outer one, and each definition builds, compiles and decorates
# a checking wrapper (jaxtyping's exec plus beartype's), which made the I/O tests three times
# slower (tests/io/test_apriltag.py 94 -> 35 s). Module-level functions, classes and methods,
# which carry the annotations users rely on, stay checked on every call; nested helpers do not.
def _check_outer_functions_only(transformer, node):
    if any(isinstance(p, ast.FunctionDef | ast.AsyncFunctionDef) for p in transformer._parents):
        transformer._parents.append(node)
        transformer.generic_visit(node)
        transformer._parents.pop()
        return node
    return _check_every_function(transformer, node)


_check_every_function = _import_hook.JaxtypingTransformer.visit_FunctionDef
_import_hook.JaxtypingTransformer.visit_FunctionDef = _check_outer_functions_only

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
# no implicit dtype promotion: dtypes come from the inputs (a float32 input stays float32, a
# Python scalar takes the array's dtype; mixing float32 and float64 arrays is an error)
jax.config.update("jax_numpy_dtype_promotion", "strict")

_libc_name = ctypes.util.find_library("c")
_LIBC = ctypes.CDLL(_libc_name) if _libc_name else None
if _LIBC is not None and not hasattr(_LIBC, "malloc_trim"):  # not glibc
    _LIBC = None

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """../shared/data beside the checkout; tests that need it skip when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data not found at {SHARED_DATA} (../shared/data beside the checkout)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def fpe_cache_dir() -> Path:
    """The session's compilation cache (`FPE_CACHE_DIR`), shared by every test and command."""
    return Path(os.environ["FPE_CACHE_DIR"])


@pytest.fixture(scope="module", autouse=True)
def _release_compiled_programs():
    """Drop JAX's in-memory compiled programs after each test file: one process runs the whole
    suite, and the programs of 50-odd files would otherwise stay resident (several GB). What a
    later file compiles again comes from the session's disk cache. The freed memory then goes
    back to the system (glibc keeps it otherwise: the process stayed at its high-water mark,
    2.3 GB after tests/fit, for the rest of the run)."""
    yield
    jax.clear_caches()
    gc.collect()
    if _LIBC is not None:
        _LIBC.malloc_trim(0)
