"""Recordings from other loggers and labs: text tables, MATLAB and NumPy files, with
their own column names, units, clocks, junk and angles, into a :class:`Session` in SI.

Columns are found by header name (``time``/``t``/``timestamp``, ``force``/``load``,
``position``/``closure``/``displacement``/``angle``, ...) or chosen with
``time=NAME,force=NAME,position=NAME`` (a name or a 1-based index). Units come from
``--units``, else from the header (``t_ms``, ``force (N)``), else SI. A position in
degrees or radians is the angle between the jaws and becomes the closure at the tips,
``x = -2 L sin(theta / 2)`` for jaws of length ``L``, and a torque about the hinge the
force at the tips, ``tau / L`` (docs/real-data.md). Time stamps
are put back on the regular clock they came from, when they did
(:func:`tissuecli.core.timebase.regularise`).
"""

from __future__ import annotations

import bisect
import math
import os
import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..core.calibration import Calibration
from ..core.errors import InputError
from ..core.plausible import unit_warnings
from ..core.session import COLUMNS, Session
from ..core.timebase import ClockFit, Stamps, fit_clock, median, regularise
from ..core.units import (
    PHYSICAL_LIMITS,
    ColumnUnits,
    beyond_physical,
    dimension_of,
    parse_units,
    unit_for,
    unit_in_header,
)
from .arrays import read_arrays
from .foreign import Columns, read_hdf5, read_tdms
from .sheets import is_workbook, read_sheet
from .tables import Block, Clock, Layout, Table, clock_seconds, sniff_table

#: header words (lower case, letters and digits only, unit removed) for each column
SYNONYMS = {
    "time": (
        "time", "t", "timestamp", "timestamps", "times", "sec", "seconds", "elapsed", "ts",
        "timesec",
        "zeit", "temps", "tiempo", "tempo", "时间", "時間", "时刻", "時刻",
    ),
    "force": (
        "force", "f", "load", "graspforce", "grip", "gripforce", "fz", "forcesensor",
        "kraft", "fuerza", "forza", "力", "荷重", "压力", "力量", "载荷",
    ),
    "position": (
        "position", "pos", "closure", "x", "displacement", "disp", "jaw", "gap", "depth",
        "indentation", "stroke", "opening", "angle", "jawangle", "theta", "jawposition",
        "jawgap", "jawopening", "weg", "déplacement", "deplacement", "desplazamiento",
        "spostamento", "位移", "変位", "位置", "变位", "ストローク",
    ),
}  # fmt: skip
#: position headers that name the opening between the jaws: closure is their negative
OPENINGS = ("gap", "opening", "jawgap", "jawopening")
ARRAY_SUFFIXES = (".mat", ".npz")
HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


@dataclass
class ImportReport:
    """What an import found and did, for the user and the session's attributes."""

    columns: dict[str, str] = field(default_factory=dict)  # quantity -> column used
    units: dict[str, str] = field(default_factory=dict)  # quantity -> unit (and where from)
    ignored: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    def lines(self) -> list[str]:
        used = ", ".join(f"{q} <- {c!r} in {self.units[q]}" for q, c in self.columns.items())
        out = [f"columns: {used}"]
        if self.ignored:
            out.append("ignored columns: " + ", ".join(repr(n) for n in self.ignored[:10]))
        out += self.notes
        out += [f"warning: {w}" for w in self.warnings]
        return out


#: a source of rows: a table in memory, a text table or another program's binary file
#: read block by block
Source = Table | Layout | Columns
#: stamps (s), force (N), closure (m) and line numbers of a block of rows
SIBlock = tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]


def open_source(path: str | os.PathLike[str], sheet: str | None = None) -> Source:
    """The reader for a recording, chosen by its suffix and its first bytes: .mat and
    .npz arrays, spreadsheets (one sheet: ``sheet``, or the only one with data), HDF5
    (and NWB), LabVIEW TDMS, else a text table."""
    path = Path(path)
    suffix = path.suffix.lower()
    if is_workbook(path):
        return read_sheet(path, sheet)
    if sheet is not None:
        raise InputError(f"--sheet {sheet!r}: {path} is not a spreadsheet (.xlsx, .xls, .ods)")
    if suffix in ARRAY_SUFFIXES:
        return read_arrays(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(8)
    except OSError:
        head = b""
    if head.startswith(b"TDSm") or suffix == ".tdms":
        return read_tdms(path)
    if head == HDF5_SIGNATURE:
        return read_hdf5(path)
    return sniff_table(path)


@dataclass
class Reading:
    """A recording being read: the columns and units chosen, and its rows in SI, block
    by block (:meth:`blocks`), so that a recording of any length can be stored as it is
    read. :meth:`finish` afterwards gives the reader's notes."""

    path: Path
    source: Source
    report: ImportReport
    picked: dict[str, tuple[int, str]]
    opening: bool
    jaw_length_m: float | None
    rate_hz: float | None
    clock: Clock | None = None
    rows: int = 0
    lost: int = 0  # samples missing from the recording's own clock (set by time_base)
    time_assumed: bool = False  # the time column's unit was assumed, not read or given
    #: force and position read in ADC counts, turned to SI by this (``--calibration``)
    calibration: Calibration | None = None

    @property
    def stamped(self) -> bool:
        """Whether the recording has a time column (else the time is the sample index
        at ``rate_hz``)."""
        return "time" in self.picked

    def blocks(self) -> Iterator[SIBlock]:
        """``(stamps, force, position, lines)`` of each block: stamps in s (the file's,
        not yet put on a clock; sample index / rate without a time column), force in N,
        closure in m, line numbers for messages.

        Raises
        ------
        InputError
            A value beyond any physical range, or a clock time that is not one.
        """
        order = [q for q in COLUMNS if q in self.picked]
        columns = [self.picked[q][0] for q in order]
        for block in self.source.blocks(columns):
            yield self.convert(block)

    def convert(self, block: Block) -> SIBlock:
        """One block of rows (the chosen columns, in the order time, force, position)
        in SI, as :meth:`blocks` yields them."""
        order = [q for q in COLUMNS if q in self.picked]
        values = {q: block.values[:, j] for j, q in enumerate(order)}
        lines = block.lines
        if "time" in self.picked:
            index, unit = self.picked["time"]
            if self.clock is not None:
                stamps = self.clock.seconds(block.text.get(index, []))
                if stamps is None:
                    raise InputError(
                        f"{self.path}: a time between lines {lines[0]} and {lines[-1]} "
                        "is not a clock time like the others; repair the time column"
                    )
            else:
                if self.time_assumed:
                    unit = self._epoch_unit(values["time"], index, unit)
                stamps = values["time"] * ColumnUnits(time=unit).factor("time")
        else:
            stamps = (self.rows + np.arange(lines.size)) / float(self.rate_hz or 1.0)
        if self.calibration is not None:  # counts: the calibration's gains say the sign
            force = self.calibration.force.to_si(values["force"])
            position = self.calibration.position.to_si(values["position"])
        else:
            force = _force(values["force"], self.picked["force"][1], self.jaw_length_m, self.path)
            position = _closure(
                values["position"], self.picked["position"][1], self.jaw_length_m, self.path
            )
            if self.opening:
                position = -position
        for quantity, si in (("force", force), ("position", position)):
            bad = beyond_physical(quantity, si)
            if bad is not None:
                raise InputError(
                    f"{self.path}: {quantity} reads {si[bad]:.3g} "
                    f"{'N' if quantity == 'force' else 'm'} at line {lines[bad]}, beyond "
                    f"any {'grasp' if quantity == 'force' else 'jaw'} (|{quantity}| <= "
                    f"{PHYSICAL_LIMITS[quantity]:.0e}); check the column and --units"
                )
        self.rows += lines.size
        return stamps, force, position, lines

    def _epoch_unit(self, values: NDArray[np.float64], index: int, unit: str) -> str:
        """The unit of a time column whose unit nothing said, from its first block: a
        PC clock's stamps since 1970 in s, ms, us or ns (:func:`epoch_unit`), else the
        unit assumed. Decided once, for the whole column."""
        self.time_assumed = False
        found = epoch_unit(values)
        if found is None:
            return unit
        self.picked["time"] = (index, found)
        self.report.units["time"] = f"{found} (PC clock stamps since 1970)"
        return found

    def fraction(self) -> float:
        """How much of the file has been read, 0 to 1."""
        return self.source.fraction()

    def finish(self) -> None:
        """After :meth:`blocks`: the reader's notes into the report (first), and a
        refusal if the table was more junk than data."""
        self.report.notes[:0] = self.source.finish()

    def time_base(self, stamps: NDArray[np.float64], lines: Any) -> NDArray[np.float64]:
        """The stamps put back on their clock (s from the first), noted in the report."""
        if not self.stamped:
            self.report.notes.append(f"time: from the sample index at {self.rate_hz:g} Hz (--rate)")
            return stamps - stamps[0]
        time, base = regularise(stamps, lines)
        self.report.notes.append("time: " + base.describe())
        self.lost = int(base.lost)
        time -= time[0]  # in place: the stamps are this reading's own
        return time

    def fit_clock(self, stamps: Stamps, lines: Any) -> ClockFit | None:
        """The clock behind stamps read a block at a time (:func:`~tissuecli.core.
        timebase.fit_clock`), noted in the report; None without a time column (the
        stamps are then the sample index over the rate, from 0 s).

        Raises
        ------
        InputError
            As :func:`~tissuecli.core.timebase.regularise`.
        """
        if not self.stamped:
            self.report.notes.append(f"time: from the sample index at {self.rate_hz:g} Hz (--rate)")
            return None
        fit = fit_clock(stamps, lines)
        fit.check_order()
        self.report.notes.append("time: " + fit.base.describe())
        self.lost = int(fit.base.lost)
        return fit

    def meta(self) -> dict[str, Any]:
        """What a session stores of how it was read."""
        return {
            "source": f"{self.source.source}:{self.path.name}",
            "import_columns": self.report.columns,
            "import_units": self.report.units,
            "import_notes": self.report.notes,
            # what the import counted, for `sessions` (docs/formats.md)
            "import_samples_lost": self.lost,
            "import_lines_skipped": int(getattr(self.source, "junk_count", 0)),
        }


def open_recording(
    path: str | os.PathLike[str],
    *,
    columns: str | None = None,
    units: str | None = None,
    jaw_length_m: float | None = None,
    rate_hz: float | None = None,
    sheet: str | None = None,
    calibration: Calibration | None = None,
) -> Reading:
    """Open a foreign recording: its layout sniffed, its columns and units chosen, nothing
    of its body read yet (see :func:`read_recording` for the parameters; ``calibration``:
    force and position are ADC counts, turned to SI by it, and ``units`` names the time
    unit only).

    Raises
    ------
    InputError
        With one line that names the file, the column or the line at fault.
    """
    path = Path(path)
    return reading_of(
        open_source(path, sheet),
        path,
        columns=columns,
        units=units,
        jaw_length_m=jaw_length_m,
        rate_hz=rate_hz,
        calibration=calibration,
    )


def reading_of(
    source: Source,
    path: Path,
    *,
    columns: str | None = None,
    units: str | None = None,
    jaw_length_m: float | None = None,
    rate_hz: float | None = None,
    time_optional: bool = False,
    calibration: Calibration | None = None,
) -> Reading:
    """:func:`open_recording` of a source already open (a table, or the first lines of a
    text logger); ``path`` names it in messages. With ``time_optional`` a source without a
    time column is read without one (a logger stamped by the host), and a bare table of
    two columns is force and position.
    """
    if calibration is not None:
        if {"force", "position"} & parse_units(units).given:
            raise InputError(
                "--calibration turns counts into N and m; give --units for time only "
                "(e.g. --units time=ms), or leave --calibration out"
            )
        # counts: read in no unit (factor 1), the calibration makes them SI
        units = ",".join(filter(None, [units, "force=N", "position=m"]))
    report = ImportReport()
    chosen = _choose_columns(
        source, _parse_columns(columns), rate_hz is not None, path, time_optional=time_optional
    )
    units_given = parse_units(units)
    picked: dict[str, tuple[int, str]] = {}
    clock: Clock | None = None
    for quantity in COLUMNS:
        index = chosen.get(quantity)
        if index is None:
            continue
        numeric = source.numeric[index]
        head = source.head_text(index) if not numeric else []
        if quantity == "time" and head and clock_seconds(head) is not None:
            clock = Clock()  # clock times are read in s, whatever --units says
            unit, origin = "s", " (clock times)"
        elif not numeric:
            raise InputError(
                f"{path}: column {source.names[index]!r} holds text, not numbers; choose "
                f"another with --columns {quantity}=NAME"
            )
        else:
            row = source.units[index] if source.units else ""
            unit, origin = _unit(quantity, source.names[index], row, units_given, source.header)
        picked[quantity] = (index, unit)
        report.columns[quantity] = source.names[index]
        report.units[quantity] = unit + origin
    report.ignored = [n for i, n in enumerate(source.names) if i not in chosen.values()]
    keys = getattr(source, "keys", source.names)
    opening = calibration is None and _normal(keys[picked["position"][0]]) in OPENINGS
    if opening:
        report.notes.append(
            f"position: {source.names[picked['position'][0]]!r} grows as the jaws open; "
            "closure is its negative"
        )
    if (
        "time" not in picked
        and not time_optional
        and not (rate_hz and rate_hz > 0 and math.isfinite(rate_hz))
    ):
        raise InputError("--rate must be a positive number of Hz")
    for quantity in ("force", "position"):  # fail before reading the body
        unit = picked[quantity][1]
        if dimension_of(unit) in ("angle", "torque") and not (
            jaw_length_m and jaw_length_m > 0 and math.isfinite(jaw_length_m)
        ):
            what = "an angle" if quantity == "position" else "a torque"
            raise InputError(
                f"{quantity} in {path} is {what} ({unit}); give the jaws' hinge-to-tip "
                "length with --jaw-length, e.g. --jaw-length 20mm"
            )
    reading = Reading(path, source, report, picked, opening, jaw_length_m, rate_hz, clock)
    reading.time_assumed = "time" in picked and report.units["time"].endswith("(SI, assumed)")
    if calibration is not None:
        reading.calibration = calibration
        report.units["force"] = report.units["position"] = "counts (--calibration)"
    return reading


def read_recording(
    path: str | os.PathLike[str],
    *,
    columns: str | None = None,
    units: str | None = None,
    jaw_length_m: float | None = None,
    rate_hz: float | None = None,
    name: str = "",
    sheet: str | None = None,
) -> tuple[Session, ImportReport]:
    """Read a foreign recording into a session in SI units.

    Parameters
    ----------
    path : path
        A text table (CSV, TSV, ...), a spreadsheet, a MATLAB .mat or a NumPy .npz file,
        another program's HDF5 or a LabVIEW TDMS file.
    columns : str, optional
        ``time=NAME,force=NAME,position=NAME``, names or 1-based indices; any omitted
        are found by header name.
    units : str, optional
        ``time=ms,force=gf,position=mm`` or the short ``mm,gf``.
    jaw_length_m : float, optional
        Hinge-to-tip length of the jaws, m: needed when position is an angle.
    rate_hz : float, optional
        Sample rate for files without a time column, Hz.
    name : str
        The session's name.
    sheet : str, optional
        The sheet of a spreadsheet (.xlsx, .xls, .ods) to read; without it the workbook
        must hold one sheet with data.

    Raises
    ------
    InputError
        With one line that names the file, the column or the line at fault.
    """
    reading = open_recording(
        path, columns=columns, units=units, jaw_length_m=jaw_length_m, rate_hz=rate_hz,
        sheet=sheet,
    )  # fmt: skip
    # block by block, as import stores it: the columns kept in blocks and joined one at
    # a time (each list freed as it is joined), the line numbers as runs
    columns: tuple[list[NDArray[np.float64]], ...] = ([], [], [])
    lines = LineNumbers()
    for block in reading.blocks():
        for kept, values in zip(columns, block[:3], strict=True):
            kept.append(values)
        lines.add(block[3])
    reading.finish()
    stamps, force, position = (_join(kept) for kept in columns)
    time = reading.time_base(stamps, lines)
    del stamps
    session = Session(time, force, position, name=name, meta=reading.meta())
    session.validate()
    reading.report.warnings = unit_warnings(
        session, position_given=dimension_of(reading.picked["position"][1]) != "angle"
    )
    return session, reading.report


def _join(blocks: list[NDArray[np.float64]]) -> NDArray[np.float64]:
    """The blocks as one array, each block freed as it is copied (never two copies)."""
    out = np.empty(sum(b.size for b in blocks))
    row = 0
    while blocks:
        block = blocks.pop(0)
        out[row : row + block.size] = block
        row += block.size
    return out


def _parse_columns(spec: str | None) -> dict[str, str]:
    out: dict[str, str] = {}
    for token in (t.strip() for t in (spec or "").split(",")):
        if not token:
            continue
        quantity, sep, column = (part.strip() for part in token.partition("="))
        if not sep or quantity not in COLUMNS or not column:
            raise InputError(
                f"--columns {token[:40]!r}: give QUANTITY=COLUMN with QUANTITY time, force or "
                "position, e.g. time=t_ms,force=3,position=closure"
            )
        if quantity in out:
            raise InputError(f"--columns gives {quantity} twice; give it once")
        out[quantity] = column
    return out


def _normal(name: str) -> str:
    """A header reduced to its word: lower case, no unit, letters (of any script) and
    digits only."""
    bare = re.sub(r"[\(\[].*?[\)\]]", "", name)
    for quantity in COLUMNS:
        unit = unit_in_header(bare, quantity)
        if unit and bare.lower().endswith(unit.lower()) and len(bare) > len(unit) + 1:
            bare = bare[: -len(unit)]
    return re.sub(r"[\W_]", "", bare.lower())


def _choose_columns(
    table: Source,
    spec: dict[str, str],
    rate_given: bool,
    path: Path,
    *,
    time_optional: bool = False,
) -> dict[str, int]:
    """Column index of each quantity: as named, else by header word, else by position."""
    names = table.names
    keys = getattr(table, "keys", names)  # the word a binary file's column is matched by
    chosen: dict[str, int] = {}
    for quantity, column in spec.items():
        if column.isdigit():
            index = int(column) - 1
            if not 0 <= index < len(names):
                raise InputError(f"--columns {quantity}={column}: {path} has {len(names)} columns")
        else:
            matches = (
                [i for i, n in enumerate(names) if n == column]
                or [i for i, n in enumerate(names) if n.lower() == column.lower()]
                or [i for i, n in enumerate(names) if n.strip("/") == column.strip("/")]
            )
            if not matches:
                raise InputError(
                    f"--columns {quantity}={column[:40]!r}: no such column in {path}; it has "
                    + _listed(names)
                )
            index = matches[0]
        chosen[quantity] = index
    wanted = [q for q in COLUMNS if q not in chosen and not (q == "time" and rate_given)]
    for quantity in wanted:
        if not table.header:
            break
        hits = [
            i
            for i, n in enumerate(names)
            if i not in chosen.values()
            and _normal(keys[i]) in SYNONYMS[quantity]
            and (quantity == "time" or table.numeric[i])
        ]
        if len(hits) > 1:
            raise InputError(
                f"{path}: columns {', '.join(repr(names[i]) for i in hits)} could each be "
                f"{quantity}; choose one with --columns {quantity}=NAME"
            )
        if hits:
            chosen[quantity] = hits[0]
    missing = [q for q in wanted if q not in chosen]
    if missing and not table.header and len(names) == len(wanted) and not chosen:
        chosen = {q: i for i, q in enumerate(wanted)}  # a bare table in the documented order
        missing = []
    if time_optional and missing == ["time"]:
        missing = []  # stamped by the host
    elif time_optional and missing and not table.header and not chosen and len(names) == 2:
        chosen, missing = {"force": 0, "position": 1}, []
    if missing:
        hint = " (or --rate HZ if the file has no time column)" if "time" in missing else ""
        raise InputError(
            f"{path}: no column for {' and '.join(missing)} among "
            + _listed(names)
            + f"; name them with --columns {missing[0]}=NAME{hint}"
        )
    return chosen


#: first stamps of a PC clock since 1970 (2001 to 2286), by unit
EPOCHS = {"s": 1e9, "ms": 1e12, "us": 1e15, "ns": 1e18}


def epoch_unit(values: NDArray[np.float64]) -> str | None:
    """The unit of time stamps counted from 1970 by a PC clock (``time.time()``,
    ``Date.now()``, ...), told by their size: 1e9-1e10 in s, 1e12-1e13 in ms, 1e15-1e16
    in us, 1e18-1e19 in ns, with a median step below a minute in that unit; None for
    stamps of any other size (a logger's own seconds or milliseconds since power-up)."""
    finite = values[np.isfinite(values)]
    if finite.size < 2:
        return None
    first = float(finite[0])
    for unit, low in EPOCHS.items():
        if low <= first < 10 * low:
            step = median(np.diff(finite)) * ColumnUnits(time=unit).factor("time")
            return unit if 0 < step < 60.0 else None
    return None


def _listed(names: list[str]) -> str:
    """Column names for a one-line message: the first eight, each cut to 40 characters
    (another program's dataset paths can be long)."""
    shown = [repr(n if len(n) <= 40 else "..." + n[-37:]) for n in names[:8]]
    return ", ".join(shown) + (f" and {len(names) - 8} more" if len(names) > 8 else "")


def _unit(
    quantity: str, header: str, row: str, given: ColumnUnits, has_header: bool
) -> tuple[str, str]:
    """The unit of a column and where it came from: ``--units``, the units row under the
    names, the header, else SI."""
    if quantity in given.given:
        return getattr(given, quantity), " (--units)"
    found = unit_for(row, quantity) if row else None
    if found:
        return found, f" (from the units row: {row!r})"
    found = unit_in_header(header, quantity) if has_header else None
    if found:
        return found, f" (from the header {header!r})"
    if quantity == "position" and _normal(header) in ("angle", "jawangle", "theta"):
        raise InputError(
            f"position column {header!r} looks like an angle; give its unit with --units "
            "position=deg (or rad) and the jaws' length with --jaw-length"
        )
    return getattr(ColumnUnits(), quantity), " (SI, assumed)"


def _force(values: np.ndarray, unit: str, jaw_length_m: float | None, path: Path) -> np.ndarray:
    """Force in N; a torque about the jaws' hinge becomes the force at the tips, ``tau / L``."""
    factor = ColumnUnits(force=unit).factor("force")
    if dimension_of(unit) != "torque":
        return values * factor
    if not (jaw_length_m and jaw_length_m > 0 and math.isfinite(jaw_length_m)):
        raise InputError(
            f"force in {path} is a torque ({unit}); give the jaws' hinge-to-tip length "
            "with --jaw-length, e.g. --jaw-length 20mm"
        )
    return values * factor / jaw_length_m


def _closure(values: np.ndarray, unit: str, jaw_length_m: float | None, path: Path) -> np.ndarray:
    """Jaw closure in m; an angle between the jaws becomes ``-2 L sin(theta / 2)``: minus
    the gap between the tips, so closure grows as the jaws close and is 0 when they meet."""
    if dimension_of(unit) != "angle":
        return values * ColumnUnits(position=unit).factor("position")
    if not (jaw_length_m and jaw_length_m > 0 and math.isfinite(jaw_length_m)):
        raise InputError(
            f"position in {path} is an angle ({unit}); give the jaws' hinge-to-tip length "
            "with --jaw-length, e.g. --jaw-length 20mm"
        )
    theta = values * ColumnUnits(position=unit).factor("position")
    return -2.0 * jaw_length_m * np.sin(theta / 2.0)


class LineNumbers:
    """Line numbers of the rows read, kept as runs of consecutive lines (the first row
    and first line of each), so that a long table's line numbers take memory only for
    the lines skipped between its rows."""

    def __init__(self) -> None:
        self._starts: list[int] = [0]  # first row of each block
        self._runs: list[int | tuple[NDArray[np.int64], NDArray[np.int64]]] = []
        self.rows = 0

    def add(self, lines: NDArray[np.int64]) -> None:
        if not lines.size or lines[-1] - lines[0] == lines.size - 1:
            self._runs.append(int(lines[0]) if lines.size else 0)
        else:
            starts = np.concatenate(([0], np.flatnonzero(np.diff(lines) != 1) + 1))
            self._runs.append((starts, lines[starts]))
        self.rows += lines.size
        self._starts.append(self.rows)

    def __getitem__(self, row: int) -> int:
        i = bisect.bisect_right(self._starts, int(row)) - 1
        run = self._runs[i]
        offset = int(row) - self._starts[i]
        if isinstance(run, int):
            return run + offset
        rows, lines = run
        j = int(np.searchsorted(rows, offset, side="right")) - 1
        return int(lines[j]) + offset - int(rows[j])


#: rows an import keeps before writing them to the file (24 MB of samples)
FLUSH_ROWS = 1 << 20
#: rows per HDF5 chunk of an imported session: written a million rows at a time and
#: read back whole for the time base, it reads at twice the pace of 4096-row chunks
IMPORT_CHUNK_ROWS = 1 << 16


def _rewrite_time(writer: Any, fit: ClockFit) -> float:
    """Write the fitted times, s from the first, over the stamps of ``writer``'s time
    column, block by block; the last time, s."""
    first: float | None = None
    last = 0.0

    def blocks() -> Iterator[NDArray[np.float64]]:
        nonlocal first, last
        for block in fit.times():
            if first is None:
                first = float(block[0])
            block = block - first
            last = float(block[-1])
            yield block

    writer.rewrite_blocks("time", blocks())
    return last


def store_recording(
    reading: Reading,
    out: str | os.PathLike[str],
    name: str,
    meta: dict[str, Any],
    progress: Callable[[float], None] | None = None,
) -> tuple[int, float, float]:
    """Read a recording block by block into a new session ``name`` of ``out``, each block
    written as it is read; the time base is then put back on its clock from the stamps
    written, read back block by block, and the times written over them.

    Memory: a few blocks, whatever the length (the line numbers take memory only for
    the lines skipped between rows). If reading fails anywhere, the session is removed
    again (and the file, if this created it).

    Returns
    -------
    samples : int
    duration_s, rate_hz : float

    Raises
    ------
    InputError, StorageError
    """
    from .sessions import discard_session, session_writer

    out = os.fspath(out)
    created = not os.path.exists(out)
    lines = LineNumbers()
    buffered = 0
    peak = 0.0
    low, high = math.inf, -math.inf
    writer = session_writer(
        out, name, meta={**meta, **reading.meta()},
        calibration=reading.calibration.as_dict() if reading.calibration else None, raw=False,
        flush_interval_s=math.inf, fsync=False, chunk_rows=IMPORT_CHUNK_ROWS,
    )  # fmt: skip
    try:
        for t, force, position, numbers in reading.blocks():
            for label, values in (("force", force), ("position", position)):
                # a finite sum says every value is finite, without an array of flags
                if math.isfinite(float(np.sum(values))):
                    continue
                bad = np.flatnonzero(~np.isfinite(values))
                if bad.size:
                    raise InputError(
                        f"{reading.path}: {label} is not a finite number at line "
                        f"{numbers[bad[0]]}; remove or repair that row"
                    )
            writer.append({"time": t, "force": force, "position": position})
            buffered += t.size
            if buffered >= FLUSH_ROWS:  # a few blocks a write: fewer flushes of the file
                writer.flush()
                buffered = 0
            lines.add(numbers)
            if force.size:
                peak = max(peak, float(force.max()), -float(force.min()))
                low, high = min(low, float(position.min())), max(high, float(position.max()))
            if progress is not None:
                progress(reading.fraction())
        reading.finish()
        if lines.rows < 3:
            raise InputError(f"{reading.path}: {lines.rows} sample(s) are too few to fit")
        stamps = writer.column("time")
        fit = reading.fit_clock(stamps, lines)
        first = float(stamps[0:1][0])
        if fit is None or fit.exact and first == 0.0 and math.copysign(1.0, first) > 0:
            last = float(stamps[len(stamps) - 1 :][0])  # the stamps are the times
        else:
            last = _rewrite_time(writer, fit)
        n, duration = lines.rows, last
        rate = (n - 1) / duration if duration > 0 else 0.0
        summary = Session(  # the extremes and the rate, for the unit warnings
            np.arange(3) / (rate or 1.0), np.array([0.0, peak, 0.0]),
            np.array([low, high, low]),
        )  # fmt: skip
        reading.report.warnings = unit_warnings(
            summary, position_given=dimension_of(reading.picked["position"][1]) != "angle"
        )
        counted = reading.meta()  # what the import counted is known only now
        writer.set_attrs(
            import_notes=reading.report.notes,
            import_samples_lost=counted["import_samples_lost"],
            import_lines_skipped=counted["import_lines_skipped"],
            **({"import_warnings": reading.report.warnings} if reading.report.warnings else {}),
        )
        writer.close()
    except BaseException:
        writer.close(complete=False)
        discard_session(out, name, created)
        raise
    return n, duration, rate
