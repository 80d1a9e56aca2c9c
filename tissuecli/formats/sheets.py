"""Spreadsheets (.xlsx, .xlsm, .xlsb, .xls, .ods) read through python-calamine, one sheet
at a time: each sheet is a recording, laid out as a text table would be (a preamble, a
header, a units row under it, then rows of numbers; clock or date cells become clock
times), with junk rows counted and reported as a text table's are.

A workbook of several sheets with data needs one named (``--sheet NAME``) to be fitted;
``import`` stores each sheet as a session named after it (:func:`data_sheets`).
"""

from __future__ import annotations

import datetime as dt
import os
from pathlib import Path
from typing import Any

import numpy as np

from ..core.errors import InputError
from .tables import Table, _bare_unit, _units_row

#: suffixes read as workbooks
SUFFIXES = (".xlsx", ".xlsm", ".xlsb", ".xls", ".ods")
#: cells a sheet may declare before any is read (a sheet of Excel's own maximum, 2^20
#: rows, of 16 columns); beyond it the workbook is refused, not allocated
MAX_CELLS = (1 << 20) * 16
#: rows looked at to tell the columns that hold numbers
SNIFF_ROWS = 400


def is_workbook(path: str | os.PathLike[str]) -> bool:
    """Whether a file is read as a spreadsheet (by its suffix)."""
    return Path(path).suffix.lower() in SUFFIXES


def _open(path: Path) -> Any:
    try:
        from python_calamine import CalamineWorkbook
    except ImportError:  # pragma: no cover - a dependency
        raise InputError(
            f"{path} is a spreadsheet; reading it needs python-calamine "
            "(pip install python-calamine), or export the sheet as CSV"
        ) from None
    if not path.exists():
        raise InputError(f"{path} does not exist; check the path")
    if path.is_dir():
        raise InputError(f"{path} is a directory; give a file")
    try:
        return CalamineWorkbook.from_path(str(path))
    except Exception as exc:  # calamine's own errors name no common class
        raise InputError(
            f"cannot read {path} as a spreadsheet ({str(exc).splitlines()[0][:120]}); "
            "check that it is an .xlsx, .xls or .ods workbook"
        ) from None


def _sheet_names(book: Any) -> list[str]:
    """The worksheets of a workbook, in order (chart sheets left out)."""
    names = []
    for meta in book.sheets_metadata:
        if "WorkSheet" in str(meta.typ) or "Work" in str(meta.typ):
            names.append(meta.name)
    return names or list(book.sheet_names)


def _sheet(book: Any, name: str, path: Path) -> Any:
    try:
        sheet = book.get_sheet_by_name(name)
    except Exception as exc:
        raise InputError(f"cannot read sheet {name!r} of {path}: {str(exc)[:120]}") from None
    if sheet.total_height * max(sheet.total_width, 1) > MAX_CELLS:
        raise InputError(
            f"sheet {name!r} of {path} declares {sheet.total_height} rows x "
            f"{sheet.total_width} columns, more than any recording tissuecli reads "
            f"({MAX_CELLS} cells); export the columns needed as CSV"
        )
    return sheet


def data_sheets(path: str | os.PathLike[str]) -> list[str]:
    """The sheets of a workbook that hold rows of numbers, in order.

    Raises
    ------
    InputError
        The file is not a workbook, or no sheet holds rows of numbers.
    """
    path = Path(path)
    book = _open(path)
    names = _sheet_names(book)
    found = []
    for name in names:
        sheet = _sheet(book, name, path)
        for k, row in enumerate(sheet.iter_rows()):
            if sum(_number(c) is not None for c in row) >= 2:
                found.append(name)
                break
            if k >= SNIFF_ROWS:
                break
    if not found:
        raise InputError(
            f"{path} holds no sheet with rows of numbers; its sheets: "
            + ", ".join(repr(n) for n in names)
        )
    return found


def read_sheet(path: str | os.PathLike[str], sheet: str | None = None) -> Table:
    """One sheet of a workbook as a :class:`~.tables.Table`.

    Parameters
    ----------
    path : path
        The workbook.
    sheet : str, optional
        The sheet's name; without it the workbook must hold one sheet with data.

    Raises
    ------
    InputError
        In one line: no such sheet (the sheets found listed), several sheets with data
        and none chosen, no rows of numbers, or more junk than data.
    """
    path = Path(path)
    book = _open(path)
    names = _sheet_names(book)
    if sheet is None:
        found = data_sheets(path)
        if len(found) > 1:
            raise InputError(
                f"{path} holds {len(found)} sheets with data ("
                + ", ".join(repr(n) for n in found)
                + "); choose one with --sheet NAME (import stores each as a session)"
            )
        sheet = found[0]
    elif sheet not in names:
        raise InputError(
            f"{path} has no sheet {sheet!r}; its sheets: " + ", ".join(repr(n) for n in names)
        )
    cells = _sheet(book, sheet, path)
    first_row = int(cells.start[0]) if cells.start else 0
    rows = [[_cell(c) for c in row] for row in cells.iter_rows()]
    table = _table(rows, first_row, path, sheet)
    many = len(names) > 1
    table.notes.insert(
        0,
        f"sheet {sheet!r}" + (f" of {len(names)} (" + ", ".join(repr(n) for n in names) + ")"
                               if many else ""),
    )  # fmt: skip
    return table


def _number(cell: Any) -> float | None:
    """A cell as a finite float, or None (text, empty, a date, a boolean)."""
    if isinstance(cell, bool):
        return None
    if isinstance(cell, (int, float)):
        value = float(cell)
    elif isinstance(cell, str):
        text = cell.strip()
        if not text:
            return None
        try:
            value = float(text.replace(",", ".") if text.count(",") == 1 and "." not in text
                          else text)  # fmt: skip
        except ValueError:
            return None
    elif isinstance(cell, dt.timedelta):
        value = cell.total_seconds()
    else:
        return None
    return value if np.isfinite(value) else None


def _cell(cell: Any) -> Any:
    """A cell as a number, or as text: a clock time or a date-and-time as the text
    tables' clock reader takes them (``12:03:04.125``, ``2021-04-14 18:24:01.123``)."""
    if isinstance(cell, dt.datetime):
        return cell.strftime("%Y-%m-%d %H:%M:%S.%f")
    if isinstance(cell, dt.time):
        return cell.strftime("%H:%M:%S.%f")
    if isinstance(cell, dt.date):  # a date-and-time at midnight is read as a date
        return cell.strftime("%Y-%m-%d 00:00:00.000000")
    number = _number(cell)
    if number is not None:
        return number
    return "" if cell is None else str(cell).strip()


def _table(rows: list[list[Any]], first_row: int, path: Path, sheet: str) -> Table:
    """The layout of a sheet's rows (as :func:`~.tables.sniff_table` finds a text
    table's), and its data."""
    where = f"sheet {sheet!r} of {path}"
    width = 0
    for row in rows:
        filled = [i for i, c in enumerate(row) if c != ""]
        if filled:
            width = max(width, filled[-1] + 1)
    rows = [(row + [""] * width)[:width] for row in rows]
    sample = [r for r in rows if sum(isinstance(c, float) for c in r) >= 2][:SNIFF_ROWS]
    if width < 2 or not sample:
        raise InputError(f"{where} holds no rows of numbers; check the sheet")
    numeric = [
        sum(isinstance(r[i], float) for r in sample) >= 0.5 * len(sample) for i in range(width)
    ]
    if sum(numeric) < 2:
        raise InputError(f"{where} holds fewer than two columns of numbers; check the sheet")

    def is_data(row: list[Any]) -> bool:
        return all(isinstance(c, float) for c, n in zip(row, numeric, strict=True) if n)

    first = next(k for k, row in enumerate(rows) if is_data(row))
    before = [[str(c) for c in row] for row in rows[:first] if any(c != "" for c in row)]
    units: list[str] | None = None
    header: list[str] | None = None
    if len(before) >= 2 and _units_row(before[-1]):
        units = [_bare_unit(f) for f in before.pop()]
    if before and sum(f.strip() != "" for f in before[-1]) >= sum(numeric):
        header = [f.strip() or str(i + 1) for i, f in enumerate(before.pop())]
    names = header if header is not None else [str(i + 1) for i in range(width)]
    data: list[list[float]] = []
    lines: list[int] = []
    text: dict[int, list[str]] = {i: [] for i in range(width) if not numeric[i]}
    junk: list[int] = []
    junk_count = 0
    for k in range(first, len(rows)):
        row = rows[k]
        if all(c == "" for c in row):
            continue
        if not is_data(row):
            junk_count += 1
            if len(junk) < 5:
                junk.append(first_row + k + 1)
            continue
        data.append([c if numeric[i] else np.nan for i, c in enumerate(row)])
        lines.append(first_row + k + 1)
        for i, column in text.items():
            column.append(str(row[i]))
    if junk_count > max(10, len(data) // 10):
        raise InputError(
            f"{where}: {junk_count} of {junk_count + len(data)} rows do not hold "
            f"{sum(numeric)} numbers (first at row {junk[0]}); check the columns"
        )
    notes = [
        ", ".join(
            ["a header" if header is not None else "no header"]
            + (["a units row"] if units else [])
            + ([f"{len(before)} preamble row(s)"] if before else [])
        )
    ]
    if text:
        notes.append("text column(s), not numbers: " + ", ".join(repr(names[i]) for i in text))
    if junk_count:
        shown = ", ".join(str(j) for j in junk) + (" ..." if junk_count > 5 else "")
        notes.append(f"{junk_count} junk row(s) skipped (row {shown})")
    suffix = path.suffix.lower().lstrip(".")
    table = Table(
        names=names,
        data=np.array(data, dtype=float).reshape(len(data), width),
        lines=np.array(lines, dtype=np.int64),
        source=suffix,
        notes=notes,
        junk=junk,
        header=header is not None,
        text=text,
        units=units,
    )
    table.junk_count = junk_count  # type: ignore[attr-defined]  # as a text table's
    return table
