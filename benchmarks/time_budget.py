"""CPU time of the fits the run-time goals are set for: the default fit of a 10 s, 1 kHz
paper-form session (goal 0.5 s), the default fit of 600,000 samples (goal 5 s), and the
import and fit of every recording of data/ (goal 10 s each at up to 1e5 samples), as the
recordings' own commands (data/recordings.json) and as a plain ``tissuecli fit FILE``.

Usage::

    python benchmarks/time_budget.py [REPEATS] [--skip-data | --data-only]

CPU seconds of this process (``time.process_time``): on a shared machine wall time
measures the queue. The 10 s session's figure is the median of REPEATS fits (default 5)
after a warm-up fit; the 600,000-sample fit's is the median of three; each recording is
imported and fitted once, in process, through the command line (benchmarks/real_data.py).
The load average is printed before and after. The memory goal (1e7 samples in 1 GB) is
benchmarks/long_session.py's.
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import real_data  # noqa: E402

from tissuecli.identify import BayesianFit  # noqa: E402
from tissuecli.sim.synth import ForcepsModel, Sensors, synthesize  # noqa: E402


def cpu(fn: object) -> float:
    """CPU seconds of one call of ``fn``."""
    c0 = time.process_time()
    fn()  # type: ignore[operator]
    return time.process_time() - c0


def load() -> str:
    return ", ".join(f"{v:.1f}" for v in os.getloadavg())


def main() -> None:
    repeats = int(sys.argv[1]) if len(sys.argv) > 1 and sys.argv[1].isdigit() else 5
    print(f"load average {load()}")
    data_only = "--data-only" in sys.argv
    # the session of benchmarks/search_timing.py, and the simulated forceps' own sensors
    for bits in () if data_only else (16, 8):
        paper = synthesize(ForcepsModel(seed=1, sensors=Sensors(bits=bits)), 10.0)[0]
        cpu(lambda p=paper: BayesianFit().fit(p))  # loads SciPy
        times = [cpu(lambda p=paper: BayesianFit().fit(p)) for _ in range(repeats)]
        print(f"default fit, 10 s at 1 kHz, {bits}-bit ({len(paper)} samples): CPU median "
              f"{np.median(times):.2f} s, min {min(times):.2f} s of {repeats} (goal 0.5 s)",
              flush=True)  # fmt: skip
    if not data_only:
        long = synthesize(ForcepsModel(seed=1, rate_hz=10000.0), 60.0)[0]
        times = [cpu(lambda: BayesianFit().fit(long)) for _ in range(3)]
        print(f"default fit, 60 s at 10 kHz ({len(long)} samples): CPU median "
              f"{np.median(times):.2f} s, max {max(times):.2f} s of 3 (goal 5 s)",
              flush=True)  # fmt: skip
    if "--skip-data" not in sys.argv:
        with tempfile.TemporaryDirectory() as tmp:
            for entry in real_data.manifest():
                lines = sum(1 for _ in open(real_data.DATA / entry["file"], "rb"))
                own_dir, plain_dir = Path(tmp, "own"), Path(tmp, "plain")
                own_dir.mkdir(exist_ok=True)
                plain_dir.mkdir(exist_ok=True)
                own = cpu(lambda e=entry, d=own_dir: real_data.run(e, d))
                plain = cpu(lambda e=entry, d=plain_dir: real_data.run({**e, "fit": []}, d))
                print(f"{entry['file']} ({lines} lines): import and fit CPU {own:.2f} s with its "
                      f"own options, {plain:.2f} s with none (goal 10 s)", flush=True)  # fmt: skip
    print(f"load average {load()}")


if __name__ == "__main__":
    main()
