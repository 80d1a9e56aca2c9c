"""Accuracy and calibration of `fit` on synthetic sessions with known truth.

Usage::

    python benchmarks/fit_accuracy.py --seeds 10 --duration 10

For each true form, rate (250 Hz to 2 kHz) and ADC resolution it draws
sessions with a random operator, fits all four forms and prints: how often the
right form was chosen, the median absolute error of K, S and M, how often the
truth fell inside the 95 % interval, and how often M was flagged.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from tissuecli.core.terms import Law
from tissuecli.core.tissue import Tissue
from tissuecli.identify import BayesianFit
from tissuecli.identify.derivatives import Gaussian
from tissuecli.sim.synth import random_session

TISSUES = [
    Tissue(Law.paper("x", "xdot"), 350.0, 3.0, 0.05),
    Tissue(Law.paper("x^3", "xdot"), 8e6, 3.0, 0.05),
    Tissue(Law.paper("x", "xdot^2"), 350.0, 60.0, 0.05),
    Tissue(Law.paper("x^3", "xdot^2"), 8e6, 60.0, 0.05),
]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--rates", default="250,500,1000,2000")
    ap.add_argument("--bits", default="8,12")
    ap.add_argument(
        "--cutoff-ratio",
        type=float,
        default=None,
        help="Gaussian kernel cutoff over the signal band (default: the fit's)",
    )
    args = ap.parse_args()
    print(
        f"{'form':<11} {'bits':>4} {'rate':>5} {'right':>6} {'|dK| %':>8} {'|dS| %':>8} "
        f"{'|dM| %':>8} {'K in':>5} {'S in':>5} {'M in':>5} {'M flag':>6} {'s/fit':>6}"
    )
    for tissue in TISSUES:
        for bits in (int(b) for b in args.bits.split(",")):
            for rate in (float(r) for r in args.rates.split(",")):
                right, errs, inside, flags, secs = 0, [], [], 0, 0.0
                for seed in range(args.seeds):
                    s, _ = random_session(
                        tissue, rate_hz=rate, seed=seed, duration_s=args.duration, bits=bits
                    )
                    t0 = time.perf_counter()
                    diff = (
                        Gaussian(cutoff_ratio=args.cutoff_ratio)
                        if args.cutoff_ratio
                        else Gaussian()
                    )
                    est = BayesianFit("paper", differentiator=diff).fit(s)
                    secs += time.perf_counter() - t0
                    best = est.best_
                    if best.name != tissue.law.name:
                        continue
                    right += 1
                    post = best.posterior
                    errs.append(np.abs(post.mean - tissue.coef) / tissue.coef * 100)
                    inside.append(
                        (post.ci95[:, 0] <= tissue.coef) & (tissue.coef <= post.ci95[:, 1])
                    )
                    flags += any(f.startswith("M ") for f in best.flags)
                n = args.seeds
                med = np.median(errs, axis=0) if errs else np.full(3, np.nan)
                cov = np.mean(inside, axis=0) if inside else np.full(3, np.nan)
                print(
                    f"{tissue.law.name:<11} {bits:>4} {rate:>5.0f} {right:>3}/{n:<2} "
                    f"{med[0]:8.3f} {med[1]:8.3f} {med[2]:8.2f} {cov[0]:5.2f} {cov[1]:5.2f} "
                    f"{cov[2]:5.2f} {flags:>6} {secs / n:6.3f}",
                    flush=True,
                )


if __name__ == "__main__":
    main()
