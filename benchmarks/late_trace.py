"""Where each late answer of a play came from: every tick of the simulated display and
every batch of frames the host ran, stamped on the machine's one monotonic clock.

Usage::

    python benchmarks/late_trace.py --runs 3 --busy 2

Each run starts the simulated display (its firmware loop traced: when each tick began,
the frame it sent, the age of the command in use) and a 2 s play of the demo's tissue
(the host loop traced: when it had run each batch of frames, how many, the newest), with
``--busy`` processes running ``while 1: pass`` beside them. For every tick the display
flagged late (the command in use not the answer to the frame before), it tells whether
the host had run that frame only after the tick (the frame reached the host late, or the
host ran late) or before it (the answer came back late); then the time from each
frame's write to the host having run it, and the first episodes of 5 or more late ticks
in a row with the host's batches during them (ms from the episode's first tick, frames,
newest seq).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from _busy import busy


def trace_display(out: str, link: str) -> None:
    """The simulated display with its ticks recorded: (tick start, frame seq, age)."""
    import tissuecli.sim.display as display

    ticks: list[tuple[float, int, int, bool]] = []
    tick = display._Firmware.tick

    def traced(self: Any, late: bool = False) -> None:
        t0 = time.monotonic()
        tick(self, late)
        if self.streaming:
            age = (self.seq - 2 - (self.answers or 0)) & 0xFFFFFFFF if self.armed else -1
            ticks.append((t0, self.seq - 1, age, late))

    display._Firmware.tick = traced  # type: ignore[method-assign]
    try:
        display.run_simulated_display(link)
    finally:
        Path(out).write_text(json.dumps(ticks))


def trace_host(out: str, link: str) -> None:
    """A 2 s play with each batch the host ran recorded: (when done, frames, newest)."""
    import tissuecli.app.play as play
    from tissuecli.core.tissue import DEFAULT_TISSUE

    batches: list[tuple[float, int, int]] = []
    receive = play.HostLoop._receive

    def traced(self: Any, stream: Any, deadline: float, fd: int | None) -> tuple[int, float]:
        got, now = receive(self, stream, deadline, fd)
        if got:
            batches.append((now, got, self.answers))
        return got, now

    play.HostLoop._receive = traced  # type: ignore[method-assign]
    s = play.play(DEFAULT_TISSUE, link, 2.0, loop="thread")
    keep = ("loop_rate_hz", "stale_frames", "modelled_frames", "period_max_ms")
    Path(out).write_text(json.dumps({"batches": batches, "summary": {k: s[k] for k in keep}}))


def report(run: int, load: float, ticks: list[Any], host: dict[str, Any]) -> None:
    batches = host["batches"]
    s = host["summary"]
    print(
        f"run {run}: load average {load:.2f}; {s['loop_rate_hz']:.1f} Hz, late ticks "
        f"{s['stale_frames'] + (s['modelled_frames'] or 0)}, longest period "
        f"{s['period_max_ms']:.2f} ms"
    )
    sent = {seq: t0 for t0, seq, _, _ in ticks}
    ran: dict[int, float] = {}  # frame seq -> when the host had run it
    for now, got, newest in batches:
        for seq in range(newest - got + 1, newest + 1):
            ran.setdefault(seq, now)
    way = np.array([ran[q] - sent[q] for q in ran if q in sent]) * 1e3
    late = [(t0, seq) for t0, seq, age, behind in ticks if age > 0 and not behind]
    after = sum(1 for t0, seq in late if ran.get(seq - 1, np.inf) > t0)
    print(
        f"  frame written to host done, ms: median {np.median(way):.3f}, p99 "
        f"{np.percentile(way, 99):.3f}, max {way.max():.2f}; batches of 2 or more "
        f"{sum(1 for _, got, _ in batches if got > 1)}"
    )
    print(
        f"  {len(late)} late ticks: the host ran the frame before only after the tick "
        f"{after}, before it (the answer late on its way back) {len(late) - after}"
    )
    ages = np.array([age for _, _, age, _ in ticks])
    starts = np.array([t0 for t0, _, _, _ in ticks])
    i, shown = 0, 0
    while i < len(ages) and shown < 3:
        if ages[i] > 0:
            j = i
            while j < len(ages) and ages[j] > 0:
                j += 1
            if j - i >= 5:
                first, last = ticks[i][1], ticks[j - 1][1]
                seen = [
                    (float(round((now - starts[i]) * 1e3, 1)), got, newest)
                    for now, got, newest in batches
                    if first - 2 <= newest <= last + 1
                ]
                print(f"  {j - i} late ticks in a row from frame {first}: batches {seen[:10]}")
                shown += 1
            i = j
        else:
            i += 1


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--busy", type=int, default=2)
    ap.add_argument("--display", nargs=2, metavar=("OUT", "LINK"), help=argparse.SUPPRESS)
    ap.add_argument("--host", nargs=2, metavar=("OUT", "LINK"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.display:
        return trace_display(*args.display)
    if args.host:
        return trace_host(*args.host)
    me = os.path.abspath(__file__)
    with busy(args.busy), tempfile.TemporaryDirectory() as tmp:
        for run in range(args.runs):
            link, d_out, h_out = (str(Path(tmp) / f"{n}{run}") for n in ("display", "d", "h"))
            sim = subprocess.Popen(
                [sys.executable, me, "--display", d_out, link], stderr=subprocess.DEVNULL
            )
            while not os.path.lexists(link):
                time.sleep(0.05)
            load = os.getloadavg()[0]
            subprocess.run([sys.executable, me, "--host", h_out, link], check=True)
            sim.send_signal(signal.SIGINT)
            sim.wait()
            report(
                run, load, json.loads(Path(d_out).read_text()), json.loads(Path(h_out).read_text())
            )
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
