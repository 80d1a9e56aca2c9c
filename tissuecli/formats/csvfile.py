"""CSV import and export of sessions: header ``time,force,position``, SI unless told."""

from __future__ import annotations

import csv
import os
from pathlib import Path

import numpy as np

from ..core.errors import InputError
from ..core.session import COLUMNS, Session
from ..core.units import ColumnUnits
from .atomic import atomic_file


def read_csv(
    path: str | os.PathLike[str], units: ColumnUnits = ColumnUnits(), name: str = ""
) -> Session:
    """Read a CSV session and convert it to SI.

    Raises
    ------
    InputError
        Missing file, a header other than ``time,force,position``, a cell that
        is not a number, NaN or Inf, fewer than 2 rows, or time not increasing.
    """
    path = Path(path)
    try:
        with path.open(newline="") as fh:
            header = next(csv.reader(fh), None)
            if header is None:
                raise InputError(f"{path} is empty; expected a header line time,force,position")
            header = [h.strip().lower() for h in header]
            if header != list(COLUMNS):
                raise InputError(
                    f"{path} has header {','.join(header)!r}; "
                    "expected exactly 'time,force,position' "
                    "(values in s, N, m, or say --units mm,gf and the like)"
                )
            rows = list(csv.reader(fh))
    except FileNotFoundError:
        raise InputError(f"{path} does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read {path}: {exc}") from None
    rows = [r for r in rows if any(c.strip() for c in r)]
    data = np.empty((len(rows), 3))
    for i, row in enumerate(rows):
        if len(row) != 3:
            raise InputError(f"{path} line {i + 2} has {len(row)} fields; expected 3")
        try:
            data[i] = [float(c) for c in row]
        except ValueError:
            raise InputError(
                f"{path} line {i + 2} has a value that is not a number: {row}"
            ) from None
    session = Session(
        *(data[:, i] * units.factor(c) for i, c in enumerate(COLUMNS)),
        name=name,
        meta={"source": f"csv:{path.name}", "csv_units": str(units)},
    )
    try:
        return session.validate()
    except InputError as exc:
        raise InputError(f"{path}: {exc}") from None


def write_csv(
    path: str | os.PathLike[str], session: Session, units: ColumnUnits = ColumnUnits()
) -> None:
    """Write ``time,force,position`` in ``units`` (SI by default), full float precision,
    atomically (see :func:`~tissuecli.formats.atomic.atomic_file`)."""
    cols = np.column_stack([getattr(session, c) / units.factor(c) for c in COLUMNS])
    with atomic_file(path) as fh:
        fh.write(",".join(COLUMNS) + "\n")
        np.savetxt(fh, cols, delimiter=",", fmt="%.17g")
