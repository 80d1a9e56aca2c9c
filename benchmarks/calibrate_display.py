"""calibrate display against simulated displays whose true constants it is not told.

Usage::

    python benchmarks/calibrate_display.py            # the defaults: 9 voltages, 3 ring-downs
    python benchmarks/calibrate_display.py --quick    # 6 voltages of 0.8 s, 2 ring-downs

For each of four displays with constants 20-40 % away from the paper's (both ways),
reporting the paper's, a simulated display runs in a process of its own with 200 g
resting on its piston (``tissuecli simulate display --profile --reports --load``),
and ``tissuecli calibrate display`` measures it over the pty. Prints each constant's
relative error, the frames the watchdog cut, the wall time and the load average.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from tissuecli.render.profile import PAPER_DISPLAY

TRUTHS = [
    {"Kp": 0.7, "alpha": 1.3, "Mp": 1.35, "b": 1.4},
    {"Kp": 1.3, "alpha": 0.7, "Mp": 0.65, "b": 0.75},
    {"Kp": 0.8, "alpha": 0.8, "Mp": 1.2, "b": 0.6},
    {"Kp": 1.2, "alpha": 1.2, "Mp": 0.8, "b": 1.3},
]


def load() -> str:
    return "load average " + ", ".join(f"{v:.2f}" for v in os.getloadavg())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="a shorter procedure")
    args = ap.parse_args()
    extra = ["--points", "6", "--hold", "0.8", "--ringdowns", "2", "--ring", "1.5"]
    print(load())
    print(
        f"{'truth (x paper)':36s} "
        + " ".join(f"{k:>8s}" for k in ("Kp", "alpha", "Mp", "b"))
        + f" {'cut':>5s} {'s':>6s}"
    )
    for factors in TRUTHS:
        with tempfile.TemporaryDirectory() as tmp:
            d = Path(tmp)
            truth = {k: getattr(PAPER_DISPLAY, k) * f for k, f in factors.items()}
            (d / "true.json").write_text(json.dumps(truth))
            (d / "paper.json").write_text("{}")
            sim = subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "tissuecli",
                    "simulate",
                    "display",
                    "--link",
                    str(d / "display"),
                    "--profile",
                    str(d / "true.json"),
                    "--reports",
                    str(d / "paper.json"),
                    "--load",
                    "200g",
                ],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
            while not (d / "display").exists():
                time.sleep(0.05)
            t0 = time.monotonic()
            res = subprocess.run(
                [
                    sys.executable,
                    "-m",
                    "tissuecli",
                    "calibrate",
                    "display",
                    "--port",
                    str(d / "display"),
                    "--mass",
                    "200g",
                    "--out",
                    str(d / "out.json"),
                    "--yes",
                    *(extra if args.quick else []),
                ],
                capture_output=True,
                text=True,
            )
            wall = time.monotonic() - t0
            sim.terminate()
            sim.wait(10)
            if res.returncode != 0:
                print(f"{json.dumps(factors):36s} failed: {res.stderr.strip()}")
                continue
            out = json.loads((d / "out.json").read_text())
            errs = [out[k]["value"] / truth[k] - 1 for k in ("Kp", "alpha", "Mp", "b")]
            cut = next(
                (
                    int(w.split("on ")[1].split(" ")[0])
                    for w in res.stdout.splitlines()
                    if "watchdog cut" in w
                ),
                0,
            )
            label = " ".join(f"{k} {f:g}" for k, f in factors.items())
            print(f"{label:36s} " + " ".join(f"{e:+8.1e}" for e in errs) + f" {cut:5d} {wall:6.1f}")
    print(load())


if __name__ == "__main__":
    main()
