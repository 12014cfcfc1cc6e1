"""The persistent XLA compilation cache: on by default, so a second run skips the compiler.

Where: `$FPE_CACHE_DIR`, else `${XDG_CACHE_HOME:-~/.cache}/fpe-jax/`. Entries live in a subfolder
named by jax + jaxlib version, backend and x64 mode, so a different installation or dtype never
reads an entry written by another (JAX's own key covers the program itself). `--no-cache` or
`FPE_NO_CACHE=1` turns it off. Everything but `enable` is JAX-free (`fpe cache info|clear`).
"""

from __future__ import annotations

import os
import shutil
import sys
import warnings
from pathlib import Path

# the start of JAX's warnings for an unreadable or unwritable entry (jax._src.compiler)
_JAX_CACHE_WARNINGS = (
    "Error reading persistent compilation cache entry",
    "Error writing persistent compilation cache entry",
)


_ACTIVE: list[Path] = []  # the folder `enable` turned on in this process (none: off)
_JAX_CACHE_ON: list[Path] = []  # where JAX's own cache was turned on in this process


def active_dir() -> Path | None:
    """The folder `enable` pointed JAX at in this process, or None (the cache is off)."""
    return _ACTIVE[-1] if _ACTIVE else None


def root_dir() -> Path:
    """The cache's top folder (each subfolder belongs to one JAX installation and mode)."""
    if os.environ.get("FPE_CACHE_DIR"):
        return Path(os.environ["FPE_CACHE_DIR"]).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(xdg).expanduser() / "fpe-jax"


def disabled() -> bool:
    """True when FPE_NO_CACHE is set to anything but '', '0' or 'false'."""
    return os.environ.get("FPE_NO_CACHE", "").strip().lower() not in ("", "0", "false")


_SHOWN: set[str] = set()  # the kinds of warning already printed in this process


def warn(kind: str, detail: str, stream=None) -> None:
    """One `fpe: warning:` line per kind ("unreadable", "unwritable") and process."""
    if kind in _SHOWN:
        return
    _SHOWN.add(kind)
    print(
        f"fpe: warning: {kind} compilation cache entry in {root_dir()} ({detail[:80]}); "
        + ("compiling instead" if kind == "unreadable" else "not stored"),
        file=stream or sys.stderr,
    )


def _one_line_warnings() -> None:
    """Show JAX's cache read/write warnings as `warn` lines."""
    if getattr(warnings.showwarning, "_fpe_cache", False):  # installed by an earlier call
        return
    previous = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):
        text = str(message)
        kind = next((k for k in _JAX_CACHE_WARNINGS if text.startswith(k)), None)
        if kind is None:
            return previous(message, category, filename, lineno, file, line)
        warn("unreadable" if "reading" in kind else "unwritable", text.rsplit(": ", 1)[-1])

    show._fpe_cache = True
    warnings.showwarning = show


def enable(executables: bool = True) -> Path | None:
    """Turn the cache on in this installation's subfolder; returns it (None: off).

    executables=True (predict, evaluate, plot, fit, demo): `aot` stores the commands' whole
    executables there and JAX's own cache stays off: an executable compiled in a process that
    had read entries of JAX's cache ran elsewhere as "NOT_FOUND: Function ... fusion not found"
    (XLA on the CPU, jax 0.10.2), so the two must not mix. False (batch, whose chunk function is
    a plain jit): JAX's persistent cache of XLA executables.
    Call after the command has set x64 mode and before its first compilation.
    """
    if disabled():
        return None
    import jax
    import jaxlib

    x64 = "x64" if jax.config.jax_enable_x64 else "x32"
    name = f"jax-{jax.__version__}_jaxlib-{jaxlib.__version__}_{jax.default_backend()}_{x64}"
    path = root_dir() / name
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        print(f"fpe: warning: no compilation cache ({path}: {e.strerror})", file=sys.stderr)
        return None
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_enable_compilation_cache", not executables)
    # our executables compile in 0.05-5 s on a CPU: store every one (JAX's default keeps >= 1 s)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    jax.config.update("jax_raise_persistent_cache_errors", False)
    _one_line_warnings()
    if not executables:
        _JAX_CACHE_ON.append(path)
        _ACTIVE.clear()
    elif not _JAX_CACHE_ON:  # after JAX's cache, even once, executables stay in memory only
        _ACTIVE.append(path)
    return path


def disable() -> None:
    """Turn the cache off for the rest of this process (`--no-cache` after an earlier enable)."""
    _ACTIVE.clear()
    if "jax" in sys.modules:
        sys.modules["jax"].config.update("jax_enable_compilation_cache", False)


def info() -> dict:
    """{"path", "exists", "entries", "bytes", "subfolders": {name: {"entries", "bytes"}}}."""
    root = root_dir()
    subs = {}
    if root.is_dir():
        # only the folders `enable` makes: FPE_CACHE_DIR may name a folder that holds other things
        for sub in sorted(p for p in root.glob("jax-*") if p.is_dir()):
            files = [f for f in sub.rglob("*") if f.is_file()]
            # JAX writes one '<key>-cache' file per executable, plus '-atime' bookkeeping files
            entries = [f for f in files if not f.name.endswith("-atime")]
            subs[sub.name] = {
                "entries": len(entries),
                "bytes": sum(f.stat().st_size for f in files),
            }
    return {
        "path": str(root),
        "exists": root.is_dir(),
        "entries": sum(s["entries"] for s in subs.values()),
        "bytes": sum(s["bytes"] for s in subs.values()),
        "subfolders": subs,
    }


def clear() -> dict:
    """Remove every subfolder of the cache (the top folder stays); returns `info()` from before."""
    before = info()
    root = root_dir()
    for name in before["subfolders"]:
        shutil.rmtree(root / name, ignore_errors=True)
    return before
