"""The default structure search on laboratory protocols and paper-form sessions: the law
chosen, how often each added term family appears where the truth has none, coverage of
the stiffness's 95 % interval, the evidence's sanity and the compute time.

Usage::

    python benchmarks/structure_calibration.py [SEEDS]

Protocols: a linear specimen pulled at constant speed (350 N/m, 10 mN noise, 1 kHz,
10 s, 1 -> 3 mm; with damping, an offset and 2 um position noise in turn), a standard
linear solid ramped 1 s and held 19 s at 500 Hz, and sessions of each of the paper's four
forms (tissuecli.sim.synth). Compute time is CPU time of the process (the machine's
load stretches wall time, not work).
"""

from __future__ import annotations

import math
import os
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "identify"))

from lab_protocols import constant_speed, relaxation  # noqa: E402

from tissuecli.core.terms import Law  # noqa: E402
from tissuecli.core.tissue import Tissue  # noqa: E402
from tissuecli.identify import BayesianFit  # noqa: E402
from tissuecli.sim.synth import ForcepsModel, Sensors, synthesize  # noqa: E402

#: term families a search may add to a law, by the terms that make them
FAMILIES = {
    "relaxation": ("maxwell",),
    "contact": ("contact", "contact*xdot"),
    "friction": ("sign(xdot)",),
    "offset": ("offset",),
    "cubic": ("x^3",),
}
PAPER = [
    Tissue(Law.paper("x", "xdot"), 350.0, 3.0, 0.05),
    Tissue(Law.paper("x^3", "xdot"), 8e6, 3.0, 0.05),
    Tissue(Law.paper("x", "xdot^2"), 350.0, 60.0, 0.05),
    Tissue(Law.paper("x^3", "xdot^2"), 8e6, 60.0, 0.05),
]


def names(est: BayesianFit) -> list[str]:
    return [t.name for t in (est.best_.family or est.best_.model).terms]


def sane(est: BayesianFit) -> bool:
    n = est.kinematics_.force.size
    return all(math.isfinite(r.ln_evidence) and abs(r.ln_evidence) <= 20 * n
               for r in est.results_)  # fmt: skip


def fit(session) -> tuple[BayesianFit, float]:
    c0 = time.process_time()
    est = BayesianFit(grasps="none").fit(session)
    return est, time.process_time() - c0


def main() -> None:
    seeds = int(sys.argv[1]) if len(sys.argv) > 1 else 4
    load = os.getloadavg()[0]
    print(f"load average {load:.1f}; {seeds} seeds per protocol; CPU seconds per fit")
    protocols = {
        "constant speed, linear": lambda k: constant_speed(k),
        "constant speed, damping + offset": lambda k: constant_speed(k, damping=2.0, offset=0.1),
        "constant speed, 2 um position noise": lambda k: constant_speed(k, position_noise=2e-6),
        "ramp and hold, standard linear solid": lambda k: relaxation(k),
    }
    for label, make in protocols.items():
        rows, times, ok, k_err = Counter(), [], 0, []
        for k in range(seeds):
            s, truth = make(100 + k)
            est, dt = fit(s)
            rows[est.best_.name] += 1
            times.append(dt)
            ok += sane(est)
            k_err.append(abs(est.best_.posterior.mean[0] / truth["K"] - 1))
        chosen = ", ".join(f"{n} x{c}" for n, c in rows.most_common())
        print(f"{label}: chosen {chosen}; evidence sane {ok}/{seeds}; K error max "
              f"{100 * max(k_err):.2f} %; CPU {np.median(times):.2f} s median, "
              f"{max(times):.2f} s max")  # fmt: skip
    # paper forms: added families where the truth has none, and coverage of K
    added, right, cover, total, times = Counter(), 0, 0, 0, []
    for tissue in PAPER:
        truth = {t.name for t in tissue.law.terms}
        for k in range(seeds):
            model = ForcepsModel(tissue=tissue, seed=200 + k, sensors=Sensors(bits=12))
            s, _ = synthesize(model, 10.0)
            est, dt = fit(s)
            times.append(dt)
            total += 1
            got = set(names(est))
            right += est.best_.name == tissue.law.name
            for family, terms in FAMILIES.items():
                if got & set(terms) and not truth & set(terms):
                    added[family] += 1
            if est.best_.name == tissue.law.name:
                lo, hi = est.best_.posterior.ci95[0]
                cover += lo <= tissue.coef[0] <= hi
    rates = ", ".join(f"{f} {added[f]}/{total}" for f in FAMILIES)
    print(f"paper forms ({total} sessions, 12-bit, 10 s at 1 kHz): form right {right}/{total}; "
          f"added where absent: {rates}; K inside its 95 % interval {cover}/{right}; "
          f"CPU {np.median(times):.2f} s median, {max(times):.2f} s max")  # fmt: skip


if __name__ == "__main__":
    main()
