"""Play a tissue on the solenoid display in real time, and the simulated display itself.

Host side, :func:`play`: identify the display, check that it can render the
tissue, then close the loop: every Encoder frame is run through the
:class:`~tissuecli.display.Controller` and answered at once with a SetVoltage.
The display's frames set the rhythm; the host keeps absolute deadlines
(:class:`~tissuecli.simulate.Deadlines`, half a period after each expected frame)
to notice missing frames, to keep the display's watchdog fed and to measure its
own period. Whatever ends the loop (duration, stop flag, a lost device, any
exception), the last thing sent is ``SetVoltage(0)`` followed by STOP.

Display side, :func:`simulate_display`: the firmware of a simulated display
behind a :class:`~tissuecli.device.VirtualPort`. At each tick of its loop it
applies the latest SetVoltage, sends an Encoder frame and integrates the
piston's physics (:func:`~tissuecli.display.piston_step`) under a simulated
operator (:class:`~tissuecli.display.OperatorForce`) until the next tick. If no
valid SetVoltage arrives for :data:`WATCHDOG_PERIODS` periods it zeroes the
voltage and raises ``FLAG_WATCHDOG``.
"""

from __future__ import annotations

import contextlib
import gc
import math
import os
import queue
import sys
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import asdict
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from . import __version__, storage
from .device import DEFAULT_BAUD, Link, VirtualPort
from .display import (
    GRASP_FORCE_N,
    NONFINITE,
    PAPER_DISPLAY,
    SATURATED,
    UNRENDERABLE,
    Controller,
    DisplayProfile,
    OperatorForce,
    check,
    piston_step,
    profile_from_dict,
    tracking_bound,
)
from .errors import DeviceError, DeviceLost, InputError, RenderError
from .models import Tissue
from .params import read_json
from .protocol import (
    FLAG_LIMIT,
    FLAG_WATCHDOG,
    IDENTIFY,
    PROTOCOL_VERSION,
    START,
    STOP,
    Command,
    Encoder,
    FrameDecoder,
    Info,
    SequenceTracker,
    SetVoltage,
    encode,
)
from .simulate import Deadlines, StopFlag, wait_readable
from .synth import CLOCK_HZ

#: The display zeroes the voltage after this many periods without a valid SetVoltage
#: (docs/protocol.md, section 7).
WATCHDOG_PERIODS = 5
#: A missing Encoder frame is bridged by repeating the last voltage this many periods,
#: then the host sends 0 V until frames return.
HOLD_PERIODS = 3
#: Rows handed to the log writer at a time.
LOG_BLOCK = 100
#: Longest a logged row stays in memory, s: each flush fsyncs, which cost the display
#: process deadlines on a 2-core machine at 0.25 s; a crash loses at most this much log.
LOG_FLUSH_S = 1.0


def read_profile(path: str | os.PathLike[str]) -> DisplayProfile:
    """Read a display profile (JSON; see :func:`tissuecli.display.profile_from_dict`)."""
    return profile_from_dict(read_json(path, "display profile"), source=str(path))


def display_info(profile: DisplayProfile, rate_hz: float) -> dict[str, Any]:
    """What a display answers to IDENTIFY: identity, loop rate, encoder scale and profile."""
    return {
        "protocol": PROTOCOL_VERSION,
        "device": "display",
        "model": "tissuecli simulated solenoid display",
        "firmware": __version__,
        "rate_hz": rate_hz,
        "clock_hz": CLOCK_HZ,
        "calibration": {"position": {"gain": profile.resolution, "offset": 0.0, "unit": "m"}},
        "profile": profile.as_dict(),
    }


# --------------------------------------------------------------------------- display side


def simulate_display(
    profile: DisplayProfile,
    port: VirtualPort,
    *,
    rate_hz: float = 1000.0,
    operator: Callable[[float], float] | None = None,
    stop: StopFlag | None = None,
    duration_s: float | None = None,
    on_ready: Callable[[VirtualPort], None] | None = None,
    say: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Run the simulated display's firmware until ``stop`` is set (or ``duration_s``).

    Each tick, in order: decode what the host sent (IDENTIFY, START, STOP,
    SetVoltage; the latest valid SetVoltage wins, clamped to [0, v_max], NaN read as
    0), run the watchdog, send ``Encoder(position, volts in use, flags)`` if
    started, then integrate the piston over one period with that voltage held.
    STOP zeroes the voltage. The operator's presses restart at every START.
    Ticks are paced by absolute deadlines; one the process misses (descheduled) is
    skipped and counted, and simulated time waits for it rather than jumping.

    Parameters
    ----------
    profile : DisplayProfile
        The simulated hardware.
    port : VirtualPort
        Where the host connects.
    rate_hz : float
        Control-loop rate, Hz.
    operator : callable, optional
        Force on the piston (N) against time since START (s); presses from
        :class:`~tissuecli.display.OperatorForce` by default.
    stop : StopFlag, optional
        Polled every tick.
    duration_s : float, optional
        Exit after this many seconds.
    on_ready : callable, optional
        Called with the port once it exists.
    say : callable, optional
        Receives one line when the watchdog trips (once per trip).

    Returns
    -------
    dict
        Counters: ``sent`` Encoder frames, ``commands`` valid SetVoltage frames,
        ``last_command_volts`` (the last SetVoltage's value, V, or None),
        ``watchdog_trips``, ``bad_frames``, ``missed_deadlines``, ``overrun_bytes``.
    """
    stop = stop if stop is not None else StopFlag()
    fw = _Firmware(profile, port, rate_hz, operator or OperatorForce(), say)
    for t in (0.0, 1.0, 2.0):
        fw.operator(t)  # first calls build the presses' random generator: not inside a tick
    clock = Deadlines(fw.period)
    if on_ready is not None:
        on_ready(port)
    with _realtime():
        while not stop:
            if duration_s is not None and clock.k * fw.period >= duration_s:
                break
            fw.receive()
            fw.tick()
            fw.advance()
            time.sleep(max(0.0, clock.next() - time.monotonic()))
    fw.receive()  # what the host sent last (its final 0 V and STOP) is counted
    return {
        "sent": fw.sent,
        "commands": fw.commands,
        "last_command_volts": fw.last_command,
        "watchdog_trips": fw.trips,
        "bad_frames": fw.decoder.bad_frames,
        "missed_deadlines": clock.missed,
        "overrun_bytes": port.overruns,
    }


class _Firmware:
    """State and steps of the simulated display's control loop (see :func:`simulate_display`)."""

    def __init__(
        self,
        profile: DisplayProfile,
        port: VirtualPort,
        rate_hz: float,
        operator: Callable[[float], float],
        say: Callable[[str], None] | None,
    ) -> None:
        self.profile, self.port, self.operator, self.say = profile, port, operator, say
        self.period = 1.0 / rate_hz
        self.decoder = FrameDecoder()
        self.info = encode(Info(display_info(profile, rate_hz)))
        self.x = self.v = self.volts = 0.0
        self.at_limit = self.streaming = self.armed = self.tripped = False
        self.seq = self.sent = self.commands = self.trips = 0
        self.last_command: float | None = None
        self.k_start = 0
        # Simulated time, the clock field and the watchdog all count ticks the firmware
        # ran: a real display's microcontroller never skips one, while this process can
        # be descheduled (with its host) for milliseconds. A stall then looks to the host
        # like transport delay, as it would with real hardware, instead of the piston
        # running open-loop through the skipped periods.
        self.ticks_run = self.tick_command = 0

    def receive(self) -> None:
        """Act on what the host sent since the last tick; the latest SetVoltage wins."""
        for msg in self.decoder.feed(self.port.read()):
            if isinstance(msg, SetVoltage):
                if self.streaming:
                    value = float(msg.volts)
                    self.volts = min(max(value, 0.0), self.profile.v_max) if value == value else 0.0
                    self.last_command, self.tick_command = value, self.ticks_run
                    self.commands += 1
                    self.armed, self.tripped = True, False
            elif isinstance(msg, Command):
                if msg.code == IDENTIFY:
                    self.port.write(self.info)
                elif msg.code == START and not self.streaming:
                    self.streaming, self.armed, self.tripped = True, False, False
                    self.k_start = -1  # set by the next tick
                elif msg.code == STOP:
                    self.streaming, self.armed, self.volts = False, False, 0.0

    def tick(self) -> None:
        """Watchdog, then this tick's Encoder frame."""
        self.ticks_run += 1
        if self.k_start < 0:
            self.k_start = self.ticks_run
        # armed by the first SetVoltage after START, so a host's start-up is not a trip
        if (
            self.streaming
            and self.armed
            and not self.tripped
            and self.ticks_run - self.tick_command > WATCHDOG_PERIODS
        ):
            self.volts, self.tripped = 0.0, True
            self.trips += 1
            if self.say is not None:
                self.say(
                    f"watchdog: no SetVoltage for {WATCHDOG_PERIODS} periods "
                    f"({WATCHDOG_PERIODS * self.period * 1e3:g} ms); solenoid off"
                )
        if self.streaming:
            flags = (FLAG_WATCHDOG if self.tripped else 0) | (FLAG_LIMIT if self.at_limit else 0)
            ticks = int(round(self.ticks_run * self.period * CLOCK_HZ)) & 0xFFFFFFFF
            counts = int(round(self.x / self.profile.resolution))
            self.port.write(
                encode(Encoder(self.seq & 0xFFFFFFFF, ticks, counts, self.volts, flags))
            )
            self.seq += 1
            self.sent += 1

    def advance(self) -> None:
        """Integrate the piston over one period, voltage held."""
        t = (self.ticks_run - self.k_start) * self.period
        force = self.operator if self.streaming else _no_force
        self.x, self.v, self.at_limit = piston_step(
            self.profile, self.x, self.v, self.volts, force, t, self.period
        )


def _no_force(t: float) -> float:
    return 0.0


@contextlib.contextmanager
def _realtime() -> Iterator[None]:
    """Keep the cyclic garbage collector out of a 1 kHz loop.

    Its passes took 0.4-0.9 ms here, most of a period. The loops make no reference
    cycles (reference counting frees everything they drop), so the collector is
    paused for their duration and what existed before is frozen out of later passes.
    """
    enabled = gc.isenabled()
    gc.collect()
    gc.freeze()
    gc.disable()
    try:
        yield
    finally:
        gc.unfreeze()
        if enabled:
            gc.enable()


def run_simulated_display(
    link: str | os.PathLike[str] | None = None,
    *,
    profile: DisplayProfile | None = None,
    rate_hz: float = 1000.0,
    seed: int = 0,
    duration_s: float | None = None,
    on_ready: Callable[[VirtualPort], None] | None = None,
    say: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """A simulated display as a process runs it: a port (symlinked at ``link``),
    SIGINT/SIGTERM for a clean stop, and the firmware loop.

    Parameters
    ----------
    link : path, optional
        Make a symlink to the pty here.
    profile : DisplayProfile, optional
        The simulated hardware (the paper's by default).
    rate_hz : float
        Control-loop rate, Hz.
    seed : int
        Seed of the operator's presses.
    duration_s : float, optional
        Exit after this many seconds.
    on_ready : callable, optional
        Called with the port once it exists (print its name here).
    say : callable, optional
        Receives watchdog messages; stderr by default.

    Returns
    -------
    dict
        The counters of :func:`simulate_display`.
    """
    if not (rate_hz > 0 and math.isfinite(rate_hz)):
        raise InputError(f"--rate {rate_hz} must be a positive number of Hz")
    stop = StopFlag().install()
    port = VirtualPort(link)
    if say is None:

        def say(line: str) -> None:
            print(line, file=sys.stderr, flush=True)

    try:
        return simulate_display(
            (profile or PAPER_DISPLAY).validate(),
            port,
            rate_hz=rate_hz,
            operator=OperatorForce(seed=seed),
            stop=stop,
            duration_s=duration_s,
            on_ready=on_ready,
            say=say,
        )
    finally:
        port.close()


# --------------------------------------------------------------------------- host side


class DisplayLink(Link):
    """A :class:`~tissuecli.device.Link` the control loop can wait on with ``select``."""

    def fileno(self) -> int | None:
        """The port's file descriptor, or None for URLs without one (``loop://``)."""
        try:
            return int(self._port.fileno())
        except (AttributeError, OSError, ValueError, TypeError):
            return None

    def nonblocking(self) -> None:
        """Make :meth:`poll` return at once: the loop waits on its own deadlines."""
        self._port.timeout = 0


class _LogThread:
    """Hands blocks of rows to a :class:`storage.SeriesWriter` in a thread of its own.

    A flush (fsync included) took up to 8.5 ms here; in the control loop that
    would starve the display's 5 ms watchdog. The thread spends its wait in
    fsync, which releases the GIL.
    """

    def __init__(self, writer: storage.SeriesWriter) -> None:
        self.writer = writer
        self.error: BaseException | None = None
        self._queue: queue.Queue[dict[str, np.ndarray] | None] = queue.Queue()
        self._thread = threading.Thread(target=self._run, name="play-log", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            block = self._queue.get()
            if block is None:
                return
            if self.error is not None:
                continue
            try:
                self.writer.append(block)
            except BaseException as exc:  # re-raised in the control loop by put()
                self.error = exc

    def put(self, block: dict[str, np.ndarray]) -> None:
        if self.error is not None:
            raise self.error
        self._queue.put(block)

    def close(self, complete: bool, **attrs: Any) -> None:
        self._queue.put(None)
        self._thread.join()
        self.writer.close(complete=complete and self.error is None, **attrs)
        if self.error is not None:
            raise self.error


LOG_COLUMNS = [
    storage.Column(
        "time", "float64", attrs={"unit": "s", "description": "display clock since the first frame"}
    ),
    storage.Column(
        "xp",
        "float64",
        attrs={"unit": "m", "description": "piston position, filtered estimate, positive down"},
    ),
    storage.Column(
        "xm",
        "float64",
        attrs={"unit": "m", "description": "tissue model position under the observed force"},
    ),
    storage.Column("e", "float64", attrs={"unit": "m", "description": "xp - xm"}),
    storage.Column(
        "V", "float64", attrs={"unit": "V", "description": "voltage sent in answer to this frame"}
    ),
    storage.Column(
        "V_applied",
        "float64",
        attrs={"unit": "V", "description": "voltage the display reported applying"},
    ),
    storage.Column(
        "force_observed",
        "float64",
        attrs={
            "unit": "N",
            "description": "Mp xp'' + b xp' + Kp xp + alpha V^2 over the last period",
        },
    ),
    storage.Column(
        "flags",
        "uint8",
        attrs={
            "unit": "1",
            "description": "0x01 watchdog, 0x02 end stop (display); 0x10 saturated, 0x20 "
            "unrenderable, 0x40 non-finite (controller)",
        },
    ),
    storage.Column(
        "counts", "int32", attrs={"unit": "count", "description": "raw encoder reading"}
    ),
]


class _Stats:
    """Running figures of a play, in bounded memory."""

    HIST_BIN_S = 1e-5  # 10 us bins of the loop period, up to 10 ms

    def __init__(self) -> None:
        self.frames = self.saturated = self.unrenderable = self.nonfinite = 0
        self.watchdog = self.limit = self.sends = 0
        self.sum_e2 = self.max_e = self.max_a = self.work = 0.0
        self.x_lo, self.x_hi = math.inf, -math.inf
        self.hist = [0] * 1001
        self.max_period = 0.0
        self.first_send: float | None = None
        self.last_send = 0.0
        self.prev_x: float | None = None
        self.prev_volts = 0.0

    def send(self, now: float) -> None:
        if self.first_send is not None:
            dt = now - self.last_send
            self.hist[min(int(dt / self.HIST_BIN_S), 1000)] += 1
            self.max_period = max(self.max_period, dt)
        else:
            self.first_send = now
        self.last_send = now
        self.sends += 1

    def percentile(self, q: float) -> float:
        """Loop period percentile, s (upper edge of its 10 us bin; NaN before two sends)."""
        total = sum(self.hist)
        if total == 0:
            return math.nan
        need, acc = q / 100.0 * total, 0
        for i, n in enumerate(self.hist):
            acc += n
            if acc >= need:
                return (i + 1) * self.HIST_BIN_S if i < 1000 else self.max_period
        return self.max_period

    def loop_rate(self) -> float:
        span = self.last_send - (self.first_send or 0.0)
        return (self.sends - 1) / span if self.sends > 1 and span > 0 else 0.0


def _unique_name(log: Path, name: str) -> str:
    """``name``, or ``name-2``, ``name-3`` ... if the log already holds it (never overwrite)."""
    if not log.exists():
        return name
    taken = set(storage.group_names(log, "plays"))
    candidate, i = name, 1
    while candidate in taken:
        i += 1
        candidate = f"{name}-{i}"
    return candidate


def _open_display(
    url: str, baudrate: int, rate_hz: float, profile: DisplayProfile | None
) -> tuple[DisplayLink, dict[str, Any], DisplayProfile]:
    """Open, identify and check a display; its link, Info and the profile to use."""
    try:
        link = DisplayLink(url, baudrate=baudrate, timeout=0.02)
    except DeviceError as exc:
        # Link's hint names the forceps simulator; here the display's is the useful one
        raise DeviceError(str(exc).replace("simulate forceps", "simulate display")) from None
    try:
        link.command("stop")  # a display left streaming by a host that crashed
        time.sleep(0.05)
        link.discard_input()
        info = link.identify()
        if info is None:
            raise DeviceError(
                f"{url} did not answer IDENTIFY within 2 s; is it a display and is it "
                f"powered? For a simulated one run `tissuecli simulate display --link {url}`"
            )
        if info.get("protocol") != PROTOCOL_VERSION:
            raise DeviceError(
                f"{url} speaks protocol version {info.get('protocol')}; this tissuecli "
                f"speaks {PROTOCOL_VERSION}. Update tissuecli or the display firmware"
            )
        if info.get("device") != "display":
            raise DeviceError(f"{url} is a {info.get('device', 'unknown device')}, not a display")
        device_rate = info.get("rate_hz")
        if isinstance(device_rate, (int, float)) and abs(device_rate - rate_hz) > 1e-6 * rate_hz:
            raise DeviceError(
                f"the display at {url} runs its loop at {device_rate:g} Hz; "
                f"pass --rate {device_rate:g}"
            )
        if profile is None:
            reported = info.get("profile")
            profile = (
                profile_from_dict(reported, source=f"profile reported by {url}")
                if isinstance(reported, Mapping)
                else PAPER_DISPLAY
            )
        return link, info, profile
    except BaseException:
        link.close()
        raise


def play(
    tissue: Tissue,
    url: str,
    duration_s: float | None,
    rate_hz: float = 1000.0,
    log: str | os.PathLike[str] | None = None,
    stop: StopFlag | None = None,
    *,
    profile: DisplayProfile | None = None,
    name: str | None = None,
    force: float = GRASP_FORCE_N,
    baudrate: int = DEFAULT_BAUD,
    idle_timeout_s: float = 0.1,
    on_status: Callable[[dict[str, Any]], None] | None = None,
    status_interval_s: float = 1.0,
) -> dict[str, Any]:
    """Render ``tissue`` on the display at ``url`` for ``duration_s`` seconds.

    Parameters
    ----------
    tissue : Tissue
        The law to render.
    url : str
        The display's port (device path, simulator link or pyserial URL).
    duration_s : float or None
        Seconds to play; None plays until ``stop`` is set.
    rate_hz : float
        Control-loop rate, Hz; must be the display's.
    log : path, optional
        HDF5 file to log every frame to, as group ``plays/<name>``.
    stop : StopFlag, optional
        Polled every period; SIGINT/SIGTERM handlers set it for a clean stop.
    profile : DisplayProfile, optional
        The display's constants; by default those it reports, else the paper's.
    name : str, optional
        Log group name (default ``play-<UTC time>``; a suffix is added if taken).
    force : float
        Force up to which the tissue must be renderable, N (see
        :func:`~tissuecli.display.check`).
    baudrate : int
        Line rate, bit/s.
    idle_timeout_s : float
        A display silent this long is taken as lost, s.
    on_status : callable, optional
        Called every ``status_interval_s`` with the running figures.

    Returns
    -------
    dict
        The summary: ``tracking_rms_m``, ``tracking_max_m``, ``tracking_bound_m``,
        ``saturated_fraction``, ``unrenderable_fraction``, ``loop_rate_hz``,
        ``period_p99_ms``, ``period_max_ms``, ``frames``, ``frames_lost``,
        ``frames_bad``, ``missed_periods``, ``watchdog_frames``, ``commands_sent``,
        ``actuator_work_j``, ``check`` and more.

    Raises
    ------
    RenderError
        If :func:`~tissuecli.display.check` refuses the tissue (nothing is moved).
    DeviceLost
        If the display vanishes; 0 V is sent (as far as the line allows) first.
    """
    tissue.validate()
    if duration_s is not None and not duration_s > 0:
        raise InputError("--duration must be a positive number of seconds")
    if not (rate_hz > 0 and math.isfinite(rate_hz)):
        raise InputError(f"--rate {rate_hz} must be a positive number of Hz")
    if name is not None and (not name or "/" in name):
        raise InputError(f'play name "{name}" is not allowed; choose a name without "/"')
    stop = stop if stop is not None else StopFlag()
    link, info, profile = _open_display(url, baudrate, rate_hz, profile)
    writer: _LogThread | None = None
    try:
        verdict = check(tissue, profile, rate_hz, force)
        if not verdict.renderable:
            raise RenderError(
                f"the display cannot render this {tissue.model.name} tissue "
                f"(K={tissue.K:g} {tissue.model.units['K']}): " + "; ".join(verdict.reasons)
            )
        ctrl = Controller(tissue, profile, rate_hz, verdict.gains)
        meta: dict[str, Any] = {}
        if log is not None:
            log = Path(log)
            stamp = datetime.now(timezone.utc)
            name = _unique_name(log, name or "play-" + stamp.strftime("%Y%m%dT%H%M%S"))
            meta = {
                "start_utc": stamp.isoformat(timespec="milliseconds"),
                "source": f"serial:{url}",
                "device": info,
                "rate_hz": rate_hz,
                "tissue": {
                    "model": tissue.model.name,
                    "K": tissue.K,
                    "S": tissue.S,
                    "M": tissue.M,
                    "units": tissue.model.units,
                },
                "profile": profile.as_dict(),
                "gains": asdict(verdict.gains),
                "check": verdict.as_dict(),
            }
            writer = _LogThread(
                storage.SeriesWriter(
                    log,
                    f"plays/{name}",
                    LOG_COLUMNS,
                    meta,
                    kind="play",
                    flush_interval_s=LOG_FLUSH_S,
                )
            )
        with _realtime():
            summary = _loop(
                link,
                ctrl,
                profile,
                rate_hz,
                duration_s,
                stop,
                writer,
                idle_timeout_s,
                on_status,
                status_interval_s,
            )
    except BaseException as exc:
        if writer is not None:
            reason = (
                f"device lost: {exc}"
                if isinstance(exc, DeviceLost)
                else f"error: {type(exc).__name__}: {exc}"
            )
            try:
                writer.close(complete=False, stop_reason=reason)
            except Exception:  # the first error is the one to report
                pass
        if isinstance(exc, DeviceLost):
            raise DeviceLost(
                f"{exc}; 0 V was sent as the loop ended, in case the line still carries it"
            ) from None
        raise
    finally:
        link.close()
    summary["check"] = verdict.as_dict()
    summary["tissue"] = {"model": tissue.model.name, "K": tissue.K, "S": tissue.S, "M": tissue.M}
    summary = _jsonable(summary)
    if writer is not None:
        summary["log"] = {"path": str(log), "group": f"plays/{name}"}
        writer.close(complete=True, **{k: v for k, v in summary.items() if k != "log"})
    return summary


def _jsonable(value: Any) -> Any:
    """NaN and infinities (a figure with no data) become None, so the summary is JSON."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    return value


def summary_lines(summary: Mapping[str, Any]) -> list[str]:
    """The summary of :func:`play` as a few lines for people."""

    def num(key: str, scale: float = 1.0, fmt: str = ".1f") -> str:
        value = summary.get(key)
        return "n/a" if value is None else format(value * scale, fmt)

    lines = [
        f"played {num('duration_s', fmt='.2f')} s: {summary.get('frames', 0)} frames at "
        f"{num('loop_rate_hz')} Hz (period p99 {num('period_p99_ms', fmt='.2f')} ms, max "
        f"{num('period_max_ms', fmt='.2f')} ms), {summary.get('frames_lost', 0)} lost, "
        f"{summary.get('frames_bad', 0)} bad, {summary.get('missed_periods', 0)} periods "
        "without a frame",
        f"tracking error rms {num('tracking_rms_m', 1e6, '.2f')} um, max "
        f"{num('tracking_max_m', 1e6)} um, bound {num('tracking_bound_m', 1e6)} um "
        "(|M - Mp| max|xp''| / (k + Cp) + encoder resolution)",
        f"saturated {num('saturated_fraction', 100, '.2f')} %, unrenderable "
        f"{num('unrenderable_fraction', 100, '.2f')} % of frames; watchdog frames "
        f"{summary.get('watchdog_frames', 0)}; solenoid work "
        f"{num('actuator_work_j', 1e3, '.3f')} mJ (> 0: energy created)",
        f"stopped: {summary.get('stop_reason', '')}",
    ]
    log = summary.get("log")
    if log:
        lines.append(f"log: {log['path']}, group {log['group']}")
    return lines


def _loop(
    link: DisplayLink,
    ctrl: Controller,
    profile: DisplayProfile,
    rate_hz: float,
    duration_s: float | None,
    stop: StopFlag,
    writer: _LogThread | None,
    idle_timeout_s: float,
    on_status: Callable[[dict[str, Any]], None] | None,
    status_interval_s: float,
) -> dict[str, Any]:
    """The control loop; always leaves the display at 0 V and stopped."""
    period = 1.0 / rate_hz
    fd = link.fileno()
    seqs = SequenceTracker()
    stats = _Stats()
    rows: dict[str, list[float]] = {c.name: [] for c in LOG_COLUMNS}
    volts = 0.0
    sent_seq = 0
    missed = misses_in_row = 0
    last_clock: int | None = None
    elapsed_dev = 0.0
    reason = "duration reached"

    def send(value: float) -> None:
        nonlocal sent_seq
        link.send(SetVoltage(sent_seq & 0xFFFFFFFF, value))
        sent_seq += 1

    try:
        link.nonblocking()
        link.command("start")
        t_start = time.monotonic()
        clock: Deadlines | None = None
        deadline = t_start + 1.0  # the first frame may take a moment
        last_frame = t_start
        next_status = t_start + status_interval_s
        while True:
            if stop:
                reason = "interrupted by signal"
                break
            got = 0
            while True:
                for msg in link.poll():
                    if not isinstance(msg, Encoder):
                        continue
                    got += 1
                    seqs.update(msg.seq)
                    if last_clock is None:
                        dt = period
                    else:
                        dt = ((msg.clock - last_clock) & 0xFFFFFFFF) / CLOCK_HZ
                        elapsed_dev += dt
                    last_clock = msg.clock
                    step = ctrl.update(msg.position * profile.resolution, msg.volts, dt)
                    volts = step.volts
                    _account(stats, rows, step, msg, profile, elapsed_dev)
                now = time.monotonic()
                if got or now >= deadline:
                    break
                if fd is None:
                    time.sleep(min(1e-4, max(0.0, deadline - now)))
                else:
                    wait_readable(fd, deadline)
            if got:
                send(volts)
                stats.send(now)
                last_frame, misses_in_row = now, 0
                if clock is None:
                    # host deadlines half a period after each expected frame
                    clock = Deadlines(period, t0=now + 0.5 * period)
                elif got == 1:
                    # track the display's clock: nudge deadlines towards arrival + T/2
                    err = now - (deadline - 0.5 * period)
                    clock.t0 += 0.01 * max(-0.5 * period, min(0.5 * period, err))
            else:
                if now - last_frame > idle_timeout_s:
                    raise DeviceLost(
                        f"no Encoder frame from {link.url} for {idle_timeout_s * 1e3:g} ms"
                    )
                if clock is not None:
                    missed += 1
                    misses_in_row += 1
                    # bridge a lost frame with the last voltage, briefly
                    send(volts if misses_in_row <= HOLD_PERIODS else 0.0)
            if writer is not None and len(rows["time"]) >= LOG_BLOCK:
                writer.put(_block(rows))
            if duration_s is not None and elapsed_dev >= duration_s:
                break
            if on_status is not None and now >= next_status:
                next_status = now + status_interval_s
                on_status(_summary(stats, seqs, link, ctrl, profile, missed, elapsed_dev))
            deadline = clock.next() if clock is not None else deadline
    finally:
        # fail-safe: whatever ended the loop, the solenoid is switched off first
        try:
            send(0.0)
            link.command("stop")
        except DeviceLost:
            pass
        if writer is not None and rows["time"]:
            try:
                writer.put(_block(rows))
            except Exception:  # reported by close()
                pass
    summary = _summary(stats, seqs, link, ctrl, profile, missed, elapsed_dev)
    summary["stop_reason"] = reason
    summary["commands_sent"] = sent_seq
    return summary


def _account(
    stats: _Stats,
    rows: dict[str, list[float]],
    step: Any,
    msg: Encoder,
    profile: DisplayProfile,
    t: float,
) -> None:
    """Fold one frame into the running figures and the log rows."""
    stats.frames += 1
    e = step.xp - step.xm
    if e == e:
        stats.sum_e2 += e * e
        stats.max_e = max(stats.max_e, abs(e))
    if step.ap == step.ap:
        stats.max_a = max(stats.max_a, abs(step.ap))
    x = msg.position * profile.resolution
    if stats.prev_x is not None:
        # work done on the piston by the solenoid over the last period (> 0: energy created)
        stats.work -= profile.alpha * stats.prev_volts**2 * (x - stats.prev_x)
    stats.prev_x, stats.prev_volts = x, msg.volts
    stats.x_lo, stats.x_hi = min(stats.x_lo, step.xp), max(stats.x_hi, step.xp)
    flags = msg.flags | step.flags
    stats.saturated += bool(flags & SATURATED)
    stats.unrenderable += bool(flags & UNRENDERABLE)
    stats.nonfinite += bool(flags & NONFINITE)
    stats.watchdog += bool(flags & FLAG_WATCHDOG)
    stats.limit += bool(flags & FLAG_LIMIT)
    rows["time"].append(t)
    rows["xp"].append(step.xp)
    rows["xm"].append(step.xm)
    rows["e"].append(e)
    rows["V"].append(step.volts)
    rows["V_applied"].append(msg.volts)
    rows["force_observed"].append(step.force)
    rows["flags"].append(flags)
    rows["counts"].append(msg.position)


def _block(rows: dict[str, list[float]]) -> dict[str, np.ndarray]:
    """Hand over the buffered rows as arrays and empty the buffers."""
    block = {c.name: np.asarray(rows[c.name], dtype=c.dtype) for c in LOG_COLUMNS}
    for c in LOG_COLUMNS:
        rows[c.name].clear()
    return block


def _summary(
    stats: _Stats,
    seqs: SequenceTracker,
    link: Link,
    ctrl: Controller,
    profile: DisplayProfile,
    missed: int,
    elapsed: float,
) -> dict[str, Any]:
    n = max(stats.frames, 1)
    if stats.x_hi >= stats.x_lo:
        k_min = min(ctrl.local_stiffness(float(x)) for x in np.linspace(stats.x_lo, stats.x_hi, 51))
    else:
        k_min = ctrl.local_stiffness(0.0)
    return {
        "duration_s": elapsed,
        "frames": stats.frames,
        "frames_lost": seqs.lost,
        "frames_bad": link.decoder.bad_frames,
        "missed_periods": missed,
        "tracking_rms_m": math.sqrt(stats.sum_e2 / n),
        "tracking_max_m": stats.max_e,
        "tracking_bound_m": tracking_bound(
            ctrl.gains.M, profile.Mp, stats.max_a, k_min, profile.resolution
        ),
        "max_accel_m_s2": stats.max_a,
        "saturated_fraction": stats.saturated / n,
        "unrenderable_fraction": stats.unrenderable / n,
        "nonfinite_frames": stats.nonfinite,
        "watchdog_frames": stats.watchdog,
        "limit_frames": stats.limit,
        "actuator_work_j": stats.work,
        "loop_rate_hz": stats.loop_rate(),
        "period_p99_ms": stats.percentile(99) * 1e3,
        "period_p50_ms": stats.percentile(50) * 1e3,
        "period_max_ms": stats.max_period * 1e3,
        "gains": asdict(ctrl.gains),
    }
