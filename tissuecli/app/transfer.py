"""Moving sessions between foreign files (CSV, TSV, spreadsheets, MATLAB, NumPy, other
programs' HDF5 and TDMS) and HDF5 files."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from ..core.calibration import Calibration
from ..core.errors import InputError
from ..core.session import Session
from ..core.units import parse_units
from ..formats.csvfile import write_csv
from ..formats.outputs import Output, check_outputs
from ..formats.params import read_calibration
from ..formats.recording import ImportReport, open_recording, read_recording, store_recording
from ..formats.sessions import (
    check_new_session,
    is_session_file,
    read_session,
)
from ..formats.sheets import data_sheets, is_workbook


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
    sheet: str | None = None,
    calibration: Calibration | str | os.PathLike[str] | None = None,
) -> tuple[Imported, ImportReport]:
    """Read a recording (text table, spreadsheet, .mat or .npz; see
    :func:`tissuecli.formats.recording.read_recording`) into a new session of the HDF5
    file ``out`` (created if missing; other sessions are never touched), named
    ``session`` or else after the sheet read or the source file (its name without the
    extension).

    The recording is read and written block by block, so its length is bounded by the
    disk, not the memory (:func:`tissuecli.formats.recording.store_recording`).

    Parameters
    ----------
    progress : callable, optional
        Called after each block with the fraction of the source read (0 to 1).
    sheet : str, optional
        The sheet of a spreadsheet; without it the workbook must hold one sheet with
        data (:func:`import_recordings` stores every sheet).
    calibration : Calibration or path, optional
        Force and position are ADC counts: SI = gain * counts + offset, by this
        calibration or the calibration file it names (as ``record --calibration``);
        ``units`` then names the time unit only. Stored with the session.

    Returns
    -------
    imported : Imported
        Name, samples, duration (s) and rate (Hz) of what was stored, in SI.
    report : ImportReport
        Columns and units used, what was repaired or skipped, and unit warnings.
    """
    cal_file = calibration if isinstance(calibration, (str, os.PathLike)) else None
    check_outputs([Output(out, "--out", appends=True)], [source, cal_file])
    if session is None:
        session = sheet if sheet is not None else Path(source).stem
    check_new_session(out, session)
    if cal_file is not None:
        calibration = read_calibration(cal_file)
    reading = open_recording(
        source, columns=columns, units=units, jaw_length_m=jaw_length_m, rate_hz=rate_hz,
        sheet=sheet, calibration=calibration,  # type: ignore[arg-type]
    )  # fmt: skip
    n, duration, rate = store_recording(
        reading, out, session, {"tissue": tissue, "note": note}, progress
    )
    return Imported(session, n, duration, rate), reading.report


def import_recordings(
    source: str | os.PathLike[str],
    out: str | os.PathLike[str],
    session: str | None = None,
    *,
    sheet: str | None = None,
    **options: object,
) -> Iterator[tuple[Imported, ImportReport]]:
    """Import a recording as :func:`import_recording` does, and every sheet of a
    workbook with data as a session named after its sheet (unless ``sheet`` picks one).
    Every session name is checked free before any is written; each sheet is stored as
    it is read, so a sheet that fails leaves the ones before it imported.

    Yields
    ------
    imported, report
        As :func:`import_recording` returns them, one pair per session.
    """
    if sheet is not None or not is_workbook(source):
        yield import_recording(source, out, session, sheet=sheet, **options)  # type: ignore[arg-type]
        return
    sheets = data_sheets(source)
    if len(sheets) == 1:
        yield import_recording(source, out, session, sheet=sheets[0], **options)  # type: ignore[arg-type]
        return
    if session is not None:
        raise InputError(
            f"{source} holds {len(sheets)} sheets with data, each imported as a session named "
            "after it; leave out --session, or import one with --sheet NAME --session NAME"
        )
    check_outputs([Output(out, "--out", appends=True)], [source])
    for name in sheets:
        check_new_session(out, name)
    for name in sheets:
        try:
            yield import_recording(source, out, name, sheet=name, **options)  # type: ignore[arg-type]
        except InputError as exc:
            raise InputError(f"sheet {name!r}: {exc}") from None


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


#: the fewest bytes a row of a text table takes (``0,1,2`` and a line end): a file
#: smaller than this many bytes a row holds fewer rows than a limit
MIN_ROW_BYTES = 6


def may_hold_more_rows(path: str | os.PathLike[str], rows: int) -> bool:
    """Whether a recording of another logger may hold more than ``rows`` rows (from its
    size alone; a tissuecli session file is never one)."""
    try:
        size = os.path.getsize(path)
    except OSError:
        return False
    return size > rows * MIN_ROW_BYTES and not is_session_file(path)


@contextmanager
def staged_recording(
    path: str | os.PathLike[str],
    session: str | None = None,
    **reading: object,
) -> Iterator[tuple[str, str]]:
    """Another logger's recording stored block by block in a temporary HDF5 file, as
    ``import`` stores it (bounded memory whatever its length), so that a fit can read
    it by row range; the file is removed on leaving.

    Yields
    ------
    h5, name : str
        The temporary file and the session's name in it (``session``, else the sheet's
        or the file's name).
    """
    with tempfile.TemporaryDirectory(prefix="tissuecli-") as work:
        h5 = os.path.join(work, "staged.h5")
        options = {k: v for k, v in reading.items() if v is not None}
        imported, _ = import_recording(path, h5, session, **options)  # type: ignore[arg-type]
        yield h5, imported.name


def load_session(
    path: str | os.PathLike[str],
    session: str | None = None,
    *,
    columns: str | None = None,
    units: str | None = None,
    jaw_length_m: float | None = None,
    rate_hz: float | None = None,
    sheet: str | None = None,
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
                ("--sheet", sheet),
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
    if sheet is not None and session is None:
        name = sheet  # a sheet is named after itself, as import names it
    return read_recording(
        path, columns=columns, units=units, jaw_length_m=jaw_length_m, rate_hz=rate_hz,
        name=name, sheet=sheet,
    )  # fmt: skip
