"""The ``record`` service: a session from a forceps over serial into an HDF5 file,
losing nothing."""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable
from dataclasses import replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..core.calibration import Calibration, calibration_from_dict
from ..core.clock import ClockMap, Stamped, TimeBase, fit_clock_map
from ..core.errors import DeviceError, DeviceLost, InputError
from ..core.session import check_name
from ..formats.outputs import Output, check_outputs
from ..formats.sessions import check_new_session, session_writer
from ..formats.writer import SeriesWriter
from ..hw.device import Device, Forceps
from ..hw.link import DEFAULT_BAUD, calibration_problem
from ..hw.protocol import Sample
from ..hw.realtime import StopFlag
from ..hw.stream import Stream
from .record_text import record_lines
from .recording import (
    Online,
    RecordOptions,
    RecordResult,
    RecordStatus,
    SampleBlock,
    check_not_stopped,
    stopped_by,
)

#: the protocols :func:`record` speaks
PROTOCOLS = ("binary", "text")


def record(
    url: str,
    out: str | os.PathLike[str],
    session: str,
    *,
    protocol: str = "binary",
    duration_s: float | None = None,
    tissue: str = "",
    note: str = "",
    calibration: Calibration | None = None,
    baudrate: int | None = None,
    stop: StopFlag | None = None,
    on_status: Callable[[RecordStatus], None] | None = None,
    status_interval_s: float = 0.5,
    flush_interval_s: float = 0.25,
    idle_timeout_s: float = 2.0,
    on_samples: Callable[[SampleBlock], None] | None = None,
    identify: bool = True,
    forgetting_s: float = 5.0,
    columns: str | None = None,
    units: str | None = None,
    jaw_length_m: float | None = None,
) -> RecordResult:
    """Record from the forceps at ``url`` into session ``session`` of ``out``.

    The device is not trusted: its Info is checked field by field, and every frame's
    clock stamp and sequence number against what the last good frames predict
    (:class:`~tissuecli.core.clock.TimeBase`), so stored time is strictly increasing
    whatever the device sends. The session is created when the first sample is kept;
    a recording that keeps none leaves nothing behind. A logger that prints lines of
    text (``protocol="text"``) is read as ``import`` reads files
    (:mod:`tissuecli.app.record_text`).

    Parameters
    ----------
    url : str
        Device path or pyserial URL.
    out : path
        HDF5 file; created if missing. Existing sessions are never touched.
    session : str
        Name of the new session; refused if the file already has it.
    protocol : {"binary", "text"}
        tissuecli's framed protocol, or a logger printing lines of text.
    duration_s : float, optional
        Stop after this much device time (s, on the repaired time base); otherwise run
        until ``stop``.
    tissue, note : str
        Stored with the session.
    calibration : Calibration, optional
        Counts-to-SI conversion; by default the one the device reports. A text logger
        that prints ADC counts for force and position: SI = gain * counts + offset
        (``units`` may then name the time column's unit only).
    baudrate : int, optional
        Line rate, bit/s [default: 921600 binary, 115200 text].
    stop : StopFlag, optional
        Polled every read; SIGINT/SIGTERM handlers set it for a clean stop.
    on_status : callable, optional
        Called with a :class:`RecordStatus` every ``status_interval_s``.
    flush_interval_s : float
        Longest time received samples stay only in memory, s.
    idle_timeout_s : float
        A device that sends no sample, or none that can be kept, for this long is
        taken as lost.
    on_samples : callable, optional
        Called in the acquisition loop with each block of samples once it is handed to
        the writer (the live view and online identification listen here); it must
        return quickly, as the loop waits for it.
    identify : bool
        Identify the tissue online while recording
        (:class:`~tissuecli.identify.online.OnlineFit`, the paper's four laws): the
        status carries its current estimate and the result its last one. An error
        in it stops the identification, never the recording.
    forgetting_s : float
        Forgetting time constant of the online identification, s.
    columns, units, jaw_length_m
        Text only: as for ``import``
        (:func:`tissuecli.formats.recording.read_recording`).

    Raises
    ------
    DeviceError
        If the device reports an unusable Info, a text logger prints nothing that
        reads as samples, or the recording is stopped before any sample was kept
        (nothing is written then).
    DeviceLost
        If the device vanishes; everything kept until then is saved first.
    InputError
        For options that do not fit the protocol or the lines.
    """
    if protocol not in PROTOCOLS:
        raise InputError(f"unknown protocol {protocol!r}; choose binary or text")
    if duration_s is not None and not duration_s > 0:
        raise InputError("--duration must be a positive number of seconds")
    given = [n for n, v in (("columns", columns), ("units", units),
                            ("jaw-length", jaw_length_m)) if v is not None]  # fmt: skip
    if protocol != "text" and given:
        raise InputError(f"--{given[0]} is for --protocol text")
    check_name(session, "session")
    options = RecordOptions(
        duration_s=duration_s,
        tissue=tissue,
        note=note,
        calibration=calibration,
        baudrate=baudrate,
        stop=stop if stop is not None else StopFlag(),
        on_status=on_status,
        status_interval_s=status_interval_s,
        flush_interval_s=flush_interval_s,
        idle_timeout_s=idle_timeout_s,
        on_samples=on_samples,
        identify=identify,
        forgetting_s=forgetting_s,
    )
    out = Path(out)
    check_outputs([Output(out, "--out", appends=True)])
    check_new_session(out, session)
    check_not_stopped(options.stop, url)
    if protocol == "text":
        return record_lines(url, out, session, options, columns, units, jaw_length_m)
    return _record_frames(url, out, session, options)


def _record_frames(url: str, out: Path, session: str, options: RecordOptions) -> RecordResult:
    """:func:`record` from a forceps speaking the framed protocol, its arguments checked."""
    stop, calibration, duration_s = options.stop, options.calibration, options.duration_s
    link = Forceps(url, baudrate=options.baudrate or DEFAULT_BAUD).open(
        require_info=calibration is None,
        no_info_hint="; for a forceps that streams without identifying, give --calibration FILE"
        "; for a logger that prints lines of text, --protocol text",
        uses_calibration=calibration is None,
    )
    info = link.info
    try:
        check_not_stopped(stop, url)
        cal = calibration or calibration_from_dict((info or {})["calibration"])
        if calibration is not None:
            _check_calibration(calibration, (info or {}).get("adc_bits", 16))
        clock_hz = float((info or {}).get("clock_hz", DEFAULT_CLOCK_HZ))
        rate_hz = float((info or {}).get("rate_hz", math.nan))
        meta = {
            "tissue": options.tissue,
            "note": options.note,
            "start_utc": datetime.now(timezone.utc).isoformat(timespec="milliseconds"),
            "source": f"serial:{url}",
            "device": info or {},
            "rate_hz": rate_hz,
            "clock_hz": clock_hz,
        }

        def open_writer() -> SeriesWriter:
            return session_writer(
                out,
                session,
                meta=meta,
                calibration=cal.as_dict(),
                flush_interval_s=options.flush_interval_s,
            )

        timebase: TimeBase[Sample] = TimeBase(
            clock_hz / rate_hz if math.isfinite(rate_hz) else None,
            limit_ticks=duration_s * clock_hz if duration_s is not None else math.inf,
        )
        online = Online(rate_hz, options.forgetting_s) if options.identify else None
        if online is not None:
            online.prepare()
        listeners = [f for f in (online, options.on_samples) if f is not None]

        def listen(block: SampleBlock) -> None:
            for f in listeners:
                f(block)

        recording = _Recording(
            link, open_writer, timebase, cal, clock_hz, out, session, meta,
            listen if listeners else None, online,
        )  # fmt: skip
        return recording.run(
            Stream(
                link,
                Sample,
                stop=stop,
                idle_timeout_s=options.idle_timeout_s,
                status_interval_s=options.status_interval_s,
                track_sequence=False,  # the time base counts losses among kept frames
            ),
            options.on_status,
        )
    finally:
        link.close()


#: device clock rate of protocol version 1, for a forceps that does not identify, Hz
DEFAULT_CLOCK_HZ = 1e6


def _check_calibration(cal: Calibration, bits: object) -> None:
    """Refuse a user's calibration that maps the ADC range to infinite or absurd values."""
    problem = calibration_problem(cal.as_dict(), bits if isinstance(bits, int) else 16)
    if problem is not None:
        name, value, must = problem
        raise InputError(
            f"--calibration {name.removeprefix('calibration.')} = {value}; it must be {must}"
        )


class _Recording:
    """One session being recorded: frames checked and stamped, samples to SI, to the
    writer (created with the first kept sample), and the clock map at the end."""

    def __init__(
        self,
        link: Device,
        open_writer: Callable[[], SeriesWriter],
        timebase: TimeBase[Sample],
        cal: Calibration,
        clock_hz: float,
        out: Path,
        session: str,
        meta: dict[str, Any],
        on_samples: Callable[[SampleBlock], None] | None = None,
        online: Online | None = None,
    ) -> None:
        self.link, self.open_writer, self.timebase = link, open_writer, timebase
        self.on_samples = on_samples
        self.online = online
        self.estimate: Any = None
        self.cal, self.clock_hz = cal, clock_hz
        self.out, self.session, self.meta = out, session, meta
        self.writer: SeriesWriter | None = None
        self.samples = 0
        self.duration_s = 0.0
        self.last_kept = math.nan  # monotonic time a sample was last kept, s
        self.time_rescaled = False
        self.host_times: list[NDArray[np.float64]] = []
        self.device_times: list[NDArray[np.float64]] = []

    def run(self, stream: Stream, on_status: Callable[[RecordStatus], None] | None) -> RecordResult:
        """The acquisition loop; the writer is closed with final counters however it ends."""
        lost: DeviceLost | None = None
        clock_map: ClockMap | None = None
        try:
            with stream:
                self.last_kept = stream.t_start
                while stream.running():
                    batch = stream.poll()
                    now = time.monotonic()
                    if batch:
                        self._take(batch, now - stream.t_start)
                        if self.timebase.done:
                            break
                        self._check_usable(now, stream)
                    else:
                        stream.check_idle(now)
                    if stream.status_due(now):
                        if self.writer is not None:
                            self.writer.set_attrs(**self._counters())
                        if on_status is not None:
                            on_status(self._status(now - stream.t_start))
        except DeviceLost as exc:
            lost = exc
        finally:
            clock_map = self._close(stream)
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
            raise stopped_by(
                DeviceError(
                    f"{stream.reason} before any sample arrived from {self.link.url}; "
                    "nothing was recorded"
                ),
                stream.stop,
            )
        duration = self.duration_s
        return RecordResult(
            path=str(self.out),
            session=self.session,
            samples=self.samples,
            duration_s=duration,
            rate_hz=(self.samples - 1) / duration if duration > 0 else 0.0,
            bad_frames=self.link.bad_frames,
            lost_frames=self.timebase.faults.frames_lost,
            stop_reason=stream.reason,
            clock_map=clock_map,
            meta=self.meta,
            faults=replace(self.timebase.faults),
            time_rescaled=self.time_rescaled,
            estimate=self.estimate,
            identify_note=self.online.note if self.online is not None else "",
        )

    def _check_usable(self, now: float, stream: Stream) -> None:
        """Frames keep arriving but none can be kept: as good as a silent device."""
        if now - self.last_kept > stream.idle_timeout_s:
            timeout = stream.idle_timeout_s
            span = f"{timeout * 1e3:g} ms" if timeout < 1 else f"{timeout:g} s"
            faults = self.timebase.faults
            period = self.timebase.period_ticks
            steady = f" of {period:g} clock ticks per sample" if period is not None else ""
            raise DeviceLost(
                f"no usable Sample frame from {self.link.url} for {span}: "
                f"{faults.frames_rejected + self.timebase.waiting} frames carried sequence "
                f"numbers and clock stamps that fit no steady stream{steady}"
            )

    def _take(self, batch: list[Any], host_s: float) -> None:
        """Check and stamp one batch, then convert and append what is kept."""
        kept = self.timebase.feed([(m.seq, m.clock, m, host_s) for m in batch])
        self._append(kept)

    def _append(self, kept: list[Stamped[Sample]]) -> None:
        if not kept:
            return
        self.last_kept = time.monotonic()
        raw = np.array(
            [(s.payload.seq, s.payload.force, s.payload.position) for s in kept], dtype=np.int64
        )
        t_dev = np.array([s.ticks for s in kept]) / self.clock_hz
        t_host = np.array([s.host_s for s in kept])
        counts = raw[:, 1:3].astype(np.int16)
        force = self.cal.force.to_si(counts[:, 0])
        position = self.cal.position.to_si(counts[:, 1])
        if self.writer is None:
            self.writer = self.open_writer()
        self.writer.append(
            {
                "time": t_dev,
                "force": force,
                "position": position,
                "raw/counts": counts,
                "raw/sequence": raw[:, 0].astype(np.uint32),
                "raw/device_clock": np.array([s.device_clock for s in kept], dtype=np.int64),
                "raw/host_time": t_host,
            }
        )
        self.samples += counts.shape[0]
        self.host_times.append(t_host)
        self.device_times.append(t_dev)
        if self.on_samples is not None:
            self.on_samples(SampleBlock(t_dev, position, force, t_host))

    def _counters(self) -> dict[str, Any]:
        return {
            "frames_good": self.samples,
            "frames_bad": self.link.bad_frames,
            **self.timebase.faults.as_dict(),
        }

    def _close(self, stream: Stream) -> ClockMap | None:
        """Decide the frames still waiting, map device time to host seconds, store the
        final counters and mark the session done; nothing if no sample was kept."""
        self.time_rescaled = False
        if not self.timebase.done:
            self._append(self.timebase.finish())
        if self.writer is None:
            return None
        device = np.concatenate(self.device_times)
        host = np.concatenate(self.host_times)
        self.duration_s = float(device[-1])
        clock_map = fit_clock_map(device, host)
        stored: dict[str, Any] = {}
        if clock_map is not None:
            self.time_rescaled = clock_map.resolved
            stored = {
                **clock_map.as_dict(),
                "time_rescaled": self.time_rescaled,
                "time_base": (
                    "device clock, repaired and rescaled to host seconds by slope"
                    if self.time_rescaled
                    else "device clock, repaired; not rescaled: drift not resolved "
                    f"({clock_map.drift_ppm:+.1f} +- {clock_map.drift_uncertainty_ppm:.1f} ppm)"
                ),
            }
        if self.time_rescaled:
            assert clock_map is not None
            # time was written on the device clock; put it on the host's seconds
            self.writer.rewrite(
                "time",
                device * clock_map.slope,
                clock="device clock, drift-corrected to host seconds by clock_map",
            )
        self.writer.close(
            **self._counters(),
            stop_reason=stream.reason,
            clock_map=stored,
        )
        return clock_map

    def _status(self, elapsed: float) -> RecordStatus:
        try:
            size = self.out.stat().st_size if self.writer is not None else 0
        except OSError:
            size = 0
        faults = self.timebase.faults
        if self.online is not None:
            self.estimate = self.online.estimate()
        return RecordStatus(
            elapsed_s=elapsed,
            samples=self.samples,
            rate_hz=self.samples / elapsed if elapsed > 0 else 0.0,
            bad_frames=self.link.bad_frames,
            lost_frames=faults.frames_lost,
            file_bytes=size,
            faults=replace(faults),
            estimate=self.estimate,
        )


def record_live(
    address: str,
    url: str,
    out: str | os.PathLike[str],
    session: str,
    *,
    on_url: Callable[[str], None],
    on_status: Callable[[RecordStatus], None] | None = None,
    on_samples: Callable[[SampleBlock], None] | None = None,
    status_interval_s: float = 0.5,
    **options: Any,
) -> RecordResult:
    """:func:`record`, with the live view served at ``address`` (``HOST:PORT``) meanwhile.

    The address is bound before the device is touched (a port in use is refused first),
    ``on_url`` is called with the page's URL, and the server stops when the recording
    ends. The recorder only copies each block into the view's bounded state in shared
    memory; the pages are served from another process, which ends with this one. The
    view takes the status at least every
    :data:`LIVE_STATUS_S`; ``on_status`` is still called every ``status_interval_s``
    and once at the end. Other parameters (``protocol`` among them) as :func:`record`.
    """
    from ..live.server import LiveServer, parse_address
    from ..live.state import LiveState

    host, port = parse_address(address)
    state = LiveState(session)
    shown = [-math.inf, None]  # when on_status was last called, and a status not shown

    def status(s: RecordStatus) -> None:
        state.set_status(s)
        state.set_estimate(s.estimate)  # the recording's own online fit: one per recording
        if on_status is None:
            return
        now = time.monotonic()
        if now - shown[0] >= status_interval_s:
            shown[:] = [now, None]
            on_status(s)
        else:
            shown[1] = s

    def samples(block: SampleBlock) -> None:
        state.append(block)
        if on_samples is not None:
            on_samples(block)

    try:
        with LiveServer(state, host, port) as server:
            on_url(server.url)
            try:
                return record(
                    url,
                    out,
                    session,
                    on_status=status,
                    on_samples=samples,
                    status_interval_s=min(status_interval_s, LIVE_STATUS_S),
                    **options,
                )
            finally:
                state.finish()
                if on_status is not None and shown[1] is not None:
                    on_status(shown[1])  # the final status, whenever it came
    finally:
        state.close()


#: how often the live view takes the recording's status (and with it the online
#: estimate, computed in the acquisition loop), s; the traces need no status
LIVE_STATUS_S = 0.5
