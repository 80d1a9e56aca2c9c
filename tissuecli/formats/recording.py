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

import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..core.errors import InputError
from ..core.plausible import unit_warnings
from ..core.session import COLUMNS, Session
from ..core.timebase import regularise
from ..core.units import ColumnUnits, dimension_of, parse_units, unit_in_header
from .arrays import read_arrays
from .tables import Table, clock_seconds, read_table

#: header words (lower case, letters and digits only, unit removed) for each column
SYNONYMS = {
    "time": ("time", "t", "timestamp", "times", "sec", "seconds", "elapsed", "ts", "timesec"),
    "force": ("force", "f", "load", "graspforce", "grip", "gripforce", "fz", "forcesensor"),
    "position": (
        "position", "pos", "closure", "x", "displacement", "disp", "jaw", "gap", "depth",
        "indentation", "stroke", "opening", "angle", "jawangle", "theta", "jawposition",
        "jawgap", "jawopening",
    ),
}  # fmt: skip
#: position headers that name the opening between the jaws: closure is their negative
OPENINGS = ("gap", "opening", "jawgap", "jawopening")
ARRAY_SUFFIXES = (".mat", ".npz")


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


def read_recording(
    path: str | os.PathLike[str],
    *,
    columns: str | None = None,
    units: str | None = None,
    jaw_length_m: float | None = None,
    rate_hz: float | None = None,
    name: str = "",
) -> tuple[Session, ImportReport]:
    """Read a foreign recording into a session in SI units.

    Parameters
    ----------
    path : path
        A text table (CSV, TSV, ...), a MATLAB .mat or a NumPy .npz file.
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

    Raises
    ------
    InputError
        With one line that names the file, the column or the line at fault.
    """
    path = Path(path)
    table = read_arrays(path) if path.suffix.lower() in ARRAY_SUFFIXES else read_table(path)
    report = ImportReport(notes=list(table.notes))
    chosen = _choose_columns(table, _parse_columns(columns), rate_hz is not None, path)
    units_given = parse_units(units)
    picked = {}
    for quantity in COLUMNS:
        index = chosen.get(quantity)
        if index is None:
            continue
        clock = (
            clock_seconds(table.text[index]) if quantity == "time" and index in table.text else None
        )
        if clock is not None:
            table.data[:, index] = clock  # clock times are read in s, whatever --units says
            unit, origin = "s", " (clock times)"
        elif np.all(np.isnan(table.data[:, index])):
            raise InputError(
                f"{path}: column {table.names[index]!r} holds text, not numbers; choose "
                f"another with --columns {quantity}=NAME"
            )
        else:
            unit, origin = _unit(quantity, table.names[index], units_given, table.header)
        picked[quantity] = (index, unit)
        report.columns[quantity] = table.names[index]
        report.units[quantity] = unit + origin
    report.ignored = [n for i, n in enumerate(table.names) if i not in chosen.values()]
    data = table.data
    force = _force(data[:, picked["force"][0]], picked["force"][1], jaw_length_m, path)
    position = _closure(data[:, picked["position"][0]], picked["position"][1], jaw_length_m, path)
    if _normal(table.names[picked["position"][0]]) in OPENINGS:
        position = -position
        report.notes.append(
            f"position: {table.names[picked['position'][0]]!r} grows as the jaws open; "
            "closure is its negative"
        )
    lost = 0
    if "time" in picked:
        stamps = data[:, picked["time"][0]] * ColumnUnits(time=picked["time"][1]).factor("time")
        time, base = regularise(stamps, table.lines)
        report.notes.append("time: " + base.describe())
        lost = base.lost
    else:
        if not (rate_hz and rate_hz > 0 and math.isfinite(rate_hz)):
            raise InputError("--rate must be a positive number of Hz")
        time = np.arange(data.shape[0]) / rate_hz
        report.notes.append(f"time: from the sample index at {rate_hz:g} Hz (--rate)")
    session = Session(
        time - time[0],
        force,
        position,
        name=name,
        meta={
            "source": f"{table.source}:{path.name}",
            "import_columns": report.columns,
            "import_units": report.units,
            "import_notes": report.notes,
            # what the import counted, for `sessions` (docs/formats.md)
            "import_samples_lost": int(lost),
            "import_lines_skipped": len(getattr(table, "junk", []) or []),
        },
    )
    session.validate()
    report.warnings = unit_warnings(
        session, position_given=dimension_of(picked["position"][1]) != "angle"
    )
    return session, report


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
    """A header reduced to its word: lower case, no unit, letters and digits only."""
    bare = re.sub(r"[\(\[].*?[\)\]]", "", name)
    for quantity in COLUMNS:
        unit = unit_in_header(bare, quantity)
        if unit and bare.lower().endswith(unit.lower()) and len(bare) > len(unit) + 1:
            bare = bare[: -len(unit)]
    return re.sub(r"[^a-z0-9]", "", bare.lower())


def _choose_columns(
    table: Table, spec: dict[str, str], rate_given: bool, path: Path
) -> dict[str, int]:
    """Column index of each quantity: as named, else by header word, else by position."""
    names = table.names
    chosen: dict[str, int] = {}
    for quantity, column in spec.items():
        if column.isdigit():
            index = int(column) - 1
            if not 0 <= index < len(names):
                raise InputError(f"--columns {quantity}={column}: {path} has {len(names)} columns")
        else:
            matches = [i for i, n in enumerate(names) if n == column] or [
                i for i, n in enumerate(names) if n.lower() == column.lower()
            ]
            if not matches:
                raise InputError(
                    f"--columns {quantity}={column[:40]!r}: no such column in {path}; it has "
                    + ", ".join(repr(n) for n in names[:12])
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
            and _normal(n) in SYNONYMS[quantity]
            and (quantity == "time" or not np.all(np.isnan(table.data[:, i])))
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
    if missing:
        hint = " (or --rate HZ if the file has no time column)" if "time" in missing else ""
        raise InputError(
            f"{path}: no column for {' and '.join(missing)} among "
            + ", ".join(repr(n) for n in names[:12])
            + f"; name them with --columns {missing[0]}=NAME{hint}"
        )
    return chosen


def _unit(quantity: str, header: str, given: ColumnUnits, has_header: bool) -> tuple[str, str]:
    """The unit of a column and where it came from."""
    if quantity in given.given:
        return getattr(given, quantity), " (--units)"
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
