"""Real-time primitives of host and device loops: a clean stop on SIGINT/SIGTERM,
absolute deadlines, waiting on a descriptor, and a loop free of the garbage collector.

Pure standard library; shared by the recorder, the play loop and the simulated
devices' firmware.
"""

from __future__ import annotations

import contextlib
import gc
import select
import signal
import time
from collections.abc import Iterator
from types import FrameType


class StopFlag:
    """Set by SIGINT or SIGTERM; long loops poll it and finish cleanly."""

    def __init__(self) -> None:
        self.signal: int | None = None

    def __bool__(self) -> bool:
        return self.signal is not None

    def set(self, signum: int, frame: FrameType | None = None) -> None:
        self.signal = signum

    def install(self) -> StopFlag:
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, self.set)
        return self


class Deadlines:
    """Absolute deadlines every ``period_s``: sleeping a fixed time after each
    step drifts (913 Hz for a 1 kHz loop); sleeping until ``t0 + k period`` does not."""

    def __init__(self, period_s: float, t0: float | None = None) -> None:
        self.period_s = period_s
        self.t0 = time.monotonic() if t0 is None else t0
        self.k = 0
        self.missed = 0

    def next(self) -> float:
        """The next deadline (monotonic s); deadlines already past are skipped and counted."""
        self.k += 1
        deadline = self.t0 + self.k * self.period_s
        late = time.monotonic() - deadline
        if late > self.period_s:
            skip = int(late // self.period_s)
            self.k += skip
            self.missed += skip
            deadline = self.t0 + self.k * self.period_s
        return deadline


def wait_readable(fd: int, deadline: float) -> bool:
    """Sleep until ``deadline`` (monotonic s) or until ``fd`` has data; True if it has."""
    timeout = max(0.0, deadline - time.monotonic())
    try:
        ready, _, _ = select.select([fd], [], [], timeout)
    except InterruptedError:
        return False
    return bool(ready)


@contextlib.contextmanager
def realtime() -> Iterator[None]:
    """Keep the cyclic garbage collector out of a 1 kHz loop.

    Its passes took 0.4-0.9 ms here, most of a period. The loops make no reference
    cycles (reference counting frees everything they drop), so the collector is
    paused for their duration and what existed before is frozen out of later passes.
    """
    enabled = gc.isenabled()
    gc.collect()
    gc.freeze()
    gc.disable()
    try:
        yield
    finally:
        gc.unfreeze()
        if enabled:
            gc.enable()
