"""Peak memory of reading a text table for a fit (what ``tissuecli fit FILE.csv`` reads
before fitting), against the number of rows: each length read in a fresh process,
its peak resident memory above that of a process that only loads the readers.

Usage::

    python benchmarks/read_memory.py [--rows 1000000 4000000]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

CHILD = """
import resource, sys
import pyarrow.csv  # loaded by either run, so that only the reading is measured
from tissuecli.app.transfer import load_session
n = len(load_session(sys.argv[1])[0]) if sys.argv[2] == "read" else 0
print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024, n)
"""


def write_csv(path: Path, rows: int) -> Path:
    """A table of ``rows`` rows: time (s), force (N), position (mm), 6 decimals."""
    t = np.arange(rows) * 1e-3
    with open(path, "w") as fh:
        fh.write("time (s),force (N),position (mm)\n")
        for start in range(0, rows, 1 << 18):
            part = t[start : start + (1 << 18)]
            np.savetxt(fh, np.c_[part, 1 + np.sin(part), 3 + np.cos(part)], fmt="%.6f",
                       delimiter=",")  # fmt: skip
    return path


def peak(path: Path, what: str) -> tuple[int, int]:
    """Peak resident bytes of a process that reads ``path`` (``what="read"``) or only
    loads the readers, and the rows it read."""
    out = subprocess.run(
        [sys.executable, "-c", CHILD, str(path), what],
        capture_output=True, text=True, check=True, timeout=600,
    ).stdout.split()  # fmt: skip
    return int(out[0]), int(out[1])


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, nargs="+", default=[1_000_000, 4_000_000])
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as work:
        base, _ = peak(write_csv(Path(work) / "tiny.csv", 10), "none")
        print(f"load average {os.getloadavg()[0]:.1f}; baseline {base / 1e6:.0f} MB")
        print(f"{'rows':>10} {'file MB':>8} {'peak MB':>8} {'bytes/row':>9} {'s':>6}")
        for rows in args.rows:
            path = write_csv(Path(work) / f"{rows}.csv", rows)
            start = time.monotonic()
            top, n = peak(path, "read")
            took = time.monotonic() - start
            assert n == rows
            above = top - base
            print(f"{rows:>10} {path.stat().st_size / 1e6:>8.1f} {above / 1e6:>8.1f} "
                  f"{above / rows:>9.0f} {took:>6.1f}")  # fmt: skip
            path.unlink()


if __name__ == "__main__":
    main()
