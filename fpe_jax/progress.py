"""Progress display on stderr for anything that takes longer than a second.

On a terminal one line is rewritten in place: the current phase and the elapsed time, ticking.
Elsewhere (CI, pipes, log files) each phase is one plain line with its elapsed time, so logs
stay readable. `quiet=True` prints nothing. Hand-written (about 60 lines) rather than a library:
a phase line with a clock is all the commands show, and the JAX-free commands must stay light.
"""

from __future__ import annotations

import sys
import threading
import time

_CLEAR = "\r\x1b[K"  # back to the line start and erase it (a shorter phase leaves no tail)


class Progress:
    """`with Progress() as say: say("phase")` prints phases with elapsed seconds on stderr."""

    def __init__(self, stream=None, tick_s: float = 0.5, quiet: bool = False):
        self.stream = stream or sys.stderr
        self.tick_s = tick_s
        self.quiet = quiet
        self.t0 = time.perf_counter()
        self.phase = ""
        self.tty = not quiet and hasattr(self.stream, "isatty") and self.stream.isatty()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._ticker, daemon=True)

    def _line(self) -> str:
        return f"[{time.perf_counter() - self.t0:6.1f} s] {self.phase}"

    def _ticker(self):
        while not self._stop.wait(self.tick_s):
            with self._lock:
                self.stream.write(_CLEAR + self._line())
                self.stream.flush()

    def __call__(self, phase: str) -> None:
        """Start a new phase (the terminal line is replaced, a log gets a new line)."""
        if self.quiet:
            return
        with self._lock:
            self.phase = phase
            self.stream.write(_CLEAR + self._line() if self.tty else self._line() + "\n")
            self.stream.flush()

    def count(self, what: str, done: int, total: int) -> None:
        """A phase with a counter, e.g. `count("predicting cars", 16384, 100000)`."""
        self(f"{what} {done}/{total}")

    def __enter__(self):
        if self.tty:
            self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        if self.quiet:
            return False
        if self.tty:
            self._thread.join()
        with self._lock:
            self.phase = "done"
            self.stream.write((_CLEAR if self.tty else "") + self._line() + "\n")
            self.stream.flush()
        return False
