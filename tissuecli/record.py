"""Record a session from a forceps over serial into an HDF5 file, losing nothing."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from . import storage
from .calibration import Calibration, calibration_from_dict
from .clock import ClockMap, TickUnwrapper, fit_clock_map
from .device import DEFAULT_BAUD, Link
from .errors import DeviceError, DeviceLost, InputError
from .protocol import PROTOCOL_VERSION, Sample, SequenceTracker
from .simulate import StopFlag


@dataclass
class Status:
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


def _check_device(
    info: dict[str, Any] | None, url: str, calibration: Calibration | None
) -> Calibration:
    """The calibration to use, after checking the device's protocol version."""
    if info is not None and info.get("device", "forceps") != "forceps":
        raise DeviceError(
            f"{url} is a {info.get('device')!r}, not a forceps; record reads the forceps "
            "(a display is driven by `tissuecli play`)"
        )
    if info is not None:
        version = info.get("protocol")
        if version != PROTOCOL_VERSION:
            raise DeviceError(
                f"{url} speaks protocol version {version}; "
                f"this tissuecli speaks {PROTOCOL_VERSION}. "
                "Update tissuecli or the device firmware"
            )
    if calibration is not None:
        return calibration
    if info is None:
        raise DeviceError(
            f"{url} did not answer IDENTIFY within 2 s. Is it a forceps and is it powered? "
            "For a device that streams without identifying, give --calibration FILE"
        )
    if "calibration" not in info:
        raise DeviceError(f"{url} reports no calibration; give --calibration FILE")
    return calibration_from_dict(info["calibration"])


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
    on_status: Callable[[Status], None] | None = None,
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
    calibration : Calibration, optional
        Counts-to-SI conversion; by default the one the device reports.
    stop : StopFlag, optional
        Polled every read; SIGINT/SIGTERM handlers set it for a clean stop.
    on_status : callable, optional
        Called with a :class:`Status` every ``status_interval_s``.
    idle_timeout_s : float
        A device that sends no sample for this long is taken as lost.

    Raises
    ------
    DeviceLost
        If the device vanishes; everything received until then is saved first.
    """
    if duration_s is not None and not duration_s > 0:
        raise InputError("--duration must be a positive number of seconds")
    if not session or "/" in session:
        raise InputError("--session must be a non-empty name without '/'")
    out = Path(out)
    storage.check_new_session(out, session)
    stop = stop if stop is not None else StopFlag()

    link = Link(url, baudrate=baudrate)
    try:
        link.command("stop")  # a device left streaming by a crashed host
        time.sleep(0.05)
        link.discard_input()
        info = link.identify()
        cal = _check_device(info, url, calibration)
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
        writer = storage.session_writer(
            out, session, meta=meta, calibration=cal.as_dict(), flush_interval_s=flush_interval_s
        )
        return _stream(
            link,
            writer,
            cal,
            clock_hz,
            out,
            session,
            duration_s,
            stop,
            on_status,
            status_interval_s,
            idle_timeout_s,
            meta,
        )
    finally:
        link.close()


def _stream(
    link: Link,
    writer: storage.SeriesWriter,
    cal: Calibration,
    clock_hz: float,
    out: Path,
    session: str,
    duration_s: float | None,
    stop: StopFlag,
    on_status: Callable[[Status], None] | None,
    status_interval_s: float,
    idle_timeout_s: float,
    meta: dict[str, Any],
) -> RecordResult:
    """The acquisition loop; the writer is closed with final counters however it ends."""
    seqs = SequenceTracker()
    unwrap = TickUnwrapper()
    tick0: int | None = None
    samples = 0
    host_times: list[np.ndarray] = []
    device_times: list[np.ndarray] = []
    t_start = time.monotonic()
    last_data = t_start
    next_status = t_start + status_interval_s
    reason = "duration reached"
    lost_error: DeviceLost | None = None
    status = Status()
    link.command("start")
    try:
        while True:
            if stop:
                reason = "interrupted by signal"
                break
            messages = link.poll()
            now = time.monotonic()
            batch = [m for m in messages if isinstance(m, Sample)]
            if batch:
                last_data = now
                raw = np.array(
                    [(m.seq, m.clock, m.force, m.position) for m in batch], dtype=np.int64
                )
                for s in raw[:, 0]:
                    seqs.update(int(s))
                ticks = unwrap(raw[:, 1])
                if tick0 is None:
                    tick0 = int(ticks[0])
                t_dev = (ticks - tick0) / clock_hz
                keep, done = slice(None), False
                if duration_s is not None and t_dev[-1] >= duration_s:
                    # keep the samples taken before the duration: exactly duration * rate
                    keep, done = slice(0, int(np.searchsorted(t_dev, duration_s))), True
                counts = raw[keep, 2:4].astype(np.int16)
                t_host = np.full(counts.shape[0], now - t_start)
                writer.append(
                    {
                        "time": t_dev[keep],
                        "force": cal.force.to_si(counts[:, 0]),
                        "position": cal.position.to_si(counts[:, 1]),
                        "raw/counts": counts,
                        "raw/sequence": raw[keep, 0].astype(np.uint32),
                        "raw/device_clock": ticks[keep],
                        "raw/host_time": t_host,
                    }
                )
                samples += counts.shape[0]
                host_times.append(t_host)
                device_times.append(t_dev[keep])
                if done:
                    break
            elif now - last_data > idle_timeout_s:
                raise DeviceLost(f"no data from {link.url} for {idle_timeout_s:g} s")
            if now >= next_status:
                next_status = now + status_interval_s
                writer.set_attrs(frames_bad=link.decoder.bad_frames, frames_lost=seqs.lost)
                status = _status(now - t_start, samples, link, seqs, out)
                if on_status is not None:
                    on_status(status)
    except DeviceLost as exc:
        lost_error = exc
        reason = f"device lost: {exc}"
    finally:
        if lost_error is None:
            try:
                link.command("stop")
            except DeviceLost:
                pass
        clock_map = fit_clock_map(
            np.concatenate(device_times) if device_times else [],
            np.concatenate(host_times) if host_times else [],
        )
        final = {
            "frames_good": samples,
            "frames_bad": link.decoder.bad_frames,
            "frames_lost": seqs.lost,
            "sequence_restarts": seqs.restarts,
            "stop_reason": reason,
            "clock_map": clock_map.as_dict() if clock_map else {},
        }
        if clock_map is not None:
            # time was written on the device clock; put it on the host's seconds
            writer.rewrite(
                "time",
                np.concatenate(device_times) * clock_map.slope,
                clock="device clock, drift-corrected to host seconds by clock_map",
            )
        writer.close(**final)
    duration = float(np.concatenate(device_times)[-1]) if samples else 0.0
    result = RecordResult(
        path=str(out),
        session=session,
        samples=samples,
        duration_s=duration,
        rate_hz=(samples - 1) / duration if duration > 0 else 0.0,
        bad_frames=link.decoder.bad_frames,
        lost_frames=seqs.lost,
        stop_reason=reason,
        clock_map=clock_map,
        meta=meta,
    )
    if on_status is not None:
        on_status(_status(time.monotonic() - t_start, samples, link, seqs, out))
    if lost_error is not None:
        raise DeviceLost(
            f"{lost_error}; the {samples} samples received are saved in {out}, session {session!r}"
        )
    return result


def _status(elapsed: float, samples: int, link: Link, seqs: SequenceTracker, out: Path) -> Status:
    try:
        size = out.stat().st_size
    except OSError:
        size = 0
    return Status(
        elapsed_s=elapsed,
        samples=samples,
        rate_hz=samples / elapsed if elapsed > 0 else 0.0,
        bad_frames=link.decoder.bad_frames,
        lost_frames=seqs.lost,
        file_bytes=size,
    )
