"""Start-up of the command line against importing the libraries it is built on.

For each command, the wall time of the whole process divided by that of
``python -c "import numpy, h5py, scipy.linalg"``, measured side by side: every round
runs the baseline and each command once, in a shuffled order, so a busy neighbour
slows all of them alike. Medians over the rounds.

Usage::

    python benchmarks/startup.py [--rounds 15] [--checkout DIR]

``--checkout DIR`` times another source tree of tissuecli beside this one (its
commands run as ``python -m tissuecli`` with ``PYTHONPATH=DIR``), e.g. an older
commit made with ``git worktree add DIR COMMIT``.

Commands timed: ``tissuecli fit`` of a 10 s, 1 kHz session (no report),
``tissuecli sessions`` of that file, and ``tissuecli play PARAMS --check``.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from tissuecli.core.tissue import DEFAULT_TISSUE
from tissuecli.formats.sessions import write_session
from tissuecli.sim.synth import ForcepsModel, synthesize

BASELINE = [sys.executable, "-c", "import numpy, h5py, scipy.linalg"]


def tissuecli_command() -> list[str]:
    """The console script installed beside this Python, as a user runs it."""
    script = Path(sys.executable).with_name("tissuecli")
    return [str(script)] if script.exists() else [sys.executable, "-m", "tissuecli"]


def wall(args: list[str], env: dict[str, str] | None = None) -> float:
    """Seconds to run ``args``; with ``env`` (another checkout) from that checkout's
    directory, since ``python -m`` puts the working directory first on the path."""
    cwd = env["PYTHONPATH"] if env else None
    t0 = time.perf_counter()
    subprocess.run(args, check=True, capture_output=True, env=env, cwd=cwd)
    return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> dict[str, dict[str, float]]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=15, help="rounds of side-by-side runs")
    parser.add_argument("--checkout", type=Path, help="another source tree to time alongside")
    args = parser.parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="tissuecli-startup-"))
    try:
        session, _ = synthesize(ForcepsModel(seed=1), 10.0)
        session.name = "bench"
        write_session(work / "grasp.h5", session)
        # the version 1 layout, which every tissuecli reads (an older checkout too)
        k, c, m = DEFAULT_TISSUE.coef
        v1 = {
            "format": "tissuecli-parameters",
            "version": 1,
            "model": {"f0": "x", "f1": "xdot"},
            "parameters": {
                "K": {"mean": k, "unit": "N/m"},
                "S": {"mean": c, "unit": "N s/m"},
                "M": {"mean": m, "unit": "kg"},
            },
        }
        (work / "tissue.json").write_text(json.dumps(v1))
        tasks = {
            "fit (10 s at 1 kHz, no report)": ["fit", str(work / "grasp.h5")],
            "sessions": ["sessions", str(work / "grasp.h5")],
            "play --check": ["play", str(work / "tissue.json"), "--check"],
        }
        commands: dict[str, tuple[list[str], dict[str, str] | None]] = {
            "baseline: import numpy, h5py, scipy.linalg": (BASELINE, None)
        }
        # the default structure search fits laws beyond the paper's four forms; the
        # paper's forms alone are what an older checkout's default fit did
        paper = ["fit", str(work / "grasp.h5"), "--forms", "paper"]
        current = {**tasks, "fit --forms paper": paper}
        for name, task in current.items():
            commands[f"tissuecli {name}"] = ([*tissuecli_command(), *task], None)
        if args.checkout is not None:
            env = {**os.environ, "PYTHONPATH": str(args.checkout.resolve())}
            for name, task in tasks.items():
                commands[f"{args.checkout.name}: {name}"] = (
                    [sys.executable, "-m", "tissuecli", *task],
                    env,
                )
        for argv_, env_ in commands.values():  # warm the file cache and the bytecode
            wall(argv_, env_)
        times: dict[str, list[float]] = {name: [] for name in commands}
        rng = random.Random(0)
        for _ in range(args.rounds):
            order = list(commands)
            rng.shuffle(order)
            for name in order:
                times[name].append(wall(*commands[name]))
    finally:
        shutil.rmtree(work, ignore_errors=True)
    base = np.array(times[next(iter(commands))])
    print(f"{'command':<52} {'median s':>9} {'ratio':>6} {'ratio IQR':>13}")
    result = {}
    for name, ts in times.items():
        t = np.array(ts)
        ratios = t / base  # per round: each command against the baseline of its round
        q1, q3 = np.percentile(ratios, [25, 75])
        result[name] = {"median_s": float(np.median(t)), "ratio": float(np.median(ratios))}
        print(f"{name:<52} {np.median(t):9.3f} {np.median(ratios):6.2f}   [{q1:4.2f}, {q3:4.2f}]")
    print(f"({args.rounds} rounds; goal: every ratio <= 1.5)")
    return result


if __name__ == "__main__":
    main()
