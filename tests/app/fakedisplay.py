"""A display simulated in the test's own process: no serial line, its frames due by
wall-clock time since START. A test subclasses it for what its display does with them
and registers the class with the ``registered_device`` fixture (tests/conftest.py)."""

from __future__ import annotations

import time
from typing import Any, ClassVar

from tissuecli.hw.device import Display
from tissuecli.render.profile import PAPER_DISPLAY

RATE_HZ = 1000.0
CLOCK_HZ = 1_000_000


class InProcessDisplay(Display):
    """The part every in-process display shares: its Info (the paper's display at
    ``RATE_HZ``, plus ``extra_info``), the host's commands kept in ``commands``, the
    instant of START in ``started`` (None once stopped), ``n`` frames sent so far, and
    nothing to wait on (the loop sleeps briefly between polls). ``opened`` is the last
    instance connected, for the test to inspect after the play."""

    extra_info: ClassVar[dict[str, Any]] = {}
    opened: ClassVar[InProcessDisplay | None] = None

    def connect(self, **options: Any) -> None:
        self.info = {
            "device": self.kind,
            "rate_hz": RATE_HZ,
            "clock_hz": CLOCK_HZ,
            "profile": PAPER_DISPLAY.as_dict(),
            **self.extra_info,
        }
        self.commands: list[str] = []
        self.started: float | None = None
        self.n = 0
        self.reset()
        type(self).opened = self

    def reset(self) -> None:
        """Set up a subclass's own state at connect."""

    def command(self, name: str) -> None:
        self.commands.append(name)
        self.started = time.monotonic() if name == "start" else None

    def due(self) -> int:
        """Frames due since START (frame k at k periods, so frame 0 at once)."""
        assert self.started is not None
        return int((time.monotonic() - self.started) * RATE_HZ) + 1

    def fileno(self) -> int | None:
        return None

    def nonblocking(self) -> None:
        pass
