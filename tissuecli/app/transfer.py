"""Moving sessions between foreign files (CSV, TSV, MATLAB, NumPy) and HDF5 files."""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from ..core.errors import InputError
from ..core.session import Session
from ..core.units import parse_units
from ..formats.csvfile import write_csv
from ..formats.outputs import Output, check_outputs
from ..formats.recording import ImportReport, open_recording, read_recording, store_recording
from ..formats.sessions import (
    check_new_session,
    is_session_file,
    read_session,
)


def import_recording(
    source: str | os.PathLike[str],
    out: str | os.PathLike[str],
    session: str | None = None,
    *,
    columns: str | None = None,
    units: str | None = None,
    jaw_length_m: float | None = None,
    rate_hz: float | None = None,
    tissue: str = "",
    note: str = "",
    progress: Callable[[float], None] | None = None,
) -> tuple[Imported, ImportReport]:
    """Read a recording (text table, .mat or .npz; see
    :func:`tissuecli.formats.recording.read_recording`) into a new session of the HDF5
    file ``out`` (created if missing; other sessions are never touched), named
    ``session`` or else after the source file (its name without the extension).

    The recording is read and written block by block, so its length is bounded by the
    disk, not the memory (:func:`tissuecli.formats.recording.store_recording`).

    Parameters
    ----------
    progress : callable, optional
        Called after each block with the fraction of the source read (0 to 1).

    Returns
    -------
    imported : Imported
        Name, samples, duration (s) and rate (Hz) of what was stored, in SI.
    report : ImportReport
        Columns and units used, what was repaired or skipped, and unit warnings.
    """
    check_outputs([Output(out, "--out", appends=True)], [source])
    if session is None:
        session = Path(source).stem
    check_new_session(out, session)
    reading = open_recording(
        source, columns=columns, units=units, jaw_length_m=jaw_length_m, rate_hz=rate_hz
    )
    n, duration, rate = store_recording(
        reading, out, session, {"tissue": tissue, "note": note}, progress
    )
    return Imported(session, n, duration, rate), reading.report


@dataclass(frozen=True)
class Imported:
    """What an import stored: the session's name, samples, duration (s) and rate (Hz)."""

    name: str
    samples: int
    duration_s: float
    rate_hz: float

    def __len__(self) -> int:
        return self.samples


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
    written = parse_units(units)
    if written.position_is_angle:
        raise InputError("export writes jaw closure; give --units position=mm (or m, um)")
    s = read_session(path, session)
    write_csv(csv_path, s, written)
    return s


def load_session(
    path: str | os.PathLike[str],
    session: str | None = None,
    *,
    columns: str | None = None,
    units: str | None = None,
    jaw_length_m: float | None = None,
    rate_hz: float | None = None,
) -> tuple[Session, ImportReport | None]:
    """A session from a tissuecli HDF5 file, or read on the fly from another logger's
    recording (as :func:`import_recording` reads it, without storing it).

    Returns
    -------
    session : Session
    report : ImportReport or None
        What reading a foreign recording found and did; None for a session file.

    Raises
    ------
    InputError
        If reading options are given for a session file, or the recording is bad.
    """
    if is_session_file(path):
        given = [
            option
            for option, value in (
                ("--columns", columns),
                ("--units", units),
                ("--jaw-length", jaw_length_m),
                ("--rate", rate_hz),
            )
            if value is not None
        ]
        if given:
            raise InputError(
                f"{', '.join(given)} read a recording from another logger; {path} is a "
                "tissuecli session file, already in SI: leave them out"
            )
        return read_session(path, session), None
    name = session if session is not None else Path(path).stem
    return read_recording(
        path, columns=columns, units=units, jaw_length_m=jaw_length_m, rate_hz=rate_hz,
        name=name,
    )  # fmt: skip
