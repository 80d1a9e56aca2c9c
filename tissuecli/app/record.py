"""The ``record`` service: a session from a forceps over serial into an HDF5 file,
losing nothing."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..core.calibration import Calibration, calibration_from_dict
from ..core.clock import ClockMap, TickUnwrapper, fit_clock_map
from ..core.errors import DeviceError, DeviceLost, InputError
from ..core.session import check_name
from ..formats.outputs import Output, check_outputs
from ..formats.sessions import check_new_session, session_writer
from ..formats.writer import SeriesWriter
from ..hw.link import DEFAULT_BAUD, Link, open_device
from ..hw.protocol import Sample
from ..hw.realtime import StopFlag
from ..hw.stream import Stream


@dataclass
class RecordStatus:
    """What the live status line shows."""

    elapsed_s: float = 0.0
    samples: int = 0
    rate_hz: float = 0.0
    bad_frames: int = 0
    lost_frames: int = 0
    file_bytes: int = 0


@dataclass
class RecordResult:
    """Summary of a finished recording."""

    path: str
    session: str
    samples: int
    duration_s: float
    rate_hz: float
    bad_frames: int
    lost_frames: int
    stop_reason: str
    clock_map: ClockMap | None
    meta: dict[str, Any] = field(default_factory=dict)


def record(
    url: str,
    out: str | os.PathLike[str],
    session: str,
    *,
    duration_s: float | None = None,
    tissue: str = "",
    note: str = "",
    calibration: Calibration | None = None,
    baudrate: int = DEFAULT_BAUD,
    stop: StopFlag | None = None,
    on_status: Callable[[RecordStatus], None] | None = None,
    status_interval_s: float = 0.5,
    flush_interval_s: float = 0.25,
    idle_timeout_s: float = 2.0,
) -> RecordResult:
    """Record from the forceps at ``url`` into session ``session`` of ``out``.

    Parameters
    ----------
    url : str
        Device path or pyserial URL.
    out : path
        HDF5 file; created if missing. Existing sessions are never touched.
    session : str
        Name of the new session; refused if the file already has it.
    duration_s : float, optional
        Stop after this much device time (s); otherwise run until ``stop``.
    tissue, note : str
        Stored with the session.
    calibration : Calibration, optional
        Counts-to-SI conversion; by default the one the device reports.
    baudrate : int
        Line rate, bit/s.
    stop : StopFlag, optional
        Polled every read; SIGINT/SIGTERM handlers set it for a clean stop.
    on_status : callable, optional
        Called with a :class:`RecordStatus` every ``status_interval_s``.
    flush_interval_s : float
        Longest time received samples stay only in memory, s.
    idle_timeout_s : float
        A device that sends no sample for this long is taken as lost.

    Raises
    ------
    DeviceLost
        If the device vanishes; everything received until then is saved first.
    """
    if duration_s is not None and not duration_s > 0:
        raise InputError("--duration must be a positive number of seconds")
    check_name(session, "session")
    out = Path(out)
    check_outputs([Output(out, "--out", appends=True)])
    check_new_session(out, session)
    link, info = open_device(
        url,
        "forceps",
        baudrate=baudrate,
        require_info=calibration is None,
        no_info_hint="; for a forceps that streams without identifying, give --calibration FILE",
    )
    try:
        cal = calibration or _device_calibration(info, url)
        clock_hz = float((info or {}).get("clock_hz", 1e6))
        meta = {
            "tissue": tissue,
            "note": note,
            "start_utc": datetime.now(timezone.utc).isoformat(timespec="milliseconds"),
            "source": f"serial:{url}",
            "device": info or {},
            "rate_hz": float((info or {}).get("rate_hz", float("nan"))),
            "clock_hz": clock_hz,
        }
        writer = session_writer(
            out, session, meta=meta, calibration=cal.as_dict(), flush_interval_s=flush_interval_s
        )
        recording = _Recording(link, writer, cal, clock_hz, out, session, meta)
        return recording.run(
            duration_s,
            Stream(
                link,
                Sample,
                stop=stop if stop is not None else StopFlag(),
                idle_timeout_s=idle_timeout_s,
                status_interval_s=status_interval_s,
            ),
            on_status,
        )
    finally:
        link.close()


def _device_calibration(info: dict[str, Any] | None, url: str) -> Calibration:
    if info is None or "calibration" not in info:
        raise DeviceError(f"{url} reports no calibration; give --calibration FILE")
    return calibration_from_dict(info["calibration"])


class _Recording:
    """One session being recorded: samples to SI, to the writer, and the clock map at the end."""

    def __init__(
        self,
        link: Link,
        writer: SeriesWriter,
        cal: Calibration,
        clock_hz: float,
        out: Path,
        session: str,
        meta: dict[str, Any],
    ) -> None:
        self.link, self.writer, self.cal, self.clock_hz = link, writer, cal, clock_hz
        self.out, self.session, self.meta = out, session, meta
        self.unwrap = TickUnwrapper()
        self.tick0: int | None = None
        self.samples = 0
        self.duration_s = 0.0
        self.host_times: list[NDArray[np.float64]] = []
        self.device_times: list[NDArray[np.float64]] = []

    def run(
        self,
        duration_s: float | None,
        stream: Stream,
        on_status: Callable[[RecordStatus], None] | None,
    ) -> RecordResult:
        """The acquisition loop; the writer is closed with final counters however it ends."""
        lost: DeviceLost | None = None
        try:
            with stream:
                while stream.running():
                    batch = stream.poll()
                    now = time.monotonic()
                    if batch:
                        if self._take(batch, now - stream.t_start, duration_s):
                            break
                    else:
                        stream.check_idle(now)
                    if stream.status_due(now):
                        self.writer.set_attrs(
                            frames_bad=self.link.decoder.bad_frames, frames_lost=stream.seqs.lost
                        )
                        if on_status is not None:
                            on_status(self._status(now - stream.t_start, stream))
        except DeviceLost as exc:
            lost = exc
        finally:
            clock_map = self._close(stream)
        if on_status is not None:
            on_status(self._status(time.monotonic() - stream.t_start, stream))
        if lost is not None:
            raise DeviceLost(
                f"{lost}; the {self.samples} samples received are saved in {self.out}, "
                f"session {self.session!r}"
            )
        duration = self.duration_s
        return RecordResult(
            path=str(self.out),
            session=self.session,
            samples=self.samples,
            duration_s=duration,
            rate_hz=(self.samples - 1) / duration if duration > 0 else 0.0,
            bad_frames=self.link.decoder.bad_frames,
            lost_frames=stream.seqs.lost,
            stop_reason=stream.reason,
            clock_map=clock_map,
            meta=self.meta,
        )

    def _take(self, batch: list[Any], host_s: float, duration_s: float | None) -> bool:
        """Convert and append one batch; True once ``duration_s`` of device time is in."""
        raw = np.array([(m.seq, m.clock, m.force, m.position) for m in batch], dtype=np.int64)
        ticks = self.unwrap(raw[:, 1])
        if self.tick0 is None:
            self.tick0 = int(ticks[0])
        t_dev = (ticks - self.tick0) / self.clock_hz
        keep, done = slice(None), False
        if duration_s is not None and t_dev[-1] >= duration_s:
            # keep the samples taken before the duration: exactly duration * rate
            keep, done = slice(0, int(np.searchsorted(t_dev, duration_s))), True
        counts = raw[keep, 2:4].astype(np.int16)
        t_host = np.full(counts.shape[0], host_s)
        self.writer.append(
            {
                "time": t_dev[keep],
                "force": self.cal.force.to_si(counts[:, 0]),
                "position": self.cal.position.to_si(counts[:, 1]),
                "raw/counts": counts,
                "raw/sequence": raw[keep, 0].astype(np.uint32),
                "raw/device_clock": ticks[keep],
                "raw/host_time": t_host,
            }
        )
        self.samples += counts.shape[0]
        self.host_times.append(t_host)
        self.device_times.append(t_dev[keep])
        return done

    def _close(self, stream: Stream) -> ClockMap | None:
        """Map device time to host seconds, store the final counters, mark the session done."""
        device = np.concatenate(self.device_times) if self.device_times else np.empty(0)
        host = np.concatenate(self.host_times) if self.host_times else np.empty(0)
        self.duration_s = float(device[-1]) if device.size else 0.0
        clock_map = fit_clock_map(device, host)
        if clock_map is not None:
            # time was written on the device clock; put it on the host's seconds
            self.writer.rewrite(
                "time",
                device * clock_map.slope,
                clock="device clock, drift-corrected to host seconds by clock_map",
            )
        self.writer.close(
            frames_good=self.samples,
            frames_bad=self.link.decoder.bad_frames,
            frames_lost=stream.seqs.lost,
            sequence_restarts=stream.seqs.restarts,
            stop_reason=stream.reason,
            clock_map=clock_map.as_dict() if clock_map else {},
        )
        return clock_map

    def _status(self, elapsed: float, stream: Stream) -> RecordStatus:
        try:
            size = self.out.stat().st_size
        except OSError:
            size = 0
        return RecordStatus(
            elapsed_s=elapsed,
            samples=self.samples,
            rate_hz=self.samples / elapsed if elapsed > 0 else 0.0,
            bad_frames=self.link.decoder.bad_frames,
            lost_frames=stream.seqs.lost,
            file_bytes=size,
        )
