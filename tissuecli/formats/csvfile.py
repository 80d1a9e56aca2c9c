"""CSV export of sessions: header ``time,force,position``, SI unless told (import reads
any table: :mod:`tissuecli.formats.recording`)."""

from __future__ import annotations

import os

import numpy as np

from ..core.session import COLUMNS, Session
from ..core.units import ColumnUnits
from .atomic import atomic_file


def write_csv(
    path: str | os.PathLike[str], session: Session, units: ColumnUnits = ColumnUnits()
) -> None:
    """Write ``time,force,position`` in ``units`` (SI by default), full float precision,
    atomically (see :func:`~tissuecli.formats.atomic.atomic_file`)."""
    cols = np.column_stack([getattr(session, c) / units.factor(c) for c in COLUMNS])
    write_table(path, list(COLUMNS), cols)


def write_table(
    path: str | os.PathLike[str],
    names: list[str],
    columns: np.ndarray,
    comment: str | None = None,
) -> None:
    """Write a header and columns (n, k) as CSV, full float precision, atomically;
    ``comment`` (one line) goes first, after ``#``, where the units are said."""
    with atomic_file(path) as fh:
        if comment:
            fh.write(f"# {comment}\n")
        fh.write(",".join(names) + "\n")
        np.savetxt(fh, columns, delimiter=",", fmt="%.17g")
