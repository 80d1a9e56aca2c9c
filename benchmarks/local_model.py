"""How well the display's local model of the tissue stands in for a late answer.

Usage::

    python benchmarks/local_model.py --duration 3 --runs 2 --busy 2

Plays the demo's tissue (K = 350 N/m, S = 3 N s/m, M = 0.05 kg) on the simulated display
for ``--duration`` seconds with a play log, ``--busy`` processes running ``while 1: pass``
beside it, ``--runs`` times. From each log's stretches where the host's answers were on
time, it takes the pull each answer asked for (``alpha V^2``, where the solenoid neither
pushed nor saturated) and asks what a display ``d`` periods late (d = 1..5) would have
applied instead of the answer due: holding the last answer's pull (a display without a
model), or moving it by the local model's slopes (what SetModel carries) over what the
encoder saw. Prints the rms and p95 of each against the answer due, mN, and how many
periods each play ran on a late answer, rendered from the model and beyond it.
"""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

import h5py
import numpy as np
from _busy import busy

from tissuecli.app.play import Rendering, play
from tissuecli.core.flags import FLAG_MODEL, FLAG_STALE
from tissuecli.core.tissue import DEFAULT_TISSUE
from tissuecli.render.check import check
from tissuecli.render.controller import Controller, Step
from tissuecli.render.profile import PAPER_DISPLAY
from tissuecli.sim.process import SimulatorProcess

HORIZON = 5


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=3.0)
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--busy", type=int, default=2)
    args = ap.parse_args()
    p = PAPER_DISPLAY
    tissue = DEFAULT_TISSUE
    ctrl = Controller(tissue, p, 1000.0, check(tissue, p, 1000.0).gains)
    # the slopes SetModel carries (a linear law: the same at every state)
    u, du_dx, du_dv = Rendering(ctrl).local_model(
        Step(1.0, 0, 1e-3, 0.0, 0.0, 1e-3, 0.0, 0.0, p.alpha), 1.0, p
    ) or (0.0, 0.0, 0.0)
    print(
        f"slopes: {du_dx * p.alpha:.1f} N/m (K - Kp), {du_dv * p.alpha:.2f} N s/m "
        "(S - b + Cv (M - Mp) / M)"
    )
    held: dict[int, list[float]] = {d: [] for d in range(1, HORIZON + 1)}
    model: dict[int, list[float]] = {d: [] for d in range(1, HORIZON + 1)}
    with busy(args.busy), tempfile.TemporaryDirectory() as tmp:
        for run in range(args.runs):
            log = Path(tmp) / f"play{run}.h5"
            load = os.getloadavg()[0]
            with SimulatorProcess("display", Path(tmp) / f"display{run}") as disp:
                s = play(tissue, str(disp.link), args.duration, log=log, loop="process")
            print(
                f"run {run}: load average {load:.2f}; {s['frames']} frames, "
                f"{s['stale_frames'] + s['modelled_frames']} on a late answer, "
                f"{s['modelled_frames']} rendered from the local model, "
                f"{s['stale_frames']} beyond it"
            )
            with h5py.File(log) as f:
                group = f["plays"][next(iter(f["plays"]))]
                volts, counts, flags = group["V"][:], group["counts"][:], group["flags"][:]
            pull = p.alpha * volts**2
            x = counts * p.resolution
            v = np.r_[0.0, np.diff(x)] * 1000.0
            on_time = (flags & (FLAG_STALE | FLAG_MODEL)) == 0
            inside = (volts > 0.0) & (volts < p.v_max)
            for d in range(1, HORIZON + 1):
                ok = inside[:-d] & inside[d:] & on_time[:-d] & on_time[d:]
                due = pull[d:][ok]
                last = pull[:-d][ok]
                moved = last + p.alpha * (
                    du_dx * (x[d:] - x[:-d])[ok] + du_dv * (v[d:] - v[:-d])[ok]
                )
                held[d] += list(np.abs(last - due) * 1e3)
                model[d] += list(np.abs(moved - due) * 1e3)
    print(f"load average after: {os.getloadavg()[0]:.2f}")
    print("periods late  pairs   held: rms    p95   local model: rms    p95   (mN)")
    for d in range(1, HORIZON + 1):
        h, m = np.array(held[d]), np.array(model[d])
        print(
            f"{d:>12} {len(h):>6} {np.sqrt(np.mean(h**2)):12.2f} {np.percentile(h, 95):6.2f} "
            f"{np.sqrt(np.mean(m**2)):19.2f} {np.percentile(m, 95):6.2f}"
        )


if __name__ == "__main__":
    main()
