"""``tissuecli demo`` run after run beside CPU-bound processes: how many pass (exit 0),
and the play step's loop figures of each.

Usage::

    python benchmarks/demo_runs.py --runs 20 --busy 2

Each run is ``tissuecli demo --duration 2`` in a process of its own, with ``--busy``
processes running ``while 1: pass`` beside it for the whole benchmark. Prints one
row per run (exit status, loop rate, p99 and longest period, watchdog frames, periods
without a frame, periods the display ran on a late answer and the longest run of them,
of those the periods it rendered from the answer's local model and the periods beyond
the model (the ones judged, at 5 %) with their longest run, the simulated display's
watchdog limit in periods, the scheduling the haptic loop and
the simulated display obtained, seconds, the faults) and the count of runs that exited
0, with the load average before and after. ``--busy 0`` runs the demo alone.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import time

from _busy import busy

PLAYED = re.compile(
    r"played [\d.]+ s: (\d+) frames at ([\d.]+) Hz \(period p99 ([\d.]+) ms, max ([\d.]+) ms\)"
    r".*?(\d+) periods without a frame"
)
LATE = re.compile(
    r"(\d+) on a late answer \(longest run (\d+)\)"
    r"(?:, (\d+) of them rendered from the display's local model and (\d+) beyond it "
    r"\(longest run (\d+)\))?"
)
WATCHDOG = re.compile(r"watchdog frames (\d+)")
LIMIT = re.compile(r"display watchdog (\d+) periods")
SCHED = re.compile(r"scheduling: haptic loop SCHED_(\w+), simulated display (?:SCHED_)?(\S+)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--busy", type=int, default=2)
    ap.add_argument("--duration", type=float, default=2.0)
    args = ap.parse_args()
    passed = 0
    with busy(args.busy):
        print(f"load average before: {os.getloadavg()[0]:.2f}; {args.busy} busy processes")
        print(
            f"{'run':>3} {'exit':>4} {'rate Hz':>8} {'p99 ms':>7} {'max ms':>7} "
            f"{'watchdog':>8} {'missed':>6} {'late':>5} {'run':>4} {'model':>5} {'beyond':>6} "
            f"{'run':>4} {'limit':>5} {'sched':>10} "
            f"{'s':>5}  faults"
        )
        for run in range(args.runs):
            t0 = time.monotonic()
            done = subprocess.run(
                [sys.executable, "-m", "tissuecli", "demo", "--duration", str(args.duration)],
                capture_output=True, text=True, timeout=600,
            )  # fmt: skip
            played = PLAYED.search(done.stdout)
            watchdog = WATCHDOG.search(done.stdout)
            limit = LIMIT.search(done.stdout)
            sched = SCHED.search(done.stdout)
            both = "/".join(sched.groups()) if sched else "?"
            passed += done.returncode == 0
            if played is None:
                last = (done.stderr.strip().splitlines() or ["?"])[-1]
                print(f"{run:>3} {done.returncode:>4} no play: {last[:100]}")
                continue
            _, rate, p99, worst, missed = played.groups()
            late = LATE.search(done.stdout)
            stale, longest, modelled, beyond, beyond_run = (
                [g if g is not None else "-" for g in late.groups()] if late else ["?"] * 5
            )
            faults = "; ".join(
                line[len("FAULT: ") :][:60]
                for line in done.stdout.splitlines()
                if line.startswith("FAULT: ")
            )
            print(
                f"{run:>3} {done.returncode:>4} {float(rate):8.1f} {float(p99):7.2f} "
                f"{float(worst):7.2f} {watchdog.group(1) if watchdog else '?':>8} "
                f"{missed:>6} {stale:>5} {longest:>4} {modelled:>5} {beyond:>6} {beyond_run:>4} "
                f"{limit.group(1) if limit else '?':>5} "
                f"{both:>10} "
                f"{time.monotonic() - t0:5.0f}  {faults}",
                flush=True,
            )
    print(f"{passed} of {args.runs} runs exited 0; load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
