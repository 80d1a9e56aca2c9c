"""Reported against true spread: one scene's posterior SDs over many noise realisations.

Usage::

    python benchmarks/interval_mc.py --seed 5 --reps 30
    python benchmarks/interval_mc.py --seed 5 --reps 30 --no-eiv

The scene is :func:`tissuecli.sim.scenes.random_scene` of ``--seed`` among the paper's
forms (as ``interval_z.py --families paper`` draws it); every realisation keeps its
tissue, motion and settings and draws the force and position noise afresh
(``noise_seed``). The first 70 % is fitted by ``BayesianFit(forms=<true law>)``, so
no structure choice selects the realisations. For each coefficient it prints the truth,
the mean estimate, the empirical SD of the estimates, the RMS of the reported posterior
SDs, their ratio (1 for honest intervals; the empirical SD's own relative spread is
``1 / sqrt(2 (reps - 1))``), the RMS z and the range of the data weight. ``--no-eiv``
fits without the errors-in-variables correction: the share of the width it carries.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence

import generalisation as gen
import numpy as np

from tissuecli.identify import BayesianFit
from tissuecli.sim.scenes import FAMILIES, random_scene


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=5, help="the scene")
    ap.add_argument("--reps", type=int, default=30, help="noise realisations")
    ap.add_argument("--max-samples", type=int, default=10_000)
    ap.add_argument("--no-eiv", action="store_true", help="fit without the correction")
    args = ap.parse_args(argv)
    paper = [f for f in FAMILIES if f.startswith("paper")]
    means, sds, weights = [], [], []
    scene = random_scene(args.seed, families=paper, max_samples=args.max_samples)
    for i in range(args.reps):
        scene = random_scene(
            args.seed, families=paper, max_samples=args.max_samples, noise_seed=1000 + i
        )
        fitted, _, _ = gen.split(scene.session)
        est = BayesianFit(forms=scene.tissue.law, eiv=not args.no_eiv, seed=i).fit(fitted)
        post = est.best_.posterior
        means.append(post.mean)
        sds.append(post.sd)
        weights.append(est.n_eff_ / est.kinematics_.time.size)
    print(f"{scene.describe()}; law {scene.tissue.law.name}; {args.reps} realisations"
          f"{' without the correction' if args.no_eiv else ''}; data weight "
          f"{min(weights):.3f}-{max(weights):.3f} a row")  # fmt: skip
    m, s, truth = np.array(means), np.array(sds), scene.coefficients
    print(f"{'param':<6} {'truth':>10} {'mean':>10} {'emp SD':>9} {'rep SD':>9} "
          f"{'rep/emp':>7} {'RMS z':>6}")  # fmt: skip
    for j, sym in enumerate(scene.tissue.law.symbols):
        emp = float(np.std(m[:, j], ddof=1))
        rep = float(np.sqrt(np.mean(s[:, j] ** 2)))
        z = (m[:, j] - truth[j]) / s[:, j]
        print(f"{sym:<6} {truth[j]:>10.4g} {np.mean(m[:, j]):>10.4g} {emp:>9.3g} {rep:>9.3g} "
              f"{rep / emp:>7.2f} {np.sqrt(np.mean(z**2)):>6.2f}")  # fmt: skip
    print(f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main(sys.argv[1:])
