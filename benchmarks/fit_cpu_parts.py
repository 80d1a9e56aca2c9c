"""Where the CPU time of the default fit of the 10 s, 1 kHz paper-form session goes (the
session of ``time_budget.py`` and ``search_timing.py``, at 16 or 8 bits): the CPU seconds
of each part, summed over the fit, and the calls to it.

Usage::

    python benchmarks/fit_cpu_parts.py [BITS] [REPEATS]

Each part is timed by the CPU clock of the fitting thread (``time.thread_time``) around
the function named beside it, over REPEATS fits (default 3) after a warm-up fit; the
figures are per fit. Parts nest (a shaped law's climbs are inside its scoring, a filter
pass inside a first pass): each figure includes what runs inside it, so they do not add
up. Unlike cProfile, which costs about as much per call as a small NumPy call does and
so inflates the many small ones, these figures are what the fit spends.
"""

from __future__ import annotations

import importlib
import os
import sys
import time
from collections.abc import Callable
from typing import Any

from tissuecli.identify import BayesianFit
from tissuecli.sim.synth import ForcepsModel, Sensors, synthesize

#: (label, module, attribute): the attribute wrapped where its callers look it up
PARTS = [
    ("prepare: filtering, grasps, contact", "tissuecli.identify.bayes", "BayesianFit.prepare"),
    ("linear laws: first passes", "tissuecli.identify.bayes", "first_pass"),
    ("linear laws: evidence and draws", "tissuecli.identify.bayes", "exact_result"),
    ("laws with shape parameters (all of it)", "tissuecli.identify.bayes", "exact_shaped"),
    ("  grid nodes' first passes", "tissuecli.identify.shaped", "ShapedPass._filtered"),
    ("  climbs' first passes", "tissuecli.identify.shaped", "ShapedPass.__call__"),
    ("  tempered statistics", "tissuecli.identify.shaped", "law_stats"),
    ("closed forms over the noise level", "tissuecli.identify.posterior",
     "ExactPosterior.__init__"),  # fmt: skip
    ("rejection draws under the bounds", "tissuecli.identify.posterior",
     "ExactPosterior.truncated"),  # fmt: skip
    ("orthant masses (lattice)", "tissuecli.identify.posterior", "orthant_log_probability"),
    ("filtered columns of the terms", "tissuecli.identify.design", "_column"),
    ("noise paths of the terms", "tissuecli.identify.design", "_noise_path"),
    ("FFT convolutions", "tissuecli.identify.derivatives.base", "convolve_valid"),
    ("blocked cross-validation", "tissuecli.identify.bayes", "cv_scores"),
]


def timed(fn: Callable[..., Any], tally: list[float]) -> Callable[..., Any]:
    """``fn``, adding its calls and the thread's CPU seconds in it to ``tally``."""

    def wrapper(*args: Any, **kwargs: Any) -> Any:
        c0 = time.thread_time()
        try:
            return fn(*args, **kwargs)
        finally:
            tally[0] += 1
            tally[1] += time.thread_time() - c0

    return wrapper


def main() -> None:
    args = sys.argv[1:]
    if "-h" in args or "--help" in args:
        print(__doc__)
        return
    bits = int(args[0]) if args else 16
    repeats = int(args[1]) if len(args) > 1 else 3
    session = synthesize(ForcepsModel(seed=1, sensors=Sensors(bits=bits)), 10.0)[0]
    BayesianFit().fit(session)  # loads SciPy, warms the caches of the closure's levels
    tallies: dict[str, list[float]] = {}
    for label, module, name in PARTS:
        owner: Any = importlib.import_module(module)
        *path, attr = name.split(".")
        for part in path:
            owner = getattr(owner, part)
        tallies[label] = tally = [0, 0.0]
        setattr(owner, attr, timed(getattr(owner, attr), tally))
    print("load average " + ", ".join(f"{v:.1f}" for v in os.getloadavg()))
    total = 0.0
    for _ in range(repeats):
        c0 = time.thread_time()
        fit = BayesianFit().fit(session)
        total += time.thread_time() - c0
    print(f"default fit, 10 s at 1 kHz, {bits}-bit: {fit.best_.name}, "
          f"CPU {total / repeats:.3f} s a fit (mean of {repeats})")  # fmt: skip
    for label, (calls, seconds) in tallies.items():
        print(f"  {label:<42} {seconds / repeats:7.3f} s  {calls / repeats:6.0f} calls")
    print("load average " + ", ".join(f"{v:.1f}" for v in os.getloadavg()))


if __name__ == "__main__":
    main()
