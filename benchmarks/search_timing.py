"""CPU time of the default fit (structure search included) on a 10 s, 1 kHz paper-form
session, a constant-speed pull and a ramp-and-hold relaxation test.

Usage::

    python benchmarks/search_timing.py [REPEATS]

CPU time of this process (``time.process_time``), the median over REPEATS fits after
one warm-up fit that loads SciPy: on a loaded machine wall time measures the queue.
The first row is the fit ``tissuecli fit FILE`` runs, ``BayesianFit().fit(session)``
with grasp detection; the others fit every sample (``grasps="none"``).
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "identify"))

from lab_protocols import constant_speed, relaxation  # noqa: E402

from tissuecli.identify import BayesianFit  # noqa: E402
from tissuecli.sim.synth import ForcepsModel, Sensors, synthesize  # noqa: E402


def main() -> None:
    repeats = int(sys.argv[1]) if len(sys.argv) > 1 else 3
    paper = synthesize(ForcepsModel(seed=1, sensors=Sensors(bits=16)), 10.0)[0]
    sessions = {  # label: session, grasps
        "default fit (grasp detection), paper form, 10 s at 1 kHz": (paper, "all"),
        "paper form x+xdot+xddot, 10 s at 1 kHz": (paper, "none"),
        "constant-speed pull, 10 s at 1 kHz": (constant_speed(0)[0], "none"),
        "ramp and hold, 20 s at 500 Hz": (relaxation(0)[0], "none"),
    }
    BayesianFit(grasps="none").fit(sessions["constant-speed pull, 10 s at 1 kHz"][0])
    print(f"load average {os.getloadavg()[0]:.1f}")
    for label, (s, grasps) in sessions.items():
        cpu, wall = [], []
        for _ in range(repeats):
            c0, w0 = time.process_time(), time.perf_counter()
            est = BayesianFit(grasps=grasps).fit(s)
            cpu.append(time.process_time() - c0)
            wall.append(time.perf_counter() - w0)
        print(f"{label}: {est.best_.name} (P {est.best_.probability:.3f}), CPU "
              f"{np.median(cpu):.2f} s, wall {np.median(wall):.1f} s")  # fmt: skip
    print(f"load average {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
