"""Delimited text tables as loggers write them: comma, tab, semicolon, bar or whitespace
separated (sniffed), with or without a byte-order mark, CRLF or LF, comment and
preamble lines, a header or none, decimal commas, and junk lines (a truncated last
line, a repeated header), which are counted and reported, never silently dropped."""

from __future__ import annotations

import codecs
import os
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ..core.errors import InputError

#: lines starting with these are comments
COMMENTS = ("#", "%", "//", "!")
#: candidate separators, in the order that wins a tie
DELIMITERS = ("\t", ";", ",", "|", " ")
_WHITESPACE = re.compile(r"\s+")


@dataclass
class Table:
    """Numeric columns read from a foreign file.

    Attributes
    ----------
    names : list of str
        Column names: the header's, or ``"1"``, ``"2"``, ... without one.
    data : ndarray, shape (n, k)
        The numeric rows, in the file's units.
    lines : ndarray of int, shape (n,)
        1-based line (or row) number of each row in the file, for messages.
    source : str
        What was read, for messages and provenance (``"csv"``, ``"mat v5"``, ...).
    notes : list of str
        What the reader found and did: delimiter, encoding, comments, junk lines.
    junk : list of int
        Line numbers of lines that are neither data, header, comment nor blank.
    header : bool
        Whether the names came from the file.
    text : dict of int to list of str
        The fields of each text column (NaN in ``data``), one per row: a clock time
        (``12:03:04.125``) may be a time column.
    """

    names: list[str]
    data: NDArray[np.float64]
    lines: NDArray[np.int64]
    source: str
    notes: list[str] = field(default_factory=list)
    junk: list[int] = field(default_factory=list)
    header: bool = True
    text: dict[int, list[str]] = field(default_factory=dict)


def decode(raw: bytes, path: Path) -> tuple[str, str]:
    """Text and the encoding it was read with: a byte-order mark wins, then UTF-8, then
    Latin-1 (which decodes anything, so it is said in the notes)."""
    if raw.startswith(codecs.BOM_UTF8):
        return raw[len(codecs.BOM_UTF8) :].decode("utf-8", "replace"), "UTF-8 with BOM"
    for bom, name in ((codecs.BOM_UTF16_LE, "utf-16-le"), (codecs.BOM_UTF16_BE, "utf-16-be")):
        if raw.startswith(bom):
            return raw[len(bom) :].decode(name, "replace"), name.upper() + " with BOM"
    if b"\x00" in raw[:65536]:
        raise InputError(
            f"{path} is a binary file, not a text table; give a CSV/TSV export, a MATLAB "
            ".mat or a NumPy .npz file"
        )
    try:
        return raw.decode("utf-8"), "UTF-8"
    except UnicodeDecodeError:
        return raw.decode("latin-1"), "Latin-1 (not valid UTF-8)"


def read_table(path: str | os.PathLike[str]) -> Table:
    """Read a delimited text table, sniffing its layout.

    Raises
    ------
    InputError
        The file is missing, binary, has no numeric rows, or more junk than data.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise InputError(f"{path} does not exist; check the path") from None
    except IsADirectoryError:
        raise InputError(f"{path} is a directory; give a file") from None
    except OSError as exc:
        raise InputError(f"cannot read {path}: {exc.strerror}") from None
    text, encoding = decode(raw, path)
    numbered: list[tuple[int, str]] = []
    comment_lines: list[tuple[int, str]] = []
    marks = 0  # lines of punctuation alone: a rich-text export's "\\", a closing "}"
    for i, raw_line in enumerate(text.splitlines()):
        line = raw_line.strip()
        if not line:
            continue
        if line.startswith(COMMENTS):
            comment_lines.append((i + 1, line))
        elif not any(c.isalnum() for c in line):
            marks += 1
        else:
            numbered.append((i + 1, line))
    comments = len(comment_lines)
    if not numbered:
        raise InputError(f"{path} holds no data lines")
    sniffed = _sniff([line for _, line in numbered[:400]])
    if sniffed is None:
        raise InputError(
            f"{path} holds no rows of numbers (no line parses as two or more numbers "
            "separated by commas, tabs, semicolons, bars or spaces)"
        )
    delimiter, width, decimal_comma, numeric = sniffed
    rows: list[list[float]] = []
    lines: list[int] = []
    header: list[str] | None = None
    before: list[tuple[int, list[str]]] = []  # lines before the first data row
    junk: list[int] = []
    text: dict[int, list[str]] = {i: [] for i in range(width) if not numeric[i]}
    for number, line in numbered:
        fields = _split(line, delimiter)
        values = _numbers(fields, decimal_comma, numeric) if len(fields) == width else None
        if values is not None:
            rows.append(values)
            lines.append(number)
            for i, column in text.items():
                column.append(fields[i].strip().strip('"'))
        elif rows:
            junk.append(number)
        else:
            before.append((number, fields))
    if not rows:
        raise InputError(
            f"{path} holds no rows of numbers ({width} fields); check that it is a table"
        )
    # the header is the line right before the data, if it has a name for every column;
    # anything earlier is a preamble (a logger's title, date, settings)
    if before and len(before[-1][1]) == width:
        header = [f.strip().strip('"').strip("'") for f in before.pop()[1]]
    elif not before:
        # some loggers write the header as the last comment line before the data
        lead = [c for c in comment_lines if c[0] < lines[0]]
        if lead:
            fields = _split(lead[-1][1].lstrip("#%/! "), delimiter)
            if len(fields) == width and _numbers(fields, decimal_comma) is None:
                header = [f.strip().strip('"').strip("'") for f in fields]
    preamble = [number for number, _ in before]
    if len(junk) > max(10, len(rows) // 10):
        raise InputError(
            f"{path}: {len(junk)} of {len(junk) + len(rows)} lines do not parse as {width} "
            f"numbers (first at line {junk[0]}); check the delimiter and the columns"
        )
    names = header if header is not None else [str(i + 1) for i in range(width)]
    text_columns = [names[i] for i in range(width) if not numeric[i]]
    shown = {"\t": "tab", " ": "whitespace", ";": "semicolon", ",": "comma", "|": "bar"}
    notes = [
        f"{shown[delimiter]}-separated, {encoding}"
        + (", decimal commas" if decimal_comma else "")
        + (f", {comments} comment line(s)" if comments else "")
        + (f", {len(preamble)} preamble line(s)" if preamble else "")
        + (f", {marks} line(s) of punctuation alone" if marks else "")
    ]
    if text_columns:
        notes.append("text column(s), not numbers: " + ", ".join(repr(n) for n in text_columns))
    if junk:
        where = ", ".join(str(j) for j in junk[:5]) + (" ..." if len(junk) > 5 else "")
        notes.append(f"{len(junk)} junk line(s) skipped (line {where})")
    return Table(
        names=names,
        data=np.array(rows, dtype=float),
        lines=np.array(lines, dtype=np.int64),
        source="text table",
        notes=notes,
        junk=junk,
        header=header is not None,
        text=text,
    )


def _split(line: str, delimiter: str) -> list[str]:
    return _WHITESPACE.split(line.strip()) if delimiter == " " else line.split(delimiter)


def _sniff(sample: list[str]) -> tuple[str, int, bool, list[bool]] | None:
    """The separator, field count and decimal mark that parse most sample lines as rows of
    numbers, and which columns hold numbers (a logger may add a text column: a status,
    a label); None if no line holds two or more numbers."""
    best: tuple[int, int, int] | None = None
    choice: tuple[str, int, bool, list[bool]] = (",", 1, False, [True])
    for rank, delim in enumerate(DELIMITERS):
        split = [_split(line, delim) for line in sample]
        widths = Counter(len(f) for f in split)
        width, _ = widths.most_common(1)[0]
        if width < 2:
            continue
        rows = [f for f in split if len(f) == width]
        for decimal_comma in (False, True):
            if decimal_comma and delim == ",":
                continue
            # a column holds numbers when most rows with numbers in them parse there
            parsed = np.array([[_number(v, decimal_comma) is not None for v in f] for f in rows])
            parsed = parsed[parsed.sum(axis=1) >= 2]
            if not parsed.size:
                continue
            numeric = list(parsed.mean(axis=0) >= 0.5)
            if sum(numeric) < 2:
                continue
            count = sum(1 for f in rows if _numbers(f, decimal_comma, numeric) is not None)
            key = (count, sum(numeric) if count else 0, -rank)
            if best is None or key > best:
                best, choice = key, (delim, width, decimal_comma, numeric)
    if best is None or best[0] == 0:
        return None
    return choice


def _number(field: str, decimal_comma: bool) -> float | None:
    """A field as a finite float, or None."""
    f = field.strip().strip('"')
    if decimal_comma:
        f = f.replace(",", ".")
    try:
        value = float(f)
    except ValueError:
        return None
    return value if np.isfinite(value) else None


def _numbers(
    fields: list[str], decimal_comma: bool, numeric: list[bool] | None = None
) -> list[float] | None:
    """The fields as finite floats (NaN in text columns, ``numeric`` False), or None if a
    numeric field is not one."""
    out = []
    for i, f in enumerate(fields):
        if numeric is not None and not numeric[i]:
            out.append(float("nan"))
            continue
        value = _number(f, decimal_comma)
        if value is None:
            return None
        out.append(value)
    return out


#: a clock time: optional date, hours, minutes and seconds (or minutes and seconds)
_CLOCK = re.compile(
    r"(?:(\d{4})[-/](\d{1,2})[-/](\d{1,2})[T ])?"
    r"(\d{1,2}):(\d{2}(?:[.,]\d+)?)(?::(\d{2}(?:[.,]\d+)?))?"
)


def clock_seconds(fields: list[str]) -> NDArray[np.float64] | None:
    """Seconds from the first of a column of clock times (``12:03:04.125``, ``03:04.5`` as
    minutes and seconds, ``2021-04-14 18:24:01.123``, ``2021-04-14T18:24:01Z``); a
    time of day that goes back by more than 12 hours has passed midnight. None if a
    field is not a clock time."""
    import datetime as dt

    out = np.empty(len(fields))
    day = 0.0
    first_day: int | None = None
    for i, f in enumerate(fields):
        m = _CLOCK.fullmatch(f.strip().removesuffix("Z"))
        if m is None:
            return None
        year, month, mday, a, b, c = m.groups()
        if c is None:  # mm:ss.s
            seconds = int(a) * 60.0 + float(b.replace(",", "."))
        elif "." in b or "," in b:
            return None
        else:
            seconds = int(a) * 3600.0 + int(b) * 60.0 + float(c.replace(",", "."))
        if year:
            try:
                ordinal = dt.date(int(year), int(month), int(mday)).toordinal()
            except ValueError:
                return None
            first_day = ordinal if first_day is None else first_day
            # days counted from the first, so that milliseconds keep their precision
            seconds += (ordinal - first_day) * 86400.0
        elif i and seconds + day < out[i - 1] - 43200.0:
            day += 86400.0
        out[i] = seconds + day
    return out - out[0] if out.size else out
