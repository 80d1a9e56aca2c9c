"""`import` of a long text table holds a few blocks whatever its length: the body is
parsed and written block by block, and the time base reads the stamps back from the
session block by block and writes the times over them, so peak memory does not grow
with the rows."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

# the benchmark's table and its child process that measures an import's peak memory
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from import_scale import child as _child  # noqa: E402
from import_scale import write_csv as _csv  # noqa: E402

#: what the peaks of 2e6 and 4e6 rows may differ by: less than one float a row more
#: (16 MB over the 2e6 rows between them) would add; what remains is the allocators'
#: rounding (a few MB either way)
BOUND_BYTES = 16e6


def _peak(tmp_path: Path, rows: int) -> float:
    path = _csv(tmp_path / f"{rows}.csv", rows)
    result = _child("import", path, tmp_path / f"{rows}.h5")
    path.unlink()
    (tmp_path / f"{rows}.h5").unlink()
    assert result["rows"] == rows
    return result["peak_bytes"]


def test_import_peak_memory_does_not_grow_with_the_rows(tmp_path: Path) -> None:
    """2e6 rows are held whole by the time base (its sample is every stamp up to two
    blocks); 4e6 are read back in blocks: neither costs more than the other."""
    small, large = _peak(tmp_path, 2_000_000), _peak(tmp_path, 4_000_000)
    assert abs(large - small) < BOUND_BYTES, f"{small / 1e6:.0f} MB, then {large / 1e6:.0f} MB"


@pytest.mark.slow
def test_a_28_hour_log_of_1e8_rows_imports_within_1_gb(tmp_path: Path) -> None:
    peak = _peak(tmp_path, 100_000_000)
    assert peak < 1e9, f"{peak / 1e6:.0f} MB"
