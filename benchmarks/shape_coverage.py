"""Coverage of the 95 % intervals of a law with shape parameters, fitted with its own law.

Usage::

    python benchmarks/shape_coverage.py --scenes 40                  # a fresh seed, printed
    python benchmarks/shape_coverage.py --scenes 40 --seed 9300      # repeat a run
    python benchmarks/shape_coverage.py --family "one branch" --scenes 20
    python benchmarks/shape_coverage.py --family "two branches" --contact grasps

Each scene is :func:`tissuecli.sim.scenes.random_scene` of one family (by default
Hunt-Crossley: ``contact+contact*xdot+xddot``, its exponent and contact point shape
parameters), its first 70 % fitted with the truth's law (``BayesianFit(law)``), so that
the structure search plays no part: what is measured is the intervals alone. For each
coefficient and shape parameter it prints how often the 95 % interval holds the truth,
the RMS of ``(mean - truth) / sd`` (1 for calibrated intervals, huge where an interval
collapses to a point) and of the same z capped at 10 (what the bulk of the scenes
says), and, pooled, the range a binomial count of that many calibrated intervals falls
in 95 % of the time. Scenes whose true shape lies outside the prior's range over the
shape are counted apart: no interval inside the prior can hold them. ``--contact``
draws only grasp sessions (free jaws between grasps) or only sessions in contact
throughout.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections import defaultdict
from collections.abc import Sequence

import numpy as np

from tissuecli.core.errors import TissueError
from tissuecli.identify import BayesianFit
from tissuecli.sim.scenes import FAMILIES, random_scene

HOLD_OUT = 0.3


def one(
    seed: int, family: str, max_samples: int, contact: str | None = None
) -> tuple[list[tuple[str, float, bool]], bool]:
    """Per parameter of one scene: name, z of the truth, whether the interval holds it;
    and whether every true shape parameter lies in the prior's range. ``contact``:
    "grasps" or "continuous" (None: either, as drawn)."""
    scene = random_scene(seed, families=[family], max_samples=max_samples, contact=contact)
    s = scene.session
    t = s.time
    i = int(np.searchsorted(t, t[0] + (1.0 - HOLD_OUT) * (t[-1] - t[0])))
    fitted = s.replace(t[:i], s.force[:i], s.position[:i])
    law = "+".join(term.name for term in scene.tissue.law.terms)
    best = BayesianFit(law, seed=seed).fit(fitted).best_
    post = best.posterior
    assert post is not None
    truth = dict(zip(scene.tissue.law.symbols, scene.coefficients, strict=True))
    out = []
    for j, sym in enumerate(best.model.symbols):
        if sym in truth:
            lo, hi = post.ci95[j]
            z = (post.mean[j] - truth[sym]) / post.sd[j] if post.sd[j] > 0 else np.inf
            out.append((sym, float(z), bool(lo <= truth[sym] <= hi)))
    inside = True
    for name, sp in (best.shape_posterior or {}).items():
        if name not in scene.shapes:
            continue
        true = scene.shapes[name]
        z = (sp["mean"] - true) / sp["sd"] if sp["sd"] > 0 else np.inf
        out.append((name, float(z), bool(sp["ci95"][0] <= true <= sp["ci95"][1])))
        lo, hi = (best.shape_ranges or {}).get(name, (-np.inf, np.inf))
        inside &= bool(lo <= true <= hi)
    return out, inside


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=40)
    ap.add_argument("--seed", type=int, default=None, help="first seed (default: fresh)")
    ap.add_argument("--family", default="Hunt-Crossley", choices=sorted(FAMILIES))
    ap.add_argument("--max-samples", type=int, default=10_000,
                    help="longest session drawn (samples)")  # fmt: skip
    ap.add_argument("--contact", choices=("grasps", "continuous"), default=None,
                    help="only grasp sessions, or only sessions in contact throughout")  # fmt: skip
    args = ap.parse_args(argv)
    seed = args.seed if args.seed is not None else int.from_bytes(os.urandom(3), "little")
    from scipy.stats import binom

    print(f"seed {seed} (repeat with --seed {seed}); load average "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}", flush=True)  # fmt: skip
    rows: dict[str, list[tuple[float, bool]]] = defaultdict(list)
    outside: list[int] = []
    refused = 0
    for k in range(args.scenes):
        try:
            got, inside = one(seed + k, args.family, args.max_samples, args.contact)
        except TissueError:
            refused += 1
            continue
        if not inside:
            outside.append(seed + k)
        for name, z, ok in got:
            rows[name].append((z, ok))
    print(f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    pooled = [ok for v in rows.values() for _, ok in v]
    n = len(pooled)
    lo, hi = (binom.ppf(0.025, n, 0.95) / n, binom.ppf(0.975, n, 0.95) / n) if n else (0, 0)
    drawn = f" ({args.contact})" if args.contact else ""
    print(f"{args.family}{drawn}, {args.scenes} scenes from seed {seed}, each fitted with its own "
          f"law; pooled cover {np.mean(pooled):.3f} of {n} [{lo:.2f},{hi:.2f}]; "
          f"refused {refused}")  # fmt: skip
    for name, v in rows.items():
        z = np.array([a for a, _ in v])
        rms = float(np.sqrt(np.mean(z**2)))
        capped = float(np.sqrt(np.mean(np.minimum(np.abs(z), 10.0) ** 2)))
        cover = np.mean([ok for _, ok in v])
        print(f"  {name:<4} n={len(v):<4} cover {cover:.3f}  RMS z {rms:.3g}  "
              f"(capped at 10: {capped:.2f})")  # fmt: skip
    print(f"true shape outside the prior's range: {len(outside)} scenes {outside}")


if __name__ == "__main__":
    main(sys.argv[1:])
