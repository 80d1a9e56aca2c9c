"""Delimited text tables as loggers write them: comma, tab, semicolon, bar or whitespace
separated (sniffed), in UTF-8, UTF-16 with a byte-order mark, cp1252, GBK or Shift-JIS,
CRLF or LF, comment and preamble lines, a header or none, a units row under the names,
decimal commas, and junk lines (a truncated last line, a repeated header), which are
counted and reported, never silently dropped.

The layout is sniffed from the first megabyte (:func:`sniff_table`); the body is then read
block by block by pyarrow's C parser (:meth:`Layout.blocks`), so a table of any length is
read in the memory of a few blocks. A block the parser cannot take whole (junk, comments,
blank lines, non-finite values) is read line by line as before, so every junk line is
still counted with its number.
"""

from __future__ import annotations

import codecs
import math
import os
import re
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ..core.errors import InputError
from ..core.units import unit_factor

#: lines starting with these are comments
COMMENTS = ("#", "%", "//", "!")
#: candidate separators, in the order that wins a tie
DELIMITERS = ("\t", ";", ",", "|", " ")
_WHITESPACE = re.compile(r"\s+")
#: bytes sniffed for the layout
HEAD_BYTES = 1 << 20
#: bytes of the body parsed at a time
BLOCK_BYTES = 1 << 23
#: a longer line is not a row of samples
MAX_LINE_BYTES = 1 << 20
#: pieces of a block that pyarrow parses side by side on the cores (each holds whole
#: lines of up to MAX_LINE_BYTES)
PARSE_BYTES = 1 << 21
#: encodings tried, in this order on a tie, when a file is not UTF-8
LEGACY_ENCODINGS = ("cp1252", "gbk", "shift_jis")


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
    units : list of str, optional
        A units row under the names, one field per column (``""`` where none).
    """

    names: list[str]
    data: NDArray[np.float64]
    lines: NDArray[np.int64]
    source: str
    notes: list[str] = field(default_factory=list)
    junk: list[int] = field(default_factory=list)
    header: bool = True
    text: dict[int, list[str]] = field(default_factory=dict)
    units: list[str] | None = None

    @property
    def numeric(self) -> list[bool]:
        return [i not in self.text for i in range(len(self.names))]

    def head_text(self, index: int) -> list[str]:
        return self.text.get(index, [])[:400]

    def blocks(self, columns: list[int]) -> Iterator[Block]:
        """The chosen columns, :data:`~.limits.BLOCK_ROWS` rows at a time."""
        from .limits import BLOCK_ROWS

        for i in range(0, max(1, len(self.lines)), BLOCK_ROWS):
            yield Block(
                self.data[i : i + BLOCK_ROWS, columns],
                self.lines[i : i + BLOCK_ROWS],
                {c: self.text[c][i : i + BLOCK_ROWS] for c in columns if c in self.text},
            )

    def finish(self) -> list[str]:
        return list(self.notes)

    def fraction(self) -> float:
        return 1.0


@dataclass
class Block:
    """Rows of the chosen columns: values (NaN in text columns), line numbers, and the
    fields of the chosen text columns."""

    values: NDArray[np.float64]
    lines: NDArray[np.int64]
    text: dict[int, list[str]] = field(default_factory=dict)


def decode(raw: bytes, path: Path) -> tuple[str, str, str]:
    """Text, the codec and the encoding in words: a byte-order mark wins, then UTF-8, then
    whichever of cp1252, GBK and Shift-JIS reads the non-ASCII text most plausibly
    (:func:`_plausible`), then Latin-1 (which decodes anything, so it is said in the
    notes)."""
    if raw.startswith(codecs.BOM_UTF8):
        return raw[len(codecs.BOM_UTF8) :].decode("utf-8", "replace"), "utf-8", "UTF-8 with BOM"
    for bom, name in ((codecs.BOM_UTF16_LE, "utf-16-le"), (codecs.BOM_UTF16_BE, "utf-16-be")):
        if raw.startswith(bom):
            return raw[len(bom) :].decode(name, "replace"), name, name.upper() + " with BOM"
    if b"\x00" in raw[:65536]:
        raise InputError(
            f"{path} is a binary file, not a text table; give a CSV/TSV export, a "
            "spreadsheet, a MATLAB .mat, a NumPy .npz, an HDF5 or a TDMS file"
        )
    try:
        return raw.decode("utf-8"), "utf-8", "UTF-8"
    except UnicodeDecodeError as exc:
        if exc.start >= len(raw) - 3 and exc.reason == "unexpected end of data":
            return raw[: exc.start].decode("utf-8"), "utf-8", "UTF-8"  # a cut character
    best: tuple[int, str, str] | None = None
    for rank, codec in enumerate(LEGACY_ENCODINGS):
        try:
            text = raw.decode(codec)
        except UnicodeDecodeError as exc:
            if not (exc.start >= len(raw) - 1 and exc.reason.startswith("incomplete")):
                continue
            text = raw[: exc.start].decode(codec)
        score = _plausible(text, codec)
        if best is None or score > best[0]:
            best = (score, codec, text)
        del rank
    if best is not None and best[0] > 0:
        label = {"cp1252": "cp1252 (Windows Western)", "gbk": "GBK", "shift_jis": "Shift-JIS"}
        return best[2], best[1], label[best[1]] + " (not valid UTF-8)"
    return raw.decode("latin-1"), "latin-1", "Latin-1 (not valid UTF-8)"


#: non-ASCII characters a Western header may hold beside letters
_SYMBOLS = "µ°²³±·€"


def _plausible(text: str, codec: str) -> int:
    """How plausibly `text` is what `codec` would make of a header: one point for each
    non-ASCII character that reads as a word of that script, minus one for each that does
    not. In cp1252 an accented letter sits in a Latin word (``Déplacement``, ``Kraft
    (µN)``), while CJK text read as cp1252 is runs of accented letters and symbols
    (``Ê±¼ä``); in GBK a character is a common one (in GB 2312) standing apart from Latin
    letters; in Shift-JIS it is a kanji, kana or full-width form, never half-width kana
    (which is what Chinese bytes read as Shift-JIS become)."""
    score = 0
    runs = re.finditer(r"[^\x00-\x7f]+", text)
    for run in runs:
        chunk = run.group()
        before = text[run.start() - 1] if run.start() else " "
        after = text[run.end()] if run.end() < len(text) else " "
        glued = before.isascii() and before.isalpha() or after.isascii() and after.isalpha()
        for c in chunk:
            if codec == "cp1252":
                good = (
                    (c.isalpha() or c in _SYMBOLS) and len(chunk) <= 2 and (glued or c in _SYMBOLS)
                )
            elif codec == "gbk":
                good = not glued and _encodes(c, "gb2312")
            else:
                good = not glued and (
                    "\u3040" <= c <= "\u30ff"
                    or "\u4e00" <= c <= "\u9fff"
                    or "\uff01" <= c <= "\uff5e"
                )
            score += 1 if good else -1
    return score


def _encodes(c: str, codec: str) -> bool:
    try:
        c.encode(codec)
    except UnicodeEncodeError:
        return False
    return True


def _read_head(path: Path) -> tuple[bytes, int]:
    """The first :data:`HEAD_BYTES` of `path` and the file's size."""
    try:
        size = path.stat().st_size
        with open(path, "rb") as fh:
            return fh.read(HEAD_BYTES), size
    except FileNotFoundError:
        raise InputError(f"{path} does not exist; check the path") from None
    except IsADirectoryError:
        raise InputError(f"{path} is a directory; give a file") from None
    except OSError as exc:
        raise InputError(f"cannot read {path}: {exc.strerror}") from None


@dataclass
class Layout:
    """How a text table is laid out, sniffed from its head; reads its body in blocks.

    Attributes
    ----------
    path : Path
    names : list of str
        Column names (the header's, or ``"1"``, ``"2"``, ...).
    header : bool
        Whether the names came from the file.
    units : list of str or None
        The units row under the names, if any.
    numeric : list of bool
        Which columns hold numbers (the others: text, e.g. clock times).
    notes : list of str
        What sniffing found.
    """

    path: Path
    names: list[str]
    header: bool
    units: list[str] | None
    numeric: list[bool]
    notes: list[str]
    codec: str
    delimiter: str
    decimal_comma: bool
    offset: int  # byte offset of the first data row
    first_line: int  # its line number
    head_rows: list[list[str]]
    lone_cr: bool = False
    source: str = "text table"
    format: str = ""
    junk: list[int] = field(default_factory=list)
    junk_count: int = 0
    comments: int = 0
    marks: int = 0
    rows: int = 0
    read_bytes: int = 0
    size: int = 0

    def fraction(self) -> float:
        """How much of the file has been read, 0 to 1."""
        return min(1.0, self.read_bytes / self.size) if self.size else 1.0

    def head_text(self, index: int) -> list[str]:
        """The fields of column `index` in the sniffed rows (to tell clock times)."""
        return [row[index].strip().strip('"') for row in self.head_rows]

    def blocks(self, columns: list[int]) -> Iterator[Block]:
        """The chosen columns of every data row, block by block (see the module)."""
        for first_line, body, count in self._bodies():
            block = self._parse(body, first_line, count, columns)
            self.rows += block.values.shape[0]
            yield block

    def finish(self) -> list[str]:
        """After :meth:`blocks`: notes on comments and junk; refuses a table that is more
        junk than data."""
        if not self.rows:
            raise InputError(
                f"{self.path} holds no rows of numbers ({len(self.names)} fields); check "
                "that it is a table"
            )
        junk = self.junk_count
        if junk > max(10, self.rows // 10):
            raise InputError(
                f"{self.path}: {junk} of {junk + self.rows} lines do not parse as "
                f"{len(self.names)} numbers (first at line {self.junk[0]}); check the "
                "delimiter and the columns"
            )
        notes = [
            self.format
            + (f", {self.comments} comment line(s)" if self.comments else "")
            + (f", {self.marks} line(s) of punctuation alone" if self.marks else ""),
            *self.notes,
        ]
        if junk:
            where = ", ".join(str(j) for j in self.junk[:5]) + (" ..." if junk > 5 else "")
            notes.append(f"{junk} junk line(s) skipped (line {where})")
        return notes

    # -- the body

    def _bodies(self) -> Iterator[tuple[int, bytes | memoryview, int]]:
        """Blocks of whole lines from the first data row on, as UTF-8 bytes with LF or
        CRLF line ends (a view of the bytes read, not a copy), each with the line number
        of its first line and its count of line ends."""
        utf8 = self.codec == "utf-8"
        decoder = None if utf8 else codecs.getincrementaldecoder(self.codec)("replace")
        line = self.first_line
        carry = b""
        with open(self.path, "rb") as fh:
            fh.seek(self.offset)
            while True:
                chunk = fh.read(BLOCK_BYTES)
                self.read_bytes = fh.tell()
                eof = not chunk
                if decoder is not None:
                    chunk = decoder.decode(chunk, final=eof).encode("utf-8")
                if self.lone_cr:
                    chunk = chunk.replace(b"\r", b"\n")
                data = carry + chunk if carry else chunk
                end = len(data)
                if not eof:
                    cut = data.rfind(b"\n")
                    if cut < 0:
                        if len(data) > MAX_LINE_BYTES:
                            raise InputError(
                                f"{self.path}: line {line} is longer than "
                                f"{MAX_LINE_BYTES >> 20} MB; not a table of samples"
                            )
                        carry = data
                        continue
                    end, carry = cut + 1, data[cut + 1 :]
                    if cut > MAX_LINE_BYTES and data.find(b"\n", 0, end) > MAX_LINE_BYTES:
                        raise InputError(
                            f"{self.path}: line {line} is longer than "
                            f"{MAX_LINE_BYTES >> 20} MB; not a table of samples"
                        )
                if end:
                    count = data.count(b"\n", 0, end)
                    yield line, memoryview(data)[:end], count
                    line += count
                if eof:
                    return

    def _parse(
        self, body: bytes | memoryview, first_line: int, count: int, columns: list[int]
    ) -> Block:
        if self.delimiter == " ":
            body = re.sub(rb"[ \t]+", b" ", bytes(body))
            body = re.sub(rb"(?m)^ | (?=\r?$)", b"", body)
        fast = self._fast(body, first_line, count, columns)
        return fast if fast is not None else self._slow(body, first_line, columns)

    def _fast(
        self, body: bytes | memoryview, first_line: int, count: int, columns: list[int]
    ) -> Block | None:
        """The block (``count`` line ends) parsed whole by pyarrow, in pieces of
        :data:`PARSE_BYTES` on every core, or None if it holds anything but rows."""
        import pyarrow as pa
        from pyarrow import csv

        invalid: list[int] = []

        def handler(row: object) -> str:
            invalid.append(1)
            return "skip"

        names = [f"c{i}" for i in range(len(self.names))]
        types = {names[c]: pa.float64() if self.numeric[c] else pa.string() for c in columns}
        try:
            table = csv.read_csv(
                pa.BufferReader(pa.py_buffer(body)),  # the bytes read, not a copy
                read_options=csv.ReadOptions(column_names=names, block_size=PARSE_BYTES),
                parse_options=csv.ParseOptions(
                    delimiter=self.delimiter, invalid_row_handler=handler
                ),
                convert_options=csv.ConvertOptions(
                    column_types=types,
                    include_columns=[names[c] for c in columns],
                    decimal_point="," if self.decimal_comma else ".",
                    quoted_strings_can_be_null=False,
                ),
            )
        except (pa.ArrowInvalid, pa.ArrowNotImplementedError):
            return None
        finally:
            pa.default_memory_pool().release_unused()  # the pool keeps what it freed
        m = table.num_rows
        # a blank line is skipped by the parser without a word: every line must be a row
        if invalid or m != count + (body[-1:] != b"\n"):
            return None
        values = np.empty((len(columns), m)).T  # each column contiguous, as it is used
        text: dict[int, list[str]] = {}
        for j, c in enumerate(columns):
            column = table.column(names[c])
            if not self.numeric[c]:
                values[:, j] = np.nan
                text[c] = [str(v).strip() for v in column.to_pylist()]
                continue
            if column.null_count:
                return None  # empty fields: junk lines, counted one by one
            row = 0
            for chunk in column.chunks:  # the values' own buffer (to_numpy loads pandas)
                v = np.frombuffer(chunk.buffers()[1], np.float64, len(chunk), chunk.offset * 8)
                # a finite sum says every value is finite, without an array of flags
                if not math.isfinite(float(np.sum(v))) and not np.isfinite(v).all():
                    return None  # NaN or Inf: junk lines, counted one by one
                values[row : row + len(chunk), j] = v
                row += len(chunk)
        return Block(values, np.arange(first_line, first_line + m, dtype=np.int64), text)

    def _slow(self, body: bytes | memoryview, first_line: int, columns: list[int]) -> Block:
        """The block line by line: rows, comments, blank lines and junk told apart."""
        width = len(self.names)
        wanted = [self.numeric[i] and i in columns for i in range(width)]
        rows: list[list[float]] = []
        lines: list[int] = []
        text: dict[int, list[str]] = {c: [] for c in columns if not self.numeric[c]}
        for i, raw_line in enumerate(str(body, "utf-8", "replace").split("\n")):
            line = raw_line.strip()
            if not line:
                continue
            if line.startswith(COMMENTS):
                self.comments += 1
                continue
            if not any(c.isalnum() for c in line):
                self.marks += 1
                continue
            fields = _split(line, self.delimiter)
            values = _numbers(fields, self.decimal_comma, wanted) if len(fields) == width else None
            if values is None:
                self.junk_count += 1
                if len(self.junk) < 5:
                    self.junk.append(first_line + i)
                continue
            rows.append([values[c] for c in columns])
            lines.append(first_line + i)
            for c, column in text.items():
                column.append(fields[c].strip().strip('"'))
        return Block(
            np.array(rows, dtype=float).reshape(len(rows), len(columns)),
            np.array(lines, dtype=np.int64),
            text,
        )


def sniff_table(path: str | os.PathLike[str]) -> Layout:
    """The layout of a delimited text table, from its first megabyte.

    Raises
    ------
    InputError
        The file is missing, binary, or its head holds no rows of numbers.
    """
    path = Path(path)
    raw, size = _read_head(path)
    text, codec, encoding = decode(raw, path)
    bom = 0
    for mark in (codecs.BOM_UTF8, codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE):
        if raw.startswith(mark):
            bom = len(mark)
            break
    lone_cr = "\r" in text and "\n" not in text
    if lone_cr:
        text = text.replace("\r", "\n")
    if size > len(raw):  # only whole lines of the head
        cut = text.rfind("\n")
        if cut < 0:
            raise InputError(
                f"{path}: line 1 is longer than {HEAD_BYTES >> 20} MB; not a table of samples"
            )
        text = text[: cut + 1]
    all_lines = text.split("\n")
    # the sniffing reads the first 400 lines with letters or digits and the 400 after
    # the first row, so the rows begin among those: the rest of the megabyte can wait
    numbered, comment_lines, marks = _classify(all_lines, SNIFF_LINES)
    if not numbered:
        raise InputError(f"{path} holds no data lines")
    sniffed = _sniff([line for _, line in numbered[:400]])
    if sniffed is None:
        raise InputError(
            f"{path} holds no rows of numbers (no line parses as two or more numbers "
            "separated by commas, tabs, semicolons, bars or spaces)"
        )
    delimiter, width, decimal_comma, numeric = sniffed
    before: list[tuple[int, list[str]]] = []  # lines before the first data row
    head_rows: list[list[str]] = []
    first: int | None = None
    for k, (number, line) in enumerate(numbered):
        fields = _split(line, delimiter)
        if len(fields) == width and _numbers(fields, decimal_comma, numeric) is not None:
            first = number
            later = (_split(ln, delimiter) for _, ln in numbered[k : k + 400])
            head_rows = [f for f in later if len(f) == width]
            break
        before.append((number, fields))
    if first is None:
        raise InputError(
            f"{path} holds no rows of numbers ({width} fields); check that it is a table"
        )
    header: list[str] | None = None
    units: list[str] | None = None
    # a units row (s, N, mm) under the names
    if len(before) >= 2 and len(before[-1][1]) == width and _units_row(before[-1][1]):
        if len(before[-2][1]) == width:
            units = [_bare_unit(f) for f in before.pop()[1]]
    # the header is the line right before the data, if it has a name for every column;
    # anything earlier is a preamble (a logger's title, date, settings)
    if before and len(before[-1][1]) == width:
        header = [f.strip().strip('"').strip("'") for f in before.pop()[1]]
    elif not before:
        # some loggers write the header as the last comment line before the data
        lead = [c for c in comment_lines if c[0] < first]
        if lead:
            fields = _split(lead[-1][1].lstrip("#%/! "), delimiter)
            if len(fields) == width and _numbers(fields, decimal_comma) is None:
                header = [f.strip().strip('"').strip("'") for f in fields]
    preamble = len(before)
    comments = sum(1 for c in comment_lines if c[0] < first)
    names = header if header is not None else [str(i + 1) for i in range(width)]
    text_columns = [names[i] for i in range(width) if not numeric[i]]
    shown = {"\t": "tab", " ": "whitespace", ";": "semicolon", ",": "comma", "|": "bar"}
    fmt = (
        f"{shown[delimiter]}-separated, {encoding}"
        + (", decimal commas" if decimal_comma else "")
        + (f", {preamble} preamble line(s)" if preamble else "")
        + (", a units row" if units else "")
    )
    notes = []
    if text_columns:
        notes.append("text column(s), not numbers: " + ", ".join(repr(n) for n in text_columns))
    prefix = "\n".join(all_lines[: first - 1]) + ("\n" if first > 1 else "")
    offset = bom + len(prefix.encode(codec, "replace"))
    return Layout(
        format=fmt,
        comments=comments,
        marks=sum(1 for m in marks if m < first),
        path=path,
        names=names,
        header=header is not None,
        units=units,
        numeric=list(numeric),
        notes=notes,
        codec=codec,
        delimiter=delimiter,
        decimal_comma=decimal_comma,
        offset=offset,
        first_line=first,
        head_rows=head_rows,
        lone_cr=lone_cr,
        size=size,
    )


#: lines with letters or digits classified while sniffing (the rows must begin among
#: the first 400 of them to be found)
SNIFF_LINES = 1000


def _classify(
    lines: list[str], limit: int | None
) -> tuple[list[tuple[int, str]], list[tuple[int, str]], list[int]]:
    """The head's lines with letters or digits, its comment lines and its lines of
    punctuation alone (a rich-text export's "\\", a "}"), each with its line number;
    stops after ``limit`` lines with letters or digits."""
    numbered: list[tuple[int, str]] = []
    comment_lines: list[tuple[int, str]] = []
    marks: list[int] = []
    for i, raw_line in enumerate(lines):
        line = raw_line.strip()
        if not line:
            continue
        if line.startswith(COMMENTS):
            comment_lines.append((i + 1, line))
        elif not any(c.isalnum() for c in line):
            marks.append(i + 1)
        else:
            numbered.append((i + 1, line))
            if limit is not None and len(numbered) >= limit:
                break
    return numbered, comment_lines, marks


def _units_row(fields: list[str]) -> bool:
    """Whether a row's fields are units (``s``, ``[N]``, ``(mm)``, ``-``): at least one
    known unit, and nothing but short unit-like words."""
    known = 0
    for f in fields:
        bare = _bare_unit(f)
        if not bare or bare in ("-", "1", "%"):
            continue
        if unit_factor(bare) is not None or unit_factor(bare.lower()) is not None:
            known += 1
        elif len(bare) > 8 or not re.fullmatch(r"[A-Za-zµ°/*^0-9.]+", bare):
            return False
    return known >= 1


def _bare_unit(field: str) -> str:
    return field.strip().strip('"').strip("'").strip("[]()").strip()


def read_table(path: str | os.PathLike[str]) -> Table:
    """Read a whole delimited text table into memory, sniffing its layout.

    Raises
    ------
    InputError
        The file is missing, binary, has no numeric rows, or more junk than data.
    """
    layout = sniff_table(path)
    columns = list(range(len(layout.names)))
    blocks = list(layout.blocks(columns))
    notes = layout.finish()
    text = {
        c: [f for b in blocks for f in b.text.get(c, [])] for c in columns if not layout.numeric[c]
    }
    return Table(
        names=layout.names,
        data=np.concatenate([b.values for b in blocks]),
        lines=np.concatenate([b.lines for b in blocks]),
        source=layout.source,
        notes=notes,
        junk=layout.junk,
        header=layout.header,
        text=text,
        units=layout.units,
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
    out = Clock().seconds(fields)
    return out - out[0] if out is not None and out.size else out


class Clock:
    """Clock times read block by block: the date of the first and the midnights passed
    are remembered from one block to the next (see :func:`clock_seconds`)."""

    def __init__(self) -> None:
        self.day = 0.0
        self.first_day: int | None = None
        self.last: float | None = None

    def seconds(self, fields: list[str]) -> NDArray[np.float64] | None:
        """Seconds of each field since the first day's midnight; None if a field is not
        a clock time."""
        import datetime as dt

        out = np.empty(len(fields))
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
                self.first_day = ordinal if self.first_day is None else self.first_day
                # days counted from the first, so that milliseconds keep their precision
                seconds += (ordinal - self.first_day) * 86400.0
            elif self.last is not None and seconds + self.day < self.last - 43200.0:
                self.day += 86400.0
            out[i] = seconds + self.day if not year else seconds
            self.last = float(out[i])
        return out
