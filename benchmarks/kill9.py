"""Crash survival of the HDF5 writer: kill -9 at random moments, then check every row.

Usage::

    python benchmarks/kill9.py --kills 200 [--interval 0.05] [--block 50] [--no-fsync]

Each trial starts the test suite's writer (tests/formats/_writer_child.py) on a new
file, lets it commit a random number of flushes, sends SIGKILL, then opens the
file with plain ``h5py.File(path, "r")`` through ``read_session`` and compares
every committed row with the values the writer wrote.
"""

from __future__ import annotations

import argparse
import random
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "formats"))

from _writer_child import expected_rows  # noqa: E402

from tissuecli.formats.sessions import read_session  # noqa: E402


def trial(path: Path, args: argparse.Namespace, rng: random.Random) -> str:
    cmd = [
        sys.executable,
        str(ROOT / "tests" / "formats" / "_writer_child.py"),
        str(path),
        "--interval",
        str(args.interval),
        "--block",
        str(args.block),
    ]
    if args.no_fsync:
        cmd.append("--no-fsync")
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True)
    flushed, want = 0, rng.randint(1, 20)
    assert proc.stdout is not None
    for _ in range(want):
        line = proc.stdout.readline()
        if not line:
            break
        flushed = int(line.split()[1])
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    proc.stdout.close()
    try:
        s = read_session(path, "crash", raw=True)
    except Exception as exc:  # what a user would meet: an unreadable file
        return f"unreadable: {exc}"
    if len(s) < flushed:
        return f"lost rows: {len(s)} < {flushed} committed"
    exp = expected_rows(0, len(s))
    if not (
        np.array_equal(s.time, exp["time"])
        and np.array_equal(s.force, exp["force"])
        and np.array_equal(s.meta["raw"]["raw/sequence"], exp["raw/sequence"])
    ):
        return "wrong values"
    return "ok"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kills", type=int, default=200)
    ap.add_argument("--interval", type=float, default=0.05)
    ap.add_argument("--block", type=int, default=50)
    ap.add_argument("--no-fsync", action="store_true")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rng = random.Random(args.seed)
    outcomes: dict[str, int] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.kills):
            result = trial(Path(tmp) / f"k{k}.h5", args, rng)
            key = result.split(":")[0]
            outcomes[key] = outcomes.get(key, 0) + 1
    print(
        f"{args.kills} kills (flush every {args.interval} s, blocks of {args.block} rows, "
        f"fsync {'off' if args.no_fsync else 'on'}): "
        + ", ".join(f"{k} {v}" for k, v in sorted(outcomes.items()))
    )


if __name__ == "__main__":
    main()
