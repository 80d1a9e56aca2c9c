"""Importing long text tables: time and peak memory of ``import`` beside ``pandas.read_csv``
on the same file, and of ``sessions`` on the file written, side by side in one run.

Usage::

    python benchmarks/import_scale.py [--rows 1e6,1e7] [--repeat 5] [--slow] [--dir /tmp]

For each row count a CSV of a 1 kHz session (time, force, position, 27-30 bytes a
row) is written once, then three child processes run one after the other on it:
``pandas.read_csv(path)`` (the reference a user would write), the library call behind
``tissuecli import`` (into a new HDF5 file) and the one behind ``tissuecli sessions`` (on
that file). Each child loads its libraries (pandas; or tissuecli, which loads h5py and, for a
text table, pyarrow), then times its one call and reports its peak resident memory
(``ru_maxrss``), which includes the interpreter and those libraries (60-90 MB), and
the CPU time of its call (every thread: pyarrow parses on every core). The CPU times'
ratio depends little on the machine's load; the wall times' does.
With ``--repeat N`` the pandas and import children take turns N times on the same file
and each figure is the median of its N runs; the ratios are the medians of the N
side-by-side pairs, so a burst of load on the shared machine moves one pair, not the
verdict. ``--slow`` adds 1e8 rows (a 28-hour 1 kHz log, 2.9 GB of text).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

CHILD = r"""
import json, resource, sys, time
what, path, out = sys.argv[1:4]
if what == "pandas":
    import pandas
else:
    import pyarrow.csv  # loaded by the first block read: a library, as pandas is
    from tissuecli.app.transfer import import_recording
    from tissuecli.formats.sessions import list_sessions
def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime
start, cpu0 = time.perf_counter(), cpu()
if what == "pandas":
    rows = len(pandas.read_csv(path))
elif what == "import":
    rows = import_recording(path, out, "s")[0].samples
else:
    rows = list_sessions(out)[0]["samples"]
wall, used = time.perf_counter() - start, cpu() - cpu0
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
print(json.dumps({"rows": rows, "wall_s": wall, "cpu_s": used, "peak_bytes": peak}))
"""


def write_csv(path: Path, rows: int) -> Path:
    """A 1 kHz session: a slow squeeze (one every 2 s) with a ripple, 27-30 bytes a row.
    The 2000 rows of one squeeze are formatted once; each squeeze after is that text
    with its seconds put in, so a file of any length is written at the disk's pace."""
    period = 2000
    t = np.arange(period) * 1e-3
    x = 2e-3 * (1 - np.cos(2 * np.pi * 0.5 * t))
    f = 350 * x + 0.01 * np.sin(2 * np.pi * 3.5 * t)
    lines = [
        f"{'AB'[j // 1000]}.{j % 1000:03d},{f[j]:.6g},{x[j]:.6g}\n".encode() for j in range(period)
    ]
    whole = b"".join(lines)
    with open(path, "wb") as fh:
        fh.write(b"time,force,position\n")
        for start in range(0, rows, period):
            part = whole if rows - start >= period else b"".join(lines[: rows - start])
            second = start // 1000
            fh.write(part.replace(b"A", b"%d" % second).replace(b"B", b"%d" % (second + 1)))
    return path


#: the checkout this script is in, so that its children time that and no other copy
ROOT = Path(__file__).resolve().parents[1]


def child(what: str, path: Path, out: Path) -> dict[str, float]:
    """Run ``what`` (``pandas``, ``import`` or ``sessions``) on ``path`` in a fresh process:
    its rows, wall and CPU time (s) and peak resident memory (bytes)."""
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
    }
    result = subprocess.run(
        [sys.executable, "-c", CHILD, what, str(path), str(out)],
        capture_output=True,
        text=True,
        check=True,
        env=env,
    )
    return json.loads(result.stdout.strip().splitlines()[-1])


def _median(runs: list[dict[str, float]]) -> dict[str, float]:
    """Each figure's median over the runs of one child."""
    return {key: float(np.median([r[key] for r in runs])) for key in runs[0]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", default="1e6,1e7")
    parser.add_argument("--repeat", type=int, default=5, help="pandas/import pairs per size")
    parser.add_argument("--slow", action="store_true", help="add 1e8 rows")
    parser.add_argument("--dir", default=None, help="where to write the files")
    args = parser.parse_args()
    counts = [int(float(r)) for r in args.rows.split(",")] + ([10**8] if args.slow else [])
    print(
        f"load average before: {os.getloadavg()[0]:.2f} ({os.cpu_count()} cores); "
        f"medians of {args.repeat} pandas/import pairs"
    )
    print(
        f"{'rows':>10} {'CSV MB':>7} | {'pandas s':>8} {'CPU s':>6} {'MB':>5} | "
        f"{'import s':>8} {'CPU s':>6} {'MB':>5} | {'ratio':>5} {'CPU':>5} | "
        f"{'sessions s':>10} {'MB':>5}"
    )
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        for rows in counts:
            path, out = Path(tmp) / f"r{rows}.csv", Path(tmp) / f"r{rows}.h5"
            write_csv(path, rows)
            refs, imps = [], []
            for _ in range(max(1, args.repeat if rows < 10**8 else 1)):
                out.unlink(missing_ok=True)
                refs.append(child("pandas", path, out))
                imps.append(child("import", path, out))
            lst = child("sessions", path, out)
            assert all(r["rows"] == rows for r in (*refs, *imps, lst)), (refs, imps, lst)
            ref, imp = _median(refs), _median(imps)
            pairs = list(zip(refs, imps, strict=True))
            ratio = float(np.median([i["wall_s"] / r["wall_s"] for r, i in pairs]))
            ratio_cpu = float(np.median([i["cpu_s"] / r["cpu_s"] for r, i in pairs]))
            print(
                f"{rows:>10.0e} {path.stat().st_size / 1e6:>7.0f} | {ref['wall_s']:>8.2f} "
                f"{ref['cpu_s']:>6.2f} {ref['peak_bytes'] / 1e6:>5.0f} | {imp['wall_s']:>8.2f} "
                f"{imp['cpu_s']:>6.2f} {imp['peak_bytes'] / 1e6:>5.0f} | "
                f"{ratio:>5.2f} {ratio_cpu:>5.2f} | "
                f"{lst['wall_s']:>10.2f} {lst['peak_bytes'] / 1e6:>5.0f}",
                flush=True,
            )
            path.unlink()
            out.unlink()
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
