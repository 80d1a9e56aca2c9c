"""Coverage of the intervals on grasp sessions whose free jaws are found, by coefficient.

Random paper-form scenes with grasps (``random_scene(seed, contact="grasps")``, seeds
``--seed`` on), each fitted with its own form and grasp detection; sessions read as one
contact are left out (their misses are the detector's). For K, S and M: the share of 95 %
intervals that hold the truth, the mean and RMS of ``(mean - truth) / sd``, over all
sessions and by ADC bits, rate and tempo. ``--bits 16`` draws the same scenes with a
16-bit ADC (the quantisation apart; everything else is drawn alike). ``--staircase``
reports M again with the errors-in-variables correction of the acceleration column taken
from the ADC's staircase rather than from white noise of the step's variance: the mean
energy of ``k_a * (Q(x_s + u + n) - x_s)`` over 16 draws of the grid's phase ``u`` and
of the analog noise ``n`` left beside the step (``x_s`` a cubic Savitzky-Golay smoothing
of the closure, ``k_a`` the acceleration kernel), its interval from the corrected
sandwich (a diagnostic, not the fit's method). ``--parts`` parts M's error by source:
each scene fitted again with the true closure (no ADC, no position noise; the measured
force), and with the true force (the measured closure), each against the truth in the
first fit's SDs, and the first with the true closure in its own SDs.

    python benchmarks/grasp_coverage.py --scenes 200
    python benchmarks/grasp_coverage.py --scenes 200 --bits 16
    python benchmarks/grasp_coverage.py --scenes 200 --parts
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Sequence

import numpy as np
from scipy.signal import savgol_filter
from scipy.stats import binom

from tissuecli.core.session import Session
from tissuecli.identify import BayesianFit
from tissuecli.identify.derivatives.base import convolve_valid
from tissuecli.identify.design import design, eiv_correction, position_noise_sd
from tissuecli.sim.scenes import FAMILIES, random_scene

PAPER_FAMILIES = [name for name in FAMILIES if name.startswith("paper")]


def band(n: int) -> str:
    """The range a calibrated interval's coverage falls in 95 % of the time."""
    lo, hi = binom.ppf([0.025, 0.975], n, 0.95) / n
    return f"[{lo:.2f},{hi:.2f}]"


def line(label: str, z: np.ndarray) -> str:
    """Coverage, mean z and RMS z of K, S and M."""
    if z.size == 0:
        return f"{label:<22} n=0"
    cover = np.mean(np.abs(z) <= 1.959964, axis=0)
    parts = " ".join(f"{s} {c:.3f} (z {m:+.2f}, rms {r:.2f})" for s, c, m, r in
                     zip("KSM", cover, z.mean(axis=0), np.sqrt(np.mean(z**2, axis=0)),
                         strict=True))  # fmt: skip
    return f"{label:<22} n={len(z):<4} {band(len(z))} {parts}"


def staircase_z(est: BayesianFit, truth: np.ndarray) -> float:
    """M's z with the acceleration column's correction from the ADC's staircase."""
    law, kin, sx = est.best_.model, est.kinematics_, est.sigma_x_
    x = est.session_.position
    q = est.session_.adc.step("position") if est.session_.adc is not None else 0.0
    fs = 1.0 / float(np.median(np.diff(est.session_.time)))
    analog = np.sqrt(max(position_noise_sd(x, fs) ** 2 - q**2 / 12, 0.0))
    smooth = savgol_filter(x, kin.kernels[0].size | 1, 3, mode="interp")
    rng = np.random.default_rng(0)
    energy = 0.0
    for _ in range(16):
        z = smooth + rng.uniform(-q / 2, q / 2) + rng.normal(0.0, analog, x.size)
        e = (q * np.round(z / q) if q > 0 else z) - smooth
        ea = kin._rows(convolve_valid(e, kin.kernels[2]))
        energy += float(ea @ ea) / 16
    A = design(law, kin, x, sx)
    G, b = A.T @ A, A.T @ kin.force
    C = eiv_correction(law, kin, x, sx)
    C2 = C.copy()
    C2[2, 2] = energy
    post = est.best_.posterior
    shift = np.linalg.solve(G - C2, b)[2] - np.linalg.solve(G - C, b)[2]
    var = [np.diag(np.linalg.pinv(G - c) @ G @ np.linalg.pinv(G - c))[2] for c in (C, C2)]
    sd = post.sd[2] * np.sqrt(var[1] / var[0])
    return float((post.mean[2] + shift - truth[2]) / sd)


def error_parts(scene, est: BayesianFit, truth: np.ndarray) -> tuple[float, float, float]:
    """M's z fitted with the true closure (no ADC, no position noise) in its own SD and
    in the first fit's, and fitted with the true force (the measured closure) in the
    first fit's SD: the force noise's share of the error, and the closure's."""
    s, law, sd = scene.session, scene.tissue.law.name, est.best_.posterior.sd[2]
    closure = BayesianFit(forms=law, seed=0).fit(Session(s.time, s.force, scene.x)).best_
    force = BayesianFit(forms=law, seed=0).fit(s.replace(s.time, scene.force, s.position))
    m = closure.posterior.mean[2] - truth[2]
    return (m / closure.posterior.sd[2], m / sd,
            (force.best_.posterior.mean[2] - truth[2]) / sd)  # fmt: skip


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=200, help="grasp scenes drawn")
    ap.add_argument("--seed", type=int, default=9000, help="first seed")
    ap.add_argument("--bits", type=int, help="impose this ADC resolution")
    ap.add_argument("--staircase", action="store_true",
                    help="also M with the staircase's correction")  # fmt: skip
    ap.add_argument("--parts", action="store_true",
                    help="also M with the true closure, and with the true force")  # fmt: skip
    args = ap.parse_args(argv)
    fixed = {"bits": args.bits} if args.bits else {}
    imposed = f"; {args.bits} bits" if fixed else ""
    print(f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}; seeds "
          f"{args.seed}-{args.seed + args.scenes - 1}{imposed}", flush=True)  # fmt: skip
    rows, c0 = [], time.process_time()
    for seed in range(args.seed, args.seed + args.scenes):
        scene = random_scene(seed, families=PAPER_FAMILIES, max_samples=20_000,
                             contact="grasps", **fixed)  # fmt: skip
        est = BayesianFit(forms=scene.tissue.law.name, seed=0).fit(scene.session)
        if est.contact_.all_contact:
            continue
        post = est.best_.posterior
        truth = np.asarray(scene.coefficients, float)
        z = (post.mean - truth) / post.sd
        st = scene.settings
        zs = staircase_z(est, truth) if args.staircase else np.nan
        parts = error_parts(scene, est, truth) if args.parts else (np.nan,) * 3
        rows.append((*z, st["bits"], st["rate_hz"], st["tempo"], zs, *parts))
    d = np.array(rows)
    z, bits, rate, tempo = d[:, :3], d[:, 3], d[:, 4], d[:, 5]
    print(line("grasps found", z) + f"  cpu {time.process_time() - c0:.1f} s")
    groups = [("  8-13 bits", bits < 14), ("  14-16 bits", bits >= 14),
              ("  below 700 Hz", rate < 700), ("  700-2700 Hz", (rate >= 700) & (rate < 2700)),
              ("  above 2700 Hz", rate >= 2700), ("  tempo above 1.5", tempo > 1.5)]  # fmt: skip
    for label, m in groups:
        print(line(label, z[m]))
    if args.staircase:
        zs = np.column_stack([z[:, :2], d[:, 6]])
        print("M with the staircase's correction (K and S as above):")
        for label, m in [("grasps found", bits > 0), *groups]:
            print(line(label, zs[m]))
    if args.parts:
        for k, what in enumerate(("the true closure, in its own SDs",
                                  "the true closure, in the first fit's SDs",
                                  "the true force, in the first fit's SDs")):  # fmt: skip
            zp = np.column_stack([z[:, :2], d[:, 7 + k]])
            print(f"M with {what} (K and S as above):")
            for label, m in [("grasps found", bits > 0), *groups]:
                print(line(label, zp[m]))
    print(f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main(sys.argv[1:])
