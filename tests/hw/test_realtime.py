"""Elevated scheduling of the haptic loop's thread, its fallback, waiting with a spin, and a
loop in a process of its own."""

from __future__ import annotations

import os
import threading
import time

import pytest

from tissuecli.core.errors import DeviceLost
from tissuecli.hw import realtime
from tissuecli.hw.realtime import (
    Deadlines,
    Elevation,
    LoopProcess,
    Parent,
    elevate,
    fallback_message,
    run_in_thread,
    wait_until,
)


def _in_thread(fn):  # type: ignore[no-untyped-def]
    return run_in_thread(fn, "test")


def test_elevation_is_granted_to_the_calling_thread_only_and_undone() -> None:
    if not hasattr(os, "sched_setscheduler"):
        pytest.skip("no POSIX scheduling here")
    main_policy = os.sched_getscheduler(0)

    def body() -> tuple[Elevation, int, int, set[int]]:
        got, restore = elevate(lock_memory=False)
        during = os.sched_getscheduler(0)
        cpus = os.sched_getaffinity(0)
        restore()
        return got, during, os.sched_getscheduler(0), cpus

    got, during, after, cpus = _in_thread(body)
    assert os.sched_getscheduler(0) == main_policy  # the main thread untouched
    if got.elevated:
        assert during == os.SCHED_FIFO and after == main_policy
        assert got.priority == realtime.FIFO_PRIORITY
        assert cpus == {got.cpu}
    else:
        assert got.refused and "SCHED_FIFO" in got.refused[0]


def test_a_refusal_is_said_once_with_its_reason(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*args: object) -> None:
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    monkeypatch.setattr(realtime, "_fallback_said", set())
    got, restore = _in_thread(lambda: elevate(lock_memory=False, cpu=None))
    restore()
    assert not got.elevated and got.scheduler == "SCHED_OTHER"
    first = fallback_message(got)
    assert first is not None and "Operation not permitted" in first
    assert "CAP_SYS_NICE" in first and "RLIMIT_RTPRIO" in first
    assert fallback_message(got) is None  # once per process
    assert fallback_message(Elevation(scheduler="SCHED_FIFO", priority=10)) is None


def test_wait_until_returns_at_once_on_data_and_waits_out_the_deadline() -> None:
    r, w = os.pipe()
    try:
        t0 = time.monotonic()
        assert wait_until(r, t0 + 0.02, spin_s=0.005) is False
        assert time.monotonic() >= t0 + 0.02
        threading.Timer(0.01, lambda: os.write(w, b"x")).start()
        assert wait_until(r, time.monotonic() + 5.0, spin_s=0.003) is True
    finally:
        os.close(r)
        os.close(w)


def test_run_in_thread_returns_and_raises_what_the_thread_did() -> None:
    assert run_in_thread(lambda: threading.current_thread().name, "haptic") == "haptic"

    def fail() -> None:
        raise ValueError("boom")

    with pytest.raises(ValueError, match="boom"):
        run_in_thread(fail, "haptic")


def test_a_loop_process_returns_its_result_and_raises_its_error() -> None:
    # builtins pickle by name: the target gets the Parent first, then the arguments
    proc = LoopProcess(isinstance, (Parent,), "test loop").start()
    assert proc.pid is not None and proc.pid != os.getpid()
    assert proc.wait(timeout_s=30.0) is True  # it was handed its Parent
    with pytest.raises(TypeError):
        LoopProcess(divmod, (0,), "test loop").start().wait(timeout_s=30.0)


def test_a_loop_process_killed_is_said_in_one_error() -> None:
    proc = LoopProcess(time.sleep, (), "test loop").start()  # sleep(parent): a TypeError
    proc.kill()
    with pytest.raises(DeviceLost, match="test loop process ended without a result"):
        proc.wait()


def test_the_threads_sharing_an_elevated_loops_interpreter_are_raised_with_it() -> None:
    """Another thread of the process (a log writer, the thread waiting on the loop) goes
    to SCHED_FIFO 1 while the loop is elevated, and back after."""
    if not hasattr(os, "sched_setscheduler"):
        pytest.skip("no POSIX scheduling here")
    release = threading.Event()
    other = threading.Thread(target=release.wait, daemon=True)
    other.start()
    tid = other.native_id
    assert tid is not None
    try:

        def body() -> tuple[Elevation, int, int]:
            got, restore = elevate(lock_memory=False, cpu=None)
            during = os.sched_getscheduler(tid)
            restore()
            return got, during, os.sched_getscheduler(tid)

        got, during, after = _in_thread(body)
    finally:
        release.set()
        other.join()
    if not got.elevated:
        pytest.skip(f"real-time scheduling not allowed here: {got.refused}")
    assert during == os.SCHED_FIFO and after == os.SCHED_OTHER
    assert got.companions >= 2  # the other thread and the main thread waiting on the loop
    assert got.as_dict()["companions"] == got.companions


def test_a_loop_gets_the_interpreter_lock_back_within_its_switch_interval() -> None:
    import sys

    before = sys.getswitchinterval()
    with realtime.realtime():
        assert sys.getswitchinterval() == pytest.approx(realtime.SWITCH_INTERVAL_S)
    assert sys.getswitchinterval() == before


def test_only_an_elevated_loop_spins(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(realtime, "cpu_to_spare", lambda: True)
    assert realtime.spin_for(Elevation()) == 0.0
    elevated = Elevation(scheduler="SCHED_FIFO", priority=10)
    assert realtime.spin_for(elevated) == realtime.SPIN_S
    monkeypatch.setattr(realtime, "cpu_to_spare", lambda: False)
    assert realtime.spin_for(elevated) == 0.0  # a saturated machine: sleep, never spin


def test_deadlines_passed_are_run_up_to_the_catch_up_and_skipped_beyond() -> None:
    # periods of 1 s: the few microseconds the test takes move no deadline across a period
    behind = time.monotonic() - 5.5  # woken 4.5 periods after the first deadline
    skipping = Deadlines(1.0, t0=behind)
    assert skipping.next() == pytest.approx(behind + 5.0)  # jumped to the last one passed
    assert (skipping.missed, skipping.behind) == (4, 0)
    catching = Deadlines(1.0, t0=behind, catch_up=10)
    got = [catching.next() for _ in range(5)]
    assert got == pytest.approx([behind + k for k in (1.0, 2.0, 3.0, 4.0, 5.0)])
    assert (catching.missed, catching.behind) == (0, 4)  # the fifth is less than a period late
    assert Deadlines(1.0, t0=behind, catch_up=3).next() == pytest.approx(behind + 5.0)
