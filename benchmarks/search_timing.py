"""CPU time of the default fit (structure search included) on a 10 s, 1 kHz paper-form
session (at 16 bits and at the simulated forceps' 8 bits: the sessions of
benchmarks/time_budget.py), a constant-speed pull and a ramp-and-hold relaxation test.

Usage::

    python benchmarks/search_timing.py [REPEATS]
    python benchmarks/search_timing.py [REPEATS] --against CHECKOUT

CPU time of this process (``time.process_time``), the median over REPEATS fits after
one warm-up fit that loads SciPy: on a loaded machine wall time measures the queue.
The first two rows are the fit ``tissuecli fit FILE`` runs, ``BayesianFit().fit(session)``
with grasp detection; the others fit every sample (``grasps="none"``).

``--against CHECKOUT`` times another checkout of tissuecli beside this one: a second
process with CHECKOUT first on ``PYTHONPATH`` fits the same sessions (built by its own
code), the two taking turns fit by fit (who goes first alternating), so that both see
the same load; each row then gives both medians and minima.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "identify"))

from lab_protocols import constant_speed, relaxation  # noqa: E402

from tissuecli.core.session import Session  # noqa: E402
from tissuecli.identify import BayesianFit  # noqa: E402
from tissuecli.sim.synth import ForcepsModel, Sensors, synthesize  # noqa: E402


def sessions() -> dict[str, tuple[Session, str]]:
    """The sessions timed, by label: the session and its ``grasps`` option."""
    paper = synthesize(ForcepsModel(seed=1, sensors=Sensors(bits=16)), 10.0)[0]
    coarse = synthesize(ForcepsModel(seed=1, sensors=Sensors(bits=8)), 10.0)[0]
    return {
        "default fit (grasp detection), paper form, 10 s at 1 kHz": (paper, "all"),
        "the same at the simulated forceps' 8 bits": (coarse, "all"),
        "paper form x+xdot+xddot, 10 s at 1 kHz": (paper, "none"),
        "constant-speed pull, 10 s at 1 kHz": (constant_speed(0)[0], "none"),
        "ramp and hold, 20 s at 500 Hz": (relaxation(0)[0], "none"),
    }


def timed(session: Session, grasps: str) -> tuple[float, float, str]:
    """CPU and wall seconds of one default fit, and its choice."""
    c0, w0 = time.process_time(), time.perf_counter()
    est = BayesianFit(grasps=grasps).fit(session)
    cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    return cpu, wall, f"{est.best_.name} (P {est.best_.probability:.3f})"


def worker() -> None:
    """Fit the session of each label read from stdin; print its CPU seconds and choice."""
    timing = sessions()
    timed(*timing["constant-speed pull, 10 s at 1 kHz"])
    print("ready", flush=True)
    for line in sys.stdin:
        cpu, _, chosen = timed(*timing[line.strip()])
        print(f"{cpu!r}\t{chosen}", flush=True)


def against(repeats: int, checkout: str) -> None:
    """This checkout and ``checkout`` fit by fit in turn (see the module's docstring)."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([checkout, os.environ.get("PYTHONPATH", "")]))
    other = subprocess.Popen(
        [sys.executable, __file__, "--worker"], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
        text=True, env=env,
    )  # fmt: skip
    assert other.stdin is not None and other.stdout is not None
    timing = sessions()
    timed(*timing["constant-speed pull, 10 s at 1 kHz"])
    other.stdout.readline()
    print(f"load average {os.getloadavg()[0]:.1f}; this checkout against {checkout}")
    for label, (s, grasps) in timing.items():
        mine: list[float] = []
        theirs: list[float] = []
        for k in range(2 * repeats):
            if (k % 2 == 0) == (k // 2 % 2 == 0):
                cpu, _, chosen = timed(s, grasps)
                mine.append(cpu)
            else:
                other.stdin.write(label + "\n")
                other.stdin.flush()
                cpu_text, their_choice = other.stdout.readline().rstrip("\n").split("\t")
                theirs.append(float(cpu_text))
        print(f"{label}: this {chosen}, CPU median {np.median(mine):.2f} s, min "
              f"{min(mine):.2f} s; against {their_choice}, CPU median {np.median(theirs):.2f} "
              f"s, min {min(theirs):.2f} s", flush=True)  # fmt: skip
    other.stdin.close()
    other.wait()
    print(f"load average {os.getloadavg()[0]:.1f}")


def main() -> None:
    if "--worker" in sys.argv:
        worker()
        return
    repeats = int(sys.argv[1]) if len(sys.argv) > 1 and sys.argv[1].isdigit() else 3
    if "--against" in sys.argv:
        against(repeats, sys.argv[sys.argv.index("--against") + 1])
        return
    timing = sessions()
    timed(*timing["constant-speed pull, 10 s at 1 kHz"])
    print(f"load average {os.getloadavg()[0]:.1f}")
    for label, (s, grasps) in timing.items():
        cpu, wall = [], []
        for _ in range(repeats):
            c, w, chosen = timed(s, grasps)
            cpu.append(c)
            wall.append(w)
        print(f"{label}: {chosen}, CPU {np.median(cpu):.2f} s, wall {np.median(wall):.1f} s")
    print(f"load average {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
