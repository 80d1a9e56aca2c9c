"""Run time of `fit` on a 10 s, 1 kHz session: library calls, report, sampler.

Usage::

    python benchmarks/fit_timing.py

Times (median of 5) exclude Python start-up; benchmarks/startup.py measures that.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from tissuecli.app.fit import write_report
from tissuecli.identify import fit_session
from tissuecli.sim.synth import ForcepsModel, synthesize


def timed(fn, repeat: int = 5) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def main() -> None:
    for duration, rate in ((10.0, 1000.0), (60.0, 1000.0), (60.0, 10000.0)):
        model = ForcepsModel(seed=1, rate_hz=rate)
        s, _ = synthesize(model, duration)
        s.name = "bench"
        exact = timed(lambda s=s: fit_session(s))
        pinv = timed(lambda s=s: fit_session(s, method="pinv", forms="x,xdot"))
        outcome = fit_session(s)
        with tempfile.TemporaryDirectory() as tmp:
            report = timed(lambda o=outcome: write_report(Path(tmp) / "r.html", o), repeat=3)
        emcee = timed(lambda s=s: fit_session(s, sampler="emcee"), repeat=1)
        print(
            f"{duration:4.0f} s at {rate:5.0f} Hz ({len(s):>7} samples): all eight laws exact "
            f"{exact:.3f} s; pinv {pinv:.3f} s; report {report:.3f} s; "
            f"--sampler emcee (+ stepping-stone) {emcee:.1f} s"
        )


if __name__ == "__main__":
    main()
