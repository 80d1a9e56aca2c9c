"""Online identification against the offline fit of the same data: how soon a grasp's
estimate settles, agreement at the end, CPU cost, and a change of tissue.

Usage::

    python benchmarks/online.py [--quick]

Sessions come from the simulated forceps' physics (sim.synth): a surgeon's grasps
(``GraspingOperator``: 1 s free, 3 s grasp) of the default tissue (K 350 N/m, S 3 N s/m,
M 0.05 kg), 8-bit ADC, fed to :class:`~tissuecli.identify.online.OnlineFit` in blocks of
25 ms as ``record`` hands them over, with ``estimate()`` asked after every block. CPU
is process time per second of data (a fraction of one core); the offline fit
(``BayesianFit(forms="paper")``) of the same session is timed in the same run.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from tissuecli.core.tissue import DEFAULT_TISSUE, Tissue
from tissuecli.identify.bayes import BayesianFit
from tissuecli.identify.online import OnlineFit
from tissuecli.sim.synth import ForcepsModel, GraspingOperator, synthesize

SOFT = Tissue(DEFAULT_TISSUE.law, 200.0, 2.0, 0.05)
GRASP = GraspingOperator()
BLOCK_S = 0.025


def session(tissue: Tissue, seconds: float, rate_hz: float, seed: int):
    model = ForcepsModel(tissue=tissue, operator=GRASP, rate_hz=rate_hz, seed=seed)
    return synthesize(model, seconds)[0]


def offline(s) -> tuple[np.ndarray, float]:
    """The offline fit's posterior means and its process time (s)."""
    t0 = time.process_time()
    fit = BayesianFit(forms="paper").fit(s)
    return fit.best_.posterior.mean, time.process_time() - t0


def stream(fit: OnlineFit, x, f, rate_hz: float, t_start: float = 0.0):
    """Feed blocks; yield (time of the newest sample received, estimate) after each."""
    n = max(1, int(round(BLOCK_S * rate_hz)))
    for i in range(0, x.size, n):
        fit.update(x[i : i + n], f[i : i + n])
        yield t_start + (min(i + n, x.size) - 1) / rate_hz, fit.estimate()


def settle_times(trace, target: np.ndarray, since: float, tol: float = 0.05):
    """Seconds after ``since`` until each coefficient is within ``tol`` of ``target``
    and stays there to the end of the trace (nan if never), and until confident."""
    out = []
    for j in range(target.size):
        t_in = math.nan
        for t, est in trace:
            if t < since:
                continue
            ok = est is not None and abs(est.mean[j] / target[j] - 1) <= tol
            if ok and math.isnan(t_in):
                t_in = t
            elif not ok:
                t_in = math.nan
        out.append(t_in - since)
    # confident about the new values: confident, and K within tol
    conf = next((t - since for t, e in trace if t >= since and e is not None and e.confident
                 and abs(e.mean[0] / target[0] - 1) <= tol), math.nan)  # fmt: skip
    return out, conf


def first_grasp(rate_hz: float) -> None:
    s = session(DEFAULT_TISSUE, 4.0 + GRASP.free_s, rate_hz, seed=11)
    ref, _ = offline(s)
    fit = OnlineFit(rate_hz=rate_hz)
    trace = list(stream(fit, s.position, s.force, rate_hz))
    times, conf = settle_times(trace, ref, since=GRASP.free_s)
    est = trace[-1][1]
    print(f"\nfirst grasp at {rate_hz:g} Hz (starts at t = {GRASP.free_s:g} s; 3 s grasp):")
    print("  time from the grasp's start until within 5 % of the offline fit, and staying:")
    for name, t in zip(("K", "S", "M"), times, strict=True):
        print(f"    {name}: {t:.2f} s")
    print(f"  confident after {conf:.2f} s")
    print("  at the end:  " + "  ".join(
        f"{n} {e:.4g} vs {r:.4g} ({100 * (e / r - 1):+.2f} %)"
        for n, e, r in zip(("K", "S", "M"), est.mean, ref, strict=True)))  # fmt: skip


def agreement_and_cost(rate_hz: float, seconds: float) -> None:
    s = session(DEFAULT_TISSUE, seconds, rate_hz, seed=12)
    ref, t_off = offline(s)
    rows = []
    for forgetting in (5.0, math.inf):
        fit = OnlineFit(rate_hz=rate_hz, forgetting_s=forgetting)
        t0 = time.process_time()
        for _ in stream(fit, s.position, s.force, rate_hz):
            pass
        cpu = time.process_time() - t0
        est = fit.estimate()
        rows.append((forgetting, est, cpu))
    # the updates alone (no estimate asked)
    fit = OnlineFit(rate_hz=rate_hz)
    n = max(1, int(round(BLOCK_S * rate_hz)))
    t0 = time.process_time()
    for i in range(0, s.time.size, n):
        fit.update(s.position[i : i + n], s.force[i : i + n])
    t_upd = time.process_time() - t0
    print(f"\n{seconds:g} s of grasps at {rate_hz:g} Hz, {BLOCK_S * 1e3:g} ms blocks "
          f"(offline fit K {ref[0]:.4g}, S {ref[1]:.4g}, M {ref[2]:.4g}):")  # fmt: skip
    for forgetting, est, cpu in rows:
        pairs = zip(("K", "S", "M"), est.mean, ref, strict=True)
        diff = "  ".join(f"{n} {100 * (e / r - 1):+.2f} %" for n, e, r in pairs)
        print(f"  forgetting {forgetting:g} s: end against offline {diff};  "
              f"CPU {100 * cpu / seconds:.2f} % of a core")  # fmt: skip
    print(f"  updates alone: {100 * t_upd / seconds:.2f} % of a core")
    print(f"  offline fit of the whole session: {t_off:.3f} s CPU "
          f"({100 * t_off / seconds:.2f} % of a core per second of data, once)")  # fmt: skip


def switch(rate_hz: float) -> None:
    a = session(DEFAULT_TISSUE, 12.0, rate_hz, seed=13)
    b = session(SOFT, 20.0, rate_hz, seed=14)
    ref_b, _ = offline(b)
    x, f = np.concatenate([a.position, b.position]), np.concatenate([a.force, b.force])
    print(f"\ntissue switch at t = 12 s (K 350 -> 200 N/m, S 3 -> 2 N s/m), {rate_hz:g} Hz;")
    print("  seconds after the new tissue's first grasp begins (t = 13 s) until within 5 % "
          "of its offline fit, and staying:")  # fmt: skip
    for forgetting in (1.0, 2.0, 5.0):
        fit = OnlineFit(rate_hz=rate_hz, forgetting_s=forgetting)
        trace = list(stream(fit, x, f, rate_hz))
        times, conf = settle_times(trace, ref_b, since=12.0 + GRASP.free_s)
        print(f"  forgetting {forgetting:g} s: K {times[0]:.2f} s, S {times[1]:.2f} s, "
              f"M {times[2]:.2f} s; confident with K within 5 % after {conf:.2f} s")  # fmt: skip


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="shorter sessions")
    args = ap.parse_args(argv)
    first_grasp(1000.0)
    agreement_and_cost(1000.0, 10.0 if args.quick else 60.0)
    agreement_and_cost(10000.0, 5.0 if args.quick else 20.0)
    switch(1000.0)


if __name__ == "__main__":
    main()
