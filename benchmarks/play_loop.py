"""Real-time control loop: rate, period jitter, watchdog trips and tracking on the
simulated display, for each way the host loop keeps time, idle and under load.

Usage::

    python benchmarks/play_loop.py --duration 10 --runs 2
    python benchmarks/play_loop.py --duration 10 --runs 2 --display-fifo

Plays K = 600 N/m (M = 50 g) for ``--duration`` s at 1 kHz against a simulated
display in its own process, with each host loop of ``tissuecli.app.play.LOOPS``
(``plain``: the loop before elevation, in the calling thread, sleeping in select;
``thread``: own thread, gc frozen, sleep then spin; ``elevated``: the same under
SCHED_FIFO with memory locked and one CPU), first on an otherwise idle machine, then
with ``--busy`` processes running ``while 1: pass``. The loops alternate run by run,
so the figures of one load are side by side. ``--display-fifo`` also raises the
simulated display's process to SCHED_FIFO (a real display is a microcontroller that
keeps its own time), so that what remains is the host's.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from tissuecli.app.play import LOOPS, play
from tissuecli.core.errors import DeviceLost
from tissuecli.core.terms import Law
from tissuecli.core.tissue import Tissue
from tissuecli.sim.process import SimulatorProcess


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--busy", type=int, default=2, help="busy processes for the loaded case")
    ap.add_argument("--loops", default=",".join(LOOPS), help="which host loops, comma-separated")
    ap.add_argument("--display-fifo", action="store_true", help="raise the display to SCHED_FIFO")
    args = ap.parse_args()
    tissue = Tissue(Law.paper("x", "xdot"), 600.0, 3.0, 0.05)
    loops = args.loops.split(",")
    print(f"{os.cpu_count()} CPUs; display {'SCHED_FIFO 20' if args.display_fifo else 'ordinary'}")
    print(
        f"{'load':<7} {'loop':<9} {'run':>3} {'rate Hz':>8} {'p50 ms':>7} {'p99 ms':>7} "
        f"{'max ms':>7} {'watchdog':>8} {'missed':>6} {'rms um':>7} {'sched':>10}"
    )
    with tempfile.TemporaryDirectory() as tmp:
        for load in ("idle", f"busy x{args.busy}"):
            hogs = []
            if load != "idle":
                hogs = [
                    subprocess.Popen([sys.executable, "-c", "while 1: pass"])
                    for _ in range(args.busy)
                ]
            try:
                for run in range(args.runs):
                    for loop in loops:
                        link = Path(tmp) / f"d-{loop}-{run}"
                        with SimulatorProcess("display", link) as disp:
                            if args.display_fifo and disp.process is not None:
                                os.sched_setscheduler(
                                    disp.process.pid, os.SCHED_FIFO, os.sched_param(20)
                                )
                            try:
                                s = play(tissue, str(link), args.duration, loop=loop)
                            except DeviceLost as exc:
                                print(f"{load:<7} {loop:<9} {run:>3} lost: {exc}", flush=True)
                                continue
                        rt = s["realtime"]
                        print(
                            f"{load:<7} {loop:<9} {run:>3} {s['loop_rate_hz']:8.2f} "
                            f"{s['period_p50_ms']:7.2f} {s['period_p99_ms']:7.2f} "
                            f"{s['period_max_ms']:7.2f} {s['watchdog_frames']:>8} "
                            f"{s['missed_periods']:>6} {s['tracking_rms_m'] * 1e6:7.2f} "
                            f"{rt['scheduler']:>10}",
                            flush=True,
                        )
            finally:
                for hog in hogs:
                    hog.kill()
                    hog.wait()


if __name__ == "__main__":
    main()
