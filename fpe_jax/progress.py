"""Progress display on stderr for anything that takes longer than a second.

On a terminal a ticking line shows the current phase and the elapsed time; elsewhere (CI, pipes)
each phase is one plain line, so logs stay readable.
"""

from __future__ import annotations

import sys
import threading
import time


class Progress:
    """`with Progress() as say: say("phase")` prints phases with elapsed seconds."""

    def __init__(self, stream=None, tick_s: float = 0.5):
        self.stream = stream or sys.stderr
        self.tick_s = tick_s
        self.t0 = time.perf_counter()
        self.phase = ""
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._ticker, daemon=True)

    def _line(self) -> str:
        return f"[{time.perf_counter() - self.t0:6.1f} s] {self.phase}"

    def _ticker(self):
        while not self._stop.wait(self.tick_s):
            self.stream.write("\r" + self._line())
            self.stream.flush()

    def __call__(self, phase: str) -> None:
        if self.tty and self.phase:
            self.stream.write("\r" + self._line() + "\n")
        self.phase = phase
        if not self.tty:
            self.stream.write(self._line() + "\n")
            self.stream.flush()

    def __enter__(self):
        if self.tty:
            self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        if self.tty:
            self._thread.join()
            self.stream.write("\r" + self._line() + "\n")
        self.stream.write(f"[{time.perf_counter() - self.t0:6.1f} s] done\n")
        self.stream.flush()
        return False
