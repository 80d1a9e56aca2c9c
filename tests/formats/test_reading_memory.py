"""`fit FILE.csv` reads a text table block by block, as `import` does: its memory grows by a
few arrays of floats per row (the session itself, 24 bytes a row, and the time base's
work), never by the text's size or a Python object per value."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

# the benchmark's table and its child process that measures the reading's peak memory
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from read_memory import peak as _peak  # noqa: E402
from read_memory import write_csv as _csv  # noqa: E402

#: what each row may cost the reading: the session (time, force, position: 24 bytes),
#: the stamps and line numbers kept for the time base (16), and the time base's own
#: work arrays (at most 8 more floats); the text of a row is about 30 bytes, and a
#: Python float per value would cost 3 x 24 bytes more
BYTES_PER_ROW = 150


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
