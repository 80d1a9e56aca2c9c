"""Real-time control loop: rate, period jitter and watchdog trips on the simulated
display, for each way the host loop keeps time, idle and under load; and ``live``.

Usage::

    python benchmarks/play_loop.py --duration 10 --runs 1 --display-fifo
    python benchmarks/play_loop.py --duration 10 --runs 1 --display-fifo --live 15

Plays K = 600 N/m (M = 50 g) for ``--duration`` s at 1 kHz against a simulated
display in its own process, with each host loop: ``plain`` (the loop before any of
this, in the calling thread, sleeping in select), ``thread`` and ``process`` (its own
thread, or its own process: ``tissuecli.app.play.LOOPS``), each without and with
elevated scheduling (``+rt``: SCHED_FIFO 10, memory locked, one CPU, a spin through each
expected frame). First on the machine as it is ("idle"), then with ``--busy``
processes running ``while 1: pass``; the loops alternate run by run, so the figures of
one load are side by side. The simulated display runs under SCHED_FIFO 11 of its own
where the system allows it, and judges its watchdog against its port at start-up
(``limit``: periods, 5 is the firmware's); ``--display-fifo`` raises it to SCHED_FIFO 20 and
``--display-other`` lowers it to ordinary scheduling, to compare.
``--live S`` then runs ``live`` for S seconds under each
load (simulated forceps and display; the haptic loop in its own process, elevated),
with the recorder and the online fit in the calling process.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path
from typing import Any

from _busy import busy

from tissuecli.app.live import live
from tissuecli.app.play import play
from tissuecli.core.errors import DeviceError, DeviceLost
from tissuecli.core.terms import Law
from tissuecli.core.tissue import Tissue
from tissuecli.sim.process import SimulatorProcess

#: (label, loop, realtime)
VARIANTS = {
    "plain": ("plain", False),
    "thread": ("thread", False),
    "thread+rt": ("thread", True),
    "process": ("process", False),
    "process+rt": ("process", True),
}


def _display(link: Path, fifo: bool, other: bool = False) -> SimulatorProcess:
    """A simulated display (SCHED_FIFO 11 of its own where allowed); ``fifo`` raises it
    to 20, ``other`` lowers it to ordinary scheduling (as before it kept its own time)."""
    disp = SimulatorProcess("display", link)
    disp.__enter__()
    if disp.process is not None and (fifo or other):
        time.sleep(0.2)  # its own elevation first, then this one over it
        policy, prio = (os.SCHED_OTHER, 0) if other else (os.SCHED_FIFO, 20)
        for tid in os.listdir(f"/proc/{disp.process.pid}/task"):
            os.sched_setscheduler(int(tid), policy, os.sched_param(prio))
    return disp


def _row(load: str, label: str, run: int, s: dict[str, Any]) -> str:
    rt = s.get("realtime") or {}
    return (
        f"{load:<8} {label:<11} {run:>3} {s.get('loop_rate_hz') or 0:8.2f} "
        f"{s.get('period_p50_ms') or 0:7.2f} {s.get('period_p99_ms') or 0:7.2f} "
        f"{s.get('period_max_ms') or 0:7.2f} {s.get('watchdog_frames', 0):>8} "
        f"{s.get('missed_periods', 0):>6} {s.get('watchdog_periods', 5):>5} "
        f"{rt.get('scheduler', 'n/a'):>11}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--runs", type=int, default=1)
    ap.add_argument("--busy", type=int, default=2, help="busy processes for the loaded case")
    ap.add_argument("--loops", default=",".join(VARIANTS), help="which host loops, comma-separated")
    ap.add_argument("--display-fifo", action="store_true", help="raise the display to SCHED_FIFO")
    ap.add_argument("--display-other", action="store_true", help="lower the display to SCHED_OTHER")
    ap.add_argument("--live", type=float, default=0.0, help="also run live for this many s")
    args = ap.parse_args()
    tissue = Tissue(Law.paper("x", "xdot"), 600.0, 3.0, 0.05)
    labels = args.loops.split(",")
    said = "SCHED_FIFO 20" if args.display_fifo else "ordinary" if args.display_other else "its own"
    print(f"{os.cpu_count()} CPUs; display scheduling {said}")
    print(f"load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())}", flush=True)
    head = (
        f"{'load':<8} {'loop':<11} {'run':>3} {'rate Hz':>8} {'p50 ms':>7} {'p99 ms':>7} "
        f"{'max ms':>7} {'watchdog':>8} {'missed':>6} {'limit':>5} {'sched':>11}"
    )
    lives: list[str] = []
    with tempfile.TemporaryDirectory() as tmp:
        print(head, flush=True)
        for load in ("idle", f"busy x{args.busy}"):
            with busy(args.busy if load != "idle" else 0):
                for run in range(args.runs):
                    for label in labels:
                        loop, rt = VARIANTS[label]
                        disp = _display(
                            Path(tmp) / f"d-{label}-{load[0]}{run}",
                            args.display_fifo,
                            args.display_other,
                        )
                        try:
                            s = play(tissue, str(disp.link), args.duration, loop=loop, realtime=rt)
                            print(_row(load, label, run, s), flush=True)
                        except DeviceLost as exc:
                            print(f"{load:<8} {label:<11} {run:>3} lost: {exc}", flush=True)
                        finally:
                            disp.stop()
                if args.live > 0:
                    lives.append(_live(Path(tmp), load, args))
    if lives:
        print()
        print(
            f"{'load':<8} {'rate Hz':>8} {'p50 ms':>7} {'p99 ms':>7} {'max ms':>7} "
            f"{'watchdog':>8} {'limit':>5} {'1st s':>6} {'rms N':>6} {'E mJ':>6} "
            f"{'Emin mJ':>7} {'diss mJ':>7}"
        )
        for line in lives:
            print(line)
    print(f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


def _live(tmp: Path, load: str, args: argparse.Namespace) -> str:
    """``live`` for ``args.live`` s on simulated devices: one row of figures."""
    tag = load.split()[0]
    try:
        with SimulatorProcess("forceps", tmp / f"f-{tag}") as forceps:
            disp = _display(tmp / f"dl-{tag}", args.display_fifo, args.display_other)
            try:
                s = live(str(forceps.link), str(disp.link), tmp / f"live-{tag}.h5", "s", args.live)
            finally:
                disp.stop()
    except (DeviceLost, DeviceError) as exc:
        return f"{load:<8} lost: {exc}"
    r, p = s["render"] or {}, s["passivity"]

    def num(value: Any, scale: float = 1.0, fmt: str = "6.2f") -> str:
        return "n/a" if value is None else format(value * scale, fmt)

    return (
        f"{load:<8} {num(r.get('loop_rate_hz'), fmt='8.2f')} "
        f"{num(r.get('period_p50_ms'), fmt='7.2f')} "
        f"{num(r.get('period_p99_ms'), fmt='7.2f')} {num(r.get('period_max_ms'), fmt='7.2f')} "
        f"{r.get('watchdog_frames', 0):>8} {r.get('watchdog_periods', 5):>5} "
        f"{num(s['first_render_delay_s'])} "
        f"{num(s.get('tracking_rms_n'), fmt='6.3f')} {num(p['energy_observed_j'], 1e3)} "
        f"{num(p['energy_min_j'], 1e3, '7.3f')} {num(p['energy_dissipated_j'], 1e3, '7.3f')}"
    )


if __name__ == "__main__":
    main()
