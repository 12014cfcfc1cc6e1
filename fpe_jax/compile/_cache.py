"""The persistent compilation cache: on by default, so a second run skips the compiler.

Where: `$FPE_CACHE_DIR`, else `${XDG_CACHE_HOME:-~/.cache}/fpe-jax/`. Entries live in a subfolder
named by jax + jaxlib version, backend, a hash of the processor's model and features, and x64
mode, so a different installation, CPU or dtype never reads an entry written by another (JAX's
own key covers the program itself). Each subfolder this module makes holds a marker file
(`MARKER`); `clear` and `info` touch only such folders (and the folders of older versions, whose
names and entries they recognise), and follow no symbolic link. `--no-cache` or `FPE_NO_CACHE=1`
turns the cache off. Everything but `enable` is JAX-free (`fpe cache info|clear`).
See docs/cache.md for what a stored entry must pass before it is used (`load_signed`).
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import hmac
import os
import platform
import re
import secrets
import stat
import sys
import time
import warnings
from pathlib import Path

# the start of JAX's warnings for an unreadable or unwritable entry (jax._src.compiler)
_JAX_CACHE_WARNINGS = (
    "Error reading persistent compilation cache entry",
    "Error writing persistent compilation cache entry",
)
MARKER = ".fpe-jax-cache"  # in every subfolder `enable` made
_MARKER_TEXT = b"compilation cache of fpe-jax: `fpe cache clear` empties this folder\n"
# folders of versions that wrote no marker: jax-<version>_jaxlib-<version>_<backend>_x64|x32
_LEGACY_NAME = re.compile(r"jax-[0-9][0-9a-z.+]*_jaxlib-[0-9][0-9a-z.+]*_[a-z]+_x(32|64)")
# the files `aot` and JAX write in a subfolder: aot/<64 hex>.exe and its temporary
# <name>.exe.tmp-* (older versions: <64 hex>.tmp<digits>), JAX's <key>-cache (ours: <64 hex>-cache
# and <name>.tmp-*) and <key>-atime
_ENTRY = re.compile(
    r"aot/[0-9a-f]{64}(\.exe(\.tmp-[0-9a-z-]+)?|\.tmp[0-9]+)|[\w.-]+-(cache|atime)(\.tmp-[0-9a-z-]+)?"
)

_ACTIVE: list[Path] = []  # the folder `enable` turned on in this process (none: off)
_JAX_CACHE_ON: list[Path] = []  # where JAX's own cache was turned on in this process

O_SAFE_READ = (
    os.O_RDONLY
    | getattr(os, "O_NOFOLLOW", 0)  # a link is refused (ELOOP), never followed
    | getattr(os, "O_NONBLOCK", 0)  # opening a FIFO does not wait for a writer
    | getattr(os, "O_CLOEXEC", 0)
)


class Refused(Exception):
    """A cache file that is not what this tool writes: the message says why."""


def active_dir() -> Path | None:
    """The folder `enable` pointed JAX at in this process, or None (the cache is off)."""
    return _ACTIVE[-1] if _ACTIVE else None


def root_dir() -> Path:
    """The cache's top folder (each subfolder belongs to one JAX installation, CPU and mode)."""
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
        f"fpe: warning: {kind} compilation cache entry in {root_dir()} ({detail[:160]}); "
        + ("compiling instead" if kind == "unreadable" else "not stored"),
        file=stream or sys.stderr,
    )


def cpu_features() -> str:
    """The processor's architecture, model and instruction-set features, as one string.

    XLA compiles for the features of the CPU it runs on: an executable made on another CPU type
    (a cache on a shared home) may run into an illegal instruction. Linux: the first processor's
    block of /proc/cpuinfo (x86: model name, flags; ARM: implementer, part, features).
    """
    fields = ("vendor_id", "model name", "flags", "cpu implementer", "cpu part", "features", "isa")
    found = {}
    try:
        with open("/proc/cpuinfo", "rb", buffering=0) as f:
            block = f.read(1 << 16).decode("utf-8", "replace").split("\n\n", 1)[0]
        for line in block.splitlines():
            name, _, value = line.partition(":")
            if name.strip().lower() in fields:
                found[name.strip().lower()] = " ".join(value.split())
    except OSError:
        pass
    return ";".join([platform.machine()] + sorted(f"{k}={v}" for k, v in found.items()))


def subfolder_name(
    jax_version: str, jaxlib_version: str, backend: str, x64: bool, machine: str
) -> str:
    """The subfolder of one installation, machine (`cpu_features` and the device kind) and mode."""
    tag = hashlib.sha256(machine.encode()).hexdigest()[:12]
    mode = "x64" if x64 else "x32"
    return f"jax-{jax_version}_jaxlib-{jaxlib_version}_{backend}-{tag}_{mode}"


def _make_marked(path: Path) -> None:
    """Make `path` with its marker file at once (a folder made in the same parent, then renamed),
    so no process sees it unmarked; raise Refused if it exists without a marker."""
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.parent / f".tmp-{path.name}-{secrets.token_hex(4)}"
        tmp.mkdir(mode=0o700)
        try:
            (tmp / MARKER).write_bytes(_MARKER_TEXT)
            os.rename(tmp, path)  # fails if another process made `path` first: theirs is used
        except OSError:
            (tmp / MARKER).unlink(missing_ok=True)
            tmp.rmdir()
    if not _ours(path, legacy=False):
        raise Refused("a folder this tool did not make")


def _ours(path: Path, legacy: bool = True) -> bool:
    """Whether `path` is a folder (not a link to one) that `enable` made: it holds a marker that
    is a regular file, or (legacy) it has the name an older version gave its folders."""
    try:
        if not stat.S_ISDIR(os.lstat(path).st_mode):
            return False
        if stat.S_ISREG(os.lstat(path / MARKER).st_mode):
            return True
    except OSError:
        pass
    return legacy and bool(_LEGACY_NAME.fullmatch(path.name))


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
    a plain jit): JAX's persistent cache of XLA executables, whose entries go through the same
    checks as `aot`'s (`_sign_jax_cache`).
    Call after the command has set x64 mode and before its first compilation.
    """
    if disabled():
        return None
    import jax
    import jaxlib

    machine = f"{cpu_features()};{jax.devices()[0].device_kind}"
    name = subfolder_name(
        jax.__version__,
        jaxlib.__version__,
        jax.default_backend(),
        jax.config.jax_enable_x64,
        machine,
    )
    path = root_dir() / name
    try:
        _make_marked(path)
    except (OSError, Refused) as e:
        why = e.strerror if isinstance(e, OSError) and e.strerror else str(e)
        print(f"fpe: warning: no compilation cache ({path}: {why})", file=sys.stderr)
        return None
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_enable_compilation_cache", not executables)
    # our executables compile in 0.05-5 s on a CPU: store every one (JAX's default keeps >= 1 s)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    jax.config.update("jax_raise_persistent_cache_errors", False)
    _one_line_warnings()
    if not executables:
        if not _sign_jax_cache(path):
            jax.config.update("jax_enable_compilation_cache", False)
            return None
        _JAX_CACHE_ON.append(path)
        _ACTIVE.clear()
    elif not _JAX_CACHE_ON:  # after JAX's cache, even once, executables stay in memory only
        _ACTIVE.append(path)
    return path


def _sign_jax_cache(path: Path) -> bool:
    """Make JAX's persistent cache read and write its entries in `path` as `aot`'s: signed
    (`store_signed`) and checked before use (`load_signed`); False (one warning) when this JAX
    has no cache object to replace, or the user's key is refused."""
    secret = user_key()
    if secret is None:
        return False
    try:  # JAX's cache object is internal: a version without it gets no disk cache
        from jax._src import compilation_cache as jax_cache
        from jax._src.compilation_cache_interface import CacheInterface

        class Signed(CacheInterface):
            def __init__(self):
                self._path = path

            def get(self, key: str) -> bytes | None:
                return load_signed(path / f"{entry_name(secret, key)}-cache", secret)

            def put(self, key: str, value: bytes) -> None:
                store_signed(path / f"{entry_name(secret, key)}-cache", secret, value)

        with jax_cache._cache_initialized_mutex:
            jax_cache._cache, jax_cache._cache_initialized = Signed(), True
    except (ImportError, AttributeError) as e:
        print(f"fpe: warning: no compilation cache (this JAX's cache: {e})", file=sys.stderr)
        return False
    return True


def disable() -> None:
    """Turn the cache off for the rest of this process (`--no-cache` after an earlier enable)."""
    _ACTIVE.clear()
    if "jax" in sys.modules:
        sys.modules["jax"].config.update("jax_enable_compilation_cache", False)


def read_regular(path: Path, max_bytes: int, private: bool = False) -> bytes:
    """The bytes of `path` if it is a regular file (not a link, FIFO or device) of at most
    `max_bytes`; private: also owned by this user and closed to others (mode 0600 or less).
    Raises FileNotFoundError when there is none, Refused when it is not such a file."""
    st = os.lstat(path)  # before opening: a device or FIFO is never opened
    if not stat.S_ISREG(st.st_mode):
        raise Refused("not a regular file")
    try:
        fd = os.open(path, O_SAFE_READ)
    except FileNotFoundError:
        raise
    except OSError as e:  # ELOOP: replaced by a link since the lstat
        raise Refused(e.strerror or str(e)) from None
    try:
        st = os.fstat(fd)  # the file opened, whatever happened since the lstat
        if not stat.S_ISREG(st.st_mode):
            raise Refused("not a regular file")
        if st.st_size > max_bytes:
            raise Refused(f"{st.st_size} bytes, more than {max_bytes}")
        if private and (st.st_uid != _uid() or st.st_mode & 0o077):
            raise Refused("not private to this user (owner and mode 0600)")
        with os.fdopen(os.dup(fd), "rb", buffering=0) as f:
            data = f.read(st.st_size + 1)
    finally:
        os.close(fd)
    if len(data) != st.st_size:
        raise Refused("changed while it was read")
    return data


def _uid() -> int:
    return os.getuid() if hasattr(os, "getuid") else 0


def secret_key() -> bytes:
    """This user's 32-byte key that authenticates stored executables (`aot`): the file
    `.key-<uid>` in the cache's top folder, made once with mode 0600. Raises Refused (or
    OSError) when it cannot be made or is not a private regular file of this user."""
    path = root_dir() / f".key-{_uid()}"
    try:
        key = read_regular(path, 32, private=True)
    except FileNotFoundError:
        # written whole under a temporary name, then linked: a concurrent process's key wins
        tmp = path.with_name(f"{path.name}.tmp-{os.getpid()}-{secrets.token_hex(4)}")
        fd = os.open(
            tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0), 0o600
        )
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(secrets.token_bytes(32))
            try:
                os.link(tmp, path)
            except FileExistsError:
                pass
        finally:
            tmp.unlink(missing_ok=True)
        key = read_regular(path, 32, private=True)
    if len(key) != 32:
        raise Refused(f"{len(key)} bytes, not 32")
    return key


# a signed entry: MAGIC, then HMAC-SHA256(user's key, MAGIC + file name + body), then the body
MAGIC = b"fpe-jax executable 2\n"
MAX_ENTRY_BYTES = 256 << 20  # the largest executables here are a few MB
STALE_TEMP_S = 600.0  # a temporary entry this old was left by a killed writer


def _mac(secret: bytes, name: str, body: bytes) -> bytes:
    h = hmac.new(secret, MAGIC + name.encode() + b"\0", "sha256")
    h.update(body)  # apart: joined to the prefix, a body of megabytes would be copied first
    return h.digest()


def entry_name(secret: bytes, key: str) -> str:
    """The file name (64 hex digits) of the entry of `key` under this user's key: users who
    share a folder never read each other's entries."""
    return hmac.digest(secret, key.encode(), "sha256").hex()


@functools.cache
def _key_of(root: Path) -> bytes | None:
    try:
        return secret_key()
    except (OSError, Refused) as e:
        warn("unreadable", f"key: {getattr(e, 'strerror', None) or e}")
        return None


def user_key() -> bytes | None:
    """`secret_key()`, read once per process and cache folder; None (one warning) when it is
    refused: executables then stay in memory."""
    return _key_of(root_dir())


def load_signed(path: Path, secret: bytes) -> bytes | None:
    """The body of the entry at `path`; None when there is none, or (one warning) when it is not
    a regular file of at most MAX_ENTRY_BYTES (`read_regular`) whose HMAC under `secret` is
    right: a damaged entry, or one this user's fpe did not write, is never used."""
    try:
        blob = read_regular(path, MAX_ENTRY_BYTES)
    except FileNotFoundError:
        return None
    except (OSError, Refused) as e:
        warn("unreadable", f"{path.name}: {getattr(e, 'strerror', None) or e}")
        return None
    n = len(MAGIC)
    mac, body = blob[n : n + 32], blob[n + 32 :]
    if blob[:n] != MAGIC or not hmac.compare_digest(mac, _mac(secret, path.name, body)):
        warn("unreadable", f"{path.name}: not written by fpe for this user, or damaged")
        return None
    return body


def store_signed(path: Path, secret: bytes, body: bytes) -> None:
    """Write the entry at `path` whole (a temporary file of mode 0600, renamed over whatever is
    there); a failed write leaves no temporary file (one warning), and temporary files of a
    killed writer (older than STALE_TEMP_S) go."""
    tmp = path.with_name(f"{path.name}.tmp-{os.getpid()}-{secrets.token_hex(4)}")
    try:
        path.parent.mkdir(exist_ok=True)
        _remove_stale_temps(path.parent)
        flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0)
        with os.fdopen(os.open(tmp, flags, 0o600), "wb") as f:
            f.write(MAGIC + _mac(secret, path.name, body))
            f.write(body)
        os.replace(tmp, path)  # atomic: a concurrent reader sees the old file or the whole new one
    except OSError as e:
        warn("unwritable", f"{path.parent}: {e.strerror or e}")
    finally:
        tmp.unlink(missing_ok=True)  # only left when the write failed


def _remove_stale_temps(folder: Path) -> None:
    now = time.time()
    for entry in os.scandir(folder):
        if ".tmp-" in entry.name and entry.is_file(follow_symlinks=False):
            with contextlib.suppress(OSError):
                if now - entry.stat(follow_symlinks=False).st_mtime > STALE_TEMP_S:
                    os.unlink(entry.path)


def _walk(folder: Path):
    """(relative name, lstat) of every entry under `folder`, without following links."""
    for top, dirs, files in os.walk(folder, followlinks=False):
        for name in dirs + files:
            p = Path(top) / name
            try:
                yield p.relative_to(folder).as_posix(), os.lstat(p)
            except OSError:
                continue


def _ours_entries(folder: Path) -> list[tuple[str, os.stat_result]]:
    """The regular files in `folder` whose names are entries this tool or JAX wrote."""
    return [
        (n, st)
        for n, st in _walk(folder)
        if stat.S_ISREG(st.st_mode) and _ENTRY.fullmatch(n) and n != MARKER
    ]


def _subfolders() -> list[Path]:
    root = root_dir()
    try:
        names = sorted(os.listdir(root))
    except OSError:
        return []
    return [root / n for n in names if n.startswith("jax-") and _ours(root / n)]


def info() -> dict:
    """{"path", "exists", "entries", "bytes", "subfolders": {name: {"entries", "bytes"}}}: the
    folders `enable` made and the entries in them (no link is followed)."""
    root = root_dir()
    subs = {}
    for sub in _subfolders():
        files = _ours_entries(sub)
        # aot: '<name>.exe' per executable; JAX: '<key>-cache' per executable, '-atime' bookkeeping
        entries = [n for n, _ in files if n.endswith(("-cache", ".exe"))]
        subs[sub.name] = {"entries": len(entries), "bytes": sum(st.st_size for _, st in files)}
    return {
        "path": str(root),
        "exists": root.is_dir(),
        "entries": sum(s["entries"] for s in subs.values()),
        "bytes": sum(s["bytes"] for s in subs.values()),
        "subfolders": subs,
    }


def clear() -> dict:
    """Remove the cache's entries (the top folder, this user's key and anything this tool did not
    write stay); returns `info()` from before."""
    before = info()
    for sub in _subfolders():
        for name, _ in _ours_entries(sub):
            (sub / name).unlink(missing_ok=True)
        try:
            if (sub / "aot").is_dir() and not (sub / "aot").is_symlink():
                (sub / "aot").rmdir()
            if not set(os.listdir(sub)) - {MARKER}:  # nothing but the marker: the folder goes
                (sub / MARKER).unlink(missing_ok=True)
                sub.rmdir()
        except OSError:  # a file this tool did not write is still there: the folder stays
            pass
    return before
