"""Quadratic damping's estimates on random scenes that have it: the truth's law as the
default fit scores it, its S2 against the truth in posterior SDs.

Usage::

    python benchmarks/quadratic_damping.py [--seed SEED] [--scenes 24]

Each scene is drawn from the paper's two forms with ``xdot|xdot|``
(:func:`tissuecli.sim.scenes.random_scene`, at most 10,000 samples); its first 70 %
is fitted by ``BayesianFit()``, and the truth's own law, among the laws the fit
scored, gives S2's posterior mean and 95 % interval (SD = width / 3.92). Calibrated
intervals give z-scores of RMS 1 and |z| > 1.96 in 5 % of scenes. The chosen law's
structure (right or wrong, as the generalisation benchmark judges it) is printed beside.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import generalisation as gen  # noqa: E402

from tissuecli.identify import BayesianFit  # noqa: E402
from tissuecli.sim.scenes import random_scene  # noqa: E402

FAMILIES = ("paper x+xdot|xdot|", "paper x^3+xdot|xdot|")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=None, help="repeat a run (default: fresh)")
    ap.add_argument("--scenes", type=int, default=24)
    args = ap.parse_args(argv)
    seed = args.seed if args.seed is not None else int.from_bytes(os.urandom(3), "little")
    print(f"seed {seed}; load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    zs, right = [], 0
    for i in range(args.scenes):
        scene = random_scene(seed + i, families=FAMILIES, max_samples=10_000)
        fitted, _, i0 = gen.split(scene.session)
        est = BayesianFit("all", seed=seed + i).fit(fitted)
        law = gen.chosen_law(est)
        ok = scene.judged_on(i0).right(law)
        right += ok
        truth = dict(zip(scene.tissue.law.symbols, scene.coefficients, strict=True))
        mine = [r for r in est.results_ if r.name == scene.tissue.law.name]
        if not mine or mine[0].posterior is None:
            print(f"[{i}] chosen {law.name} {'right' if ok else 'WRONG'}; truth's law not scored")
            continue
        post = mine[0].posterior
        j = list(mine[0].model.symbols).index("S2")
        sd = (post.ci95[j][1] - post.ci95[j][0]) / 3.92
        z = (float(post.mean[j]) - truth["S2"]) / sd
        zs.append(z)
        verdict = "right" if ok else "WRONG"
        print(f"[{i}] {scene.describe()} chosen {law.name} {verdict}; S2 {post.mean[j]:.4g} "
              f"(truth {truth['S2']:.4g}) z {z:+.2f}", flush=True)  # fmt: skip
    z = np.array(zs)
    print(f"\nload average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print(f"structure right {right}/{args.scenes}; S2 of the truth's law in {z.size} scenes: "
          f"z RMS {np.sqrt(np.mean(z**2)):.2f}, |z| > 1.96 in {np.sum(np.abs(z) > 1.96)}, "
          f"median z {np.median(z):+.2f}")  # fmt: skip


if __name__ == "__main__":
    main()
