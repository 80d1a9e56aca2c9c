"""Moving sessions between CSV files and HDF5 files."""

from __future__ import annotations

import os

from ..core.session import Session
from ..core.units import parse_units
from ..formats.csvfile import read_csv, write_csv
from ..formats.outputs import Output, check_outputs
from ..formats.sessions import check_new_session, read_session, write_session


def import_csv(
    csv_path: str | os.PathLike[str],
    out: str | os.PathLike[str],
    session: str,
    *,
    units: str | None = None,
    tissue: str = "",
    note: str = "",
) -> Session:
    """Read a ``time,force,position`` CSV (in ``units``, SI by default) into a new session
    of the HDF5 file ``out`` (created if missing; other sessions are never touched)."""
    check_outputs([Output(out, "--out", appends=True)], [csv_path])
    check_new_session(out, session)
    s = read_csv(csv_path, parse_units(units), name=session)
    s.meta.update(tissue=tissue, note=note)
    write_session(out, s)
    return s


def export_csv(
    path: str | os.PathLike[str],
    session: str | None,
    csv_path: str | os.PathLike[str],
    *,
    units: str | None = None,
    force: bool = False,
) -> Session:
    """Write a stored session to CSV in ``units`` (SI by default); an existing CSV is
    replaced only with ``force``, and never the HDF5 file read."""
    check_outputs([Output(csv_path, "--csv")], [path], force=force)
    s = read_session(path, session)
    write_csv(csv_path, s, parse_units(units))
    return s
