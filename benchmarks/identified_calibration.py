"""Is the "not identified" verdict calibrated? A relaxation branch's stiffness Km1 judged
on simulated sessions where the branch is present and well excited (it must be called
identified), absent (the data cannot pin it: not identified, but in about 2.5 % of
sessions, the share of an absent term's unbounded 95 % intervals that miss zero), and
weak, each fitted with the branch in its law at two seeds (the verdict must not
depend on the seed).

Usage::

    python benchmarks/identified_calibration.py [--chain 8] [--grid 100] [--scenes LIST]

``chain``: contact+maxwell+xddot (three shape parameters: its shape sampled by emcee,
the coefficients' posterior pooled over the chain's draws), Hunt-Crossley contact
(Kc 5000 N/m^1.5, n 1.5, x0 1 mm), tau1 0.3 s, 6 s at 250 Hz. ``grid``:
x+maxwell+xdot+xddot (one shape parameter, a quadrature grid), K 300 N/m, tau1 0.5 s,
S 2 N s/m, 10 s at 500 Hz. Both 12-bit, force noise 50 mN, the random operator of each
session's seed (100, 101, ...); Km1 200 N/m (present), 0 (absent), and weak: about
three posterior SDs (5 N/m with the chain, 1.5 N/m on the grid). Beside each verdict's
count is what an SD-based verdict (SD above half the mean, over the same draws) gives.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from tissuecli.core.terms import Law
from tissuecli.core.tissue import Tissue
from tissuecli.identify import fit_session
from tissuecli.identify.diagnostics import unidentified
from tissuecli.sim.synth import random_session

#: Km1 of each scene, N/m
SCENES = {"present": 200.0, "absent": 0.0, "weak": {"chain": 5.0, "grid": 1.5}}

PARTS = {
    "chain": dict(
        law=Law.of(["contact", "maxwell", "xddot"]),
        shape={"n": 1.5, "x0": 1e-3, "tau1": 0.3},
        coefficients=lambda km: (5000.0, km, 0.05),
        rate_hz=250.0,
        duration_s=6.0,
    ),
    "grid": dict(
        law=Law.of(["x", "maxwell", "xdot", "xddot"]),
        shape={"tau1": 0.5},
        coefficients=lambda km: (300.0, km, 2.0, 0.05),
        rate_hz=500.0,
        duration_s=10.0,
    ),
}


def verdicts(part: str, km: float, seed: int, fit_seeds: tuple[int, ...]) -> list[dict]:
    """Fit one session with the branch in its law at each of ``fit_seeds``."""
    spec = PARTS[part]
    tissue = Tissue(spec["law"].bind(spec["shape"]), *spec["coefficients"](km))
    session, _ = random_session(
        tissue,
        rate_hz=spec["rate_hz"],
        duration_s=spec["duration_s"],
        seed=seed,
        bits=12,
        force_noise_n=0.05,
    )
    out = []
    for fs in fit_seeds:
        start = time.process_time()
        best = fit_session(session, forms=spec["law"].name, seed=fs).bayes.best_
        cpu = time.process_time() - start
        j = [t.name for t in best.model.terms].index("maxwell")
        post = best.posterior
        lo, hi = post.ci95[j]
        out.append(
            {
                "identified": j not in unidentified(best),
                "sd_verdict": not post.sd[j] > 0.5 * abs(post.mean[j]),
                "ratio": lo / hi if hi > 0 else 0.0,
                "below": float(post.below_zero[j]) if post.below_zero is not None else np.nan,
                "cpu": cpu,
            }
        )
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--chain", type=int, default=8, help="Sessions of each chain scene.")
    parser.add_argument("--grid", type=int, default=100, help="Sessions of each grid scene.")
    parser.add_argument("--scenes", default=",".join(SCENES), help="Scenes to run.")
    args = parser.parse_args()
    print(f"load average {', '.join(f'{v:.1f}' for v in os.getloadavg())}", flush=True)
    for part in ("grid", "chain"):
        n = getattr(args, part)
        for scene in args.scenes.split(",") if n else ():
            value = SCENES[scene]
            km = value[part] if isinstance(value, dict) else value
            rows = [verdicts(part, km, 100 + s, (0, 1)) for s in range(n)]
            ident = [sum(r[k]["identified"] for r in rows) for k in (0, 1)]
            sd = [sum(r[k]["sd_verdict"] for r in rows) for k in (0, 1)]
            flips = sum(r[0]["identified"] != r[1]["identified"] for r in rows)
            sd_flips = sum(r[0]["sd_verdict"] != r[1]["sd_verdict"] for r in rows)
            ratio = np.median([x["ratio"] for r in rows for x in r])
            below = np.median([x["below"] for r in rows for x in r])
            cpu = np.median([x["cpu"] for r in rows for x in r])
            print(
                f"{part} {scene} (Km1 {km:g} N/m), {len(rows)} sessions: identified "
                f"{ident[0]} and {ident[1]} (fit seeds 0, 1), verdict differs in {flips}; "
                f"SD verdict {sd[0]} and {sd[1]}, differs in {sd_flips}; median lo/hi "
                f"{ratio:.3g}, below zero {below:.3g}; CPU median {cpu:.1f} s",
                flush=True,
            )
    print(f"load average {', '.join(f'{v:.1f}' for v in os.getloadavg())}", flush=True)


if __name__ == "__main__":
    main()
