"""The default structure search on laboratory protocols and paper-form sessions: the law
chosen, how often each added term family appears where the truth has none, coverage of
the stiffness's 95 % interval, the evidence's sanity and the compute time.

Usage::

    python benchmarks/structure_calibration.py [SEEDS] [--parts protocols,paper,families]

Protocols: a linear specimen pulled at constant speed (350 N/m, 10 mN noise, 1 kHz,
10 s, 1 -> 3 mm; with damping, an offset and 2 um position noise in turn), a standard
linear solid ramped 1 s and held 19 s at 500 Hz, and sessions of each of the paper's four
forms (tissuecli.sim.synth). Compute time is CPU time of the process (the machine's
load stretches wall time, not work).

False positives of each added term family (relaxation, contact, friction, offset,
cubic), counted on every session whose truth lacks it: the paper's four forms and, with
the ``families`` part, each family of :data:`tissuecli.sim.families.FAMILIES` (10 s,
12-bit, 1 kHz grasps of its own random operator). Beside the count, ``expected`` is what
the fit's own probabilities promise: the sum over those sessions of the posterior
probability of the laws holding the family (equal prior odds between laws), and ``95 %
up`` the Clopper-Pearson upper bound of the observed rate.
"""

from __future__ import annotations

import argparse
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
from tissuecli.identify import BayesianFit, whiten  # noqa: E402
from tissuecli.identify.whiten import LIKELIHOODS  # noqa: E402
from tissuecli.sim.families import FAMILIES as LAWS  # noqa: E402
from tissuecli.sim.synth import ForcepsModel, Sensors, random_session, synthesize  # noqa: E402

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


def fit(session, grasps: str = "none") -> tuple[BayesianFit, float]:
    c0 = time.process_time()
    est = BayesianFit(grasps=grasps).fit(session)
    return est, time.process_time() - c0


class FalsePositives:
    """Per term family: sessions whose truth lacks it, how many chose it, and the count
    the fit's probabilities promise (their sum for the laws holding it)."""

    def __init__(self) -> None:
        self.sessions: Counter[str] = Counter()
        self.added: Counter[str] = Counter()
        self.expected: Counter[str] = Counter()

    def count(self, est: BayesianFit, truth: set[str]) -> None:
        got = set(names(est))
        for family, terms in FAMILIES.items():
            if truth & set(terms):
                continue
            self.sessions[family] += 1
            self.added[family] += bool(got & set(terms))
            self.expected[family] += sum(
                r.probability
                for r in est.results_
                if math.isfinite(r.probability)
                and {t.name for t in (r.family or r.model).terms} & set(terms)
            )

    def lines(self) -> list[str]:
        out = []
        for family in FAMILIES:
            n, k = self.sessions[family], self.added[family]
            if not n:
                continue
            out.append(f"  {family:<11} added {k:>3}/{n:<3} rate {k / n:5.3f}  95 % up "
                       f"{upper95(k, n):5.3f}  expected {self.expected[family]:6.2f}")  # fmt: skip
        return out


def upper95(k: int, n: int) -> float:
    """Clopper-Pearson upper bound (two-sided 95 %) of a rate k/n."""
    from scipy.stats import beta

    return 1.0 if k >= n else float(beta.ppf(0.975, k + 1, n - k))


def protocols_part(seeds: int) -> None:
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
              f"{max(times):.2f} s max", flush=True)  # fmt: skip


def paper_part(seeds: int, fp: FalsePositives) -> None:
    """Paper forms: added families where the truth has none, and coverage of K."""
    mine = FalsePositives()
    right, cover, total, times = 0, 0, 0, []
    for tissue in PAPER:
        truth = {t.name for t in tissue.law.terms}
        for k in range(seeds):
            model = ForcepsModel(tissue=tissue, seed=200 + k, sensors=Sensors(bits=12))
            s, _ = synthesize(model, 10.0)
            est, dt = fit(s)
            times.append(dt)
            total += 1
            right += est.best_.name == tissue.law.name
            mine.count(est, truth)
            fp.count(est, truth)
            if est.best_.name == tissue.law.name:
                lo, hi = est.best_.posterior.ci95[0]
                cover += lo <= tissue.coef[0] <= hi
    rates = ", ".join(f"{f} {mine.added[f]}/{mine.sessions[f]}" for f in FAMILIES)
    print(f"paper forms ({total} sessions, 12-bit, 10 s at 1 kHz): form right {right}/{total}; "
          f"added where absent: {rates}; K inside its 95 % interval {cover}/{right}; "
          f"CPU {np.median(times):.2f} s median, {max(times):.2f} s max", flush=True)  # fmt: skip


def families_part(seeds: int, fp: FalsePositives) -> None:
    """Each family of sim.families on its own random operator (grasps, as recorded)."""
    for label, tissue in LAWS.items():
        if label.startswith("paper"):
            continue  # the paper part has them
        truth = {t.name for t in tissue.law.terms}
        right, times, wrong = 0, [], Counter()
        for k in range(seeds):
            s, _ = random_session(tissue, seed=300 + k, duration_s=10.0, bits=12)
            est, dt = fit(s, grasps="all")
            times.append(dt)
            fp.count(est, truth)
            law = est.best_.family or est.best_.model
            ok = sorted(t.name for t in law.terms) == sorted(t.name for t in tissue.law.terms)
            right += ok
            if not ok:
                wrong[law.name] += 1
        misses = "; ".join(f"{n} x{c}" for n, c in wrong.most_common())
        chose = f"; chose {misses}" if misses else ""
        print(f"{label}: structure right {right}/{seeds}{chose}; CPU {np.median(times):.2f} s "
              f"median, {max(times):.2f} s max", flush=True)  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seeds", nargs="?", type=int, default=4, help="seeds per protocol or law")
    ap.add_argument("--parts", default="protocols,paper,families")
    ap.add_argument("--likelihood", choices=sorted(LIKELIHOODS), help="the fits' likelihood")
    args = ap.parse_args()
    if args.likelihood:
        whiten.DEFAULT_LIKELIHOOD = args.likelihood
    parts = {p.strip() for p in args.parts.split(",")}
    seeds = args.seeds
    print(f"load average {os.getloadavg()[0]:.1f}; {seeds} seeds per protocol; "
          "CPU seconds per fit", flush=True)  # fmt: skip
    fp = FalsePositives()
    if "protocols" in parts:
        protocols_part(seeds)
    if "paper" in parts:
        paper_part(seeds, fp)
    if "families" in parts:
        families_part(seeds, fp)
    if fp.sessions:
        print(f"false positives of each added family, over every session whose truth lacks it "
              f"(load average {os.getloadavg()[0]:.1f} at the end):")  # fmt: skip
        for line in fp.lines():
            print(line)


if __name__ == "__main__":
    main()
