"""Progress drawn on a terminal: one status line on stderr, rewritten in place."""

from __future__ import annotations

import sys
import threading
import time
from typing import TextIO

from ..core.progress import Progress

#: a stage shorter than this draws nothing, s
QUIET_S = 2.0
#: the line is redrawn at least this often while a stage runs, s
TICK_S = 0.5


class TerminalProgress(Progress):
    """Draws the current stage, its count and its elapsed time on one line of
    ``stream`` once the stage has run :data:`QUIET_S`; a ticker redraws it while
    nothing reports (reading a file, drawing the report). Each stage that drew leaves
    its final line behind, so the terminal keeps what took the time."""

    def __init__(self, stream: TextIO | None = None) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self._lock = threading.Lock()
        self._name = ""
        self._detail = ""
        self._started = time.monotonic()
        self._drawn = 0  # width of the line on screen, 0: nothing drawn
        self._stop = threading.Event()
        self._ticker = threading.Thread(target=self._tick, daemon=True)
        self._ticker.start()

    @classmethod
    def for_terminal(cls) -> TerminalProgress | None:
        """One on stderr when stderr is a terminal, else None (no progress in pipes)."""
        return cls() if sys.stderr.isatty() else None

    def stage(self, name: str, total: int | None = None) -> None:
        with self._lock:
            self._finish_line()
            self._name, self._detail = name, ""
            self._started = time.monotonic()

    def advance(self, done: int, total: int | None = None, note: str = "") -> None:
        left = f", {total - done} left" if total is not None and total > done else ""
        what = f": {note}" if note else ""
        self._update(f"{done} done{left}{what}")

    def sampling(self, form: str, steps: int, need: int) -> None:
        done = min(1.0, steps / max(need, 1))
        bar = "#" * int(20 * done) + "-" * (20 - int(20 * done))
        self._update(f"{form} [{bar}] {steps} steps of ~{need}")

    def close(self) -> None:
        self._stop.set()
        with self._lock:
            self._finish_line()
            self._name = ""

    def _update(self, detail: str) -> None:
        with self._lock:
            self._detail = detail
            self._draw()

    def _tick(self) -> None:
        while not self._stop.wait(TICK_S):
            with self._lock:
                self._draw()

    def _draw(self) -> None:
        elapsed = time.monotonic() - self._started
        if not self._name or elapsed < QUIET_S:
            return
        line = f"{self._name} ({elapsed:.0f} s)" + (f": {self._detail}" if self._detail else "")
        line = line[:119]
        pad = " " * max(0, self._drawn - len(line))
        self.stream.write(f"\r{line}{pad}")
        self.stream.flush()
        self._drawn = len(line)

    def _finish_line(self) -> None:
        if self._drawn:
            self._draw()
            self.stream.write("\n")
            self.stream.flush()
            self._drawn = 0
