"""The ``play`` service: render a tissue on the solenoid display in real time.

Identify the display, check that it can render the tissue, then close the loop:
every Encoder frame is run through the :class:`~tissuecli.render.controller.Controller`
and answered at once with a SetVoltage. The display's frames set the rhythm; the host
keeps absolute deadlines (:class:`~tissuecli.hw.realtime.Deadlines`, half a period
after each expected frame) to notice missing frames, to keep the display's watchdog
fed and to measure its own period. Whatever ends the loop (duration, stop flag, a lost
device, any exception), the last thing sent is ``SetVoltage(0)`` followed by STOP.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict
from datetime import datetime, timezone
from typing import TYPE_CHECKING, Any

from ..core.errors import (
    EXIT_NOT_RENDERED,
    DeviceLost,
    InputError,
    RenderError,
    worst_fault,
)
from ..core.session import check_name
from ..core.tissue import Tissue
from ..formats.jsonfile import write_json
from ..formats.outputs import Output, check_outputs
from ..formats.params import read_profile, read_tissue
from ..hw.device import Device, Display, device_class
from ..hw.link import DEFAULT_BAUD
from ..hw.protocol import Encoder, SetModel, SetVoltage
from ..hw.realtime import (
    Deadlines,
    Elevation,
    LoopProcess,
    Parent,
    StopFlag,
    elevate,
    fallback_message,
    realtime,
    run_in_thread,
    spin_for,
    wait_readable,
    wait_until,
)
from ..hw.stream import Stream
from ..render.check import GRASP_FORCE_N, CheckResult, check
from ..render.controller import Controller, Step
from ..render.handover import tissue_data, tissue_from_data
from ..render.profile import (
    PAPER_DISPLAY,
    DisplayProfile,
    clamp_volts,
)
from .faults import classify_faults
from .loopstats import PlayFigures, jsonable, silence_figures

if TYPE_CHECKING:
    from ..formats.playlog import PlayLog

#: A display cuts the solenoid after this many periods without a SetVoltage, unless
#: it states its own limit (docs/protocol.md, section 7).
WATCHDOG_PERIODS = 5

#: A missing Encoder frame is bridged by repeating the last voltage this many periods,
#: then the host sends 0 V until frames return.
HOLD_PERIODS = 3

#: Where the host loop runs (docs/rendering.md, "Keeping time"): ``"thread"`` in a
#: thread of its own, ``"process"`` in a process of its own
#: (:class:`~tissuecli.hw.realtime.LoopProcess`: an interpreter it shares with nothing,
#: as ``live`` needs beside its recorder), ``"plain"`` in the calling thread, never
#: elevated (the loop before these, kept for side-by-side benchmarks). With
#: ``realtime`` the thread or process runs under SCHED_FIFO with memory locked and one
#: CPU, sleeping until :data:`~tissuecli.hw.realtime.SPIN_S` before each expected frame
#: and spinning through it; without (``--no-realtime``, and the fallback when the
#: system refuses elevation) it sleeps in ``select``.
LOOPS = ("thread", "process", "plain")


#: The display silent this long ends a play whose loop has elevated scheduling, s ...
DISPLAY_SILENCE_S = 0.1
#: ... and one whose loop runs as an ordinary thread (the system refused SCHED_FIFO, or
#: ``--no-realtime``): on a busy machine such a loop, and a simulated display beside it,
#: are descheduled for tens of ms at a time, which is not a display gone.
DISPLAY_SILENCE_UNELEVATED_S = 0.5


class PlayFaults(RenderError):
    """The play ran, but not as the check promised (see :func:`.faults.play_faults`); raised by
    :func:`play_file` after the summary and the log are written. ``summary`` holds them;
    :attr:`exit_code` is the class of the worst (``summary["exit_code"]``)."""

    def __init__(self, message: str, summary: dict[str, Any]) -> None:
        super().__init__(message)
        self.summary = summary
        code = summary.get("exit_code")
        self.exit_code = code if isinstance(code, int) and code > 1 else EXIT_NOT_RENDERED

    def __reduce__(self) -> tuple[Any, ...]:  # from a loop process, summary and all
        return type(self), (str(self), self.summary)


class PlayLost(DeviceLost):
    """The display went silent during the play; 0 V was sent. ``summary`` holds the
    figures up to the loss (``verdict`` ``"display lost"``); :func:`play_file` writes it
    to ``--summary`` before the command exits 1."""

    def __init__(self, message: str, summary: dict[str, Any]) -> None:
        super().__init__(message)
        self.summary = summary

    def __reduce__(self) -> tuple[Any, ...]:
        return type(self), (str(self), self.summary)


def check_file(
    params: str | os.PathLike[str],
    *,
    profile: str | os.PathLike[str] | None = None,
    rate_hz: float = 1000.0,
    summary: str | os.PathLike[str] | None = None,
    force: bool = False,
) -> CheckResult:
    """``play --check``: can the display (``profile``, the paper's by default) render the
    tissue of a parameter file? Writes the verdict as JSON to ``summary`` if given (an
    existing file only with ``force``; never an input)."""
    check_outputs(
        [Output(summary, "--summary") if summary else None], [params, profile], force=force
    )
    tissue = read_tissue(params)
    result = check(tissue, read_profile(profile) if profile else PAPER_DISPLAY, rate_hz)
    if summary is not None:
        write_json(summary, {"check": result.as_dict()})
    return result


def play_file(
    params: str | os.PathLike[str],
    url: str,
    duration_s: float | None = None,
    *,
    profile: str | os.PathLike[str] | None = None,
    summary: str | os.PathLike[str] | None = None,
    force: bool = False,
    **options: Any,
) -> dict[str, Any]:
    """``play``: render the tissue of a parameter file (see :func:`play` for ``options``);
    writes the summary as JSON to ``summary`` if given. Outputs are checked before the
    display is opened: ``summary`` replaces a file only with ``force``, never an input.

    Raises
    ------
    PlayFaults
        After the summary and the log are written, when the play was faulty (its
        ``faults`` are not empty; see :func:`.faults.play_faults`): the command exits 1.
    PlayLost
        After the summary up to the loss is written, when the display went silent.
    """
    log = options.get("log")
    check_outputs(
        [
            Output(summary, "--summary") if summary else None,
            Output(log, "--log", appends=True) if log else None,
        ],
        [params, profile],
        force=force,
    )
    tissue = read_tissue(params)
    try:
        result = play(
            tissue, url, duration_s, profile=read_profile(profile) if profile else None, **options
        )
    except PlayLost as exc:  # the figures up to the loss are still the user's
        if summary is not None:
            write_json(summary, exc.summary)
        raise PlayLost(f"{exc}{_kept(summary, exc.summary)}", exc.summary) from None
    if summary is not None:
        write_json(summary, result)
    if result["faults"]:
        raise PlayFaults(
            "the play was faulty: " + "; ".join(result["faults"]) + _kept(summary, result),
            result,
        )
    return result


def _kept(summary: str | os.PathLike[str] | None, result: Mapping[str, Any]) -> str:
    """' (summary S and log L written)' for the files a play wrote, or ''."""
    log = result.get("log") or {}
    kept = [
        f"{what} {os.fspath(path)}"
        for what, path in (("summary", summary), ("log", log.get("path")))
        if path
    ]
    return f" ({' and '.join(kept)} written)" if kept else ""


def play(
    tissue: Tissue,
    url: str,
    duration_s: float | None = None,
    *,
    rate_hz: float = 1000.0,
    log: str | os.PathLike[str] | None = None,
    name: str | None = None,
    stop: StopFlag | None = None,
    profile: DisplayProfile | None = None,
    force: float = GRASP_FORCE_N,
    baudrate: int = DEFAULT_BAUD,
    idle_timeout_s: float | None = None,
    on_status: Callable[[dict[str, Any]], None] | None = None,
    status_interval_s: float = 1.0,
    loop: str = "thread",
    realtime: bool = True,
    on_message: Callable[[str], None] | None = None,
    device: str = "display",
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
    name : str, optional
        Log group name (default ``play-<UTC time>``; a suffix is added if taken).
    stop : StopFlag, optional
        Polled every period; SIGINT/SIGTERM handlers set it for a clean stop.
    profile : DisplayProfile, optional
        The display's constants; by default those it reports, else the paper's.
    force : float
        Force up to which the tissue must be renderable, N (see
        :func:`~tissuecli.render.check.check`).
    baudrate : int
        Line rate, bit/s.
    idle_timeout_s : float, optional
        A display silent this long (while the host runs) is taken as lost, s; by
        default :data:`DISPLAY_SILENCE_S` for a loop with elevated scheduling and
        :data:`DISPLAY_SILENCE_UNELEVATED_S` for one without.
    on_status : callable, optional
        Called every ``status_interval_s`` with the running figures.
    loop : {"thread", "process", "plain"}
        Where the host loop runs (see :data:`LOOPS`).
    realtime : bool
        Ask for elevated scheduling (SCHED_FIFO, locked memory, one CPU) and spin
        through each expected frame; ignored by ``"plain"``.
    on_message : callable, optional
        Told, once per process, when elevated scheduling was refused.
    device : str
        The kind of display (a :class:`~tissuecli.hw.device.Display` class registered
        under that name; a loop process finds only those its module registers on import).

    Returns
    -------
    dict
        The summary: ``tracking_rms_m``, ``tracking_max_m``, ``tracking_bound_m``,
        ``saturated_fraction``, ``unrenderable_fraction``, ``loop_rate_hz`` (frames run
        through the loop per second), ``answer_rate_hz``, ``unanswered_frames``,
        ``stale_frames`` and ``stale_run_max`` (periods the display ran on a late answer,
        as it reports them, beyond its local model if it has one), ``modelled_frames``
        and ``late_run_max`` (periods it rendered from the local model of a late answer,
        and the longest run of late answers; see :meth:`.loopstats.PlayFigures.rates`),
        ``period_p99_ms``, ``period_max_ms``, ``frames``, ``frames_lost``,
        ``frames_bad``, ``missed_periods``, ``watchdog_frames``, ``watchdog_periods``
        (the display's stated watchdog limit), ``commands_sent``,
        ``clamped_commands`` (brought within [0, v_max] before sending),
        ``actuator_work_j``, ``realtime`` (what :func:`~tissuecli.hw.realtime.elevate`
        obtained), ``check`` and more; ``faults`` (what went wrong, see
        :func:`.faults.play_faults`; empty for a good play) and ``verdict`` (``"as checked"``
        or ``"faulty"``).

    Raises
    ------
    RenderError
        If :func:`~tissuecli.render.check.check` refuses the tissue (nothing is moved).
    PlayLost
        If the display vanishes (a :class:`~tissuecli.core.errors.DeviceLost`); 0 V is
        sent (as far as the line allows) first, and ``summary`` holds the figures up to
        the loss.
    """
    tissue.validate()
    if duration_s is not None and not duration_s > 0:
        raise InputError("--duration must be a positive number of seconds")
    if not (rate_hz > 0 and math.isfinite(rate_hz)):
        raise InputError(f"--rate {rate_hz} must be a positive number of Hz")
    if name is not None:
        check_name(name, "play")
    if loop not in LOOPS:
        raise InputError(f"loop {loop!r} is not one of {', '.join(LOOPS)}")
    if log is not None:
        from ..formats.playlog import check_log  # h5py only when a log is asked for

        check_log(log, rate_hz)  # a foreign file or a full drive: refused before the display
    options: dict[str, Any] = dict(
        rate_hz=rate_hz,
        log=log,
        name=name,
        profile=profile,
        force=force,
        baudrate=baudrate,
        idle_timeout_s=idle_timeout_s,
        status_interval_s=status_interval_s,
        realtime=realtime and loop != "plain",
        device=device,
    )
    if loop == "process":
        proc = LoopProcess(
            _play_loop, (tissue_data(tissue), url, duration_s, options), "haptic loop"
        ).start()

        def relay(message: Any) -> None:
            if message[0] == "status" and on_status is not None:
                on_status(message[1])
            elif message[0] == "message" and on_message is not None:
                on_message(message[1])

        summary: dict[str, Any] = proc.wait(stop, relay)
        return summary
    return _render(
        tissue,
        url,
        duration_s,
        stop=stop,
        on_status=on_status,
        on_message=on_message,
        in_thread=loop == "thread",
        **options,
    )


def _play_loop(
    parent: Parent,
    tissue: tuple[Any, ...],
    url: str,
    duration_s: float | None,
    options: dict[str, Any],
) -> dict[str, Any]:
    """A play in a loop process: figures and messages to ``parent``, which may stop it."""
    return _render(
        tissue_from_data(tissue),
        url,
        duration_s,
        stop=parent.stop,
        on_status=lambda s: parent.send(("status", s)),
        on_message=lambda m: parent.send(("message", m)),
        in_thread=False,
        inbox=parent,
        **options,
    )


def _render(
    tissue: Tissue,
    url: str,
    duration_s: float | None,
    *,
    rate_hz: float,
    log: str | os.PathLike[str] | None,
    name: str | None,
    stop: StopFlag | None,
    profile: DisplayProfile | None,
    force: float,
    baudrate: int,
    idle_timeout_s: float | None,
    on_status: Callable[[dict[str, Any]], None] | None,
    status_interval_s: float,
    in_thread: bool,
    realtime: bool,
    on_message: Callable[[str], None] | None,
    device: str = "display",
    inbox: Parent | None = None,
) -> dict[str, Any]:
    """:func:`play` from opening the display on, in this process (its loop in a thread
    of its own if ``in_thread``)."""
    link = open_display(url, kind=device, baudrate=baudrate, rate_hz=rate_hz, profile=profile)
    info, profile = link.info or {}, link.profile
    log_file: PlayLog | None = None
    player: HostLoop | None = None
    stream: Stream | None = None
    try:
        verdict = check(tissue, profile, rate_hz, force)
        if not verdict.renderable:
            raise RenderError(
                f"the display cannot render this {tissue.law.name} tissue: "
                + "; ".join(verdict.reasons)
            )
        if log is not None:
            from ..formats.playlog import PlayLog  # h5py only when a log is asked for

            stamp = datetime.now(timezone.utc)
            meta = {
                "start_utc": stamp.isoformat(timespec="milliseconds"),
                "source": f"serial:{url}",
                "device": info,
                "rate_hz": rate_hz,
                "tissue": {**tissue.describe(), "units": tissue.law.units},
                "profile": profile.as_dict(),
                "gains": asdict(verdict.gains),
                "check": verdict.as_dict(),
            }
            log_file = PlayLog(log, name or "play-" + stamp.strftime("%Y%m%dT%H%M%S"), meta)
        player = HostLoop(
            link,
            Controller(tissue, profile, rate_hz, verdict.gains),
            profile,
            rate_hz,
            float(info.get("clock_hz", 1e6)),
            log_file,
            realtime,
            on_message,
            inbox,
        )
        stream = Stream(
            link,
            Encoder,
            stop=stop if stop is not None else StopFlag(),
            idle_timeout_s=DISPLAY_SILENCE_S if idle_timeout_s is None else idle_timeout_s,
            status_interval_s=status_interval_s,
            # fail-safe: the solenoid off first, with no model to render from
            before_stop=lambda: player.send(0.0, modelled=False),
        )
        player.auto_silence = idle_timeout_s is None
        player.watchdog_periods = watchdog_periods(info)
        player.where = "process" if inbox is not None else "thread" if in_thread else "plain"
        if in_thread:  # the main thread stays free for signals
            summary = run_in_thread(
                lambda: player.run(stream, duration_s, on_status), "haptic loop"
            )
        else:
            summary = player.run(stream, duration_s, on_status)
    except BaseException as exc:
        if log_file is not None:
            reason = (
                f"device lost: {exc}"
                if isinstance(exc, DeviceLost)
                else f"error: {type(exc).__name__}: {exc}"
            )
            try:
                log_file.close(complete=False, stop_reason=reason)
            except Exception:  # the first error is the one to report
                pass
        if isinstance(exc, DeviceLost):
            message = f"{exc}; 0 V was sent as the loop ended, in case the line still carries it"
            if player is None or stream is None:
                raise DeviceLost(message) from None
            partial = player.summary(stream)
            partial["stop_reason"] = f"display lost: {exc}"
            partial["commands_sent"] = player.sent
            partial["check"] = verdict.as_dict()
            partial["tissue"] = tissue.describe()
            partial = jsonable(partial)
            partial["faults"] = [f"the display was lost: {exc}"]
            partial["exit_code"] = DeviceLost.exit_code
            partial["verdict"] = "display lost"
            if log_file is not None:
                partial["log"] = {"path": str(log), "group": log_file.group}
            raise PlayLost(message, partial) from None
        raise
    finally:
        link.close()
    summary["check"] = verdict.as_dict()
    summary["tissue"] = tissue.describe()
    summary = jsonable(summary)
    classified = classify_faults(summary, rate_hz)
    summary["faults"] = [text for _, text in classified]
    summary["exit_code"] = worst_fault({code for code, _ in classified})
    summary["verdict"] = "faulty" if summary["faults"] else "as checked"
    if log_file is not None:
        summary["log"] = {"path": str(log), "group": log_file.group}
        log_file.close(complete=True, **{k: v for k, v in summary.items() if k != "log"})
    return summary


def open_display(
    url: str,
    *,
    kind: str = "display",
    baudrate: int = DEFAULT_BAUD,
    rate_hz: float | None = None,
    profile: DisplayProfile | None = None,
) -> Display:
    """Open and identify the display of ``kind`` (a registered
    :class:`~tissuecli.hw.device.Display` class) at ``url``, checked against the loop's
    rate; its :attr:`~tissuecli.hw.device.Display.profile` is the one to render with."""
    cls = device_class(kind)
    if not (isinstance(cls, type) and issubclass(cls, Display)):
        raise InputError(f"a {kind} is not a display; {cls.role}")
    display: Display = cls(url, baudrate=baudrate, timeout=0.02).open(
        rate_hz=rate_hz, profile=profile
    )
    return display


class Rendering:
    """What the haptic loop computes for each frame (read, *compute*, command): the
    controller's answer. The base renders one tissue with ``ctrl``; ``live`` composes
    its own (a tissue that arrives and changes while the loop runs, behind a passivity
    controller) into the same :class:`HostLoop`.

    Parameters
    ----------
    ctrl : Controller or None
        The per-frame controller (None: nothing to render yet, 0 V).
    """

    def __init__(self, ctrl: Controller | None) -> None:
        self.ctrl = ctrl

    def step(self, x: float, volts: float, dt: float) -> Step:
        """The answer to one frame: encoder reading ``x`` (m), volts in use, ``dt`` (s)."""
        assert self.ctrl is not None
        return self.ctrl.update(x, volts, dt)

    def handle(self, message: Any) -> None:
        """A message from the process that started the loop (``live`` sends tissues)."""

    def local_model(
        self, step: Step, volts: float, profile: DisplayProfile
    ) -> tuple[float, float, float] | None:
        """The tissue's local linear model around the answer ``volts`` to ``step``, for a
        display that renders from it while the next answer is late
        (:class:`~tissuecli.hw.protocol.SetModel`): the pull over ``alpha`` (V^2) and its
        slopes against the piston's position (V^2/m) and velocity (V^2 s/m) over the
        first periods after the answer. Against position, the law's local stiffness (its
        relaxation branches' springs included, as they act within a few periods) less the
        display's spring: the tracking error moves only over tens of periods. Against
        velocity, the law's local damping less the piston's, plus the error feedback's
        share: before its damping acts, the error equation
        ``M e'' + (s + Cv) e' + (k + Cp) e = (M - Mp) xp''`` moves the error's velocity by
        ``(M - Mp) / M`` of the piston's, so ``Cv e'`` by ``Cv (M - Mp) / M`` of it. None
        when there is nothing to model (no controller yet, a non-finite step), or when
        ``volts`` is not the law's own answer to the pull it asked for (``live`` switched
        off, or its passivity controller changed the answer): a model would then render
        the law where the answer did not."""
        ctrl, alpha = self.ctrl, profile.alpha
        if ctrl is None or not alpha > 0 or not ctrl.mass > 0:
            return None
        law, x, v = ctrl.law, step.xp, step.vp
        # the pull as asked over alpha, negative where the solenoid cannot push
        u = step.pull / alpha
        v_max = law.v_max
        own = 0.0 if not u > 0.0 else v_max if u >= v_max * v_max else math.sqrt(u)
        if not math.isclose(volts, own, rel_tol=1e-6, abs_tol=1e-9):
            return None
        hx, hv = SLOPE_STEP_M, SLOPE_STEP_M_S
        try:
            k = (law.static(x + hx) - law.static(x - hx)) + (
                law.mixed(x + hx, v) - law.mixed(x - hx, v)
            )
            k = k / (2 * hx) + sum(br.Km for br in law.branches) - law.Kp
            s = (law.speed(v + hv) - law.speed(v - hv)) + (
                law.mixed(x, v + hv) - law.mixed(x, v - hv)
            )
            s = s / (2 * hv) - law.b + law.Cv * (ctrl.mass - profile.Mp) / ctrl.mass
        except (ArithmeticError, ValueError, TypeError):
            return None
        model = (u, k / alpha, s / alpha)
        return model if all(math.isfinite(z) for z in model) else None


#: Steps of the central differences that give the law's local slopes, m and m/s: small
#: against the depths (mm) and speeds (tens of mm/s) of a grasp, large against rounding.
SLOPE_STEP_M = 1e-6
SLOPE_STEP_M_S = 1e-4


class HostLoop:
    """The haptic loop over a display: read each Encoder frame, compute the answer
    (:class:`Rendering`), command it at once; deadlines, figures and the log.

    Parameters
    ----------
    link : Device
        The open display (:class:`~tissuecli.hw.device.Display` or any device that
        streams Encoder frames and takes SetVoltage commands).
    rendering : Rendering or Controller
        What computes each answer (a bare controller is wrapped in :class:`Rendering`).
    """

    def __init__(
        self,
        link: Device,
        rendering: Rendering | Controller | None,
        profile: DisplayProfile,
        rate_hz: float,
        clock_hz: float,
        log: PlayLog | None,
        realtime: bool = False,
        on_message: Callable[[str], None] | None = None,
        inbox: Parent | None = None,
    ) -> None:
        if not isinstance(rendering, Rendering):
            rendering = Rendering(rendering)
        self.rendering = rendering
        self.link, self.profile, self.log = link, profile, log
        self.realtime, self.on_message, self.inbox = realtime, on_message, inbox
        self.where = "plain"  # which of LOOPS runs it, for the summary
        # the display's watchdog limit, periods: as it states it, else the firmware's
        self.watchdog_periods = WATCHDOG_PERIODS
        # the display's silence limit follows what the loop's scheduling can guarantee
        self.auto_silence = False
        self.spin_s = 0.0
        self.elevation = Elevation()
        self.period = 1.0 / rate_hz
        self.clock_hz = clock_hz
        self.figures = PlayFigures()
        # a display that says so marks the periods it ran on a late answer (FLAG_STALE)
        info = getattr(link, "info", None)
        self.figures.reports_stale = isinstance(info, dict) and info.get("stale_flag") is True
        # a display that renders from the local model of a late answer takes SetModel
        self.modelled = isinstance(info, dict) and info.get("local_model") is True
        self.figures.reports_model = self.modelled
        self.last_step: Step | None = None
        self.volts = 0.0
        self.sent = 0
        self.clamped = 0  # commands clamped to [0, v_max] before sending
        self.missed = self.misses_in_row = 0
        self.last_clock: int | None = None
        self.answers = 0  # seq of the last Encoder frame: the one the next command answers
        self.elapsed = 0.0  # display clock since the first frame, s

    def send(self, value: float, modelled: bool = True) -> None:
        # every command within the limits the display reported (or a lower --profile)
        value, clamped = clamp_volts(value, self.profile.v_max)
        self.clamped += clamped
        # numbered by the frame it answers: the display tells a late answer (FLAG_STALE)
        model = (
            self.rendering.local_model(self.last_step, value, self.profile)
            if modelled and self.modelled and self.last_step is not None and not clamped
            else None
        )
        if model is None:
            self.link.send(SetVoltage(self.answers, value))
        else:
            self.link.send(SetModel(self.answers, value, *model))
        self.sent += 1

    def run(
        self,
        stream: Stream,
        duration_s: float | None,
        on_status: Callable[[dict[str, Any]], None] | None,
    ) -> dict[str, Any]:
        """Loop until the duration, the stop flag or a lost display; always ends at 0 V."""
        period = self.period
        fd = self.link.fileno()
        self.link.nonblocking()
        restore: Callable[[], None] = lambda: None  # noqa: E731
        if self.realtime:
            self.elevation, restore = elevate(cpu=None)
            message = fallback_message(self.elevation)
            if message is not None and self.on_message is not None:
                self.on_message(message)
        self.spin_s = spin_for(self.elevation)  # the simulated devices' rule too
        if self.auto_silence:
            elevated = self.elevation.elevated
            stream.idle_timeout_s = DISPLAY_SILENCE_S if elevated else DISPLAY_SILENCE_UNELEVATED_S
            stream.limit_note = f"; the limit is {stream.idle_timeout_s * 1e3:g} ms for a loop " + (
                "under SCHED_FIFO" if elevated else "without real-time scheduling"
            )
        try:
            summary = self._loop(stream, duration_s, on_status, period, fd)
        finally:
            restore()
        summary["watchdog_periods"] = self.watchdog_periods
        info = getattr(self.link, "info", None)
        summary["realtime"] = {
            "loop": self.where,
            **self.elevation.as_dict(),
            "spin_ms": self.spin_s * 1e3,
            # a simulated display says what its own loop obtained; hardware says nothing
            "display_scheduler": info.get("scheduler") if isinstance(info, dict) else None,
        }
        if self.inbox is not None and self.inbox.gone:
            summary["stop_reason"] = "the process that started the loop ended"
        return summary

    def _loop(
        self,
        stream: Stream,
        duration_s: float | None,
        on_status: Callable[[dict[str, Any]], None] | None,
        period: float,
        fd: int | None,
    ) -> dict[str, Any]:
        with realtime(), stream:
            clock: Deadlines | None = None
            deadline = stream.t_start + 1.0  # the first frame may take a moment
            inbox = self.inbox
            while stream.running():
                if inbox is not None:  # one select a period; the parent's stop and death
                    for message in inbox.poll():
                        self.handle(message)
                got, now = self._receive(stream, deadline, fd)
                if got:
                    self.send(self.volts)
                    self.figures.send(now)
                    self.figures.handled(now, got)
                    self.misses_in_row = 0
                    if clock is None:
                        # host deadlines half a period after each expected frame
                        clock = Deadlines(period, t0=now + 0.5 * period)
                    elif got == 1:
                        # track the display's clock: nudge deadlines towards arrival + T/2
                        err = now - (deadline - 0.5 * period)
                        clock.t0 += 0.01 * max(-0.5 * period, min(0.5 * period, err))
                else:
                    stream.check_idle(now)
                    if clock is not None:
                        self.missed += 1
                        self.misses_in_row += 1
                        # bridge a lost frame with the last voltage (and its model), briefly
                        if self.misses_in_row <= HOLD_PERIODS:
                            self.send(self.volts)
                        else:
                            self.send(0.0, modelled=False)
                if duration_s is not None and self.elapsed >= duration_s:
                    break
                if on_status is not None and stream.status_due(now):
                    on_status(self.summary(stream))
                deadline = clock.next() if clock is not None else deadline
        summary = self.summary(stream)
        summary["stop_reason"] = stream.reason
        summary["commands_sent"] = self.sent
        return summary

    @property
    def ctrl(self) -> Controller | None:
        return self.rendering.ctrl

    def handle(self, message: Any) -> None:
        """A message from the process that started the loop, for the rendering."""
        self.rendering.handle(message)

    def step(self, x: float, volts: float, dt: float) -> Step:
        """The rendering's answer to one frame."""
        return self.rendering.step(x, volts, dt)

    def _receive(self, stream: Stream, deadline: float, fd: int | None) -> tuple[int, float]:
        """Answer-ready: run every Encoder frame that arrives before ``deadline`` through
        the controller; the number of frames and the time."""
        got = 0
        while True:
            for msg in stream.poll():
                assert isinstance(msg, Encoder)
                got += 1
                if self.last_clock is None:
                    dt = self.period
                else:
                    dt = ((msg.clock - self.last_clock) & 0xFFFFFFFF) / self.clock_hz
                    self.elapsed += dt
                self.last_clock, self.answers = msg.clock, msg.seq
                x = msg.position * self.profile.resolution
                step = self.step(x, msg.volts, dt)
                self.volts, self.last_step = step.volts, step
                flags = self.figures.account(step, msg, x, self.profile.alpha)
                if self.log is not None:
                    self.log.add(
                        self.elapsed,
                        step.xp,
                        step.xm,
                        step.volts,
                        msg.volts,
                        step.force,
                        flags,
                        msg.position,
                    )
            now = time.monotonic()
            if got or now >= deadline:
                return got, now
            expected = deadline - 0.5 * self.period  # when the display's frame is due
            if fd is None:
                time.sleep(min(1e-4, max(0.0, deadline - now)))
            elif self.spin_s > 0 and now < expected + self.spin_s:
                # asleep until just before the frame is due, awake through its arrival
                wait_until(fd, expected + self.spin_s, 2 * self.spin_s)
            else:
                wait_readable(fd, deadline)

    def summary(self, stream: Stream) -> dict[str, Any]:
        if self.ctrl is None:  # nothing was ever rendered: the loop's figures alone
            f = self.figures
            return {
                "duration_s": self.elapsed,
                "frames": f.frames,
                "frames_lost": stream.seqs.lost,
                "frames_bad": self.link.bad_frames,
                "missed_periods": self.missed,
                "watchdog_frames": f.watchdog,
                **f.rates(),
                "period_p99_ms": f.percentile(99) * 1e3,
                "period_p50_ms": f.percentile(50) * 1e3,
                "period_max_ms": f.max_period * 1e3,
                **silence_figures(stream),
            }
        figures = self.figures.summary(self.ctrl, self.profile)
        return {
            "duration_s": self.elapsed,
            "frames": figures.pop("frames"),
            "frames_lost": stream.seqs.lost,
            "frames_bad": self.link.bad_frames,
            "missed_periods": self.missed,
            "clamped_commands": self.clamped,
            **figures,
            **silence_figures(stream),
        }


def watchdog_periods(info: Mapping[str, Any]) -> int:
    """The watchdog limit a display states in its IDENTIFY answer, periods (a simulated
    display's may be longer than the firmware's, judged against its port); the
    firmware's :data:`WATCHDOG_PERIODS` if it states none."""
    value = info.get("watchdog_periods")
    return int(value) if isinstance(value, int) and value > 0 else WATCHDOG_PERIODS
