"""How often the 95 % intervals hold the truth, over fixed seeds.

The paper's four forms on 12-bit sessions (10 s at 1 kHz, the simulator's sensors:
5 mN of force noise, 5 um of position noise), at 20 um of position noise and at 8 bits,
each fitted with its own form (the default search chooses the same form on these
sessions and nearly the same intervals); then the lab protocols the stability bounds
are stated for, drawn over the stress space and fitted with the truth's law. For each
coefficient: the share of intervals that hold the truth and the RMS of
``(mean - truth) / sd`` (1 when the intervals are calibrated).

    python benchmarks/coverage.py --sessions 100 --draws 40
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Sequence

import numpy as np
from scipy.stats import binom

from tissuecli.core.terms import Law
from tissuecli.core.tissue import Tissue
from tissuecli.identify import BayesianFit
from tissuecli.sim.protocols import random_protocol
from tissuecli.sim.synth import ForcepsModel, Sensors, synthesize

PAPER = [
    Tissue(Law.paper("x", "xdot"), 350.0, 3.0, 0.05),
    Tissue(Law.paper("x^3", "xdot"), 8e6, 3.0, 0.05),
    Tissue(Law.paper("x", "xdot^2"), 350.0, 60.0, 0.05),
    Tissue(Law.paper("x^3", "xdot^2"), 8e6, 60.0, 0.05),
]
SENSORS = {
    "12-bit": {"bits": 12},
    "12-bit, 20 um": {"bits": 12, "position_noise_m": 20e-6},
    "8-bit": {"bits": 8},
}
PROTOCOLS = ["ramp linear", "ramp offset", "ramp stiffening", "triangle viscoelastic",
             "ramp-hold SLS"]  # fmt: skip


def band(n: int) -> str:
    """The range a calibrated interval's coverage falls in 95 % of the time."""
    lo, hi = binom.ppf([0.025, 0.975], n, 0.95) / n
    return f"[{lo:.2f},{hi:.2f}]"


def row(label: str, symbols: Sequence[str], z: np.ndarray, cpu: float) -> str:
    """One line: coverage and RMS z of each coefficient."""
    inside = np.abs(z) <= 1.959964
    parts = " ".join(f"{s} {np.mean(inside[:, j]):.2f} (z {np.sqrt(np.mean(z[:, j] ** 2)):.2f})"
                     for j, s in enumerate(symbols))  # fmt: skip
    return f"{label:<34} n={len(z):<4} {band(len(z))} {parts}  cpu {cpu:.1f} s"


def paper(sessions: int) -> None:
    for name, sensors in SENSORS.items():
        for tissue in PAPER:
            c0, z = time.process_time(), []
            for seed in range(200, 200 + sessions):
                model = ForcepsModel(tissue=tissue, seed=seed, sensors=Sensors(**sensors))
                s, _ = synthesize(model, 10.0)
                post = BayesianFit(forms=tissue.law.name, seed=0).fit(s).best_.posterior
                z.append((post.mean - tissue.coef) / post.sd)
            label = f"{tissue.law.name}, {name}"
            print(row(label, tissue.law.symbols, np.array(z), time.process_time() - c0),
                  flush=True)  # fmt: skip


def protocols(draws: int) -> None:
    for name in PROTOCOLS:
        c0, z, symbols = time.process_time(), [], None
        for seed in range(draws):
            scene = random_protocol(seed, name, max_samples=2000)
            law = scene.tissue.law
            post = BayesianFit(grasps="none", forms=law.name, seed=0).fit(scene.session)
            p = post.best_.posterior
            z.append((p.mean - np.asarray(scene.coefficients)) / p.sd)
            symbols = law.symbols
        print(row(name, symbols or [], np.array(z), time.process_time() - c0), flush=True)


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", type=int, default=100, help="seeds per paper form")
    ap.add_argument("--draws", type=int, default=40, help="draws of each protocol")
    ap.add_argument("--only", choices=["paper", "protocols"], help="one half of the table")
    args = ap.parse_args(argv)
    print(f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}; coverage of each "
          "coefficient's 95 % interval (RMS z); [binomial 95 % range]", flush=True)  # fmt: skip
    if args.only != "protocols":
        paper(args.sessions)
    if args.only != "paper":
        protocols(args.draws)
    print(f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main(sys.argv[1:])
