"""The simulated solenoid display's firmware, behind a :class:`~tissuecli.sim.port.VirtualPort`.

At each tick of its loop it applies the latest SetVoltage, sends an Encoder frame
and integrates the piston's physics (:func:`~tissuecli.render.plant.piston_step`)
under a simulated finger (:class:`~tissuecli.sim.finger.OperatorForce`) until the
next tick. If no valid SetVoltage arrives for :data:`WATCHDOG_PERIODS` periods it
zeroes the voltage and raises ``FLAG_WATCHDOG``.
"""

from __future__ import annotations

import math
import os
import sys
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

from .._version import __version__
from ..core.errors import InputError
from ..hw.protocol import (
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
    SetVoltage,
    encode,
)
from ..hw.realtime import Deadlines, StopFlag, realtime
from ..render.plant import piston_step
from ..render.profile import PAPER_DISPLAY, DisplayProfile
from .finger import OperatorForce
from .port import VirtualPort
from .synth import CLOCK_HZ

#: The display zeroes the voltage after this many periods without a valid SetVoltage
#: (docs/protocol.md, section 7).
WATCHDOG_PERIODS = 5
#: Heaviest reference mass the simulated piston carries, kg.
MAX_LOAD_KG = 5.0
#: Standard gravity, m/s^2.
G = 9.80665


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
    load_kg: float = 0.0,
    reports: DisplayProfile | None = None,
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
        :class:`~tissuecli.sim.finger.OperatorForce` by default.
    stop : StopFlag, optional
        Polled every tick.
    duration_s : float, optional
        Exit after this many seconds.
    on_ready : callable, optional
        Called with the port once it exists.
    say : callable, optional
        Receives one line when the watchdog trips (once per trip).
    load_kg : float
        A reference mass resting on the piston instead of the finger, kg (its
        weight pushes down, and it moves with the piston): the load of
        ``tissuecli calibrate display``.
    reports : DisplayProfile, optional
        The profile it answers to IDENTIFY (``profile`` by default): a display whose
        stored constants are not its true ones.

    Returns
    -------
    dict
        Counters: ``sent`` Encoder frames, ``commands`` valid SetVoltage frames,
        ``last_command_volts`` (the last SetVoltage's value, V, or None),
        ``max_command_volts`` (the largest SetVoltage value received, V, or None),
        ``watchdog_trips``, ``bad_frames``, ``missed_deadlines``, ``overrun_bytes``.
    """
    stop = stop if stop is not None else StopFlag()
    if load_kg > 0:
        weight = load_kg * G

        def operator(t: float) -> float:
            return weight

    fw = _Firmware(
        profile, port, rate_hz, operator or OperatorForce(), say, load_kg, reports or profile
    )
    for t in (0.0, 1.0, 2.0):
        fw.operator(t)  # first calls build the presses' random generator: not inside a tick
    clock = Deadlines(fw.period)
    if on_ready is not None:
        on_ready(port)
    with realtime():
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
        "max_command_volts": fw.max_command,
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
        load_kg: float = 0.0,
        reports: DisplayProfile | None = None,
    ) -> None:
        self.profile, self.port, self.operator, self.say = profile, port, operator, say
        # a mass resting on the piston moves with it
        self.plant = replace(profile, Mp=profile.Mp + load_kg) if load_kg > 0 else profile
        self.loaded = load_kg > 0
        self.period = 1.0 / rate_hz
        self.decoder = FrameDecoder()
        self.info = encode(Info(display_info(reports or profile, rate_hz)))
        self.x = self.v = self.volts = 0.0
        self.at_limit = self.streaming = self.armed = self.tripped = False
        self.seq = self.sent = self.commands = self.trips = 0
        self.last_command: float | None = None
        self.max_command: float | None = None
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
                    if value == value and (self.max_command is None or value > self.max_command):
                        self.max_command = value
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
        force = self.operator if self.streaming or self.loaded else _no_force
        self.x, self.v, self.at_limit = piston_step(
            self.plant, self.x, self.v, self.volts, force, t, self.period
        )


def _no_force(t: float) -> float:
    return 0.0


def run_simulated_display(
    link: str | os.PathLike[str] | None = None,
    *,
    profile: DisplayProfile | None = None,
    rate_hz: float = 1000.0,
    seed: int = 0,
    duration_s: float | None = None,
    on_ready: Callable[[VirtualPort], None] | None = None,
    say: Callable[[str], None] | None = None,
    load_kg: float = 0.0,
    reports: DisplayProfile | None = None,
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
    load_kg : float
        A reference mass resting on the piston instead of the finger, kg.
    reports : DisplayProfile, optional
        The profile it answers to IDENTIFY (``profile`` by default).

    Returns
    -------
    dict
        The counters of :func:`simulate_display`.
    """
    if not (rate_hz > 0 and math.isfinite(rate_hz)):
        raise InputError(f"--rate {rate_hz} must be a positive number of Hz")
    if not (0 <= load_kg <= MAX_LOAD_KG):
        raise InputError(f"--load {load_kg:g} kg must be between 0 and {MAX_LOAD_KG:g} kg")
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
            load_kg=load_kg,
            reports=reports.validate() if reports is not None else None,
        )
    finally:
        port.close()
