"""How close ``predict`` comes to the true force on held-out data of known law, against
the noise floor of a Savitzky-Golay smoother of the measured force.

For each family of :data:`tissuecli.sim.families.FAMILIES` and seed, a 10 s, 12-bit,
1 kHz session is fitted (its own law's terms, ``--hold-out 0.3``) and predicted whole;
over the held-out 30 % the RMS error against the noise-free force is divided by the
floor: the RMS error of a cubic Savitzky-Golay smoother of the measured force, with the
window of the position's signal band. Two predictions: the law on Savitzky-Golay
kinematics (``predict``'s default; each derivative's smoother chosen on the fitted 70 %'s
force) and the force filtered as in a fit (``predict --filtered``).

Usage::

    python benchmarks/predict_floor.py [--seeds 1,2]
"""

from __future__ import annotations

import argparse
import os

import numpy as np
from scipy.signal import savgol_filter

from tissuecli.core.tissue import Tissue
from tissuecli.identify import fit_session
from tissuecli.identify.derivatives import SavitzkyGolay
from tissuecli.identify.predict import predict_band
from tissuecli.sim.families import FAMILIES
from tissuecli.sim.synth import random_session


def ratios(name: str, seed: int) -> tuple[float, float]:
    """Held-out error over the floor: law on Savitzky-Golay kinematics, and filtered."""
    tissue = FAMILIES[name]
    s, model = random_session(tissue, seed=seed, duration_s=10.0, bits=12)
    truth = model.truth(np.arange(len(s)))[3]
    forms = "+".join(t.name for t in tissue.law.terms)
    best = fit_session(s, forms=forms, hold_out=0.3).bayes.best_
    fitted = Tissue(best.model, *best.posterior.mean)
    after = np.arange(len(s)) >= int(0.7 * len(s))
    w = SavitzkyGolay().kernels(s.position, float(np.median(np.diff(s.time))))[0][0].size
    floor = np.sqrt(np.mean((savgol_filter(s.force, w, 3)[after] - truth[after]) ** 2))
    out = []
    for filtered in (False, True):
        # the smoothers are chosen on the fitted part's force, as an estimator does
        pred = predict_band(fitted, s, filtered=filtered, tune=~after).predicted
        e = pred[after] - truth[after]
        out.append(float(np.sqrt(np.mean(e[np.isfinite(e)] ** 2)) / floor))
    return out[0], out[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="1,2")
    args = ap.parse_args()
    seeds = [int(x) for x in args.seeds.split(",")]
    print(f"{'family':<18} {'seed':>4} {'predict / floor':>16} {'--filtered / floor':>19}")
    for name in FAMILIES:
        for seed in seeds:
            raw, filt = ratios(name, seed)
            print(f"{name:<18} {seed:>4} {raw:>16.2f} {filt:>19.2f}", flush=True)
    print(f"load average {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
