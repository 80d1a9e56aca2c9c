"""The simulated solenoid display's firmware, behind a :class:`~tissuecli.sim.port.VirtualPort`.

At each tick of its loop it applies the latest SetVoltage, sends an Encoder frame
and integrates the piston's physics (:func:`~tissuecli.render.plant.piston_step`)
under a simulated finger (:class:`~tissuecli.sim.finger.OperatorForce`) until the
next tick. If no valid SetVoltage arrives for its watchdog's periods it zeroes the
voltage and raises ``FLAG_WATCHDOG``: :data:`WATCHDOG_PERIODS`, as the firmware, or a
limit judged against its own port (:func:`watchdog_limit`), stated in its IDENTIFY
answer as ``watchdog_periods``.
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
    FLAG_MODEL,
    FLAG_STALE,
    FLAG_WATCHDOG,
    IDENTIFY,
    PROTOCOL_VERSION,
    START,
    STOP,
    Command,
    Encoder,
    FrameDecoder,
    Info,
    SetModel,
    SetVoltage,
    encode,
)
from ..hw.realtime import (
    Deadlines,
    StopFlag,
    cpu_to_spare,
    device_loop,
    realtime,
    spin_for,
    wait_readable,
    wait_until,
)
from ..render.plant import piston_step
from ..render.profile import PAPER_DISPLAY, DisplayProfile
from .finger import OperatorForce
from .port import VirtualPort
from .synth import CLOCK_HZ

#: The display zeroes the voltage after this many periods without a valid SetVoltage
#: (docs/protocol.md, section 7): the firmware's limit, which no host changes.
WATCHDOG_PERIODS = 5
#: The simulated display's own limit may be lengthened to what its port can guarantee
#: (:func:`watchdog_limit`), never beyond this, s: half the host's 100 ms no-frame
#: limit, and a third of the 150 ms a person takes to react, so a dead host's last
#: command is never felt for longer than the firmware's own limit would allow a person
#: to notice.
SIM_WATCHDOG_MAX_S = 0.05
#: Round trips through the port timed at start-up, and the margin over the longest of
#: them that the watchdog allows on top of the firmware's periods: a start-up sample of
#: 100 sees the p99 of the transfer, a play of seconds its p99.99, 2-4 times longer on
#: this machine (docs/benchmarks.md, "Where a loop's time goes").
PROBES = 100
ROUND_TRIP_MARGIN = 4.0
#: The least the simulated display's judged limit may be, s: a start-up sample of quick
#: round trips (0.1-0.3 ms on a quiet port) said 6 periods, and beside two busy processes
#: the same port then held single frames for 2-20 ms (docs/benchmarks.md, "Where the
#: late answers come from"), so the watchdog cut a host that kept time. A hold that long
#: is the port's, not the host's silence; 20 ms stays under the 50 ms bound.
SIM_WATCHDOG_FLOOR_S = 0.02
#: How far behind its schedule the display's loop may fall and still run every tick it
#: owes, s: woken late, it runs the ticks it missed back to back (physics, Encoder frame
#: and all) so a late wake-up costs jitter, not rate; further behind, its schedule jumps
#: to now and the ticks jumped are skipped and counted. The longest periods of demo
#: plays beside two busy processes were 2.5-18 ms (docs/benchmarks.md); 20 ms is well
#: under the watchdog's 50 ms bound and the host's 100 ms no-frame limit, so a stall
#: longer than that still reaches the host as silence.
CATCH_UP_S = 0.02
#: While catching up, how long the display waits for the host's answer to the frame it
#: has just sent before running the next owed tick, periods: a host that answers within
#: it closes the loop at every tick, as it would on time (frames sent back to back are
#: read together and answered once, and the display then holds one command for several
#: ticks); one that does not is not waited for longer, so catching up still gains at
#: least half a period a tick.
ANSWER_WAIT_PERIODS = 0.5
#: The display counts its ticks by the age of the command in use, in periods, up to
#: this one (and more).
AGES = 4
#: How many periods the display renders from the local model of a late answer
#: (:class:`~tissuecli.hw.protocol.SetModel`): the firmware's watchdog limit, the longest
#: a display may hold a command without a new one. Within it, a late answer costs the
#: rendering the model's second-order terms (the tracking error's change, the curvature
#: of the law), not the tissue's stiffness; beyond it the display holds its voltage and
#: flags the periods stale, as a display without a model does.
MODEL_HORIZON_PERIODS = WATCHDOG_PERIODS
#: Encoder positions the display keeps, by tick: enough to reach the tick a late answer
#: was meant for, and the one before it (its velocity), within the horizon.
HISTORY = 16
#: Heaviest reference mass the simulated piston carries, kg.
MAX_LOAD_KG = 5.0
#: Standard gravity, m/s^2.
G = 9.80665


def watchdog_limit(
    round_trips_s: list[float], period_s: float, saturated: bool = False
) -> tuple[int, str]:
    """The simulated display's watchdog, periods, judged against its port: the firmware's
    :data:`WATCHDOG_PERIODS` plus :data:`ROUND_TRIP_MARGIN` times the longest round trip
    timed at start-up (``round_trips_s``, s; :meth:`VirtualPort.round_trips`), at most
    :data:`SIM_WATCHDOG_MAX_S`; on a ``saturated`` machine (no CPU to spare:
    :func:`~tissuecli.hw.realtime.cpu_to_spare`) that bound itself. And the one line
    that says how it was set.

    Never under :data:`SIM_WATCHDOG_FLOOR_S` (nor the firmware's periods), and a sample
    of fewer than :data:`PROBES` round trips (a start-up starved of CPU, its time budget
    spent) is not enough to judge by: the bound is taken.

    A host that answers every frame at once is then cut only when it, or the line,
    stalls for longer than the port showed it could be trusted with. On a saturated
    machine a start-up sample does not see the port's tail: its kernel worker waits
    behind every runnable task, and 100 round trips timed there at a load average of 16
    were all under 0.3 ms while the same port held single frames for 5-16 ms during
    the play that followed. A real display's firmware keeps its own limit.
    """
    cap = max(WATCHDOG_PERIODS, int(SIM_WATCHDOG_MAX_S / period_s))
    if not round_trips_s:
        return WATCHDOG_PERIODS, f"watchdog {WATCHDOG_PERIODS} periods, as the firmware"
    ordered = sorted(round_trips_s)
    worst, median = ordered[-1], ordered[len(ordered) // 2]
    timed = (
        f"{len(ordered)} round trips through the port at start-up ({median * 1e3:.2f} ms "
        f"median, {worst * 1e3:.2f} ms longest)"
    )
    if saturated or len(ordered) < PROBES:
        why = "no CPU to spare" if saturated else f"fewer than {PROBES} timed"
        return cap, (
            f"watchdog {cap} periods ({cap * period_s * 1e3:g} ms), its bound: {why}, so "
            f"{timed} cannot show the port's tail"
        )
    floor = min(cap, max(WATCHDOG_PERIODS, math.ceil(SIM_WATCHDOG_FLOOR_S / period_s - 1e-9)))
    judged = WATCHDOG_PERIODS + math.ceil(ROUND_TRIP_MARGIN * worst / period_s)
    periods = min(cap, max(floor, judged))
    return periods, (
        f"watchdog {periods} periods ({periods * period_s * 1e3:g} ms): the firmware's "
        f"{WATCHDOG_PERIODS} plus {ROUND_TRIP_MARGIN:g} x the longest of {timed}, at least "
        f"{SIM_WATCHDOG_FLOOR_S * 1e3:g} ms and at most {SIM_WATCHDOG_MAX_S * 1e3:g} ms"
    )


def display_info(
    profile: DisplayProfile,
    rate_hz: float,
    watchdog_periods: int = WATCHDOG_PERIODS,
    scheduler: str | None = None,
) -> dict[str, Any]:
    """What a display answers to IDENTIFY: identity, loop rate, encoder scale, watchdog
    and profile; a simulated one also the ``scheduler`` its loop obtained (a host then
    reports whether every loop of the play ran elevated)."""
    extra = {"scheduler": scheduler} if scheduler else {}
    return {
        **extra,
        "protocol": PROTOCOL_VERSION,
        "device": "display",
        "model": "tissuecli simulated solenoid display",
        "firmware": __version__,
        "rate_hz": rate_hz,
        "clock_hz": CLOCK_HZ,
        "watchdog_periods": watchdog_periods,
        "stale_flag": True,
        "local_model": True,
        "model_horizon_periods": MODEL_HORIZON_PERIODS,
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
    watchdog_periods: int = WATCHDOG_PERIODS,
    spin_s: float = 0.0,
    scheduler: str | None = None,
) -> dict[str, Any]:
    """Run the simulated display's firmware until ``stop`` is set (or ``duration_s``).

    Each tick, in order: decode what the host sent (IDENTIFY, START, STOP,
    SetVoltage; the latest valid SetVoltage wins, clamped to [0, v_max], NaN read as
    0), run the watchdog, send ``Encoder(position, volts in use, flags)`` if
    started, then integrate the piston over one period with that voltage held.
    STOP zeroes the voltage. The operator's presses restart at every START.
    Ticks are paced by absolute deadlines (:class:`~tissuecli.hw.realtime.Deadlines`):
    woken late (descheduled), the loop runs the ticks it owes back to back, up to
    :data:`CATCH_UP_S` behind, so the display keeps its rate over the run and stamps
    every frame with its scheduled time (while the host answers, each owed tick waits up
    to :data:`ANSWER_WAIT_PERIODS` for its answer to the last frame, so a host that keeps
    up answers every tick); further behind, the ticks jumped are skipped
    and counted, and simulated time waits for them rather than jumping. Ticks run to
    catch up do not count towards the watchdog: the host cannot answer frames sent
    faster than a period apart, and the display's own stall is not the host's silence.

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
    watchdog_periods : int
        Periods without a valid SetVoltage before the watchdog cuts (stated in the
        IDENTIFY answer).
    spin_s : float
        Sleep until this long before each tick, then spin, s
        (:func:`~tissuecli.hw.realtime.spin_for`: the host loop's rule).
    scheduler : str, optional
        The scheduling its loop obtained, stated in its IDENTIFY answer.

    Returns
    -------
    dict
        Counters: ``sent`` Encoder frames, ``commands`` valid SetVoltage frames,
        ``last_command_volts`` (the last SetVoltage's value, V, or None),
        ``max_command_volts`` (the largest SetVoltage value received, V, or None),
        ``watchdog_trips``, ``watchdog_periods``, ``bad_frames``, ``missed_deadlines``
        (ticks skipped), ``late_ticks`` (ticks run back to back to catch up),
        ``overrun_bytes``.
    """
    stop = stop if stop is not None else StopFlag()
    if load_kg > 0:
        weight = load_kg * G

        def operator(t: float) -> float:
            return weight

    fw = _Firmware(
        profile,
        port,
        rate_hz,
        operator or OperatorForce(),
        say,
        load_kg,
        reports or profile,
        watchdog_periods,
        scheduler,
    )
    for t in (0.0, 1.0, 2.0):
        fw.operator(t)  # first calls build the presses' random generator: not inside a tick
    if on_ready is not None:
        on_ready(port)
    late = False
    with realtime():
        # the schedule starts with the loop: the collector's pass on entry (a second
        # in a large process on a loaded machine) is not deadlines missed
        clock = Deadlines(fw.period, catch_up=max(1, round(CATCH_UP_S / fw.period)))
        while not stop:
            if duration_s is not None and clock.k * fw.period >= duration_s:
                break
            fw.receive()
            fw.tick(late)
            fw.advance()
            behind = clock.behind
            deadline = clock.next()
            late = clock.behind > behind  # this tick is owed: run it at once
            if not late:
                wait_until(None, deadline, spin_s)
            elif fw.streaming and fw.answered:
                # ... once a host that answered the last frame has answered this one, or
                # has had its time (a silent host is not waited for: its watchdog is)
                wait_readable(port.fileno(), time.monotonic() + ANSWER_WAIT_PERIODS * fw.period)
    fw.receive()  # what the host sent last (its final 0 V and STOP) is counted
    return {
        "sent": fw.sent,
        "commands": fw.commands,
        "last_command_volts": fw.last_command,
        "max_command_volts": fw.max_command,
        "watchdog_trips": fw.trips,
        "watchdog_periods": fw.watchdog_periods,
        "bad_frames": fw.decoder.bad_frames,
        "missed_deadlines": clock.missed,
        "late_ticks": clock.behind,
        "stale_ticks": sum(fw.ages[1:]),
        "command_ages": fw.ages,
        "command_ages_late": fw.ages_late,
        "model_ticks": fw.modelled,
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
        watchdog_periods: int = WATCHDOG_PERIODS,
        scheduler: str | None = None,
    ) -> None:
        self.watchdog_periods = watchdog_periods
        self.profile, self.port, self.operator, self.say = profile, port, operator, say
        # a mass resting on the piston moves with it
        self.plant = replace(profile, Mp=profile.Mp + load_kg) if load_kg > 0 else profile
        self.loaded = load_kg > 0
        self.period = 1.0 / rate_hz
        self.decoder = FrameDecoder()
        self.info = encode(
            Info(display_info(reports or profile, rate_hz, watchdog_periods, scheduler))
        )
        self.x = self.v = self.volts = 0.0
        self.at_limit = self.streaming = self.armed = self.tripped = False
        self.answered = False  # a SetVoltage came since the last tick
        # which Encoder frame the command in use answers (its seq; None before one), the
        # frames sent since START, and the ticks by the age of their command in periods
        # (0: the answer to the frame before; the last entry counts that age and more),
        # those on time and those run late to catch up
        self.answers: int | None = None
        self.streamed = 0
        self.ages = [0] * (AGES + 1)
        self.ages_late = [0] * (AGES + 1)
        # the local model of the last answer (u V^2, du/dx V^2/m, du/dv V^2 s/m), or None
        # (a plain SetVoltage); the encoder's positions by tick, m; ticks rendered from it
        self.model: tuple[float, float, float] | None = None
        self.history = [0.0] * HISTORY
        self.modelled = 0
        self.seq = self.sent = self.commands = self.trips = 0
        self.last_command: float | None = None
        self.max_command: float | None = None
        self.k_start = 0
        # Simulated time, the clock field and the watchdog all count ticks the firmware
        # ran: a real display's microcontroller never skips one, while this process can
        # be descheduled (with its host) for milliseconds. A stall then looks to the host
        # like transport delay, as it would with real hardware, instead of the piston
        # running open-loop through the skipped periods.
        self.ticks_run = 0
        # the watchdog counts the ticks run on time: one run late to catch up comes
        # faster than the host can answer it (see simulate_display)
        self.watched = self.watched_command = 0

    def receive(self) -> None:
        """Act on what the host sent since the last tick; the latest SetVoltage wins."""
        self.answered = False
        for msg in self.decoder.feed(self.port.read()):
            if isinstance(msg, (SetVoltage, SetModel)):
                if self.streaming:
                    value = float(msg.volts)
                    self.volts = min(max(value, 0.0), self.profile.v_max) if value == value else 0.0
                    self.model = (
                        (float(msg.u), float(msg.du_dx), float(msg.du_dv))
                        if isinstance(msg, SetModel)
                        and all(math.isfinite(z) for z in (msg.u, msg.du_dx, msg.du_dv))
                        else None
                    )
                    self.last_command, self.watched_command = value, self.watched
                    if value == value and (self.max_command is None or value > self.max_command):
                        self.max_command = value
                    self.commands += 1
                    self.answered = True
                    self.answers = msg.seq
                    self.armed, self.tripped = True, False
            elif isinstance(msg, Command):
                if msg.code == IDENTIFY:
                    self.port.write(self.info)
                elif msg.code == START and not self.streaming:
                    self.streaming, self.armed, self.tripped = True, False, False
                    self.k_start = -1  # set by the next tick
                    self.answers, self.streamed, self.model = None, 0, None
                elif msg.code == STOP:
                    self.streaming, self.armed, self.volts = False, False, 0.0
                    self.model = None

    def tick(self, late: bool = False) -> None:
        """Watchdog, then this tick's Encoder frame; a ``late`` tick (run to catch up)
        does not count towards the watchdog."""
        self.ticks_run += 1
        self.watched += not late
        if self.k_start < 0:
            self.k_start = self.ticks_run
        # armed by the first SetVoltage after START, so a host's start-up is not a trip
        if (
            self.streaming
            and self.armed
            and not self.tripped
            and self.watched - self.watched_command > self.watchdog_periods
        ):
            self.volts, self.tripped = 0.0, True
            self.trips += 1
            if self.say is not None:
                self.say(
                    f"watchdog: no SetVoltage for {self.watchdog_periods} periods "
                    f"({self.watchdog_periods * self.period * 1e3:g} ms); solenoid off"
                )
        if self.streaming:
            flags = (FLAG_WATCHDOG if self.tripped else 0) | (FLAG_LIMIT if self.at_limit else 0)
            counts = int(round(self.x / self.profile.resolution))
            seq = self.seq
            self.history[seq % HISTORY] = counts * self.profile.resolution
            if self.armed and self.streamed:
                # the voltage in use answers the frame sent a tick ago, or is stale; a tick
                # run late to catch up comes before the host could answer (its watchdog
                # rule): counted apart and not flagged
                age = AGES if self.tripped else (seq - 1 - (self.answers or 0)) & 0xFFFFFFFF
                (self.ages_late if late else self.ages)[min(age, AGES)] += 1
                if age and not self.tripped and self._bridge(seq, age):
                    self.modelled += not late
                    flags |= FLAG_MODEL if not late else 0
                else:
                    flags |= FLAG_STALE if age and not late else 0
            ticks = int(round(self.ticks_run * self.period * CLOCK_HZ)) & 0xFFFFFFFF
            self.port.write(
                encode(Encoder(self.seq & 0xFFFFFFFF, ticks, counts, self.volts, flags))
            )
            self.seq += 1
            self.sent += 1
            self.streamed += 1

    def _bridge(self, seq: int, age: int) -> bool:
        """On an answer ``age`` periods late, set the voltage from its local model (the
        answer's pull moved by the law's slopes over what the encoder saw since the tick
        it was meant for); False (voltage held) without a model or beyond the horizon.

        The velocities are the encoder's differences over one period, as a firmware
        would have them."""
        if self.model is None or age > MODEL_HORIZON_PERIODS or self.streamed < age + 1:
            return False
        h, period = self.history, self.period
        meant = seq - age  # the tick the answer was meant for
        x, x_prev = h[seq % HISTORY], h[(seq - 1) % HISTORY]
        x_meant, x_before = h[meant % HISTORY], h[(meant - 1) % HISTORY]
        u, du_dx, du_dv = self.model
        u += du_dx * (x - x_meant) + du_dv * ((x - x_prev) - (x_meant - x_before)) / period
        v_max = self.profile.v_max
        self.volts = math.sqrt(min(u, v_max * v_max)) if u > 0.0 else 0.0
        return True

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
    watchdog_periods: int | None = None,
) -> dict[str, Any]:
    """A simulated display as a process runs it: a port (symlinked at ``link``),
    SIGINT/SIGTERM for a clean stop, and the firmware loop, kept on time as the host's
    haptic loop is (SCHED_FIFO and locked memory where allowed, absolute deadlines,
    the same spin rule).

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
    watchdog_periods : int, optional
        The watchdog's limit, periods (:data:`WATCHDOG_PERIODS` is the firmware's); by
        default judged against the port at start-up (:func:`watchdog_limit`, said on
        ``say`` when longer than the firmware's), before the link is made; its bound on a
        machine with no CPU to spare.

    Returns
    -------
    dict
        The counters of :func:`simulate_display`.
    """
    if not (rate_hz > 0 and math.isfinite(rate_hz)):
        raise InputError(f"--rate {rate_hz} must be a positive number of Hz")
    if not (0 <= load_kg <= MAX_LOAD_KG):
        raise InputError(f"--load {load_kg:g} kg must be between 0 and {MAX_LOAD_KG:g} kg")
    if watchdog_periods is not None and watchdog_periods < 1:
        raise InputError(f"--watchdog-periods {watchdog_periods} must be 1 or more")
    stop = StopFlag().install()
    port = VirtualPort(link if watchdog_periods is not None else None)
    if say is None:

        def say(line: str) -> None:
            print(line, file=sys.stderr, flush=True)

    try:
        with device_loop(say) as elevation:  # SCHED_FIFO where allowed, as the host's loop
            if watchdog_periods is None:
                # timed under the loop's own scheduling, before a host can open the port
                watchdog_periods, basis = watchdog_limit(
                    port.round_trips(PROBES), 1 / rate_hz, saturated=not cpu_to_spare()
                )
                if watchdog_periods > WATCHDOG_PERIODS:
                    say(f"note: {basis}")
                if link is not None:
                    port.publish(link)
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
                watchdog_periods=watchdog_periods,
                spin_s=spin_for(elevation),
                scheduler=elevation.scheduler,
            )
    finally:
        port.close()
