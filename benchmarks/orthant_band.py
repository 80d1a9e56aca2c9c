"""The orthant lattice's absolute target only near a mass of 1, against everywhere: CPU
of default fits run in turns in one process, and the largest change of any law's ln Z.

Usage::

    python benchmarks/orthant_band.py [REPEATS]

``orthant.ABS_BAND`` = 1 asks every mass for 1e-5 absolute (the code before); 0.01
asks it only of masses within 0.01 of 1, where the sampling rule reads it, and every
other mass for ln P to 1e-3. Sessions: the 10 s, 1 kHz paper form at 8 bits, a 6 kHz
one-branch slow squeeze whose broad time-constant grids run hundreds of lattices
(generalisation scene 8537428), and a 2,000-sample Hunt-Crossley grasp session.
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np

from tissuecli.identify import BayesianFit, orthant
from tissuecli.sim.scenes import random_scene
from tissuecli.sim.synth import ForcepsModel, Sensors, synthesize


def sessions() -> dict[str, object]:
    branch = random_scene(8537428, families=["one branch"], max_samples=10000).session
    t = branch.time
    head = int(np.searchsorted(t, t[0] + 0.7 * (t[-1] - t[0])))
    return {
        "paper form, 10 s at 1 kHz, 8 bits": synthesize(
            ForcepsModel(seed=1, sensors=Sensors(bits=8)), 10.0)[0],
        "one branch, 6.2 kHz slow squeeze (scene 8537428)": branch.replace(
            t[:head], branch.force[:head], branch.position[:head]),
        "Hunt-Crossley grasps (scene 3)": random_scene(
            3, families=["Hunt-Crossley"], max_samples=2000, contact="grasps").session,
    }  # fmt: skip


def main() -> None:
    repeats = int(sys.argv[1]) if len(sys.argv) > 1 else 2
    print(f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    BayesianFit("paper").fit(synthesize(ForcepsModel(seed=2), 2.0)[0])  # loads what a fit needs
    for name, session in sessions().items():
        cpu: dict[float, list[float]] = {1.0: [], 0.01: []}
        z: dict[float, dict[str, float]] = {}
        for _ in range(repeats):
            for band in (1.0, 0.01):
                orthant.ABS_BAND = band
                c0 = time.process_time()
                est = BayesianFit(seed=0).fit(session)  # type: ignore[arg-type]
                cpu[band].append(time.process_time() - c0)
                z[band] = {r.name: r.ln_evidence for r in est.results_}
        worst = max(abs(z[1.0][k] - z[0.01][k]) for k in z[1.0] if np.isfinite(z[1.0][k]))
        print(f"{name}: CPU everywhere {', '.join(f'{c:.2f}' for c in cpu[1.0])} s; near 1 "
              f"{', '.join(f'{c:.2f}' for c in cpu[0.01])} s; largest ln Z change "
              f"{worst:.1e} nats", flush=True)  # fmt: skip
    print(f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
