"""How often the 95 % intervals hold the truth, over fixed seeds.

The paper's four forms on 12-bit sessions (10 s at 1 kHz, the simulator's sensors:
5 mN of force noise, 5 um of position noise), at 20 um of position noise and at 8 bits,
each fitted with its own form (the default search chooses the same form on these
sessions and nearly the same intervals); then the lab protocols the stability bounds
are stated for, drawn over the stress space and fitted with the truth's law. For each
coefficient: the share of intervals that hold the truth and the RMS of
``(mean - truth) / sd`` (1 when the intervals are calibrated).

Then randomised paper-form sessions from a fresh seed (printed; ``--seed`` repeats a
run), each fitted as ``tissuecli fit --forms FORM`` would with the truth's form (grasp
detection on): the paper's four forms drawn by :func:`tissuecli.sim.scenes.random_scene`
(250 Hz-10 kHz, 8-16 bits, force noise 0.5-10 % of its range, grasps with free jaws or
continuous contact, 3-60 s cut at 20,000 samples, slow squeezes to fast taps), grasp
sessions apart by whether detection found their free jaws or read them as one contact;
and noisy sessions in contact throughout (``continuous_contact.py``: an ``x^3`` law, an
8-bit ADC, 250-2000 Hz, force noise up to 10 % of the range). K, S and M are the
stiffness, damping and inertia of each form (``K3`` and ``S2`` pooled with ``K`` and
``S``); refusals are counted.

    python benchmarks/coverage.py --sessions 100 --draws 40 --scenes 200
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Sequence

import numpy as np
from continuous_contact import noisy_contact_truth
from scipy.stats import binom

from tissuecli.core.errors import TissueError
from tissuecli.core.session import Session
from tissuecli.core.terms import Law
from tissuecli.core.tissue import Tissue
from tissuecli.identify import BayesianFit, whiten
from tissuecli.identify.whiten import LIKELIHOODS
from tissuecli.sim.protocols import random_protocol
from tissuecli.sim.scenes import FAMILIES, random_scene
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


#: the paper's four forms among the random scenes' families
PAPER_FAMILIES = [name for name in FAMILIES if name.startswith("paper")]


def _inside(session: Session, law: Law, truth: np.ndarray) -> tuple[np.ndarray, bool]:
    """Which of the coefficients' 95 % intervals hold the truth, the truth's form fitted
    with grasp detection, and whether detection read the session as one contact."""
    est = BayesianFit(forms=law.name, seed=0).fit(session)
    lo, hi = est.best_.posterior.ci95.T
    return (truth >= lo) & (truth <= hi), bool(est.contact_.all_contact)


def _cover_row(label: str, inside: list[np.ndarray], refused: int, cpu: float) -> str:
    """One line: coverage of K, S and M (each form's three coefficients in that order)."""
    if not inside:
        return f"{label:<34} n=0    refused {refused}"
    share = np.mean(np.array(inside), axis=0)
    parts = " ".join(f"{s} {c:.3f}" for s, c in zip("KSM", share, strict=True))
    pooled = f"pooled {np.mean(inside):.3f}"  # three intervals a session: not independent
    return (f"{label:<34} n={len(inside):<4} {band(len(inside))} {parts}  {pooled}  "
            f"refused {refused}  cpu {cpu:.1f} s")  # fmt: skip


def randomised(scenes: int, seed: int) -> None:
    """Coverage over random paper-form scenes and noisy continuous-contact sessions."""
    groups: dict[str, list[np.ndarray]] = {
        "grasps found": [], "grasps read as one contact": [], "continuous contact": [],
    }  # fmt: skip
    refused, c0 = 0, time.process_time()
    for i in range(scenes):
        scene = random_scene(seed + i, families=PAPER_FAMILIES, max_samples=20_000)
        try:
            inside, whole = _inside(scene.session, scene.tissue.law,
                                    np.asarray(scene.coefficients, float))  # fmt: skip
        except TissueError:
            refused += 1
            continue
        if scene.settings["contact"] == "continuous":
            groups["continuous contact"].append(inside)
        else:
            groups["grasps read as one contact" if whole else "grasps found"].append(inside)
    cpu = time.process_time() - c0
    every = [v for g in groups.values() for v in g]
    print(_cover_row("random paper forms, all", every, refused, cpu), flush=True)
    for name, got in groups.items():
        print(_cover_row(f"  {name}", got, 0, 0.0).rsplit("  refused", 1)[0], flush=True)
    inside_c, refused, c0 = [], 0, time.process_time()
    for i in range(scenes):
        session, tissue = noisy_contact_truth(seed + i)
        try:
            inside_c.append(_inside(session, tissue.law, np.asarray(tissue.coef, float))[0])
        except TissueError:
            refused += 1
    print(_cover_row("noisy continuous contact", inside_c, refused,
                     time.process_time() - c0), flush=True)  # fmt: skip


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", type=int, default=100, help="seeds per paper form")
    ap.add_argument("--draws", type=int, default=40, help="draws of each protocol")
    ap.add_argument("--scenes", type=int, default=200,
                    help="random paper-form scenes, and as many in continuous contact")  # fmt: skip
    ap.add_argument("--seed", type=int, help="first seed of the random sessions (fresh if unset)")
    ap.add_argument("--only", choices=["paper", "protocols", "random"],
                    help="one part of the table")  # fmt: skip
    ap.add_argument("--likelihood", choices=sorted(LIKELIHOODS), help="the fits' likelihood")
    args = ap.parse_args(argv)
    if args.likelihood:
        whiten.DEFAULT_LIKELIHOOD = args.likelihood
    seed = args.seed if args.seed is not None else int(np.random.SeedSequence().entropy % 2**31)
    print(f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}; coverage of each "
          "coefficient's 95 % interval (RMS z); [binomial 95 % range]", flush=True)  # fmt: skip
    if args.only in (None, "paper"):
        paper(args.sessions)
    if args.only in (None, "protocols"):
        protocols(args.draws)
    if args.only in (None, "random"):
        print(f"random sessions from seed {seed} (--seed {seed} repeats them)", flush=True)
        randomised(args.scenes, seed)
    print(f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main(sys.argv[1:])
