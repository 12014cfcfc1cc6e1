"""The compilation cache against a hostile or damaged cache folder: an entry is loaded only when
it is an authenticated regular file, anything else gives one warning and a recompile with the
same numbers; `fpe cache clear|info` touch only what fpe wrote and follow no link."""

import json
import os
import pickle
import select
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from fpe_jax.compile import _aot as aot
from fpe_jax.compile import _cache as cache

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "data" / "samples"

# a child process: the cache on in FPE_CACHE_DIR, one stored executable, its numbers as JSON
_SETUP = """
import json, resource, sys
import numpy as np
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
from fpe_jax.compile import _aot as aot
from fpe_jax.compile import _cache as cache

def wave(x):
    return {"y": jnp.cumsum(jnp.sin(3.0 * x) * jnp.exp(-x)) / (1.0 + x * x)}

def run():
    x = np.linspace(0.0, 2.0, 257)
    exe = aot.executable(wave, x)
    y = np.asarray(exe(x)["y"])
    return {"y": y.tolist(), "compile_s": exe.seconds["compile_s"],
            "maxrss_kb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss}
"""
_CHILD = _SETUP + "cache.enable()\nprint(json.dumps(run()))\n"
# _CHILD once for each line on stdin (a cache folder), one JSON line back each: a round starts
# as a new process does (nothing kept in memory, the cache turned on anew, the user's key read
# again, no warning shown yet), and its "stderr" is what that round printed
_ROUNDS = (
    _SETUP
    + """
import contextlib, io, os
for line in sys.stdin:
    os.environ["FPE_CACHE_DIR"] = line.rstrip("\\n")
    aot._MEMO.clear()
    cache._ACTIVE.clear()
    cache._SHOWN.clear()
    cache._key_of.cache_clear()
    jax.clear_caches()
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        cache.enable()
        out = run()
    print(json.dumps({**out, "stderr": err.getvalue()}), flush=True)
"""
)


def child(cache_dir: Path, timeout_s: float = 120.0, limit_bytes: int | None = None) -> dict:
    """Run _CHILD (with an address-space limit, if given); its JSON, return code and stderr."""
    # the limit is set by the child itself before anything else: a preexec_fn would fork this
    # process, which has JAX's threads running
    prefix = ""
    if limit_bytes:
        prefix = (
            "import resource; "
            f"resource.setrlimit(resource.RLIMIT_AS, ({limit_bytes}, {limit_bytes}))\n"
        )
    r = subprocess.run(
        [sys.executable, "-c", prefix + _CHILD],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env={**os.environ, "FPE_CACHE_DIR": str(cache_dir)},
        timeout=timeout_s,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    return {**json.loads(r.stdout.strip().splitlines()[-1]), "stderr": r.stderr}


class ChildRounds:
    """One child running _ROUNDS for this file's cache folders: calling it with a folder gives
    what `child` gives for it, without a fresh interpreter per round (which spends most of its
    time importing JAX). A child that does not answer is ended (the next call starts another);
    its own stderr must stay empty."""

    def __init__(self):
        self._p = None

    def __call__(self, cache_dir: Path, timeout_s: float = 120.0) -> dict:
        if self._p is None:
            self._p = subprocess.Popen(
                [sys.executable, "-c", _ROUNDS],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
                cwd=ROOT,
            )
        p = self._p
        p.stdin.write(f"{cache_dir}\n")
        p.stdin.flush()
        ready, _, _ = select.select([p.stdout], [], [], timeout_s)
        line = p.stdout.readline() if ready else ""
        if not line:
            err = self.close()
            raise AssertionError(f"the child gave no answer within {timeout_s} s: {err[-3000:]}")
        return json.loads(line)

    def close(self) -> str:
        """End the child; what it printed on its stderr."""
        p, self._p = self._p, None
        if p is None:
            return ""
        p.stdin.close()
        try:
            p.wait(timeout=60)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()
        err = p.stderr.read()
        p.stdout.close()
        p.stderr.close()
        return err


@pytest.fixture(scope="module")
def child_round():
    rounds = ChildRounds()
    yield rounds
    assert rounds.close() == ""


X = np.linspace(0.0, 2.0, 257)  # the child's input


def entries(cache_dir: Path) -> list[Path]:
    return sorted(cache_dir.rglob("aot/*.exe"))


def assert_one_warning_and_recompiled(run: dict, fresh: dict) -> None:
    lines = run["stderr"].strip().splitlines()
    assert len(lines) == 1, run["stderr"]
    assert lines[0].startswith("fpe: warning: unreadable compilation cache entry"), lines
    assert run["compile_s"] > 0
    assert run["y"] == fresh["y"]  # bit for bit what a fresh compile gives


@pytest.fixture(scope="module")
def filled_once(tmp_path_factory, child_round) -> tuple[Path, dict, dict]:
    """A cache folder holding the child's one executable, stored by one child (the first round
    of `child_round`) and loaded by another: (folder, fresh result, warm result). Tests damage
    copies of it (`filled`)."""
    folder = tmp_path_factory.mktemp("filled") / "cache"
    fresh = child_round(folder)
    assert fresh["stderr"] == "" and fresh["compile_s"] > 0
    [_] = entries(folder)
    warm = child(folder)
    assert warm["compile_s"] == 0.0 and warm["y"] == fresh["y"], warm["stderr"]
    return folder, fresh, warm


@pytest.fixture
def filled(tmp_path, filled_once) -> tuple[Path, dict, Path]:
    """A copy of `filled_once` (the user's key and the entry, modes kept) for this test:
    (folder, fresh result, entry). An entry's MAC covers its name, not its folder."""
    folder, fresh, _ = filled_once
    shutil.copytree(folder, tmp_path / "cache", symlinks=True)
    [entry] = entries(tmp_path / "cache")
    return tmp_path / "cache", fresh, entry


def test_a_flipped_bit_anywhere_gives_one_warning_and_a_recompile(
    filled, child_round, monkeypatch, capsys
):
    cache_dir, fresh, entry = filled
    monkeypatch.setenv("FPE_CACHE_DIR", str(cache_dir))
    secret = cache.secret_key()
    good = entry.read_bytes()
    for offset in (3, 40, len(good) // 4, len(good) // 2, 3 * len(good) // 4, len(good) - 1):
        damaged = bytearray(good)
        damaged[offset] ^= 0x10
        entry.write_bytes(bytes(damaged))
        assert_one_warning_and_recompiled(child_round(cache_dir), fresh)
        # the recompiled executable replaced the damaged entry: it loads without a warning and
        # gives the fresh numbers (loaded here, as a later child's `aot.executable` would)
        healed = aot._load(entry, secret, traced=[0])
        assert healed is not None and capsys.readouterr().err == "", offset
        assert np.asarray(healed(X)["y"]).tolist() == fresh["y"], offset


def test_a_crafted_pickle_entry_is_never_unpickled(filled, child_round, tmp_path):
    cache_dir, fresh, entry = filled
    touched = tmp_path / "touched"

    class Touch:
        def __reduce__(self):
            return (os.system, (f"touch {touched}",))

    crafted = pickle.dumps(Touch())
    # a bare pickle, and one behind the entry's header with a MAC made without the user's key
    header = cache.MAGIC + bytes(32)
    for blob in (crafted, header + crafted, cache.MAGIC + entry.read_bytes()[-32:]):
        entry.write_bytes(blob)
        assert_one_warning_and_recompiled(child_round(cache_dir), fresh)
        assert not touched.exists()


def test_an_entry_from_another_users_key_is_not_loaded(filled, child_round):
    cache_dir, fresh, entry = filled
    [key] = cache_dir.glob(".key-*")
    key.unlink()  # a new key: every stored entry is now unauthenticated (and named otherwise)
    run = child_round(cache_dir)
    assert run["compile_s"] > 0 and run["y"] == fresh["y"] and run["stderr"] == ""


def test_a_fifo_entry_does_not_hang(filled, child_round):
    cache_dir, fresh, entry = filled
    entry.unlink()
    os.mkfifo(entry)
    t0 = time.perf_counter()
    assert_one_warning_and_recompiled(child_round(cache_dir, timeout_s=60), fresh)
    assert time.perf_counter() - t0 < 60
    assert entry.is_file()  # replaced by the recompiled executable


def test_a_link_to_dev_zero_is_refused_with_flat_memory(filled, filled_once):
    cache_dir, fresh, entry = filled
    warm = filled_once[2]  # a child that loaded the entry
    entry.unlink()
    entry.symlink_to("/dev/zero")
    # an address-space limit keeps a reader that would follow the link from eating the machine
    run = child(cache_dir, timeout_s=60, limit_bytes=3 << 30)
    assert_one_warning_and_recompiled(run, fresh)
    # memory: the compile's own, nothing like an endless read (KiB)
    assert run["maxrss_kb"] < warm["maxrss_kb"] + 300_000
    assert not entry.is_symlink() and entry.is_file()


def test_an_oversized_or_foreign_key_file_is_refused(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("FPE_CACHE_DIR", str(tmp_path))
    key = cache.secret_key()
    assert len(key) == 32 and cache.secret_key() == key
    path = tmp_path / f".key-{os.getuid()}"
    assert path.stat().st_mode & 0o777 == 0o600
    path.chmod(0o644)  # others could read it: it authenticates nothing
    with pytest.raises(cache.Refused, match="private"):
        cache.secret_key()
    path.unlink()
    path.symlink_to("/dev/zero")
    with pytest.raises(cache.Refused, match="regular"):
        cache.secret_key()


def test_read_regular_refuses_what_is_not_a_bounded_regular_file(tmp_path):
    (tmp_path / "ok").write_bytes(b"12345")
    assert cache.read_regular(tmp_path / "ok", 5) == b"12345"
    with pytest.raises(cache.Refused, match="more than 4"):
        cache.read_regular(tmp_path / "ok", 4)
    os.mkfifo(tmp_path / "fifo")
    (tmp_path / "link").symlink_to(tmp_path / "ok")
    for name in ("fifo", "link"):
        with pytest.raises(cache.Refused, match="not a regular file"):
            cache.read_regular(tmp_path / name, 1 << 20)
    with pytest.raises(cache.Refused):
        cache.read_regular(Path("/dev/zero"), 1 << 20)
    with pytest.raises(FileNotFoundError):
        cache.read_regular(tmp_path / "none", 5)


def test_the_key_holds_the_cpu_model_and_features():
    features = cache.cpu_features()
    if Path("/proc/cpuinfo").is_file():
        assert "model name=" in features or "features=" in features, features
    one = cache.subfolder_name("0.10.2", "0.10.2", "cpu", True, features)
    assert one == cache.subfolder_name("0.10.2", "0.10.2", "cpu", True, features)
    other = cache.subfolder_name("0.10.2", "0.10.2", "cpu", True, features + " avx512f")
    assert one != other and one.startswith("jax-0.10.2_jaxlib-0.10.2_cpu-")
    assert one.endswith("_x64") and other.endswith("_x64")


def _store_one(tmp_path, monkeypatch):
    """aot.executable of a small function with the cache in tmp_path/sub (key in tmp_path)."""
    import jax.numpy as jnp

    monkeypatch.setenv("FPE_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(cache, "_ACTIVE", [tmp_path / "sub"])
    monkeypatch.setattr(cache, "_SHOWN", set())
    monkeypatch.setattr(aot, "_MEMO", {})
    x = np.linspace(0.0, 1.0, 9)
    exe = aot.executable(lambda x: jnp.cos(x) * 2.0, x)
    np.testing.assert_allclose(exe(x), np.cos(x) * 2.0, rtol=1e-14)


def test_a_failed_write_leaves_no_temporary_file(tmp_path, monkeypatch, capsys):
    def full_disk(src, dst):
        raise OSError(28, "No space left on device")

    with monkeypatch.context() as m:
        m.setattr(os, "replace", full_disk)
        _store_one(tmp_path, monkeypatch)
    err = capsys.readouterr().err
    assert err.startswith("fpe: warning: unwritable compilation cache entry"), err
    assert [p.name for p in (tmp_path / "sub").rglob("*") if p.is_file()] == []


def test_an_entry_is_stored_as_magic_hmac_body(tmp_path, monkeypatch, capsys):
    """The stored format (MAGIC, HMAC-SHA256 of MAGIC + name + NUL + body under the user's key,
    body): entries written by earlier versions stay valid, and one byte changed anywhere is not."""
    import hmac

    monkeypatch.setattr(cache, "_SHOWN", set())
    secret, body = os.urandom(32), os.urandom(100_000)
    path = tmp_path / f"{'c' * 64}.exe"
    cache.store_signed(path, secret, body)
    mac = hmac.digest(secret, cache.MAGIC + path.name.encode() + b"\0" + body, "sha256")
    assert path.read_bytes() == cache.MAGIC + mac + body
    assert cache.load_signed(path, secret) == body
    blob = bytearray(path.read_bytes())
    blob[-1] ^= 1
    path.write_bytes(bytes(blob))
    assert cache.load_signed(path, secret) is None
    assert "not written by fpe for this user, or damaged" in capsys.readouterr().err


def test_temporary_entries_of_a_killed_writer_are_removed(tmp_path, monkeypatch):
    aot_dir = tmp_path / "sub" / "aot"
    aot_dir.mkdir(parents=True)
    stale, recent = aot_dir / f"{'a' * 64}.exe.tmp-1-0", aot_dir / f"{'b' * 64}.exe.tmp-2-0"
    stale.write_bytes(b"partial")
    recent.write_bytes(b"being written")
    hour_ago = time.time() - 3600
    os.utime(stale, (hour_ago, hour_ago))
    _store_one(tmp_path, monkeypatch)
    assert not stale.exists() and recent.exists()
    assert len(list(aot_dir.glob("*.exe"))) == 1


def test_clear_removes_only_what_fpe_wrote(tmp_path, monkeypatch):
    monkeypatch.setenv("FPE_CACHE_DIR", str(tmp_path / "cache"))
    root = tmp_path / "cache"
    mine = root / "jax-0.10.2_jaxlib-0.10.2_cpu-abc_x64"
    (mine / "aot").mkdir(parents=True)
    (mine / cache.MARKER).write_bytes(b"")
    (mine / "aot" / f"{'c' * 64}.exe").write_bytes(b"1234")
    (mine / "jit_f-0123-cache").write_bytes(b"12")
    (mine / "notes.txt").write_text("the user's")  # not an entry: stays, and so does the folder
    legacy = root / "jax-0.4.30_jaxlib-0.4.30_cpu_x64"  # an older version's folder
    (legacy / "aot").mkdir(parents=True)
    (legacy / "aot" / f"{'d' * 64}.exe").write_bytes(b"123")
    users = root / "jax-foo"  # the user's, named like ours
    (users / "aot").mkdir(parents=True)
    (users / "data-cache").write_bytes(b"precious")
    (users / "aot" / f"{'e' * 64}.exe").write_bytes(b"precious")
    outside = tmp_path / "outside"
    (outside / "aot").mkdir(parents=True)
    (outside / cache.MARKER).write_bytes(b"")
    (outside / "aot" / f"{'f' * 64}.exe").write_bytes(b"precious")
    (root / "jax-0.1_jaxlib-0.1_cpu_x64").symlink_to(outside)  # a link named like an old folder
    (mine / "aot" / "link.exe").symlink_to(outside / "aot" / f"{'f' * 64}.exe")

    removed = cache.clear()
    assert removed["entries"] == 3 and removed["bytes"] == 4 + 2 + 3
    assert sorted(p.name for p in root.iterdir()) == sorted(
        ["jax-0.10.2_jaxlib-0.10.2_cpu-abc_x64", "jax-foo", "jax-0.1_jaxlib-0.1_cpu_x64"]
    )
    assert sorted(p.relative_to(mine).as_posix() for p in mine.rglob("*")) == [
        cache.MARKER,
        "aot",
        "aot/link.exe",
        "notes.txt",
    ]
    assert (users / "data-cache").read_bytes() == b"precious"
    assert (users / "aot" / f"{'e' * 64}.exe").read_bytes() == b"precious"
    assert (outside / "aot" / f"{'f' * 64}.exe").read_bytes() == b"precious"


def test_info_follows_no_link_out_of_the_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("FPE_CACHE_DIR", str(tmp_path))
    (tmp_path / "jax-0.1_jaxlib-0.1_cpu_x64").symlink_to("/usr")
    mine = tmp_path / "jax-0.10.2_jaxlib-0.10.2_cpu-abc_x64"
    mine.mkdir()
    (mine / cache.MARKER).write_bytes(b"")
    (mine / "aot").symlink_to("/usr/lib")
    t0 = time.perf_counter()
    summary = cache.info()
    assert time.perf_counter() - t0 < 1.0
    assert summary["entries"] == 0 and summary["bytes"] == 0
    assert list(summary["subfolders"]) == [mine.name]


def test_a_flipped_bit_in_a_predict_entry_changes_no_number(tmp_path):
    """End to end: `fpe predict` on the sample drive with a bit of each stored executable flipped:
    one warning line and the predictions of the cold run."""

    def predict(out: Path) -> subprocess.CompletedProcess:
        argv = [
            "predict",
            str(SAMPLE / "drive.mcap"),
            "--waypoints",
            str(ROOT / "data/tracks/oval.csv"),
        ]
        return subprocess.run(
            [sys.executable, "-m", "fpe_jax.cli", *argv, "--out", str(out), "--quiet"],
            capture_output=True,
            text=True,
            cwd=ROOT,
            env={**os.environ, "FPE_CACHE_DIR": str(tmp_path / "cache")},
            timeout=600,
        )

    cold = predict(tmp_path / "a.csv")
    assert cold.returncode == 0, cold.stderr
    stored = entries(tmp_path / "cache")
    assert stored
    for entry in stored:
        blob = bytearray(entry.read_bytes())
        blob[len(blob) * 9 // 10] ^= 0x01  # unchecked, this one loaded silently
        entry.write_bytes(bytes(blob))
    again = predict(tmp_path / "b.csv")
    assert again.returncode == 0, again.stderr
    lines = again.stderr.strip().splitlines()
    assert len(lines) == 2 and lines[0].startswith("fpe: warning: unreadable"), again.stderr
    assert (tmp_path / "a.csv").read_bytes() == (tmp_path / "b.csv").read_bytes()


def test_batch_entries_of_jax_own_cache_are_checked_too(tmp_path):
    """`fpe batch` keeps JAX's own cache of XLA executables: its entries pass the same checks
    (a flipped bit, then a FIFO: one warning each, the same cars, no hang)."""

    def batch(out: str) -> subprocess.CompletedProcess:
        argv = [
            "batch",
            str(SAMPLE / "cars.csv"),
            "--waypoints",
            str(ROOT / "data/tracks/oval.csv"),
        ]
        return subprocess.run(
            [sys.executable, "-m", "fpe_jax.cli", *argv, "--preset", "default", "--quiet"]
            + ["--out", str(tmp_path / out)],
            capture_output=True,
            text=True,
            cwd=ROOT,
            env={**os.environ, "FPE_CACHE_DIR": str(tmp_path / "cache")},
            timeout=120,
        )

    assert batch("a.npy").returncode == 0
    stored = sorted(p for p in (tmp_path / "cache").glob("jax-*/*-cache") if p.name != cache.MARKER)
    assert stored and all(len(p.name) == len("-cache") + 64 for p in stored)
    for p in stored:
        blob = bytearray(p.read_bytes())
        blob[len(blob) * 9 // 10] ^= 0x04
        p.write_bytes(bytes(blob))
    stored[0].unlink()
    os.mkfifo(stored[0])
    for out in ("b.npy", "c.npy"):  # damaged, then healed by the recompile
        r = batch(out)
        assert r.returncode == 0, r.stderr
        lines = r.stderr.strip().splitlines()
        warned = [line for line in lines if line.startswith("fpe: warning: unreadable")]
        assert len(warned) == (1 if out == "b.npy" else 0) and len(lines) == 1 + len(warned)
        np.testing.assert_array_equal(np.load(tmp_path / out), np.load(tmp_path / "a.npy"))
