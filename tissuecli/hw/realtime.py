"""Real-time primitives of host and device loops: a clean stop on SIGINT/SIGTERM,
absolute deadlines, waiting on a descriptor (sleeping, then spinning to the deadline),
a loop free of the garbage collector, elevated scheduling for the haptic loop's
thread (SCHED_FIFO, memory locked, one CPU) where the system allows it, and a loop in a
process of its own (:class:`LoopProcess`, :class:`Parent`).

Standard library and :mod:`tissuecli.core.errors`; shared by the recorder, the play loop
and the simulated devices' firmware.
"""

from __future__ import annotations

import contextlib
import ctypes
import gc
import math
import os
import resource
import select
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from pathlib import Path
from types import FrameType
from typing import Any, TypeVar

from ..core.errors import DeviceLost, signal_exit_code, signal_name

T = TypeVar("T")


#: The signals a long command ends on cleanly: Ctrl-C, SIGTERM, and the hang-up of a
#: closed terminal or a logout, handled alike (docs/usage.md, "Exit status").
STOP_SIGNALS = tuple(
    getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name)
)


class StopFlag:
    """Set by SIGINT, SIGTERM or SIGHUP; long loops poll it and finish cleanly.

    The first signal is the one kept (:attr:`signal`): it names the stop reason and
    the exit status (``128 + signum``)."""

    def __init__(self) -> None:
        self.signal: int | None = None

    def __bool__(self) -> bool:
        return self.signal is not None

    def set(self, signum: int, frame: FrameType | None = None) -> None:
        if self.signal is None:
            self.signal = signum

    def install(self) -> StopFlag:
        """Handle :data:`STOP_SIGNALS` by setting this flag (main thread only)."""
        for sig in STOP_SIGNALS:
            signal.signal(sig, self.set)
        return self

    @property
    def reason(self) -> str:
        """``interrupted by signal SIGHUP (hang-up)``: the stop reason stored and printed."""
        if self.signal is None:
            return ""
        return f"interrupted by signal {signal_name(self.signal)}"

    @property
    def exit_code(self) -> int:
        """``128 + signum`` once set (130 for Ctrl-C), else 0."""
        return signal_exit_code(self.signal) if self.signal is not None else 0


class Deadlines:
    """Absolute deadlines every ``period_s``: sleeping a fixed time after each
    step drifts (913 Hz for a 1 kHz loop); sleeping until ``t0 + k period`` does not.

    A loop that wakes late is handed the deadlines it has passed, up to ``catch_up``
    periods behind, so it runs them back to back and keeps its rate (the lateness is
    jitter); further behind, the schedule jumps to now, and the deadlines jumped are
    skipped and counted (:attr:`missed`). With ``catch_up`` = 1, a loop that answers a
    peer's frames never runs stale periods in a burst.

    Attributes
    ----------
    k : int
        Deadlines handed out or skipped since ``t0``.
    missed : int
        Deadlines skipped.
    behind : int
        Deadlines handed out already more than a period past (run to catch up).
    """

    def __init__(self, period_s: float, t0: float | None = None, catch_up: int = 1) -> None:
        self.period_s = period_s
        self.t0 = time.monotonic() if t0 is None else t0
        self.catch_up = max(int(catch_up), 1)
        self.k = 0
        self.missed = 0
        self.behind = 0

    def next(self) -> float:
        """The next deadline (monotonic s); up to ``catch_up`` periods past it is handed
        out as it is, beyond that the deadlines already past are skipped and counted."""
        self.k += 1
        deadline = self.t0 + self.k * self.period_s
        late = time.monotonic() - deadline
        if late > self.catch_up * self.period_s:
            skip = int(late // self.period_s)
            self.k += skip
            self.missed += skip
            deadline = self.t0 + self.k * self.period_s
        elif late > self.period_s:
            self.behind += 1
        return deadline


def wait_readable(fd: int, deadline: float) -> bool:
    """Sleep until ``deadline`` (monotonic s) or until ``fd`` has data; True if it has."""
    timeout = max(0.0, deadline - time.monotonic())
    try:
        ready, _, _ = select.select([fd], [], [], timeout)
    except InterruptedError:
        return False
    return bool(ready)


#: The interpreter's switch interval while a loop runs, s. A thread that wants the
#: interpreter lock waits this long before asking its holder to let go: the default
#: 5 ms is the display's whole watchdog, so a loop that woke while another thread of
#: its process (the play log's writer, the thread waiting on the loop) held the lock
#: answered 5 ms late.
SWITCH_INTERVAL_S = 1e-4


@contextlib.contextmanager
def realtime() -> Iterator[None]:
    """Keep the cyclic garbage collector out of a 1 kHz loop, and hand the interpreter
    lock back to it within :data:`SWITCH_INTERVAL_S`.

    The collector's passes took 0.4-0.9 ms here, most of a period. The loops make no
    reference cycles (reference counting frees everything they drop), so the collector
    is paused for their duration and what existed before is frozen out of later passes.
    """
    enabled = gc.isenabled()
    interval = sys.getswitchinterval()
    gc.collect()
    gc.freeze()
    gc.disable()
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    try:
        yield
    finally:
        sys.setswitchinterval(interval)
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
#: Priority of the other threads of an elevated loop's process while it runs (the
#: lowest real-time one): they share its interpreter lock, and one of them descheduled
#: by an ordinary process while holding it stopped the loop for 5-20 ms (a priority
#: inversion); at this priority they still yield to the loop and to every device loop.
COMPANION_PRIORITY = 1

_MCL_CURRENT, _MCL_FUTURE = 1, 2


def cpu_to_spare() -> bool:
    """Whether the machine has a CPU to spare: its 1-minute load average below the
    number of CPUs this process may use, less one (True where the OS does not say)."""
    try:
        load = os.getloadavg()[0]
        cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    except OSError:
        return True
    return load < max((cpus or 1) - 1, 1)


def spin_for(elevation: Elevation) -> float:
    """How long before each deadline a loop with ``elevation`` should stop sleeping and
    spin, s: :data:`SPIN_S` under SCHED_FIFO with a CPU to spare, else 0.

    The one rule of the host's haptic loop and the simulated devices' firmware loops. A
    spin pays only at real-time priority (an ordinary thread spinning on a busy machine
    spends its time slice and is then descheduled for longer), and only with a CPU to
    spare: on a saturated machine the spins of real-time loops add up to the kernel's
    real-time budget (95 %), and then every such loop is stopped for tens of ms, where
    an elevated loop that sleeps wakes within 0.1-0.8 ms.
    """
    return SPIN_S if elevation.elevated and cpu_to_spare() else 0.0


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
    companions : int
        Other threads of the process raised to :data:`COMPANION_PRIORITY` with it.
    """

    scheduler: str = "SCHED_OTHER"
    priority: int = 0
    memory_locked: bool = False
    cpu: int | None = None
    refused: list[str] = field(default_factory=list)
    companions: int = 0

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
            "companions": self.companions,
        }


def elevate(
    priority: int = FIFO_PRIORITY,
    cpu: int | None = -1,
    lock_memory: bool = True,
    companions: bool = True,
) -> tuple[Elevation, Callable[[], None]]:
    """Give the calling thread what real haptic loops run with, as far as allowed.

    SCHED_FIFO at ``priority`` (Linux schedules threads, so only the calling thread is
    raised), all pages locked in memory (``mlockall``), and the thread pinned to one CPU
    (``cpu``: an index into the CPUs allowed, -1 the last; None leaves it free). With
    ``companions`` the process's other threads, which share the loop's interpreter lock,
    go to SCHED_FIFO :data:`COMPANION_PRIORITY` (see there). Each is tried on its own and
    a refusal (not root, no CAP_SYS_NICE, RLIMIT_RTPRIO 0, another OS) is recorded, not
    raised.

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
    if companions and got.elevated:
        got.companions = _raise_companions(undo)
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


def _raise_companions(undo: list[Callable[[], None]]) -> int:
    """Raise the process's other threads to :data:`COMPANION_PRIORITY` (Linux: each
    is a task of ``/proc/self/task``); push their undoing to ``undo``; how many."""
    try:
        tids = [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        return 0
    own, raised = threading.get_native_id(), 0
    for tid in tids:
        if tid == own:
            continue
        try:
            policy, param = os.sched_getscheduler(tid), os.sched_getparam(tid)
            if policy != os.SCHED_OTHER:
                continue  # a thread already given its own scheduling keeps it
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(COMPANION_PRIORITY))
        except OSError:
            continue  # ended meanwhile, or not allowed: it stays as it was
        undo.append(lambda tid=tid, policy=policy, param=param: os.sched_setscheduler(
            tid, policy, param
        ))  # fmt: skip
        raised += 1
    return raised


def fallback_message(elevation: Elevation, what: str = "the haptic loop") -> str | None:
    """The one line to tell people when the loop runs without elevated scheduling; None
    if it has it, or if that line was already given in this process."""
    if elevation.elevated or not elevation.refused:
        return None
    text = (
        f"real-time scheduling not allowed, {what} runs as an ordinary thread "
        "(expect a slower, jittery loop under load): " + "; ".join(elevation.refused)
    )
    if text in _fallback_said:
        return None
    _fallback_said.add(text)
    return text


@contextlib.contextmanager
def device_loop(
    say: Callable[[str], None] | None = None, *, enabled: bool = True
) -> Iterator[Elevation]:
    """A simulated device's firmware loop kept on time as the host's haptic loop is:
    the calling thread under SCHED_FIFO (at the host loop's priority, on any CPU) with
    memory locked, where the system allows it; ``say`` is told once when it does not.
    Undone on leaving. A real device's microcontroller never waits for the host's
    scheduler; a simulated one descheduled for tens of ms looks to the host like a
    display gone (``no Encoder frame for 100 ms``).
    """
    if not enabled:
        yield Elevation()
        return
    # one above the host loop: a device keeps its own time whatever the host does
    got, restore = elevate(FIFO_PRIORITY + 1, cpu=None)
    message = fallback_message(got, "the simulated device's loop")
    if message is not None and say is not None:
        say(f"note: {message}")
    try:
        yield got
    finally:
        restore()


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


class Parent:
    """A loop process's side of its pipes to the process that started it.

    :meth:`poll` costs one ``select`` and is meant for every period: it returns the
    messages that have arrived without waiting, and sets :attr:`stop` when the parent
    asks (a ``("stop",)`` message) or is gone (its pipe closed, or this process
    reparented: a parent killed with SIGKILL sends nothing). SIGINT and SIGTERM set it
    too, so Ctrl-C at a terminal, which reaches both processes, ends the loop cleanly.

    Attributes
    ----------
    stop : StopFlag
        Set by the parent's ``("stop",)``, its death, SIGINT or SIGTERM.
    gone : bool
        The parent died (it did not ask to stop).
    """

    def __init__(self, inbox: Connection, outbox: Connection, parent_pid: int) -> None:
        self.inbox, self.outbox, self.parent_pid = inbox, outbox, parent_pid
        self.fd = inbox.fileno()
        self.stop = StopFlag().install()
        self.gone = False

    def poll(self) -> list[Any]:
        """The messages that have arrived (without waiting); ``("stop",)`` is taken."""
        got: list[Any] = []
        try:
            while select.select([self.fd], [], [], 0.0)[0]:
                message = self.inbox.recv()
                if message == ("stop",):
                    self.stop.set(signal.SIGTERM)
                else:
                    got.append(message)
        except InterruptedError:
            pass
        except (EOFError, OSError):
            self._lost()
        if os.getppid() != self.parent_pid:
            self._lost()
        return got

    def _lost(self) -> None:
        if not self.gone:
            self.gone = True
            self.stop.set(signal.SIGHUP)

    def send(self, message: Any) -> None:
        """Send ``message`` to the parent; nothing if it is gone."""
        if self.gone:
            return
        try:
            self.outbox.send(message)
        except (OSError, EOFError):
            self._lost()


def _loop_child(inbox_fd: int, outbox_fd: int, parent_pid: int) -> None:
    """A loop process's body: read ``(target, args)``, run ``target(parent, *args)`` and
    hand its result or error to the parent."""
    parent = Parent(
        Connection(inbox_fd, writable=False), Connection(outbox_fd, readable=False), parent_pid
    )
    try:
        target, args = parent.inbox.recv()
        result = target(parent, *args)
    except BaseException as exc:  # handed to the parent, which raises it
        try:
            parent.outbox.send(("error", exc))
        except Exception:  # noqa: BLE001  (an error that does not pickle: its words)
            parent.send(("error", RuntimeError(f"{type(exc).__name__}: {exc}")))
        return
    parent.send(("done", result))


class LoopProcess:
    """Run ``target(parent, *args)`` in a process of its own: an interpreter, a garbage
    collector and a scheduling policy that nothing else in the program shares.

    The process is a fresh interpreter (``python -c``: neither a fork of a threaded
    program, which can copy a lock half-taken, nor ``multiprocessing``'s spawn, which
    runs the parent's main script again) that imports this package from where the
    parent did. Two one-way pipes join them: the parent :meth:`send` s, the loop
    :meth:`Parent.poll` s once a period; the loop :meth:`Parent.send` s, the parent
    :meth:`receive` s. ``target``'s result comes back as ``("done", result)`` and what
    it raises as ``("error", exception)``; :meth:`wait` returns or raises them. When the
    parent ends, however it ends, the loop sees its pipe close and stops.

    Parameters
    ----------
    target : callable
        A module-level function ``target(parent: Parent, *args)``; ``args`` and its
        result must pickle.
    args : tuple
        Its arguments.
    name : str
        What the process is, for messages.
    """

    def __init__(self, target: Callable[..., Any], args: tuple[Any, ...], name: str) -> None:
        self.target, self.args, self.name = target, args, name
        self.process: subprocess.Popen[bytes] | None = None
        self.ended = False  # the loop's pipe closed: it has exited

    def start(self) -> LoopProcess:
        """Start the process and hand it ``target`` and ``args``."""
        to_loop = os.pipe()
        from_loop = os.pipe()
        root = os.fspath(Path(__file__).resolve().parents[2])
        code = (
            f"import sys; sys.path.insert(0, {root!r}); "
            "from tissuecli.hw.realtime import _loop_child; "
            f"_loop_child({to_loop[0]}, {from_loop[1]}, {os.getpid()})"
        )
        try:
            self.process = subprocess.Popen(
                [sys.executable, "-c", code], pass_fds=(to_loop[0], from_loop[1])
            )
        finally:
            # only the loop holds its ends now, so its exit closes the pipe to us
            os.close(to_loop[0])
            os.close(from_loop[1])
        self._to_loop = Connection(to_loop[1], readable=False)
        self._from_loop = Connection(from_loop[0], writable=False)
        self.send((self.target, self.args))
        return self

    @property
    def pid(self) -> int | None:
        return self.process.pid if self.process is not None else None

    def send(self, message: Any) -> bool:
        """Send ``message`` to the loop; False if it has ended."""
        try:
            self._to_loop.send(message)
            return True
        except OSError:
            return False

    def receive(self, timeout_s: float = 0.0) -> list[Any]:
        """The loop's messages, waiting up to ``timeout_s`` for the first; sets
        :attr:`ended` when its pipe closes."""
        got: list[Any] = []
        if self.ended:
            return got
        try:
            if self._from_loop.poll(timeout_s):
                got.append(self._from_loop.recv())
                while self._from_loop.poll(0.0):
                    got.append(self._from_loop.recv())
        except (EOFError, OSError):
            self.ended = True
        except InterruptedError:
            pass
        return got

    def wait(
        self,
        stop: StopFlag | None = None,
        on_message: Callable[[Any], None] | None = None,
        timeout_s: float | None = None,
        grace_s: float = 5.0,
    ) -> Any:
        """Until the loop ends: its result, or raise its error.

        ``stop`` set (by a signal in this process) is passed on as ``("stop",)``; other
        messages go to ``on_message``. After ``timeout_s`` (s; 0 at once) the loop is
        asked to stop, and killed if it has not ended ``grace_s`` later.
        """
        try:
            return self._wait(stop, on_message, timeout_s, grace_s)
        except BaseException:
            # interrupted here (Ctrl-C without a stop flag): the loop ends cleanly too
            if self.process is not None and self.process.poll() is None:
                self.send(("stop",))
                self.join(grace_s)
            raise

    def _wait(
        self,
        stop: StopFlag | None,
        on_message: Callable[[Any], None] | None,
        timeout_s: float | None,
        grace_s: float,
    ) -> Any:
        asked = False
        give_up = math.inf if timeout_s is None else time.monotonic() + timeout_s
        while True:
            if not asked and (stop or time.monotonic() >= give_up):
                self.send(("stop",))
                asked = True
                give_up = time.monotonic() + grace_s
            elif asked and time.monotonic() > give_up:
                self.kill()
            for message in self.receive(0.05):
                kind = message[0] if isinstance(message, tuple) and message else None
                if kind == "done":
                    self.join()
                    return message[1]
                if kind == "error":
                    self.join()
                    raise message[1]
                if on_message is not None:
                    on_message(message)
            if self.ended:
                code = self.join()
                raise DeviceLost(
                    f"the {self.name} process ended without a result (exit code {code})"
                )

    def join(self, timeout_s: float = 5.0) -> int | None:
        """Wait for the process to exit (killing it after ``timeout_s``); its exit code."""
        if self.process is None:
            return None
        try:
            self.process.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.kill()
        self.close()
        return self.process.returncode

    def kill(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            self.process.wait()
        self.close()

    def close(self) -> None:
        """Close this side's pipes (the loop, if still running, then stops)."""
        self.ended = True
        for conn in (getattr(self, "_to_loop", None), getattr(self, "_from_loop", None)):
            if conn is not None:
                conn.close()
