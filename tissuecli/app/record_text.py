"""``record --protocol text``: a session from a plain-text serial logger (an Arduino or
Teensy printing ``t,force,pos``, Serial Plotter ``force:1.23 pos:4.5``, Teleplot
``>force:1.23``) into the same crash-safe session file, with the same live view and
online identification as the binary protocol.

The first lines are sniffed for their dialect (:func:`tissuecli.hw.text.sniff_dialect`)
and their columns and units chosen by the import's machinery
(:func:`tissuecli.formats.recording.reading_of`: ``--columns``, ``--units``,
``--jaw-length``), or counts turned to SI by ``--calibration``. A line with the
device's own stamps keeps them (a 32-bit ``millis()``/``micros()`` unwrapped, a stamp
that goes back rejected), put back at the end on the regular clock they came from; a
line without is stamped by its place in the stream, on a clock fitted to the host's
arrival times. Malformed lines are counted, never fatal.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..core.calibration import Calibration
from ..core.clock import ClockFaults, ClockMap, fit_clock_map
from ..core.errors import DeviceError, DeviceLost, InputError, TissueError
from ..core.session import COLUMNS
from ..core.timebase import regularise
from ..core.units import ColumnUnits, parse_units
from ..formats.recording import Reading, reading_of
from ..formats.sessions import session_writer
from ..formats.tables import Block, Table
from ..formats.writer import SeriesWriter
from ..hw.device import TextLogger
from ..hw.stream import Stream
from ..hw.text import (
    Delimited,
    Line,
    LineDialect,
    MalformedLine,
    StampChecker,
    Teleplot,
    read_lines,
    sniff_dialect,
)
from .recording import (
    Online,
    RecordOptions,
    RecordResult,
    RecordStatus,
    SampleBlock,
    check_not_stopped,
)

#: lines read to learn the dialect and columns, and how long to wait for them, s
SNIFF_LINES = 64
SNIFF_S = 2.0
#: a logger sampling more slowly than this has its time unit wrong, Hz
MIN_RATE_HZ = 1.0
#: line rate when none is given: what Arduino sketches use most
TEXT_BAUD = 115200


def record_lines(
    url: str,
    out: Path,
    session: str,
    options: RecordOptions,
    columns: str | None,
    units: str | None,
    jaw_length_m: float | None,
) -> RecordResult:
    """Record from the text logger at ``url`` into session ``session`` of ``out``: what
    :func:`tissuecli.app.record.record` does for a logger printing lines, its arguments
    checked there.

    Parameters
    ----------
    columns, units, jaw_length_m
        As for ``import`` (:func:`tissuecli.formats.recording.read_recording`).
    options : RecordOptions
        What every recording takes; ``calibration`` turns ADC counts for force and
        position into SI (gain * counts + offset), and ``units`` may then name the time
        column's unit only.

    Raises
    ------
    DeviceError
        If the port prints nothing, or nothing that reads as samples.
    DeviceLost
        If the port vanishes; what was kept is saved first.
    InputError
        For ``--columns`` or ``--units`` that do not fit the lines.
    """
    stop, calibration = options.stop, options.calibration
    if calibration is not None and {"force", "position"} & parse_units(units).given:
        raise InputError(
            "--calibration turns counts into N and m; give --units for time only "
            "(e.g. --units time=ms), or leave --calibration out"
        )
    online = Online(math.nan, options.forgetting_s) if options.identify else None
    if online is not None:
        online.prepare()  # slow (SciPy): before the lines start to queue
    link = TextLogger(url, baudrate=options.baudrate or TEXT_BAUD).open()
    try:
        first = read_lines(link, count=SNIFF_LINES, within_s=SNIFF_S)
        check_not_stopped(stop, url)
        if not first:
            raise DeviceError(
                f"{url} printed no line within {SNIFF_S:g} s; is the logger running and "
                "printing lines ending in a newline at this --baud? For a simulated one "
                f"run `tissuecli simulate forceps --protocol text --link {url}`"
            )
        try:
            dialect = sniff_dialect([ln.text for ln in first])
            if isinstance(dialect, Delimited) and not dialect.header and not columns:
                # a logger that prints its header now and then: wait a while for it
                first += _until_header(link, dialect, SNIFF_S)
                dialect = sniff_dialect([ln.text for ln in first])
        except MalformedLine as exc:
            raise DeviceError(
                f"{url}: {exc}; is it a text logger (else leave out --protocol text)"
            ) from None
        if isinstance(dialect, Teleplot):
            dialect.align([(ln.text, ln.host_s) for ln in first])
        reader = _Lines(
            dialect, url, columns, units, jaw_length_m, calibration, [ln.text for ln in first]
        )
        rate = reader.rate_from(first)
        meta = {
            "tissue": options.tissue,
            "note": options.note,
            "start_utc": datetime.now(timezone.utc).isoformat(timespec="milliseconds"),
            "source": f"serial:{url}",
            "protocol": "text",
            "device": {},
            "rate_hz": rate,
            "text_dialect": dialect.describe(),
            "import_columns": reader.reading.report.columns,
            "import_units": reader.reading.report.units,
        }

        def open_writer() -> SeriesWriter:
            return session_writer(
                out,
                session,
                meta=meta,
                calibration=calibration.as_dict() if calibration is not None else None,
                raw=False,
                flush_interval_s=options.flush_interval_s,
            )

        if online is not None:
            online.rate_hz = rate
        listeners = [f for f in (online, options.on_samples) if f is not None]
        recording = _TextRecording(
            link, reader, open_writer, out, session, meta, rate, options.duration_s,
            listeners, online,
        )  # fmt: skip
        stream = Stream(
            link,  # a text logger: START and STOP send nothing
            Line,  # type: ignore[arg-type]
            stop=stop,
            idle_timeout_s=options.idle_timeout_s,
            status_interval_s=options.status_interval_s,
            track_sequence=False,
        )
        return recording.run(stream, first, options.on_status)
    finally:
        link.close()


def _until_header(link: TextLogger, dialect: Delimited, within_s: float) -> list[Line]:
    """Lines read until one is a header for ``dialect``'s rows, or ``within_s`` passed."""
    out: list[Line] = []
    deadline = time.monotonic() + within_s
    while time.monotonic() < deadline:
        lines = link.poll()
        out += lines
        if any(dialect.is_header(ln.text) for ln in lines):
            break
    return out


class _Lines:
    """The lines of one logger as samples in SI: the dialect, the columns and units the
    import's machinery chose, and the device's stamps checked.

    Attributes
    ----------
    malformed, ignored : int
        Lines the dialect could not read, and lines that carry no sample (blank,
        comments, a repeated header).
    """

    def __init__(
        self,
        dialect: LineDialect,
        url: str,
        columns: str | None,
        units: str | None,
        jaw_length_m: float | None,
        calibration: Calibration | None,
        sample: list[str],
    ) -> None:
        self.dialect = dialect
        self.calibration = calibration
        rows = []
        for text in sample:
            try:
                row = dialect.read(text)
            except MalformedLine:
                continue
            if row:
                rows.append([row.get(n, math.nan) for n in dialect.names])
        dialect.reset()
        row_units = [dialect.units.get(n, "") for n in dialect.names]
        table = Table(
            names=list(dialect.names),
            data=np.array(rows, dtype=float).reshape(-1, len(dialect.names)),
            lines=np.arange(1, len(rows) + 1),
            source=f"text {dialect.name}",
            header=dialect.header,
            units=row_units if any(row_units) else None,
        )
        given = units
        if calibration is not None:
            # counts: read in no unit (factor 1), the calibration makes them SI
            given = ",".join(filter(None, [units, "force=N", "position=m"]))
        self.reading: Reading = reading_of(
            table,
            Path(url),
            columns=columns,
            units=given,
            jaw_length_m=jaw_length_m,
            time_optional=True,
        )
        if calibration is not None:
            self.reading.report.units["force"] = "counts (--calibration)"
            self.reading.report.units["position"] = "counts (--calibration)"
        self.order = [q for q in COLUMNS if q in self.reading.picked]
        self.keys = [dialect.names[self.reading.picked[q][0]] for q in self.order]
        dialect.select(self.keys)
        self.stamped = self.reading.stamped
        self.stamps = StampChecker()
        self._malformed = self._ignored = 0
        self.bad_lines = []  # numbers of the malformed lines of the last take
        self.first_stamp: float | None = None  # the first kept stamp, in its own unit
        self.slots = 0  # sample slots so far: rows and malformed lines (host-stamped)

    @property
    def malformed(self) -> int:
        """Lines the dialect could not read, and rows cut short."""
        return self._malformed + int(getattr(self.dialect, "incomplete", 0))

    @property
    def ignored(self) -> int:
        """Lines that carry no sample: blank, comments, a header again, the rest of a
        broken row."""
        return self._ignored + int(getattr(self.dialect, "dropped", 0))

    def rate_from(self, lines: list[Line]) -> float:
        """The sample rate the sniffed lines suggest, Hz (NaN if they cannot tell): from
        the device's stamps, else from the lines' arrival times."""
        arrivals, stamps = [], []
        for ln in lines:
            try:
                row = self.dialect.read(ln.text)
            except MalformedLine:
                continue
            if row and all(k in row for k in self.keys):
                arrivals.append(ln.host_s)
                stamps.append(row[self.keys[0]])
        self.dialect.reset()  # the lines are read again, from the start, as samples
        if self.stamped and len(stamps) >= 3:
            steps = np.diff(np.array(stamps))
            steps = steps[steps > 0]
            if steps.size:
                unit = self.reading.picked["time"][1]
                step = float(np.median(steps))
                rate = 1.0 / (step * ColumnUnits(time=unit).factor("time"))
                if rate < MIN_RATE_HZ:
                    raise InputError(
                        f"time column {self.keys[0]!r} steps by {step:g} {unit} a sample "
                        f"({rate:.3g} Hz); if it counts ms or us (millis(), micros()) say so "
                        "with --units time=ms (or us)"
                    )
                return rate
        if len(arrivals) >= 3 and arrivals[-1] > arrivals[0]:
            return float((len(arrivals) - 1) / (arrivals[-1] - arrivals[0]))
        return math.nan

    def uncount(self, after: int) -> None:
        """Count no more the malformed lines of the last take after line ``after`` (past
        the end of the recording)."""
        late = sum(1 for n in self.bad_lines if n > after)
        self._malformed -= late

    def take(self, lines: list[Line]) -> tuple[SampleTable, int]:
        """The samples of ``lines``: ``(raw stamps or slots, force N, position m, host s)``
        and how many lines were malformed."""
        values: list[list[float]] = []
        numbers: list[int] = []
        host: list[float] = []
        slots: list[float] = []
        bad = 0
        self.bad_lines: list[int] = []
        for ln in lines:
            try:
                row = self.dialect.read(ln.text)
            except MalformedLine:
                bad += 1
                self.bad_lines.append(ln.number)
                self.slots += 1  # a damaged sample: it keeps its place in time
                continue
            if row is None:
                self._ignored += 1
                continue
            if not row:
                continue  # part of a row (one variable of several)
            try:
                vals = [row[k] for k in self.keys]
            except KeyError:
                bad += 1  # a labelled line without a chosen label
                self.bad_lines.append(ln.number)
                self.slots += 1
                continue
            if self.stamped:
                stamp = self.stamps(vals[0])
                if stamp is None:
                    continue  # counted by the checker
                if self.first_stamp is None:
                    self.first_stamp = vals[0]
                vals[0] = stamp
            values.append(vals)
            numbers.append(ln.number)
            host.append(ln.host_s)
            slots.append(float(self.slots))
            self.slots += 1
        self._malformed += bad
        if not values:
            empty = np.zeros(0)
            return (empty, empty, empty, empty), bad
        self.numbers = np.array(numbers, dtype=np.int64)
        block = Block(np.array(values, dtype=float), self.numbers)
        if self.calibration is not None:
            force_col = self.order.index("force")
            pos_col = self.order.index("position")
            raw = block.values.copy()
        stamps, force, position, keep = self._convert(block)
        self.numbers = self.numbers[keep]
        if self.calibration is not None:
            raw = raw[keep]
            force = self.calibration.force.to_si(raw[:, force_col])
            position = self.calibration.position.to_si(raw[:, pos_col])
        t = stamps if self.stamped else np.array(slots)[keep]
        return (t, force, position, np.array(host)[keep]), bad

    def _convert(self, block: Block) -> tuple[Any, Any, Any, NDArray[np.bool_]]:
        """The block in SI, and which rows were kept: a row whose value is beyond any
        grasp or jaw (a garbled digit) is malformed, not the end of the recording."""
        keep = np.ones(block.lines.size, dtype=bool)
        try:
            stamps, force, position, _ = self.reading.convert(block)
            return stamps, force, position, keep
        except InputError:
            pass
        for i in range(block.lines.size):
            try:
                self.reading.convert(Block(block.values[i : i + 1], block.lines[i : i + 1]))
            except InputError:
                keep[i] = False
                self._malformed += 1
                self.bad_lines.append(int(block.lines[i]))
        kept = Block(block.values[keep], block.lines[keep])
        stamps, force, position, _ = self.reading.convert(kept)
        return stamps, force, position, keep


SampleTable = tuple[
    NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]
]


class _TextRecording:
    """One session from a text logger: lines to samples, to the writer (created with the
    first sample), and the time base at the end."""

    def __init__(
        self,
        link: TextLogger,
        reader: _Lines,
        open_writer: Callable[[], SeriesWriter],
        out: Path,
        session: str,
        meta: dict[str, Any],
        rate_hz: float,
        duration_s: float | None,
        listeners: list[Callable[[SampleBlock], None]],
        online: Online | None,
    ) -> None:
        self.link, self.reader, self.open_writer = link, reader, open_writer
        self.out, self.session, self.meta = out, session, meta
        self.rate_hz = rate_hz if math.isfinite(rate_hz) and rate_hz > 0 else 1.0
        self.duration_s = duration_s
        self.listeners, self.online = listeners, online
        self.writer: SeriesWriter | None = None
        self.samples = 0
        self.first: float | None = None  # first stamp or slot
        self.times: list[NDArray[np.float64]] = []
        self.hosts: list[NDArray[np.float64]] = []
        self.lost = 0  # lines that never arrived (holes in the device's clock not malformed)
        self.missing = 0  # holes in the device's clock, malformed lines included
        self.estimate: Any = None
        self.done = False

    def run(
        self,
        stream: Stream,
        first: list[Line],
        on_status: Callable[[RecordStatus], None] | None,
    ) -> RecordResult:
        lost: DeviceLost | None = None
        clock_map: ClockMap | None = None
        last_line = time.monotonic()
        try:
            with stream:
                self._take(first, stream.t_start)
                while stream.running() and not self.done:
                    lines = self.link.poll()
                    now = time.monotonic()
                    if lines:
                        last_line = now
                        self._take(lines, stream.t_start)
                    elif now - last_line > stream.idle_timeout_s:
                        span = stream.idle_timeout_s
                        raise DeviceLost(
                            f"no line from {self.link.url} for "
                            + (f"{span * 1e3:g} ms" if span < 1 else f"{span:g} s")
                        )
                    if stream.status_due(now):
                        if self.writer is not None:
                            self.writer.set_attrs(**self._counters())
                        if on_status is not None:
                            on_status(self._status(now - stream.t_start))
        except DeviceLost as exc:
            lost = exc
            stream.reason = f"device lost: {exc}"
        finally:
            clock_map, rescaled, note = self._close(stream)
            if self.online is not None:
                self.estimate = self.online.estimate()
        if on_status is not None:
            on_status(self._status(time.monotonic() - stream.t_start))
        where = f"in {self.out}, session {self.session!r}"
        if lost is not None:
            if not self.samples:
                raise DeviceLost(f"{lost}; nothing was recorded")
            raise DeviceLost(f"{lost}; the {self.samples} samples received are saved {where}")
        if not self.samples:
            raise DeviceError(
                f"{stream.reason} before any sample arrived from {self.link.url}; "
                "nothing was recorded"
            )
        duration = self._duration
        return RecordResult(
            path=str(self.out),
            session=self.session,
            samples=self.samples,
            duration_s=duration,
            rate_hz=(self.samples - 1) / duration if duration > 0 else 0.0,
            bad_frames=self.reader.malformed + self.link.bad_frames,
            lost_frames=self.lost,
            stop_reason=stream.reason,
            clock_map=clock_map,
            meta={**self.meta, **self._counters(), "time_base": note},
            faults=self._faults(),
            time_rescaled=rescaled,
            estimate=self.estimate,
            identify_note=self.online.note if self.online is not None else "",
        )

    @property
    def _duration(self) -> float:
        return self._final_duration if hasattr(self, "_final_duration") else 0.0

    def _seconds(self, t: NDArray[np.float64]) -> NDArray[np.float64]:
        """Stamps (s) or slots as seconds from the first sample."""
        if self.first is None:
            self.first = float(t[0])
        rel = t - self.first
        return rel if self.reader.stamped else rel / self.rate_hz

    def _take(self, lines: list[Line], t_start: float) -> None:
        (t, force, position, host), _ = self.reader.take(lines)
        if not t.size:
            return
        secs = self._seconds(t)
        if self.duration_s is not None and secs[-1] > self.duration_s:
            keep = secs <= self.duration_s
            secs, force, position, host = secs[keep], force[keep], position[keep], host[keep]
            self.done = True
            # lines after the last sample kept are not part of the recording
            beyond = self.reader.numbers[~keep]
            self.reader.uncount(int(beyond[0]) - 1)
            if not secs.size:
                return
        host = host - t_start
        for label, values in (("force", force), ("position", position)):
            if not np.all(np.isfinite(values)):
                raise InputError(f"{label} from {self.link.url} is not finite")  # pragma: no cover
        if self.writer is None:
            self.writer = self.open_writer()
        self.writer.append({"time": secs, "force": force, "position": position})
        self.samples += secs.size
        self.times.append(secs)
        self.hosts.append(host)
        block = SampleBlock(secs, position, force, host)
        for listen in self.listeners:
            listen(block)

    def _counters(self) -> dict[str, Any]:
        return {
            "frames_good": self.samples,
            "frames_bad": self.reader.malformed + self.link.bad_frames,
            "lines_received": self.link.lines,
            "lines_malformed": self.reader.malformed + self.link.bad_frames,
            "lines_ignored": self.reader.ignored,
            "stamps_rejected": self.reader.stamps.rejected,
            "clock_wraps": self.reader.stamps.wraps,
            "sequence_restarts": self.reader.stamps.restarts,
            "frames_lost": self.lost,
            "samples_missing": self.missing,
            **(
                {"device_stamp_first": self.reader.first_stamp}
                if self.reader.first_stamp is not None
                else {}
            ),
        }

    def _faults(self) -> ClockFaults:
        checker = self.reader.stamps
        return ClockFaults(
            frames_rejected=checker.rejected,
            sequence_restarts=checker.restarts,
            clock_wraps=checker.wraps,
            frames_lost=self.lost,
        )

    def _close(self, stream: Stream) -> tuple[ClockMap | None, bool, str]:
        """The time base: device stamps on their regular clock (losses counted) or slots
        on a clock fitted to the arrivals; drift corrected when resolved; final counters."""
        if self.writer is None:
            return None, False, ""
        t = np.concatenate(self.times)
        host = np.concatenate(self.hosts)
        note = ""
        clock_map: ClockMap | None = None
        rescaled = False
        if self.reader.stamped:
            try:
                regular, base = regularise(t)
                # a malformed line held a sample: its hole is counted there, not as lost
                self.missing = int(base.lost)
                self.lost = max(0, self.missing - self.reader.malformed - self.link.bad_frames)
                t = regular - regular[0]
                note = "device stamps: " + base.describe().replace(
                    "lost sample(s)", "sample(s) missing (malformed or lost lines)"
                )
            except (InputError, ValueError) as exc:
                note = f"device stamps kept as received ({exc})"
            clock_map = fit_clock_map(t, host)
            if clock_map is not None and clock_map.resolved:
                t = t * clock_map.slope
                rescaled = True
                note += "; rescaled to host seconds by the clock map"
        else:
            slots = t * self.rate_hz  # back to slots
            clock_map = fit_clock_map(slots / self.rate_hz, host)
            period = (clock_map.slope if clock_map is not None else 1.0) / self.rate_hz
            t = slots * period
            rescaled = clock_map is not None
            note = (
                "no device stamps: each line's place in the stream on a clock fitted to "
                f"the host's arrival times ({1 / period:.6g} Hz)"
            )
        self._final_duration = float(t[-1]) if t.size else 0.0
        stored: dict[str, Any] = {}
        if clock_map is not None:
            stored = {**clock_map.as_dict(), "time_rescaled": rescaled, "time_base": note}
        try:
            self.writer.rewrite("time", t, clock=note)
        except TissueError:  # pragma: no cover  (a storage fault: the writer says so)
            pass
        self.writer.close(
            **self._counters(), stop_reason=stream.reason, clock_map=stored, time_base=note
        )
        return clock_map, rescaled, note

    def _status(self, elapsed: float) -> RecordStatus:
        try:
            size = self.out.stat().st_size if self.writer is not None else 0
        except OSError:
            size = 0
        if self.online is not None:
            self.estimate = self.online.estimate()
        return RecordStatus(
            elapsed_s=elapsed,
            samples=self.samples,
            rate_hz=self.samples / elapsed if elapsed > 0 else 0.0,
            bad_frames=self.reader.malformed + self.link.bad_frames,
            lost_frames=self.reader.stamps.rejected,
            file_bytes=size,
            faults=self._faults(),
            estimate=self.estimate,
        )
