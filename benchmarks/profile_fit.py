"""Where the CPU time of one default fit of a long session goes: the fit of ``SECONDS``
of the simulated forceps at 10 kHz (default 60 s, 600,000 samples) under cProfile,
its CPU seconds, the laws scored, the shape nodes evaluated and the functions of
most cumulative time. Run it at two lengths to see how each part scales.

``--scene hunt-crossley-12bit`` profiles instead the noisy 12-bit Hunt-Crossley session
of ``decimated_fit.py`` (its closure flickers over hundreds of ADC levels in each filter
window).

Usage::

    python benchmarks/profile_fit.py [--scene SCENE] [SECONDS]
"""

from __future__ import annotations

import cProfile
import os
import pstats
import sys
import time

from tissuecli.identify import BayesianFit
from tissuecli.sim.synth import ForcepsModel, synthesize


def main() -> None:
    args = sys.argv[1:]
    if "-h" in args or "--help" in args:
        print(__doc__)
        return
    from decimated_fit import SCENES, take_scene  # the same sessions, beside this file

    scene = take_scene(args)
    seconds = float(args[0]) if args else 60.0
    session = SCENES[scene](seconds)
    BayesianFit().fit(synthesize(ForcepsModel(seed=1), 2.0)[0])  # loads SciPy
    print("load average " + ", ".join(f"{v:.1f}" for v in os.getloadavg()))
    profile = cProfile.Profile()
    c0 = time.process_time()
    profile.enable()
    fit = BayesianFit().fit(session)
    profile.disable()
    cpu = time.process_time() - c0
    stats = pstats.Stats(profile)
    calls = {f"{k[0].rsplit('/', 1)[-1]}:{k[2]}": v for k, v in stats.stats.items()}  # type: ignore[attr-defined]
    shaped = calls.get("shaped.py:exact_shaped", (0,))[0]
    nodes = calls.get("shaped.py:parts", (0,))[0]  # each distinct shape node once
    print(
        f"{len(session)} samples: CPU {cpu:.2f} s, {len(fit.results_)} laws kept, "
        f"{shaped} laws with shape parameters scored, {nodes} shape nodes evaluated"
    )
    stats.sort_stats("cumulative").print_stats(25)


if __name__ == "__main__":
    main()
