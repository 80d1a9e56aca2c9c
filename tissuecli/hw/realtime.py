"""Real-time primitives of host and device loops: a clean stop on SIGINT/SIGTERM,
absolute deadlines, waiting on a descriptor (sleeping, then spinning to the deadline),
a loop free of the garbage collector, and elevated scheduling for the haptic loop's
thread (SCHED_FIFO, memory locked, one CPU) where the system allows it.

Pure standard library; shared by the recorder, the play loop and the simulated
devices' firmware.
"""

from __future__ import annotations

import contextlib
import ctypes
import gc
import os
import resource
import select
import signal
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from types import FrameType
from typing import Any, TypeVar

T = TypeVar("T")


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


#: How long before a deadline a waiting loop stops sleeping and spins, s: the kernel's
#: wake-up from a sleep is late by 50-100 us on an idle machine and by milliseconds
#: under load; a spin is late by the time it takes to test the descriptor.
SPIN_S = 3e-4

#: Priority of an elevated loop under SCHED_FIFO (1-99): above every ordinary process
#: and the kernel's default threaded interrupts are at 50, so a modest 10 leaves them
#: (and anything a lab gives a higher priority) in front.
FIFO_PRIORITY = 10

_MCL_CURRENT, _MCL_FUTURE = 1, 2
_fallback_said: set[str] = set()


@dataclass
class Elevation:
    """What :func:`elevate` obtained for the calling thread.

    Attributes
    ----------
    scheduler : str
        ``"SCHED_FIFO"`` if granted, else ``"SCHED_OTHER"``.
    priority : int
        Real-time priority (0 when not elevated).
    memory_locked : bool
        ``mlockall(MCL_CURRENT | MCL_FUTURE)`` succeeded: no page of the process is
        paged out, so no period waits for the disk.
    cpu : int or None
        The one CPU the thread is pinned to, if any.
    refused : list of str
        What was asked and not granted, with the reason, one item each.
    """

    scheduler: str = "SCHED_OTHER"
    priority: int = 0
    memory_locked: bool = False
    cpu: int | None = None
    refused: list[str] = field(default_factory=list)

    @property
    def elevated(self) -> bool:
        return self.scheduler != "SCHED_OTHER"

    def as_dict(self) -> dict[str, Any]:
        return {
            "scheduler": self.scheduler,
            "priority": self.priority,
            "memory_locked": self.memory_locked,
            "cpu": self.cpu,
            "refused": list(self.refused),
        }


def elevate(
    priority: int = FIFO_PRIORITY, cpu: int | None = -1, lock_memory: bool = True
) -> tuple[Elevation, Callable[[], None]]:
    """Give the calling thread what real haptic loops run with, as far as allowed.

    SCHED_FIFO at ``priority`` (Linux schedules threads, so only the calling thread is
    raised; the rest of the process stays ordinary), all pages locked in memory
    (``mlockall``), and the thread pinned to one CPU (``cpu``: an index into the CPUs
    allowed, -1 the last; None leaves it free). Each is tried on its own and a refusal
    (not root, no CAP_SYS_NICE, RLIMIT_RTPRIO 0, another OS) is recorded, not raised.

    Returns
    -------
    elevation : Elevation
        What was granted and what refused.
    restore : callable
        Undo it all (call from the same thread).
    """
    got = Elevation()
    undo: list[Callable[[], None]] = []
    if hasattr(os, "sched_setscheduler"):
        try:
            old_policy, old_param = os.sched_getscheduler(0), os.sched_getparam(0)
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
            got.scheduler, got.priority = "SCHED_FIFO", priority
            undo.append(lambda: os.sched_setscheduler(0, old_policy, old_param))
        except OSError as exc:
            rtprio = resource.getrlimit(resource.RLIMIT_RTPRIO)[0]
            got.refused.append(
                f"SCHED_FIFO ({exc.strerror}; needs root, CAP_SYS_NICE or RLIMIT_RTPRIO >= "
                f"{priority}, which is {rtprio})"
            )
    else:
        got.refused.append("SCHED_FIFO (not on this OS)")
    if lock_memory:
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            if libc.mlockall(_MCL_CURRENT | _MCL_FUTURE) != 0:
                raise OSError(ctypes.get_errno(), os.strerror(ctypes.get_errno()))
            got.memory_locked = True
            undo.append(libc.munlockall)
        except (OSError, AttributeError) as exc:
            got.refused.append(f"mlockall ({getattr(exc, 'strerror', None) or exc})")
    if cpu is not None and hasattr(os, "sched_setaffinity"):
        try:
            allowed = sorted(os.sched_getaffinity(0))
            chosen = allowed[cpu]
            os.sched_setaffinity(0, {chosen})
            got.cpu = chosen
            undo.append(lambda: os.sched_setaffinity(0, allowed))
        except (OSError, IndexError) as exc:
            got.refused.append(f"CPU affinity ({exc})")

    def restore() -> None:
        for step in reversed(undo):
            with contextlib.suppress(OSError):
                step()

    return got, restore


def fallback_message(elevation: Elevation) -> str | None:
    """The one line to tell people when the loop runs without elevated scheduling; None
    if it has it, or if that line was already given in this process."""
    if elevation.elevated or not elevation.refused:
        return None
    text = (
        "real-time scheduling not allowed, the haptic loop runs as an ordinary thread "
        "(expect a slower, jittery loop under load): " + "; ".join(elevation.refused)
    )
    if text in _fallback_said:
        return None
    _fallback_said.add(text)
    return text


def wait_until(fd: int | None, deadline: float, spin_s: float = SPIN_S) -> bool:
    """Wait for data on ``fd`` or for ``deadline`` (monotonic s): sleep until ``spin_s``
    before it, then spin. True if ``fd`` has data.

    With ``spin_s`` = 0 this is :func:`wait_readable`. ``fd`` None only waits.
    """
    wake = deadline - spin_s
    if time.monotonic() < wake:
        if fd is None:
            time.sleep(max(0.0, wake - time.monotonic()))
        elif wait_readable(fd, wake):
            return True
    poll = [fd] if fd is not None else []
    while time.monotonic() < deadline:
        if poll:
            try:
                if select.select(poll, [], [], 0.0)[0]:
                    return True
            except InterruptedError:
                pass
    return bool(poll) and bool(select.select(poll, [], [], 0.0)[0])


def run_in_thread(target: Callable[[], T], name: str) -> T:
    """Run ``target`` in a thread of its own and return its result (or raise what it
    raised), keeping the calling (main) thread free for signals.

    The main thread only waits, in short slices, so Ctrl-C and SIGTERM handlers run
    at once (a :class:`StopFlag` set there is seen by ``target``).
    """
    box: dict[str, Any] = {}

    def body() -> None:
        try:
            box["result"] = target()
        except BaseException as exc:  # handed to the caller below
            box["error"] = exc

    thread = threading.Thread(target=body, name=name, daemon=True)
    thread.start()
    while thread.is_alive():
        thread.join(0.05)
    if "error" in box:
        raise box["error"]
    return box["result"]  # type: ignore[no-any-return]
