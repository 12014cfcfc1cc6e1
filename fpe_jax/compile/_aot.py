"""Compiled executables kept on disk, so a warm command skips tracing, lowering and compiling.

JAX's persistent cache (`cache.enable`) stores only XLA's output: every run still traces and
lowers each function again, which took most of a warm command's seconds (0.3-5 s a function).
`jit(f)` keys an executable by f, the package's source, the library versions, the JAX settings
that shape a trace, the static (non-array) leaves and tree structure of the arguments and the
shapes and dtypes of their arrays, and stores it (`jax.experimental.serialize_executable`) in
the cache folder's `aot/`. Within one process every executable is made once. With the cache off
(`--no-cache`, or `cache.enable` never called) executables are only kept in memory. JAX's own
cache must be off while executables are stored (`cache.enable` says why).

An entry cannot be made safe by its format: `serialize_executable` pickles the executable with
its shardings, and the executable itself is machine code, so whoever can change an entry can run
code as the user. An entry is unpickled only when `cache.load_signed` accepts it (a regular file
of bounded size, authenticated with the user's own key); anything else gives one warning and a
compile, whose result replaces it.

Arguments follow `equinox.filter_jit`: arrays (NumPy or JAX) and `jax.ShapeDtypeStruct`s are
traced, every other leaf is static. `executable(f, *args)` with shapes alone compiles ahead of the
data (fit compiles its solver while the states are estimated).
"""

from __future__ import annotations

import functools
import hashlib
import pickle
import threading
import time
from pathlib import Path

import jax
import numpy as np

from fpe_jax.compile import _cache as cache

_MEMO: dict[str, Executable] = {}
_MAKING: dict[str, threading.Lock] = {}  # held while an executable is loaded or compiled
_LOCK = threading.Lock()
# XLA's CPU backend has two code generators for fused loops. On these programs (vmapped history
# windows, short scans, many small reductions) its older loop emitters compile faster and run as
# fast, with bitwise the same values. Functions in FUSION_EMITTERS keep XLA's defaults: the
# fit's solver also compiles faster with the loop emitters, but its steps, the work a warm fit
# repeats, run slower (experiments/benchmarks/results.md, History).
CPU_COMPILER_OPTIONS = {"xla_cpu_use_fusion_emitters": False}
FUSION_EMITTERS: set = set()


def fusion_emitters(fun):
    """Mark `fun` to compile with XLA's default emitters (see FUSION_EMITTERS); returns it."""
    FUSION_EMITTERS.add(fun)
    return fun


@functools.cache
def _fingerprint() -> str:
    """The package's source and the versions of the libraries that shape a traced program."""
    from importlib import metadata

    h = hashlib.sha256()
    root = Path(__file__).parents[1]  # the fpe_jax package root, not this sub-package
    for f in sorted(root.rglob("*.py")):
        h.update(f.relative_to(root).as_posix().encode() + b"\0" + f.read_bytes())
    for dist in ("jax", "jaxlib", "equinox", "optimistix", "lineax", "numpy"):
        try:
            h.update(f"{dist}={metadata.version(dist)};".encode())
        except metadata.PackageNotFoundError:
            h.update(f"{dist}=none;".encode())
    return h.hexdigest()


def _is_traced(x) -> bool:
    return isinstance(x, jax.Array | np.ndarray | np.generic | jax.ShapeDtypeStruct)


def _aval(x) -> str:
    return f"{np.dtype(x.dtype).str}{tuple(np.shape(x))}{'w' if getattr(x, 'weak_type', 0) else ''}"


def _split(args, kwargs):
    leaves, treedef = jax.tree.flatten((args, kwargs))
    traced = [i for i, x in enumerate(leaves) if _is_traced(x)]
    return leaves, treedef, traced


def _key(fun, leaves, treedef, traced) -> str:
    config = jax.config
    settings = (
        config.jax_enable_x64,
        config.jax_numpy_rank_promotion,
        config.jax_numpy_dtype_promotion,
        config.jax_default_matmul_precision,
    )
    is_traced = set(traced)
    parts = [
        f"{fun.__module__}.{fun.__qualname__}",
        _fingerprint(),
        repr(settings),
        jax.default_backend(),
        repr(treedef),
        ";".join(_aval(x) if i in is_traced else repr(x) for i, x in enumerate(leaves)),
    ]
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()


class Executable:
    """One compiled function: call it with arguments of the structure it was compiled for."""

    def __init__(self, compiled, out_treedef, traced: list[int], **seconds):
        self._compiled, self._out, self._traced = compiled, out_treedef, traced
        # where its time went [s]: trace_s (tracing and lowering), compile_s (XLA), load_s (disk)
        self.seconds = {"trace_s": 0.0, "compile_s": 0.0, "load_s": 0.0, **seconds}

    def __call__(self, *args, **kwargs):
        leaves = jax.tree.leaves((args, kwargs))
        out = self._compiled(*[leaves[i] for i in self._traced])
        return jax.tree.unflatten(self._out, out)


def _load(path: Path, secret: bytes, traced: list[int]) -> Executable | None:
    """The executable stored at `path`, or None (absent, or refused with one warning): only an
    authenticated entry (`cache.load_signed`) is unpickled."""
    from jax.experimental import serialize_executable

    t0 = time.perf_counter()
    body = cache.load_signed(path, secret)
    if body is None:
        return None
    try:
        payload, in_tree, out_tree, skeleton = pickle.loads(body)
        compiled = serialize_executable.deserialize_and_load(payload, in_tree, out_tree)
        seconds = {"load_s": time.perf_counter() - t0}
        return Executable(compiled, jax.tree.structure(skeleton), traced, **seconds)
    except Exception as e:  # noqa: BLE001 -- an executable of an incompatible jaxlib: compile
        cache.warn("unreadable", f"{path.name}: {type(e).__name__}: {e}")
        return None


def _build(fun, leaves, treedef, traced, store: tuple[Path, bytes] | None) -> Executable:
    out_treedef = []

    def flat(*traced_leaves):
        full = list(leaves)
        for i, x in zip(traced, traced_leaves):
            full[i] = x
        args, kwargs = jax.tree.unflatten(treedef, full)
        out_leaves, out = jax.tree.flatten(fun(*args, **kwargs))
        out_treedef.append(out)
        return out_leaves

    t0 = time.perf_counter()
    shapes = [
        jax.ShapeDtypeStruct(np.shape(x), x.dtype, weak_type=bool(getattr(x, "weak_type", False)))
        for x in (leaves[i] for i in traced)
    ]
    lowered = jax.jit(flat).lower(*shapes)
    t1 = time.perf_counter()
    compiled = _compile(lowered, None if fun in FUSION_EMITTERS else CPU_COMPILER_OPTIONS)
    seconds = {"trace_s": t1 - t0, "compile_s": time.perf_counter() - t1}
    exe = Executable(compiled, out_treedef[0], traced, **seconds)
    if store is not None:
        _store(*store, compiled, out_treedef[0])
    return exe


def _compile(lowered, cpu_options: dict | None):
    """XLA's executable of a lowered program, with cpu_options on the CPU (a jaxlib that does
    not know one of them compiles with its defaults)."""
    if jax.default_backend() != "cpu" or cpu_options is None:
        return lowered.compile()
    try:
        return lowered.compile(compiler_options=cpu_options)
    except Exception as e:  # noqa: BLE001 -- jaxlib's error type differs between versions
        if "no such compile option" not in str(e).lower():
            raise
        return lowered.compile()


def _store(path: Path, secret: bytes, compiled, out_treedef) -> None:
    """Store the executable at `path`, authenticated by `secret` (`cache.store_signed`)."""
    from jax.experimental import serialize_executable

    try:
        payload, in_tree, out_tree = serialize_executable.serialize(compiled)
        # the output tree as a skeleton of zeros: treedefs of equinox Modules do not pickle
        skeleton = jax.tree.unflatten(out_treedef, [0] * out_treedef.num_leaves)
        body = pickle.dumps((payload, in_tree, out_tree, skeleton))
    except Exception:  # noqa: BLE001 -- not serializable (e.g. constants): kept in memory only
        return
    cache.store_signed(path, secret, body)


def _entry(key: str) -> tuple[Path, bytes] | None:
    """Where the executable of `key` is stored and this user's key that authenticates it; None
    when the cache is off or the key is refused (one warning: executables stay in memory)."""
    folder = cache.active_dir()
    if folder is None or jax.distributed.is_initialized():
        # a multi-process program's executables name the devices of every process: kept in
        # memory, as each process of the group compiles the same programs
        return None
    secret = cache.user_key()
    if secret is None:
        return None
    return folder / "aot" / f"{cache.entry_name(secret, key)}.exe", secret


def executable(fun, *args, **kwargs) -> Executable:
    """The executable of `fun` for arguments like these (arrays or ShapeDtypeStructs). Threads
    that ask for one executable at once wait for the first to make it."""
    leaves, treedef, traced = _split(args, kwargs)
    key = _key(fun, leaves, treedef, traced)
    with _LOCK:
        exe = _MEMO.get(key)
        making = _MAKING.setdefault(key, threading.Lock()) if exe is None else None
    if exe is not None:  # made earlier in this process: it cost this call nothing
        return Executable(exe._compiled, exe._out, exe._traced)
    with making:
        with _LOCK:
            exe = _MEMO.get(key)
        if exe is not None:  # another thread made it while this one waited
            return Executable(exe._compiled, exe._out, exe._traced)
        store = _entry(key)
        exe = (_load(*store, traced) if store is not None else None) or _build(
            fun, leaves, treedef, traced, store
        )
        with _LOCK:
            _MAKING.pop(key, None)
            return _MEMO.setdefault(key, exe)


def jit(fun):
    """`fun` compiled once per argument structure (see the module docstring), kept on disk."""

    @functools.wraps(fun)
    def call(*args, **kwargs):
        leaves = jax.tree.leaves((args, kwargs))
        if any(isinstance(x, jax.core.Tracer) for x in leaves):  # inside another trace: inline
            return fun(*args, **kwargs)
        return executable(fun, *args, **kwargs)(*args, **kwargs)

    return call
