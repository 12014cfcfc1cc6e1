"""Progress display on stderr for every step that takes longer than about a second.

On a terminal one line is rewritten in place: the current phase and the elapsed time, ticking.
Elsewhere (CI, pipes, log files) a phase that has lasted `delay_s` gets one plain line stamped
with its start time, so logs stay readable. Shorter phases print nothing, and a command that
fails on bad input within them leaves only its one error line. `quiet=True` prints nothing.
Hand-written (about 80 lines) rather than a library: a phase line with a clock is all the
commands show, and the JAX-free commands must stay light.
"""

from __future__ import annotations

import sys
import threading
import time

_CLEAR = "\r\x1b[K"  # back to the line start and erase it (a shorter phase leaves no tail)


class Progress:
    """`with Progress() as say: say("phase")` shows phases with elapsed seconds on stderr."""

    def __init__(self, stream=None, tick_s: float = 0.5, quiet: bool = False, delay_s=1.0):
        self.stream = stream or sys.stderr
        self.tick_s = min(tick_s, delay_s) if delay_s > 0 else tick_s
        self.delay_s = delay_s
        self.quiet = quiet
        self.t0 = time.perf_counter()
        self.phase, self.phase_t = "", self.t0
        self.tty = not quiet and hasattr(self.stream, "isatty") and self.stream.isatty()
        self.shown = False  # anything written yet (then the end gets a 'done' line)
        self._printed_phase = True  # the current phase's plain line is out
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._ticker, daemon=True)

    def _line(self, t: float | None = None) -> str:
        return f"[{(t or time.perf_counter()) - self.t0:6.1f} s] {self.phase}"

    def _show(self, now: float) -> None:
        """Write what is due (call with the lock held)."""
        if now - self.phase_t < self.delay_s and not (self.tty and self.shown):
            return
        if self.tty:
            self.stream.write(_CLEAR + self._line(now))
        elif not self._printed_phase:
            self.stream.write(self._line(self.phase_t) + "\n")
            self._printed_phase = True
        else:
            return
        self.shown = True
        self.stream.flush()

    def _ticker(self):
        while not self._stop.wait(self.tick_s):
            with self._lock:
                self._show(time.perf_counter())

    def __call__(self, phase: str) -> None:
        """Start a new phase (the terminal line is replaced, a log gets a line if it lasts)."""
        if self.quiet:
            return
        with self._lock:
            self.phase, self.phase_t, self._printed_phase = phase, time.perf_counter(), False
            self._show(self.phase_t)

    def count(self, what: str, done: int, total: int) -> None:
        """A phase with a counter, e.g. `count("predicting cars", 16384, 100000)`."""
        self(f"{what} {done}/{total}")

    def __enter__(self):
        if not self.quiet:
            self._thread.start()
        return self

    def __exit__(self, exc_type, *exc):
        self._stop.set()
        if self.quiet:
            return False
        self._thread.join()
        with self._lock:
            if self.tty and self.shown and exc_type is not None:
                self.stream.write(_CLEAR)  # the error line takes the progress line's place
            elif self.shown and exc_type is None:
                self.phase = "done"
                self.stream.write((_CLEAR if self.tty else "") + self._line() + "\n")
            self.stream.flush()
        return False
