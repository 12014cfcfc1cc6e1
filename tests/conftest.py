"""Strict JAX settings for every test: float64, no implicit rank or dtype promotion."""

import ctypes
import ctypes.util
import gc
import os
import shutil
import signal
import tempfile
from pathlib import Path

# the compilation cache of the tests and of the commands they start is a temporary folder: never
# the user's, and each session starts cold (subprocesses inherit the environment). The process
# that starts pytest makes it and removes it when the run ends; the workers of a parallel run
# (pytest-xdist) inherit it and share it, so each executable is compiled once per run; its
# writes are atomic renames, so a worker reads an executable whole or compiles it itself.
_OWN_CACHE = "FPE_TEST_CACHE_DIR" not in os.environ
if _OWN_CACHE:
    os.environ["FPE_TEST_CACHE_DIR"] = tempfile.mkdtemp(prefix="fpe-test-cache-")
os.environ["FPE_CACHE_DIR"] = os.environ["FPE_TEST_CACHE_DIR"]


def pytest_unconfigure(config):
    if _OWN_CACHE:
        shutil.rmtree(os.environ["FPE_TEST_CACHE_DIR"], ignore_errors=True)


# The suite compiles a few thousand programs and runs each on little data, so XLA's compiler is
# most of its time. Its programs (and the commands it starts) compile as a debug build would:
# without LLVM's optimisation passes and with the loop emitters the stored executables already
# use, so the largest (the fit's loss and gradient) compile several times faster; and each
# program as one LLVM module, not split into parts compiled on threads: with both cores busy
# running tests the split only adds work (a short fit's process, 8.0 -> 7.0 CPU s). Every test
# passes either way; FPE_TEST_XLA_OPTIMIZE=1 runs the suite with XLA's own defaults, and the
# benchmarks and experiments always compile as a user's command does.
if os.environ.get("FPE_TEST_XLA_OPTIMIZE") != "1":
    os.environ["XLA_FLAGS"] = (
        "--xla_cpu_use_fusion_emitters=false --xla_backend_optimization_level=0"
        " --xla_llvm_disable_expensive_passes=true --xla_cpu_parallel_codegen_split_count=1 "
        + os.environ.get("XLA_FLAGS", "")
    ).strip()

# a suite started in the background (`make test &`, nohup) inherits SIGINT ignored, and so would
# every command it starts: the Ctrl-C tests need the interactive default, in here and in children
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

import ast  # noqa: E402

import jax  # noqa: E402
import pytest  # noqa: E402
from jaxtyping import _import_hook  # noqa: E402


# The run-time checks (`--jaxtyping-packages` in pyproject.toml) decorate every function and class
# of fpe_jax as its module loads. Two changes keep their cost in proportion, both measured:
# - functions nested in other functions are not decorated: a nested function is defined anew on
#   each call of its outer one, and each definition built, compiled and decorated a checking
#   wrapper (tests/io/test_apriltag.py 94 -> 35 s);
# - in a module without jaxtyping's array annotations (no shapes to bind across arguments) the
#   functions get the typechecker directly, without jaxtyping's per-call wrapper, which binds
#   each call's arguments to the signature: the runner's, the node's and the readers' calls per
#   message cost 1.7x their time with it (tests/runner, the node core, the hostile-input and
#   AprilTag tests, the rollout tests: 169 CPU s with the wrapper, 101 without, 96 unchecked).
# Module-level functions, classes and methods keep every check of their annotations.
class _Typechecker:
    """The hook's typechecker, applied as a plain decorator (see above)."""

    def __init__(self, hooked):
        self._lookup = f"jaxtyping._import_hook.Typechecker.lookup[{hooked.get_hash()!r}]"

    def get_ast(self):
        return ast.parse(f"@{self._lookup}\ndef _():\n    ...").body[0].decorator_list[0]


def _uses_jaxtyping(node: ast.Module) -> bool:
    return any(
        (isinstance(n, ast.ImportFrom) and n.module == "jaxtyping")
        or (isinstance(n, ast.Import) and any(a.name == "jaxtyping" for a in n.names))
        for n in node.body
    )


def _visit_module(transformer, node):
    transformer._plain = None if _uses_jaxtyping(node) else _Typechecker(transformer._typechecker)
    return _visit_module_as_hooked(transformer, node)


def _check_outer_functions_only(transformer, node):
    if any(isinstance(p, ast.FunctionDef | ast.AsyncFunctionDef) for p in transformer._parents):
        transformer._parents.append(node)
        transformer.generic_visit(node)
        transformer._parents.pop()
        return node
    if transformer._plain is None:
        return _check_every_function(transformer, node)
    hooked, transformer._typechecker = transformer._typechecker, transformer._plain
    try:
        return _check_every_function(transformer, node)
    finally:
        transformer._typechecker = hooked


_visit_module_as_hooked = _import_hook.JaxtypingTransformer.visit_Module
_import_hook.JaxtypingTransformer.visit_Module = _visit_module
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


@pytest.fixture(scope="session", autouse=True)
def _collector_as_in_fpe():
    """The collector's young passes every `cli.GC_YOUNG_THRESHOLD` new objects, as in an `fpe`
    process (`cli.entry`): at Python's default its passes scan the many long-lived objects of
    JAX, equinox and the tests' traces again and again."""
    from fpe_jax.cli import GC_YOUNG_THRESHOLD

    gc.set_threshold(GC_YOUNG_THRESHOLD, *gc.get_threshold()[1:])


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


def release_compiled_programs() -> None:
    """Drop the compiled programs held in memory (JAX's and the package's executables) and give
    the freed memory back to the system; what is used again is compiled again, or loaded from
    the session's disk cache once a command run in this process has turned it on (`pipeline`).
    glibc keeps freed memory otherwise (a process stayed at its high-water mark, 2.3 GB after
    tests/fit, for the rest of the run), and the package's executables alone held 0.65 GB."""
    from fpe_jax.compile import _aot

    jax.clear_caches()
    _aot._MEMO.clear()
    gc.collect()
    if _LIBC is not None:
        _LIBC.malloc_trim(0)


def _resident_bytes() -> int:
    try:
        with open("/proc/self/statm") as f:  # Linux: (total, resident, ...) in pages
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except OSError:
        return 0


# After a test file that left its process above _KEEP_BELOW_BYTES, the next file starts with
# nothing compiled: one process runs many files, and the programs of 50-odd files would otherwise
# stay resident (several GB). Below it the programs stay: a release costs 0.3 CPU s (most of it
# jax.clear_caches and the garbage collector), and the next file often compiles the same ones
# (tests/model, tests/geometry and tests/runner in one process: 115 -> 105 CPU s).
_KEEP_BELOW_BYTES = 0.7e9
# A test that leaves its process above _RELEASE_ABOVE_BYTES keeps nothing compiled for the next
# one: the two workers of `make test` (`pytest -n 2`) then stay within 3 GB together (4.0 GB
# before), while the many small tests keep their programs (releasing after every test made
# tests/fit 28 % slower; above 1.5 GB instead of 1.2, tests/fit/test_fit.py and test_blocks.py
# took 129 CPU s instead of 140, but make test was no faster and its peak rose to 2.6-3.0 GB).
_RELEASE_ABOVE_BYTES = 1.2e9


@pytest.fixture(scope="module", autouse=True)
def _release_compiled_programs():
    yield
    if _resident_bytes() > _KEEP_BELOW_BYTES:
        release_compiled_programs()


@pytest.fixture(autouse=True)
def _release_when_large():
    yield
    if _resident_bytes() > _RELEASE_ABOVE_BYTES:
        release_compiled_programs()


# `make test` hands whole files to two workers (`--dist loadfile`) in collection order
# (`--no-loadscope-reorder`; pytest-xdist's own order puts the files with the most tests first,
# which left the few-test fits and subprocess runs to the end, one worker busy for a minute
# while the other idled). The files that take longest start first, so the short ones fill the
# end; the rest (5 s or less) keep their order. Wall seconds per file within a worker, `make test`
# on 2 cores (`pytest -n 2 --dist loadfile --durations=0` gives them per test, to sum by file).
LONGEST_FIRST = (
    "tests/fit/test_fit.py",  # 73 s
    "tests/fit/test_blocks.py",  # 40 s
    "tests/compile/test_executables.py",  # 26 s
    "tests/fit/test_processes.py",  # 23 s
    "tests/io/test_apriltag.py",  # 21 s
    "tests/node/test_ros1.py",  # 20 s, mostly waiting on roscore
    "tests/node/test_foxglove.py",  # 16 s, mostly waiting on the client
    "tests/runner/test_runner.py",  # 16 s
    "tests/test_horizon.py",  # 15 s
    "tests/predict/test_batch.py",  # 14 s
    "tests/test_hostile.py",  # 12 s
    "tests/test_demo.py",  # 12 s
    "tests/model/test_rollout.py",  # 12 s
    "tests/test_pipeline.py",  # 11 s
    "tests/node/test_ros2.py",  # 11 s, mostly waiting on DDS discovery
    "tests/geometry/test_track_check.py",  # 10 s
    "tests/compile/test_cache.py",  # 10 s
    "tests/runner/test_adapt.py",  # 10 s
    "tests/io/test_hostile.py",  # 10 s
    "tests/test_robust.py",  # 9 s
    "tests/predict/test_predict.py",  # 9 s
    "tests/predict/test_batch_io.py",  # 9 s
    "tests/model/test_kalman.py",  # 7 s
    "tests/predict/test_scale.py",  # 7 s
    "tests/fit/test_speed_shift.py",  # 7 s
    "tests/predict/test_shard.py",  # 6 s
    "tests/io/test_export.py",  # 6 s
)


def pytest_collection_modifyitems(items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    # stable: each file's tests, and the other files, keep their order (node ids start with the
    # file's path from the checkout's root)
    items.sort(key=lambda item: rank.get(item.nodeid.split("::", 1)[0], len(rank)))
