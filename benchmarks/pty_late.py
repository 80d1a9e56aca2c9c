"""Where a late answer comes from: a display-like and a host-like loop over one
pseudo-terminal, every frame stamped when written and when read, in both directions.

Usage::

    python benchmarks/pty_late.py --seconds 3 --busy 2 --runs 2

A "display" process on the master side (SCHED_FIFO 11, as the simulated display) sends a
24-byte frame every 1 ms and notes, at each tick, whether the answer to its previous
frame has come back; a "host" process on the slave side (SCHED_FIFO 10, as the haptic
loop) answers each frame after 0.15 ms of work (the host's control step at the
median). Both stamp on the machine's monotonic clock, so each late answer is put down
to its frame reaching the host late (more than 0.6 ms on the way in: the host's work
and the way back then no longer fit in the period) or to the answer coming back late.
No tissuecli code runs in the loops: what is late here is the transport's and the
scheduler's. Each run is repeated with both loops on any CPU, both pinned to the last
CPU, and each on a CPU of its own (``--placements``), ``--busy`` processes running
``while 1: pass`` beside them. Prints one row per run with the 1-minute load average.
"""

from __future__ import annotations

import argparse
import os
import pty
import select
import struct
import sys
import time
import tty
from multiprocessing import Pipe
from multiprocessing.connection import Connection

from _busy import busy

FRAME = struct.Struct("<Id12x")  # seq, time written (monotonic s), padding to 24 bytes
PERIOD_S = 1e-3
WORK_S = 1.5e-4
INBOUND_LATE_S = 0.6e-3
PLACEMENTS = {"any": (None, None), "same": (-1, -1), "apart": (0, -1)}


def _elevate(priority: int, cpu: int | None) -> str:
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        got = "SCHED_FIFO"
    except OSError:
        got = "SCHED_OTHER"
    if cpu is not None:
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[cpu]})
    return got


def _frames(buf: bytearray, data: bytes, at: float, into: dict[int, tuple[float, float]]) -> int:
    """Decode whole frames of ``buf + data`` into ``into[seq] = (written, read)``; the
    newest seq or -1."""
    buf += data
    newest = -1
    while len(buf) >= FRAME.size:
        seq, written = FRAME.unpack_from(buf)
        del buf[: FRAME.size]
        into[seq] = (written, at)
        newest = max(newest, seq)
    return newest


def host(fd: int, seconds: float, cpu: int | None, out: Connection) -> None:
    """Answer each frame (the newest of those read together) after :data:`WORK_S`."""
    sched = _elevate(10, cpu)
    os.set_blocking(fd, False)
    got: dict[int, tuple[float, float]] = {}
    buf = bytearray()
    end = time.monotonic() + seconds + 1.0
    while time.monotonic() < end:
        if not select.select([fd], [], [], 0.1)[0]:
            continue
        try:
            data = os.read(fd, 4096)
        except BlockingIOError:
            continue
        newest = _frames(buf, data, time.monotonic(), got)
        if newest >= 0:
            until = time.monotonic() + WORK_S
            while time.monotonic() < until:
                pass
            os.write(fd, FRAME.pack(newest, time.monotonic()))
    out.send((sched, got))


def display(fd: int, seconds: float, cpu: int | None) -> dict[str, object]:
    """Tick every :data:`PERIOD_S`; between ticks wait on the port to stamp answers."""
    sched = _elevate(11, cpu)
    os.set_blocking(fd, False)
    answers: dict[int, tuple[float, float]] = {}
    buf = bytearray()
    newest, late, wake = -1, [], []
    t0 = time.monotonic() + 0.2
    for k in range(int(seconds / PERIOD_S)):
        deadline = t0 + k * PERIOD_S
        while (now := time.monotonic()) < deadline:
            if select.select([fd], [], [], deadline - now)[0]:
                try:
                    newest = max(newest, _frames(buf, os.read(fd, 4096), time.monotonic(), answers))
                except BlockingIOError:
                    pass
        wake.append(time.monotonic() - deadline)
        if k:
            late.append(k - 1 > newest)
        os.write(fd, FRAME.pack(k, time.monotonic()))
    return {"sched": sched, "answers": answers, "late": late, "wake": wake}


def run(seconds: float, placement: str) -> dict[str, object]:
    master, slave = pty.openpty()
    tty.setraw(slave)
    host_fd = os.open(os.ttyname(slave), os.O_RDWR | os.O_NOCTTY)
    recv, send = Pipe(duplex=False)
    d_cpu, h_cpu = PLACEMENTS[placement]
    pid = os.fork()
    if pid == 0:
        os.close(master)
        try:
            host(host_fd, seconds, h_cpu, send)
        finally:
            os._exit(0)
    os.close(host_fd)
    shown = display(master, seconds, d_cpu)
    h_sched, frames = recv.recv()
    os.waitpid(pid, 0)
    for fd in (master, slave):
        os.close(fd)
    return {**shown, "host_sched": h_sched, "frames": frames}


def _took(stamps: tuple[float, float]) -> float:
    return stamps[1] - stamps[0]


def q(values: list[float], p: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(p * len(ordered)))] * 1e3 if ordered else float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--busy", type=int, default=2)
    ap.add_argument("--runs", type=int, default=1)
    ap.add_argument("--placements", default="any,same,apart")
    args = ap.parse_args()
    print(
        f"{'cpus':>5} {'late %':>6} {'in':>4} {'back':>4} {'in p50':>6} {'p99':>6} {'max':>6}"
        f" {'back p50':>8} {'p99':>6} {'max':>6} {'wake p99':>8} {'sched':>10} {'load1':>6}"
    )
    with busy(args.busy):
        time.sleep(1.0)
        for _ in range(args.runs):
            for placement in args.placements.split(","):
                r = run(args.seconds, placement)
                frames, answers = r["frames"], r["answers"]
                late = r["late"]
                assert isinstance(frames, dict) and isinstance(answers, dict)
                assert isinstance(late, list)
                inbound = sorted(b - a for a, b in frames.values())
                back = sorted(b - a for a, b in answers.values())
                # a late tick k: its frame k-1 reached the host late, or the answer came back late
                late_in = sum(
                    1
                    for k, was in enumerate(late, 1)
                    if was and (k - 1 not in frames or _took(frames[k - 1]) > INBOUND_LATE_S)
                )
                n_late = sum(late)
                both = f"{r['sched'][6:]}/{r['host_sched'][6:]}"  # type: ignore[index]
                print(
                    f"{placement:>5} {100 * n_late / len(late):6.2f} {late_in:>4}"
                    f" {n_late - late_in:>4}"
                    f" {q(inbound, 0.5):6.3f} {q(inbound, 0.99):6.2f} {q(inbound, 1):6.2f}"
                    f" {q(back, 0.5):8.3f} {q(back, 0.99):6.2f} {q(back, 1):6.2f}"
                    f" {q(r['wake'], 0.99):8.3f} {both:>10} {os.getloadavg()[0]:6.2f}",  # type: ignore[arg-type]
                    flush=True,
                )


if __name__ == "__main__":
    sys.exit(main())
