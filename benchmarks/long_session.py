"""Time and peak memory of the fit of one long session.

Usage::

    python benchmarks/long_session.py --samples 1e7            # in memory, all four forms
    python benchmarks/long_session.py --samples 1e8 --stored   # tissuecli fit FILE.h5
    python benchmarks/long_session.py --samples 1e7 --stored --grasps

The first draws the session in memory and fits the paper's four forms on it: the
run time, the peak resident memory after drawing the session and after fitting it,
and the answer. ``--stored`` writes the session block by block into an HDF5 file
(never holding it whole), then runs ``tissuecli fit`` on it in a child process, as a
user would: above a few million samples the command fits from sums streamed block by
block, and the child's peak memory is what the fit needs. ``--grasps``: the forceps
grasps and lets go (3 s grasps, 1 s of free jaws resting open inside the position
range) through a 12-bit ADC, the force sensor reading an offset of 0.1 N and noise
that dithers its ADC, so the fit keeps to the grasps, their edges and the open jaws.
"""

from __future__ import annotations

import argparse
import os
import re
import resource
import subprocess
import sys
import tempfile
import time

from tissuecli.identify import BayesianFit
from tissuecli.sim.synth import ForcepsModel, GraspingOperator, Sensors, synthesize


def peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # kB on Linux


def model(grasps: bool) -> ForcepsModel:
    """The simulated forceps: squeezing the tissue throughout, or grasping it."""
    if not grasps:
        return ForcepsModel(seed=1)
    return ForcepsModel(
        operator=GraspingOperator(open_m=3e-4),
        sensors=Sensors(bits=12, force_noise_n=0.01, force_offset_n=0.1),
        seed=1,
    )


def stored(n: int, grasps: bool = False) -> None:
    """Write ``n`` samples of the simulated forceps block by block, then fit the file
    with the command line in a child process and print its time and peak memory."""
    from tissuecli.formats.sessions import session_writer
    from tissuecli.sim.synth import CLOCK_HZ

    forceps = model(grasps)
    cal = forceps.sensors.calibration
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "long.h5")
        t0 = time.perf_counter()
        writer = session_writer(
            path, "long", meta={"rate_hz": forceps.rate_hz}, calibration=None, raw=False,
            fsync=False,
        )  # fmt: skip
        with writer:
            block = 1_000_000
            for a in range(0, n, block):
                ticks, counts = forceps.samples(a, min(a + block, n))
                writer.append(
                    {
                        "time": ticks / CLOCK_HZ,
                        "force": cal.force.to_si(counts[:, 0]),
                        "position": cal.position.to_si(counts[:, 1]),
                    }
                )
        written = time.perf_counter() - t0
        t0 = time.perf_counter()
        done = subprocess.run(
            [sys.executable, "-m", "tissuecli", "fit", path], capture_output=True, text=True
        )
        seconds = time.perf_counter() - t0
        child = resource.getrusage(resource.RUSAGE_CHILDREN)
        peak = child.ru_maxrss / 1024
        lines = (done.stdout + done.stderr).strip().splitlines()
        print(f"{n} samples written in {written:.1f} s ({os.path.getsize(path) / 1e9:.2f} GB)")
        print(
            f"tissuecli fit: exit {done.returncode} in {seconds:.1f} s (CPU "
            f"{child.ru_utime + child.ru_stime:.1f} s); child peak memory "
            f"{peak:.0f} MB; load average {', '.join(f'{v:.2f}' for v in os.getloadavg())}"
        )
        # the grasps, one line each, are left out: the law and its figures are kept
        listed = re.compile(r"^\s*\*?\s*\d+\s+[\d.]+-[\d.]+ s")
        print("\n".join([line for line in lines if not listed.match(line)][:12]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=float, default=1e7)
    ap.add_argument("--stored", action="store_true", help="fit an HDF5 file with the CLI")
    ap.add_argument("--grasps", action="store_true", help="grasps with free jaws between")
    args = ap.parse_args()
    n = int(args.samples)
    if args.stored:
        stored(n, args.grasps)
        return
    session, truth = synthesize(model(args.grasps), n / 1000.0)
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
