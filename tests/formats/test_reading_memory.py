"""`fit FILE.csv` reads a text table block by block, as `import` does: its memory grows by a
few arrays of floats per row (the session itself, 24 bytes a row, and the time base's
work), never by the text's size or a Python object per value."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

#: what each row may cost the reading: the session (time, force, position: 24 bytes),
#: the stamps and line numbers kept for the time base (16), and the time base's own
#: work arrays (at most 8 more floats); the text of a row is about 30 bytes, and a
#: Python float per value would cost 3 x 24 bytes more
BYTES_PER_ROW = 150

CHILD = """
import resource, sys
import pyarrow.csv  # loaded by either run, so that only the reading is measured
from tissuecli.app.transfer import load_session
n = 0
if sys.argv[2] == "read":
    session, _ = load_session(sys.argv[1])
    n = len(session)
print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024, n)
"""


def _csv(path: Path, rows: int) -> Path:
    t = np.arange(rows) * 1e-3
    with open(path, "w") as fh:
        fh.write("time (s),force (N),position (mm)\n")
        for start in range(0, rows, 1 << 18):
            part = t[start : start + (1 << 18)]
            np.savetxt(fh, np.c_[part, 1 + np.sin(part), 3 + np.cos(part)], fmt="%.6f",
                       delimiter=",")  # fmt: skip
    return path


def _peak(path: Path, what: str) -> tuple[int, int]:
    out = subprocess.run(
        [sys.executable, "-c", CHILD, str(path), what],
        capture_output=True,
        text=True,
        check=True,
        timeout=600,
    ).stdout.split()
    return int(out[0]), int(out[1])


def _slope(tmp_path: Path, small: int, large: int) -> float:
    """Peak memory per row of reading, from two lengths (the constant part cancels)."""
    base, _ = _peak(_csv(tmp_path / "a.csv", 10), "none")
    peaks = []
    for rows in (small, large):
        peak, n = _peak(_csv(tmp_path / f"{rows}.csv", rows), "read")
        assert n == rows
        peaks.append(max(peak, base))
    return (peaks[1] - peaks[0]) / (large - small)


def test_reading_a_text_table_for_a_fit_costs_a_few_floats_a_row(tmp_path: Path) -> None:
    per_row = _slope(tmp_path, 200_000, 800_000)
    assert per_row <= BYTES_PER_ROW, f"{per_row:.0f} bytes a row"


@pytest.mark.slow
def test_reading_millions_of_rows_for_a_fit_stays_bounded(tmp_path: Path) -> None:
    per_row = _slope(tmp_path, 1_000_000, 4_000_000)
    assert per_row <= BYTES_PER_ROW, f"{per_row:.0f} bytes a row"
