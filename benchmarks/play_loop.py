"""Real-time control loop: rate, period jitter and tracking on the simulated display.

Usage::

    python benchmarks/play_loop.py --duration 20 --runs 3

Plays two tissues (K = 600 N/m, and a model with the piston's own mass) for
``--duration`` s at 1 kHz against a simulated display in its own process.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from tissuecli.app.play import play
from tissuecli.core.terms import Law
from tissuecli.core.tissue import Tissue
from tissuecli.render import PAPER_DISPLAY
from tissuecli.sim.process import SimulatorProcess


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=20.0)
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()
    tissues = {
        "K=600 N/m, M=50 g": Tissue(Law.paper("x", "xdot"), 600.0, 3.0, 0.05),
        "M = Mp": Tissue(Law.paper("x", "xdot"), 600.0, 3.0, PAPER_DISPLAY.Mp),
    }
    print(
        f"{'tissue':<18} {'run':>3} {'rate Hz':>9} {'p50 ms':>7} {'p99 ms':>7} {'max ms':>7} "
        f"{'lost':>5} {'rms um':>7} {'bound um':>9} {'sat %':>6} {'unrend %':>8}"
    )
    with tempfile.TemporaryDirectory() as tmp:
        for label, tissue in tissues.items():
            for run in range(args.runs):
                with SimulatorProcess("display", Path(tmp) / f"d{run}") as disp:
                    s = play(tissue, str(disp.link), args.duration, log=Path(tmp) / "log.h5")
                print(
                    f"{label:<18} {run:>3} {s['loop_rate_hz']:9.2f} {s['period_p50_ms']:7.2f} "
                    f"{s['period_p99_ms']:7.2f} {s['period_max_ms']:7.2f} {s['frames_lost']:>5} "
                    f"{s['tracking_rms_m'] * 1e6:7.2f} {s['tracking_bound_m'] * 1e6:9.1f} "
                    f"{100 * s['saturated_fraction']:6.2f} {100 * s['unrenderable_fraction']:8.2f}",
                    flush=True,
                )


if __name__ == "__main__":
    main()
