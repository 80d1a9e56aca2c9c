"""Plain-text serial loggers: the lines a microcontroller prints, read as rows of numbers.

Labs' forceps often print text rather than frames: an Arduino or Teensy printing
``t,force,pos`` (with or without a header line), the Arduino Serial Plotter's
``force:1.23 pos:4.5``, or Teleplot's ``>force:1.23``. Each way of writing a line is a
:class:`LineDialect` (a strategy behind a small base class, in :data:`DIALECTS`);
:func:`sniff_dialect` picks the one that reads the first lines best. A line that its
dialect cannot read is *malformed*: counted, never fatal. Blank lines, comments, a
repeated header and Teleplot's text logs are *ignored*: counted apart.

:class:`TextLink` reads a port line by line (through :class:`~.link.Link`, which owns
pyserial), stamping each line with its host arrival time, and
:class:`StampChecker` turns a device's own stamps (``millis()``, ``micros()``, seconds)
into a continuous count: a 32-bit counter's wrap-around is undone, a stamp that goes
back is rejected, and a device reset is continued. This module is pure parsing and
reading: which column is which quantity, and units, are decided above it.
"""

from __future__ import annotations

import math
import re
import time
from abc import ABC, abstractmethod
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import ClassVar, Protocol

from .link import Link

#: a line longer than this, in bytes, without a newline is not a line of numbers
MAX_LINE_BYTES = 512
#: lines starting with these are comments
COMMENTS = ("#", "%", "//", "!")
#: a 32-bit counter (``millis()``, ``micros()``) wraps at this many of its units
WRAP = 1 << 32


class MalformedLine(ValueError):
    """A line its dialect cannot read (the reason in words)."""


@dataclass(frozen=True)
class Line:
    """One line received: its text (without the newline), its number since the port was
    opened (1-based) and the host's monotonic time it arrived, s."""

    text: str
    number: int
    host_s: float


def _number(text: str) -> float | None:
    """A field as a finite float, or None."""
    try:
        value = float(text.strip().strip('"'))
    except ValueError:
        return None
    return value if math.isfinite(value) else None


def _ignorable(text: str) -> bool:
    """Blank or a comment."""
    s = text.strip()
    return not s or s.startswith(COMMENTS)


class LineDialect(ABC):
    """How a logger writes its lines. Subclasses set ``name`` and implement
    :meth:`score` (how well sample lines fit, for sniffing), :meth:`learn` (the columns,
    from sample lines) and :meth:`read` (one line to a row).

    Attributes (after :meth:`learn`)
    ----------
    names : list of str
        The columns, in order: a header's names, labels, or ``"1"``, ``"2"``, ...
    header : bool
        Whether the names came from the device (a header line or labels).
    units : dict of str to str
        Units the lines themselves name (Teleplot's ``§unit``), by column.
    """

    name: ClassVar[str] = ""

    def __init__(self) -> None:
        self.names: list[str] = []
        self.header = False
        self.units: dict[str, str] = {}

    @classmethod
    @abstractmethod
    def score(cls, lines: Sequence[str]) -> float:
        """The fraction of ``lines`` (not ignorable) this dialect reads as data, 0 to 1."""

    @abstractmethod
    def learn(self, lines: Sequence[str]) -> None:
        """Set :attr:`names` (and :attr:`header`, :attr:`units`) from sample lines.

        Raises
        ------
        MalformedLine
            If the lines show no columns at all.
        """

    @abstractmethod
    def read(self, text: str) -> dict[str, float] | None:
        """The values of a row this line completes; an empty dict for a line that is part
        of a row not complete yet; None for a line that carries no sample (blank,
        comment, header).

        Raises
        ------
        MalformedLine
            For a line this dialect cannot read.
        """

    def select(self, names: Iterable[str]) -> None:  # noqa: B027  (optional hook)
        """The columns the host will use (a dialect that gathers a row over several lines
        waits for these only)."""

    def reset(self) -> None:  # noqa: B027  (optional hook)
        """Forget a row begun but not complete (lines are about to be read again)."""

    def describe(self) -> str:
        """The dialect and its columns in words."""
        source = "label" if self.name != "delimited" else "header" if self.header else "position"
        return f"{self.name} lines, columns by {source}: " + ", ".join(map(repr, self.names))


# --------------------------------------------------------------------------- dialects

#: separators of delimited values, in the order that wins a tie
DELIMITERS = (",", "\t", ";", " ")


def _split(text: str, delimiter: str) -> list[str]:
    s = text.strip()
    return s.split() if delimiter == " " else [f.strip() for f in s.split(delimiter)]


class Delimited(LineDialect):
    """Values separated by commas, tabs, semicolons or spaces (``12345,0.81,0.0042``),
    with or without a header line of names (``t_ms,force_N,closure_mm``), which may be
    printed again at any time."""

    name = "delimited"

    def __init__(self, delimiter: str = ",") -> None:
        super().__init__()
        self.delimiter = delimiter
        self._header_line: list[str] | None = None

    @classmethod
    def _best(cls, lines: Sequence[str]) -> tuple[float, str, int]:
        """(fraction of lines that are rows, delimiter, width)."""
        data = [ln for ln in lines if not _ignorable(ln)]
        best = (0.0, ",", 0)
        for rank, delim in enumerate(DELIMITERS):
            widths: dict[int, int] = {}
            for ln in data:
                fields = _split(ln, delim)
                if len(fields) >= 2 and all(_number(f) is not None for f in fields):
                    widths[len(fields)] = widths.get(len(fields), 0) + 1
            if not widths:
                continue
            width, count = max(widths.items(), key=lambda kv: (kv[1], kv[0]))
            fraction = count / max(len(data), 1)
            if fraction > best[0] + 1e-9 or (abs(fraction - best[0]) <= 1e-9 and rank == 0):
                best = (fraction, delim, width)
        return best

    @classmethod
    def score(cls, lines: Sequence[str]) -> float:
        return cls._best(lines)[0]

    def learn(self, lines: Sequence[str]) -> None:
        fraction, self.delimiter, width = self._best(lines)
        if not fraction:
            raise MalformedLine("no line holds two or more numbers")
        for ln in lines:
            fields = _split(ln, self.delimiter)
            if (
                not _ignorable(ln)
                and len(fields) == width
                and all(_number(f) is None and f for f in fields)
            ):
                self._header_line = fields
                break
        self.header = self._header_line is not None
        self.names = self._header_line or [str(i + 1) for i in range(width)]

    def is_header(self, text: str) -> bool:
        """Whether ``text`` is a line of names as wide as the rows."""
        fields = _split(text, self.delimiter)
        return (
            not _ignorable(text)
            and len(fields) == len(self.names)
            and all(f and _number(f) is None for f in fields)
        )

    def read(self, text: str) -> dict[str, float] | None:
        if _ignorable(text):
            return None
        fields = _split(text, self.delimiter)
        if fields == self._header_line:
            return None  # the header, printed again
        if len(fields) != len(self.names):
            raise MalformedLine(f"{len(fields)} fields, not {len(self.names)}")
        out: dict[str, float] = {}
        for name, field in zip(self.names, fields, strict=True):
            value = _number(field)
            if value is None:
                raise MalformedLine(f"{field[:20]!r} is not a number")
            out[name] = value
        return out


#: one ``label:value`` part of a Serial Plotter line
_PART = re.compile(r"\s*([^:\s,][^:,\t]*?)\s*:\s*([^\s,]*)\s*")


class SerialPlotter(LineDialect):
    """The Arduino Serial Plotter's labelled values: ``force:1.23 pos:4.5``, parts
    separated by spaces, tabs or commas; a line of labels only (``force: pos:``)
    carries no sample."""

    name = "plotter"

    @staticmethod
    def _parts(text: str) -> list[tuple[str, str]] | None:
        pieces = [p for p in re.split(r"[\t,]|\s+(?=[^\s:]+\s*:)", text.strip()) if p.strip()]
        out = []
        for piece in pieces:
            m = _PART.fullmatch(piece)
            if m is None:
                return None
            out.append((m.group(1), m.group(2)))
        return out or None

    @classmethod
    def score(cls, lines: Sequence[str]) -> float:
        data = [ln for ln in lines if not _ignorable(ln) and not ln.lstrip().startswith(">")]
        good = 0
        for ln in data:
            parts = cls._parts(ln)
            if parts and all(v == "" or _number(v) is not None for _, v in parts):
                good += 1
        return good / max(len([ln for ln in lines if not _ignorable(ln)]), 1)

    def learn(self, lines: Sequence[str]) -> None:
        for ln in lines:
            for label, _ in self._parts(ln) or []:
                if label not in self.names:
                    self.names.append(label)
        if not self.names:
            raise MalformedLine("no label:value pairs")
        self.header = True

    def read(self, text: str) -> dict[str, float] | None:
        if _ignorable(text):
            return None
        parts = self._parts(text)
        if parts is None:
            raise MalformedLine("not label:value pairs")
        if all(v == "" for _, v in parts):
            return None  # labels only
        out: dict[str, float] = {}
        for label, raw in parts:
            value = _number(raw)
            if value is None:
                raise MalformedLine(f"{label}: {raw[:20]!r} is not a number")
            out[label] = value
        return out


#: ``>name:value``, ``>name:timestamp_ms:value``, optionally ``§unit`` and ``|flags``
_TELEPLOT = re.compile(
    r">\s*([^:|§]+?)\s*:\s*(?:([-+0-9.eE]+)\s*:\s*)?([^:§|]*?)\s*(?:§\s*([^|]*?)\s*)?(?:\|(.*))?"
)
#: a Teleplot log line, ``>:text`` or ``>1627551892437:text``
_TELEPLOT_LOG = re.compile(r"\s*>\s*[0-9.]*:")
#: the column a Teleplot line's own timestamp becomes (milliseconds, by its name)
TELEPLOT_TIME = "t_ms"


class Teleplot(LineDialect):
    """Teleplot's ``>name:value`` lines, one variable a line, optionally with a
    millisecond timestamp (``>force:1627551892437:1.23``) and a unit
    (``>force:1.23§N``). The variables of a row come in the order the first lines
    showed; a row is complete when the last has arrived. A line that breaks a row
    (unreadable, or out of order) is malformed and the rest of that row is dropped
    (:attr:`dropped`); a row cut short by a line that never came is counted in
    :attr:`incomplete`. Text telemetry (``|t``) and logs (``>:text``) carry no sample.
    """

    name = "teleplot"

    def __init__(self) -> None:
        super().__init__()
        self._order: list[str] = []
        self._pending: dict[str, float] = {}
        self._stamp: float | None = None
        self._broken = True  # until a row begins: the tail of one begun before
        self._started = False
        self.dropped = 0
        self.incomplete = 0

    @staticmethod
    def _match(text: str) -> re.Match[str] | None:
        return _TELEPLOT.fullmatch(text.strip())

    @classmethod
    def score(cls, lines: Sequence[str]) -> float:
        data = [ln for ln in lines if not _ignorable(ln)]
        good = sum(1 for ln in data if ln.lstrip().startswith(">") and cls._match(ln))
        return good / max(len(data), 1)

    def learn(self, lines: Sequence[str]) -> None:
        stamped = False
        seen: list[str] = []
        parsed = [m for m in map(self._match, lines) if m is not None and m.group(3)]
        parsed = [m for m in parsed if "t" not in (m.group(5) or "").split(",")]
        stamps = [m.group(2) for m in parsed]
        if all(stamps) and len(set(stamps)) > 1:
            # rows share a stamp: the first whole row begins where the stamp first changes
            parsed = parsed[next(i for i, st in enumerate(stamps) if st != stamps[0]) :]
        for m in parsed:
            name = m.group(1)
            if name in seen:
                break  # one whole row seen: its order is the order
            seen.append(name)
            if m.group(4):
                self.units[name] = m.group(4)
            stamped = stamped or m.group(2) is not None
        if not seen:
            raise MalformedLine("no >name:value lines")
        self.names = ([TELEPLOT_TIME] if stamped else []) + seen
        self.header = True
        self._order = seen

    def select(self, names: Iterable[str]) -> None:
        wanted = set(names)
        self._order = [n for n in self.names if n in wanted and n != TELEPLOT_TIME]

    def align(self, lines: Sequence[tuple[str, float]]) -> None:
        """Without stamps, which variable begins a row is a guess from where the first
        lines began; a logger prints a row at once and then waits a period, so take the
        order whose rows are least often split between two arrivals (``(text, host
        time)`` of the first lines)."""
        if TELEPLOT_TIME in self.names or len(self._order) < 2:
            return
        seen = [(m.group(1), t) for m, t in ((self._match(x), t) for x, t in lines) if m]
        seen = [(n, t) for n, t in seen if n in self._order]

        def splits(first: str) -> int:
            count, start = 0, None
            for name, t in seen:
                if name == first:
                    start = t
                elif start is not None and t != start:
                    count += 1
                    start = None  # count each row once
            return count

        order = self._order
        best = min(range(len(order)), key=lambda i: (splits(order[i]), i))
        self._order = order[best:] + order[:best]
        self.names = [n for n in self.names if n not in order] + self._order

    def reset(self) -> None:
        self._pending, self._stamp, self._broken, self._started = {}, None, True, False
        self.dropped = self.incomplete = 0

    def _break(self, reason: str) -> MalformedLine:
        self._pending, self._stamp, self._broken = {}, None, True
        return MalformedLine(reason)

    def read(self, text: str) -> dict[str, float] | None:
        if _ignorable(text) or _TELEPLOT_LOG.match(text):
            return None
        m = self._match(text)
        if m is None:
            raise self._break("not a >name:value line")
        name, stamp, raw, flags = m.group(1), m.group(2), m.group(3), m.group(5) or ""
        if "t" in flags.split(",") or name not in self._order:
            return None  # text telemetry, a log, or a variable the host does not use
        value = _number(raw)
        if value is None:
            raise self._break(f"{name}: {raw[:20]!r} is not a number")
        if name == self._order[0]:
            if self._pending:
                self.incomplete += 1
            self._pending, self._stamp, self._broken, self._started = {}, None, False, True
        elif self._broken:
            self.dropped += self._started
            return None
        if name != self._order[len(self._pending)]:
            raise self._break(f"{name} out of order")
        self._pending[name] = value
        if stamp is not None and self._stamp is None:
            self._stamp = _number(stamp)
        if len(self._pending) < len(self._order):
            return {}
        row, self._pending = self._pending, {}
        self._broken = True  # until the next row begins
        if TELEPLOT_TIME in self.names:
            if self._stamp is None:
                raise MalformedLine("no timestamp in the row")
            row[TELEPLOT_TIME] = self._stamp
        return row


#: the dialects, by name, in the order that wins a tie
DIALECTS: dict[str, type[LineDialect]] = {d.name: d for d in (Teleplot, SerialPlotter, Delimited)}


def sniff_dialect(lines: Sequence[str]) -> LineDialect:
    """The dialect that reads most of ``lines`` as data, with its columns learnt.

    Raises
    ------
    MalformedLine
        If no dialect reads even a third of them.
    """
    best: tuple[float, type[LineDialect]] | None = None
    for dialect in DIALECTS.values():
        s = dialect.score(lines)
        if best is None or s > best[0] + 1e-9:
            best = (s, dialect)
    if best is None or best[0] < 1 / 3:
        shown = next((ln for ln in lines if not _ignorable(ln)), "")
        raise MalformedLine(
            f"the lines are not delimited numbers, label:value pairs nor >name:value "
            f"(one read {shown[:40]!r})"
        )
    out = best[1]()
    out.learn(lines)
    return out


# --------------------------------------------------------------------------- stamps


class StampChecker:
    """A device's own time stamps, in its own unit, made continuous.

    A stamp may be a wrapping 32-bit counter (``millis()``, ``micros()``): a step back
    by more than half of 2**32 from a stamp in [0, 2**32) is a wrap and adds 2**32.
    A stamp that repeats is kept (a coarse clock stamps two samples alike; the time base
    sorts that out). A step back, or forward by more than :data:`MAX_JUMP` periods (two
    lines run together make one huge stamp), is rejected, unless :data:`CONFIRM`
    stamps in a row make it while agreeing with each other: then the logger paused
    (forward; the gap is kept) or restarted (back; its new stamps continue one period
    after the last kept one).

    Attributes
    ----------
    wraps, rejected, restarts, pauses : int
        Counts of each.
    """

    CONFIRM = 3
    MAX_JUMP = 1000

    def __init__(self) -> None:
        self.last_raw: float | None = None
        self.offset = 0.0  # added to the raw stamps (wraps, restarts)
        self.wraps = self.rejected = self.restarts = self.pauses = 0
        self._steps: list[float] = []
        self._held: list[float] = []

    @property
    def period(self) -> float:
        """The median step of the stamps so far, in their unit (1 before any)."""
        steps = sorted(s for s in self._steps if s > 0)
        return steps[len(steps) // 2] if steps else 1.0

    def _plausible(self, step: float) -> bool:
        if step < 0:
            return False
        return len(self._steps) < 8 or step <= self.MAX_JUMP * self.period

    def __call__(self, raw: float) -> float | None:
        """The continuous stamp of ``raw``, or None if it is rejected."""
        last = self.last_raw
        if last is None:
            self.last_raw = raw
            return raw + self.offset
        step = raw - last
        if step < 0 and 0 <= raw < WRAP and last < WRAP and -step > WRAP / 2:
            self.wraps += 1
            self.offset += WRAP
            step += WRAP
            last -= WRAP
        if self._plausible(step):
            self._held.clear()
            if len(self._steps) < 64:
                self._steps.append(step)
            self.last_raw = raw
            return raw + self.offset
        self._held.append(raw)
        held = self._held
        agree = len(held) >= self.CONFIRM and all(
            self._plausible(b - a) for a, b in zip(held, held[1:], strict=False)
        )
        if not agree:
            self._held = held[-(self.CONFIRM - 1) :]
            self.rejected += 1
            return None
        # the stamps held back agree with each other: the logger paused or restarted
        if held[0] < last:
            self.offset += (last - held[0]) + self.period
            self.restarts += 1
        else:
            self.pauses += 1
        self._held.clear()
        self.last_raw = raw
        return raw + self.offset


# --------------------------------------------------------------------------- the link


class TextLink:
    """A text logger on a serial port: lines in, stamped with their arrival.

    Text loggers take no commands, so :meth:`command` sends nothing; the line that was
    being printed when the port was opened is dropped, as only its tail arrived.

    Parameters
    ----------
    url : str
        Device path or pyserial URL.
    baudrate : int
        Line rate, bit/s (ignored by pseudo-terminals and USB CDC).
    timeout : float
        Longest one :meth:`poll` waits for the first byte, s.

    Attributes
    ----------
    lines : int
        Lines received (the partial first one excluded).
    overlong : int
        Runs longer than :data:`MAX_LINE_BYTES` without a newline (each counted once,
        as a malformed line).
    undecodable : int
        Lines that are not text (not UTF-8 or Latin-1 control junk), counted as malformed.
    """

    def __init__(self, url: str, baudrate: int = 115200, timeout: float = 0.05) -> None:
        self.url = url
        self.link = Link(url, baudrate=baudrate, timeout=timeout, kind="forceps")
        self._buffer = b""
        self._skipping = True  # until the first newline: the tail of a line begun before
        self.lines = 0
        self.overlong = 0
        self.undecodable = 0

    @property
    def bad_frames(self) -> int:
        """Lines lost to the link itself (overlong runs, bytes that are not text)."""
        return self.overlong + self.undecodable

    def command(self, name: str) -> None:
        """Text loggers take no commands."""

    def discard_input(self) -> None:
        """Drop whatever arrived before now (and the partial line it ends in)."""
        self.link.discard_input()
        self._buffer, self._skipping = b"", True

    def poll(self) -> list[Line]:
        """The complete lines that have arrived (waiting up to ``timeout`` for a byte)."""
        data = self.link.read_bytes()
        if not data:
            return []
        now = time.monotonic()
        pieces = (self._buffer + data).split(b"\n")
        self._buffer = pieces.pop()
        out: list[Line] = []
        for piece in pieces:
            if self._skipping:
                self._skipping = False
                continue
            self.lines += 1
            if len(piece) > MAX_LINE_BYTES:
                self.overlong += 1
                continue
            text = self._decode(piece)
            if text is None:
                self.undecodable += 1
                continue
            out.append(Line(text, self.lines, now))
        if len(self._buffer) > MAX_LINE_BYTES and not self._skipping:
            self.lines += 1
            self.overlong += 1
            self._buffer, self._skipping = b"", True
        elif self._skipping and len(self._buffer) > MAX_LINE_BYTES:
            self._buffer = b""
        return out

    @staticmethod
    def _decode(raw: bytes) -> str | None:
        try:
            text = raw.decode("utf-8").rstrip("\r")
        except UnicodeDecodeError:
            return None
        if any(ord(c) < 32 and c not in "\t" for c in text):
            return None  # control bytes: line noise, not a logger's text
        return text

    def fileno(self) -> int | None:
        return self.link.fileno()

    def close(self) -> None:
        self.link.close()

    def __enter__(self) -> TextLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class LineSource(Protocol):
    """What :func:`read_lines` reads from: a :class:`TextLink` or a
    :class:`~tissuecli.hw.device.TextLogger`."""

    def poll(self) -> list[Line]: ...


def read_lines(link: LineSource, *, count: int, within_s: float) -> list[Line]:
    """Up to ``count`` lines, waiting at most ``within_s`` for them (fewer if the logger is
    slow or silent).

    Raises
    ------
    DeviceLost
        If the port goes away.
    """
    out: list[Line] = []
    deadline = time.monotonic() + within_s
    while len(out) < count and time.monotonic() < deadline:
        out += link.poll()
    return out


__all__ = [
    "DIALECTS",
    "Delimited",
    "Line",
    "LineDialect",
    "LineSource",
    "MalformedLine",
    "SerialPlotter",
    "StampChecker",
    "Teleplot",
    "TextLink",
    "read_lines",
    "sniff_dialect",
]
