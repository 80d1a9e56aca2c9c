"""Time and peak memory of the default fit on one long session.

Usage::

    python benchmarks/long_session.py --samples 1e7

Prints the run time, the process's peak resident memory after drawing the
session and after fitting it, and the answer.
"""

from __future__ import annotations

import argparse
import resource
import time

from tissuecli.identify import BayesianFit
from tissuecli.sim.synth import ForcepsModel, synthesize


def peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # kB on Linux


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=float, default=1e7)
    n = int(ap.parse_args().samples)
    session, truth = synthesize(ForcepsModel(seed=1), n / 1000.0)
    del truth
    data_mb = peak_mb()
    t0 = time.perf_counter()
    est = BayesianFit("paper").fit(session)
    seconds = time.perf_counter() - t0
    print(
        f"{n} samples: fit in {seconds:.1f} s; peak memory {peak_mb():.0f} MB "
        f"({data_mb:.0f} MB after drawing the session); {est.best_.name}, "
        f"K = {est.best_.posterior.mean[0]:.4f} N/m"
    )


if __name__ == "__main__":
    main()
