"""Grasp sessions fitted from streamed sums (:class:`~tissuecli.identify.stream.StreamedFit`)
against the same sessions fitted in memory (:class:`~tissuecli.identify.BayesianFit`):
the laws each chooses, the filtered samples each fits, and the largest difference of a
coefficient's posterior mean in the in-memory posterior SDs.

Usage::

    python benchmarks/streamed_grasps.py [--seconds 90] [--pilot 30000] [--block 20000]
        [--forms paper]

The simulated forceps grasping at 1 kHz through a 12-bit ADC (3 s grasps, 1 s of free
jaws), four sensor settings: force noise 5 mN and no offset; 20 mN and a 50 mN offset;
1 mN (its ADC not dithered) and a 100 mN offset; 10 mN and a 100 mN offset with the
jaws resting open inside the position range (the open jaws fitted for the offset). The
pilot is a stretch of the session; the load average is printed.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from tissuecli.core.session import Session
from tissuecli.identify import BayesianFit
from tissuecli.identify.stream import StreamedFit
from tissuecli.sim.synth import ForcepsModel, GraspingOperator, Sensors, synthesize

#: force noise (N), force offset (N), how far short of the tissue the jaws open (m)
SETTINGS = [(0.005, 0.0, 2e-3), (0.02, 0.05, 2e-3), (0.001, 0.1, 2e-3), (0.01, 0.1, 3e-4)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=90.0)
    ap.add_argument("--pilot", type=int, default=30_000)
    ap.add_argument("--block", type=int, default=20_000)
    ap.add_argument("--forms", default="paper")
    args = ap.parse_args()
    print(f"load average {', '.join(f'{v:.2f}' for v in os.getloadavg())}")
    print("| noise, offset, open | in memory | streamed | rows in memory / streamed | "
          "max abs(mean diff) / SD | CPU s in memory / streamed |")  # fmt: skip
    print("| --- | --- | --- | --- | --- | --- |")
    for seed, (noise, offset, open_m) in enumerate(SETTINGS):
        model = ForcepsModel(
            operator=GraspingOperator(open_m=open_m),
            sensors=Sensors(bits=12, force_noise_n=noise, force_offset_n=offset),
            seed=seed,
        )
        session, _ = synthesize(model, args.seconds)

        def read(a: int, b: int, s: Session = session) -> Session:
            return s.replace(s.time[a:b], s.force[a:b], s.position[a:b])

        t0 = time.process_time()
        full = BayesianFit(forms=args.forms).fit(session)
        t1 = time.process_time()
        fit = StreamedFit(args.pilot, args.block, bayes={"forms": args.forms}).fit(
            read, len(session)
        )
        t2 = time.process_time()
        z = "-"
        if fit.best_.name == full.best_.name:
            a, b = full.best_.posterior, fit.best_.posterior
            z = f"{float(np.max(np.abs(a.mean - b.mean) / a.sd)):.3f}"
        print(
            f"| {noise * 1e3:g} mN, {offset * 1e3:g} mN, {open_m * 1e3:g} mm | "
            f"{full.best_.name} | {fit.best_.name} | {full.kinematics_.time.size:,} / "
            f"{fit.n_samples_:,} | {z} | {t1 - t0:.1f} / {t2 - t1:.1f} |"
        )


if __name__ == "__main__":
    main()
