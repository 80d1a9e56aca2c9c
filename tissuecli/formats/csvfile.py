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
    with atomic_file(path) as fh:
        fh.write(",".join(COLUMNS) + "\n")
        np.savetxt(fh, cols, delimiter=",", fmt="%.17g")
