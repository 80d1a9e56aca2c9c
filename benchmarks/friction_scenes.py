"""Dry friction fitted and predicted on random continuous-contact scenes: the fitted
damping and friction against the truth, and the held-out force against the noise floor.

Each scene of ``random_scene(seed, families=["friction", "friction+offset"],
contact="continuous", max_samples=N)`` is fitted with its own law on its first 70 %
(the default seed of the fit) and predicted on the rest; the held-out RMS error
against the noise-free force is divided by the floor, the best cubic Savitzky-Golay
smoother of the measured force against the same truth (``generalisation.sg_floor``,
as in ``tests/identify/test_predict_friction.py``).

Usage::

    python benchmarks/friction_scenes.py [--seeds 0-23] [--max-samples 20000]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
from generalisation import sg_floor as floor

from tissuecli.identify import BayesianFit
from tissuecli.sim.scenes import random_scene

FRICTION = ["friction", "friction+offset"]


def scene_figures(seed: int, max_samples: int) -> dict[str, object]:
    """One scene's settings, its S and Fc errors (fractions), how many coefficients'
    95 % intervals hold the truth, and its held-out error over the floor."""
    scene = random_scene(seed, families=FRICTION, max_samples=max_samples, contact="continuous")
    s = scene.session
    i = int(0.7 * len(s))
    fitted = s.replace(s.time[:i], s.force[:i], s.position[:i])
    rest = s.replace(s.time[i:], s.force[i:], s.position[i:])
    forms = "+".join(t.name for t in scene.tissue.law.terms)
    start = time.process_time()
    est = BayesianFit(forms, seed=seed).fit(fitted)
    cpu = time.process_time() - start
    law, coef = est._coefficients()
    truth = dict(zip(scene.tissue.law.symbols, scene.tissue.coef, strict=True))
    sd, ci = est._uncertainty()
    err, z, inside = {}, {}, {}
    for j, sym in enumerate(law.symbols):
        err[sym] = float(coef[j] / truth[sym] - 1)
        z[sym] = float((coef[j] - truth[sym]) / sd[j])
        inside[sym] = bool(ci[j][0] <= truth[sym] <= ci[j][1])
    held = scene.force[i:]
    pred = est.predict(rest)
    ok = np.isfinite(pred)
    ratio = float(np.sqrt(np.mean((pred[ok] - held[ok]) ** 2))) / floor(rest.force, held)
    return {
        "seed": seed,
        "excitation": scene.settings["excitation"],
        "rate_hz": float(scene.settings["rate_hz"]),
        "bits": int(scene.settings["bits"]),
        "S": err.get("S", float("nan")),
        "Fc": err.get("Fc", float("nan")),
        "zS": z.get("S", float("nan")),
        "zFc": z.get("Fc", float("nan")),
        "inside": sum(inside.values()),
        "terms": len(inside),
        "ratio": ratio,
        "cpu": cpu,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0-23", help="a range a-b or a list 0,2,21")
    ap.add_argument("--max-samples", type=int, default=20_000)
    args = ap.parse_args()
    if "-" in args.seeds:
        lo, hi = (int(v) for v in args.seeds.split("-"))
        seeds = list(range(lo, hi + 1))
    else:
        seeds = [int(v) for v in args.seeds.split(",")]
    print(f"load average {os.getloadavg()[0]:.1f}")
    print(f"{'seed':>4} {'excitation':<14} {'rate Hz':>8} {'bits':>4} "
          f"{'S err':>8} {'Fc err':>8} {'z S':>6} {'z Fc':>6} {'in 95 %':>7} "
          f"{'held/floor':>10} {'cpu s':>6}")  # fmt: skip
    rows = []
    for seed in seeds:
        r = scene_figures(seed, args.max_samples)
        rows.append(r)
        print(f"{seed:>4} {r['excitation']:<14} {r['rate_hz']:>8.0f} {r['bits']:>4} "
              f"{r['S']:>+8.1%} {r['Fc']:>+8.1%} {r['zS']:>+6.2f} {r['zFc']:>+6.2f} "
              f"{r['inside']:>5}/{r['terms']:<1} {r['ratio']:>10.2f} {r['cpu']:>6.2f}",
              flush=True)  # fmt: skip
    ratio = np.array([r["ratio"] for r in rows])
    s_err = np.abs([r["S"] for r in rows])
    fc_err = np.abs([r["Fc"] for r in rows])
    inside = sum(int(r["inside"]) for r in rows)  # type: ignore[call-overload]
    terms = sum(int(r["terms"]) for r in rows)  # type: ignore[call-overload]
    print(f"held/floor: median {np.median(ratio):.2f}, 90th percentile "
          f"{np.percentile(ratio, 90):.2f}, within 1.5: {int(np.sum(ratio <= 1.5))}/{ratio.size}; "
          f"|S err| median {np.nanmedian(s_err):.1%}, max {np.nanmax(s_err):.1%}; "
          f"|Fc err| median {np.nanmedian(fc_err):.1%}, max {np.nanmax(fc_err):.1%}; "
          f"coefficients inside their 95 % interval {inside}/{terms}")  # fmt: skip
    print(f"load average {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
