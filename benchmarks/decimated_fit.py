"""The default fit of long sessions scored on every stride-th filtered sample
(:mod:`tissuecli.identify.decimate`) against the same fit scored on every sample: CPU
seconds of each, the stride, the chosen laws, the largest difference of a coefficient's
posterior mean in posterior SDs, the SDs' ratio and the effective samples.

Usage::

    python benchmarks/decimated_fit.py [SECONDS ...]

The simulated forceps at 10 kHz (default 20, 60 and 100 s: 200,000, 600,000 and
1,000,000 samples), each fitted once each way in this process (``time.process_time``);
the load average is printed before each session.
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np

from tissuecli.identify import BayesianFit, decimate
from tissuecli.identify.decimate import fit_stride
from tissuecli.sim.synth import ForcepsModel, synthesize


def fit(session: object, above: int) -> tuple[BayesianFit, float]:
    """The default fit with sessions above ``above`` filtered samples decimated, and its
    CPU seconds."""
    decimate.DECIMATE_ABOVE = above
    c0 = time.process_time()
    out = BayesianFit().fit(session)  # type: ignore[arg-type]
    return out, time.process_time() - c0


def main() -> None:
    seconds = [float(a) for a in sys.argv[1:]] or [20.0, 60.0, 100.0]
    default = decimate.DECIMATE_ABOVE
    BayesianFit().fit(synthesize(ForcepsModel(seed=1), 2.0)[0])  # loads SciPy
    for s in seconds:
        session = synthesize(ForcepsModel(seed=1, rate_hz=10000.0), s)[0]
        print("load average " + ", ".join(f"{v:.1f}" for v in os.getloadavg()), flush=True)
        full, t_full = fit(session, 10**15)
        coarse, t_coarse = fit(session, default)
        stride = fit_stride(coarse.kinematics_)
        pf, pc = full.best_.posterior, coarse.best_.posterior
        same = full.best_.name == coarse.best_.name
        shift = float(np.max(np.abs(pc.mean - pf.mean) / pf.sd)) if same else float("nan")
        ratio = pc.sd / pf.sd if same else np.array([np.nan])
        print(
            f"{len(session)} samples: every sample CPU {t_full:.2f} s ({full.best_.name}, "
            f"{full.n_eff_:.0f} effective); stride {stride} CPU {t_coarse:.2f} s "
            f"({coarse.best_.name}, {coarse.n_eff_:.0f} effective); "
            f"{t_full / t_coarse:.1f}x; largest shift {shift:.4f} SD, SDs x{ratio.min():.3f}-"
            f"{ratio.max():.3f}",
            flush=True,
        )
    decimate.DECIMATE_ABOVE = default


if __name__ == "__main__":
    main()
