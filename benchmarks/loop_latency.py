"""Where a 1 kHz loop's time goes on this machine: waking at a deadline, the same fixed work
from one period to the next, and one frame through a pseudo-terminal against a pipe.

Usage::

    python benchmarks/loop_latency.py --seconds 3 --busy 2

Each line is one measurement of ``--seconds`` s, first on the machine as it is ("idle"),
then with ``--busy`` processes running ``while 1: pass`` beside it:

- ``wake``: a loop sleeping to absolute deadlines 1 ms apart, how late it wakes, at
  ordinary priority and under SCHED_FIFO, sleeping all the way (``spin 0``) or waking
  0.3 ms early and spinning to the deadline (``hw.realtime.wait_until``);
- ``work``: the time a fixed piece of Python (about 0.1 ms) takes, once a period under
  SCHED_FIFO: what is left of a period for the loop's own code;
- ``pty`` / ``pipe``: one 8-byte frame a period from one process to another, stamped
  when written and when the reader's ``select`` returned, both under SCHED_FIFO as the
  simulated display (11) and the host loop (10) run: a pseudo-terminal passes each frame
  through the kernel's tty buffer work, done by a kernel worker thread at ordinary
  priority; a pipe wakes the reader from the writer's own call.

Prints p50, p99, p99.9 and the longest, ms, with the 1-minute load average.
"""

from __future__ import annotations

import argparse
import os
import pty
import select
import struct
import time
import tty

from _busy import busy

from tissuecli.hw.realtime import wait_until


def _fifo(priority: int) -> bool:
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        return True
    except (OSError, AttributeError):
        return False


def _other() -> None:
    try:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except (OSError, AttributeError):
        pass


def _row(what: str, values: list[float]) -> str:
    ordered = sorted(values)

    def q(p: float) -> float:
        return ordered[min(len(ordered) - 1, int(p * len(ordered)))] * 1e3

    return (
        f"{what:<28} {len(ordered):>6} {q(0.5):7.3f} {q(0.99):7.3f} {q(0.999):7.3f} "
        f"{ordered[-1] * 1e3:7.2f} {os.getloadavg()[0]:6.2f}"
    )


def wake(seconds: float, fifo: bool, spin_s: float) -> list[float]:
    """Lateness past each deadline of a loop paced every 1 ms, s."""
    if fifo:
        _fifo(10)
    late: list[float] = []
    t0 = time.monotonic()
    k = 0
    while time.monotonic() - t0 < seconds:
        k += 1
        deadline = t0 + k * 1e-3
        wait_until(None, deadline, spin_s)
        now = time.monotonic()
        late.append(now - deadline)
        if now - deadline > 1e-3:  # a missed period is counted once, not as a backlog
            k = int((now - t0) / 1e-3)
    _other()
    return late


def work(seconds: float) -> list[float]:
    """Time of a fixed piece of Python, run once a period under SCHED_FIFO, s."""
    _fifo(10)
    took: list[float] = []
    t0 = time.monotonic()
    while time.monotonic() - t0 < seconds:
        a = time.monotonic()
        total = 0.0
        for i in range(1500):
            total += i * 0.5
        took.append(time.monotonic() - a)
        time.sleep(max(0.0, 1e-3 - (time.monotonic() - a)))
    _other()
    return took


def transfer(seconds: float, kind: str) -> list[float]:
    """One-way time of a stamped frame from a SCHED_FIFO 11 writer process to a
    SCHED_FIFO 10 reader, s."""
    if kind == "pty":
        master, slave = pty.openpty()
        tty.setraw(slave)
        wfd, rfd, extra = master, slave, None
    else:
        rfd, wfd = os.pipe()
        extra = None
    n = int(seconds * 1000)
    pid = os.fork()
    if pid == 0:  # the writer: a device's loop
        _fifo(11)
        t0 = time.monotonic() + 0.02
        for k in range(n):
            wait_until(None, t0 + k * 1e-3, 3e-4)
            os.write(wfd, struct.pack("d", time.monotonic()))
        os._exit(0)
    _fifo(10)
    got: list[float] = []
    buf = b""
    give_up = time.monotonic() + seconds + 5.0
    while len(got) < n and time.monotonic() < give_up:
        select.select([rfd], [], [], 0.5)
        buf += os.read(rfd, 4096)
        now = time.monotonic()
        while len(buf) >= 8:
            (sent,), buf = struct.unpack("d", buf[:8]), buf[8:]
            got.append(now - sent)
    _other()
    os.waitpid(pid, 0)
    for fd in {rfd, wfd} | ({extra} if extra else set()):
        os.close(fd)
    return got


def measure(load: str, seconds: float) -> None:
    for fifo in (False, True):
        for spin in (0.0, 3e-4):
            what = f"wake {'SCHED_FIFO' if fifo else 'ordinary'} spin {spin * 1e3:g}"
            print(f"{load:<8} " + _row(what, wake(seconds, fifo, spin)), flush=True)
    print(f"{load:<8} " + _row("work 0.1 ms SCHED_FIFO", work(seconds)), flush=True)
    for kind in ("pty", "pipe"):
        print(f"{load:<8} " + _row(f"{kind} one way", transfer(seconds, kind)), flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--busy", type=int, default=2)
    args = ap.parse_args()
    if not _fifo(1):
        print("note: SCHED_FIFO not allowed here; the SCHED_FIFO rows run at ordinary priority")
    _other()
    print(f"{os.cpu_count()} CPUs; load average before: {os.getloadavg()[0]:.2f}")
    print(
        f"{'load':<8} {'what':<28} {'n':>6} {'p50 ms':>7} {'p99 ms':>7} {'p99.9':>7} "
        f"{'max ms':>7} {'load1':>6}"
    )
    measure("idle", args.seconds)
    with busy(args.busy):
        time.sleep(1.0)
        measure(f"busy x{args.busy}", args.seconds)
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
