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

import numpy as np

from ..core.errors import (
    EXIT_LOST_DATA,
    EXIT_NOT_RENDERED,
    EXIT_OFF_RATE,
    EXIT_WATCHDOG,
    DeviceError,
    DeviceLost,
    InputError,
    RenderError,
    worst_fault,
)
from ..core.flags import FLAG_LIMIT, FLAG_WATCHDOG, NONFINITE, SATURATED, UNRENDERABLE
from ..core.session import check_name
from ..core.tissue import Tissue
from ..formats.jsonfile import write_json
from ..formats.outputs import Output, check_outputs
from ..formats.params import read_profile, read_tissue
from ..hw.link import DEFAULT_BAUD, Link, open_device
from ..hw.protocol import Encoder, SetVoltage
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
from ..render.controller import Controller, Step, tracking_bound
from ..render.handover import tissue_data, tissue_from_data
from ..render.profile import (
    PAPER_DISPLAY,
    DisplayProfile,
    clamp_volts,
    exceeded_limits,
    profile_from_dict,
)

if TYPE_CHECKING:
    from ..formats.playlog import PlayLog

#: A display cuts the solenoid after this many periods without a SetVoltage, unless
#: it states its own limit (docs/protocol.md, section 7).
WATCHDOG_PERIODS = 5

#: A missing Encoder frame is bridged by repeating the last voltage this many periods,
#: then the host sends 0 V until frames return.
HOLD_PERIODS = 3

#: When a play is faulty (docs/rendering.md, "When a play is faulty"): the loop rate more
#: than this fraction off nominal (on an idle machine it stays within 0.2 %) ...
MAX_RATE_ERROR = 0.02
#: ... more periods without a frame, or frames lost or corrupt on the line, than this
#: fraction of the frames (each missed period is bridged with a stale voltage; normal
#: plays on a 2-core machine running the simulated display miss 0.1-1.1 %) ...
MAX_MISSED_FRACTION = 0.05
#: ... the tracking error above its bound plus the check's soft gap (where the tissue is
#: softer than the display's spring) by more than this, m: the bound holds for an
#: unclamped law in steady state, and touch-down transients, the estimator's lag and
#: frames where the solenoid is clamped added up to 0.27 mm at most over 197 random
#: tissues the check accepts, on the offline loop ...
TRACKING_ALLOWANCE_M = 4e-4
#: ... or more saturated or unrenderable frames than a tissue the check accepts shows
#: on the offline loop (at most 0.9 % and 11 % of all frames over 197 accepted tissues:
#: docs/rendering.md).
MAX_SATURATED_FRACTION = 0.05
MAX_UNRENDERABLE_FRACTION = 0.3

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
    """The play ran, but not as the check promised (see :func:`play_faults`); raised by
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


def play_faults(summary: Mapping[str, Any], rate_hz: float) -> list[str]:
    """What went wrong in a play, one short sentence each (empty if nothing did); see
    :func:`classify_faults` for the rules."""
    return [text for _, text in classify_faults(summary, rate_hz)]


def classify_faults(summary: Mapping[str, Any], rate_hz: float) -> list[tuple[int, str]]:
    """What went wrong in a play: ``(exit status of its class, sentence)`` each.

    A play is faulty when the display's watchdog cut the solenoid (watchdog frames
    > 0; :data:`~tissuecli.core.errors.EXIT_WATCHDOG`), the loop ran more than
    :data:`MAX_RATE_ERROR` off ``rate_hz`` or more than :data:`MAX_MISSED_FRACTION` of
    the periods went without a frame (``EXIT_OFF_RATE``), frames were lost or corrupt on
    the line beyond that fraction (``EXIT_LOST_DATA``), or the rendering left what the
    check promised (``EXIT_NOT_RENDERED``): the controller met a non-finite value, the
    tracking error exceeded its bound (plus the check's ``soft_gap_m``) by more than
    :data:`TRACKING_ALLOWANCE_M`, or the solenoid was saturated or unable to follow on
    more frames than :data:`MAX_SATURATED_FRACTION` and :data:`MAX_UNRENDERABLE_FRACTION`.
    A watchdog cut or a slow loop names what the loop's scheduling could guarantee.
    """

    def num(key: str) -> float:
        value = summary.get(key)
        return float(value) if isinstance(value, (int, float)) and value == value else 0.0

    faults: list[tuple[int, str]] = []
    frames = max(num("frames"), 1.0)
    sched = summary.get("realtime")
    scheduler = sched.get("scheduler") if isinstance(sched, Mapping) else None
    guarantee = (
        f"; the loop's longest period was {num('period_max_ms'):.3g} ms under {scheduler}"
        + ("" if scheduler == "SCHED_FIFO" else ", real-time scheduling not granted")
        if scheduler
        else ""
    )
    if num("watchdog_frames") > 0:
        limit = num("watchdog_periods") or WATCHDOG_PERIODS  # as the display stated it
        faults.append(
            (
                EXIT_WATCHDOG,
                f"the display's watchdog cut the solenoid on {num('watchdog_frames'):.0f} "
                f"frame(s): the host stopped answering for {limit:.0f} periods "
                f"({limit * 1e3 / rate_hz:g} ms)" + guarantee,
            )
        )
    rate = num("loop_rate_hz")
    if num("frames") > 1 and abs(rate - rate_hz) > MAX_RATE_ERROR * rate_hz:
        faults.append(
            (
                EXIT_OFF_RATE,
                f"the loop ran at {rate:.1f} Hz, {100 * abs(rate / rate_hz - 1):.1f} % off "
                f"{rate_hz:g} Hz (p99 period {num('period_p99_ms'):.2f} ms)",
            )
        )
    if num("missed_periods") > MAX_MISSED_FRACTION * frames:
        faults.append(
            (
                EXIT_OFF_RATE,
                f"{num('missed_periods'):.0f} periods passed without a frame "
                f"({100 * num('missed_periods') / frames:.1f} % of {frames:.0f})",
            )
        )
    lost = num("frames_lost") + num("frames_bad")
    if lost > MAX_MISSED_FRACTION * frames:
        faults.append((EXIT_LOST_DATA, f"{lost:.0f} frame(s) lost or corrupt on the line"))
    if num("nonfinite_frames") > 0:
        faults.append(
            (EXIT_NOT_RENDERED, f"{num('nonfinite_frames'):.0f} frame(s) with non-finite values")
        )
    err, bound = num("tracking_max_m"), summary.get("tracking_bound_m")
    check = summary.get("check")
    gap = check.get("soft_gap_m") if isinstance(check, Mapping) else None
    gap = float(gap) if isinstance(gap, (int, float)) else 0.0
    if isinstance(bound, (int, float)) and err > bound + gap + TRACKING_ALLOWANCE_M:
        faults.append(
            (
                EXIT_NOT_RENDERED,
                f"tracking error reached {err * 1e3:.3g} mm, above its bound "
                f"{bound * 1e3:.3g} mm"
                + (f" + soft gap {gap * 1e3:.3g} mm" if gap else "")
                + f" + {TRACKING_ALLOWANCE_M * 1e3:g} mm",
            )
        )
    for key, limit, what in (
        ("saturated_fraction", MAX_SATURATED_FRACTION, "saturated"),
        ("unrenderable_fraction", MAX_UNRENDERABLE_FRACTION, "unrenderable (a push asked)"),
    ):
        if num(key) > limit:
            faults.append(
                (
                    EXIT_NOT_RENDERED,
                    f"{100 * num(key):.1f} % of frames {what}, more than {100 * limit:g} %",
                )
            )
    return faults


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
        ``faults`` are not empty; see :func:`play_faults`): the command exits 1.
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

    Returns
    -------
    dict
        The summary: ``tracking_rms_m``, ``tracking_max_m``, ``tracking_bound_m``,
        ``saturated_fraction``, ``unrenderable_fraction``, ``loop_rate_hz``,
        ``period_p99_ms``, ``period_max_ms``, ``frames``, ``frames_lost``,
        ``frames_bad``, ``missed_periods``, ``watchdog_frames``, ``watchdog_periods``
        (the display's stated watchdog limit), ``commands_sent``,
        ``clamped_commands`` (brought within [0, v_max] before sending),
        ``actuator_work_j``, ``realtime`` (what :func:`~tissuecli.hw.realtime.elevate`
        obtained), ``check`` and more; ``faults`` (what went wrong, see
        :func:`play_faults`; empty for a good play) and ``verdict`` (``"as checked"``
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
    inbox: Parent | None = None,
) -> dict[str, Any]:
    """:func:`play` from opening the display on, in this process (its loop in a thread
    of its own if ``in_thread``)."""
    link, info, profile = _open_display(url, baudrate, rate_hz, profile)
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
            before_stop=lambda: player.send(0.0),  # fail-safe: the solenoid off first
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
            partial = _jsonable(partial)
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
    summary = _jsonable(summary)
    classified = classify_faults(summary, rate_hz)
    summary["faults"] = [text for _, text in classified]
    summary["exit_code"] = worst_fault({code for code, _ in classified})
    summary["verdict"] = "faulty" if summary["faults"] else "as checked"
    if log_file is not None:
        summary["log"] = {"path": str(log), "group": log_file.group}
        log_file.close(complete=True, **{k: v for k, v in summary.items() if k != "log"})
    return summary


def _open_display(
    url: str, baudrate: int, rate_hz: float, profile: DisplayProfile | None
) -> tuple[Link, dict[str, Any], DisplayProfile]:
    """Open and identify a display; its link, Info and the profile to use."""
    link, info = open_device(url, "display", baudrate=baudrate, timeout=0.02)
    assert info is not None  # open_device refuses a silent display
    try:
        device_rate = info.get("rate_hz")
        if isinstance(device_rate, (int, float)) and abs(device_rate - rate_hz) > 1e-6 * rate_hz:
            raise DeviceError(
                f"the display at {url} runs its loop at {device_rate:g} Hz; "
                f"pass --rate {device_rate:g}"
            )
        reported = info.get("profile")
        limits = (
            profile_from_dict(reported, source=f"profile reported by {url}")
            if isinstance(reported, Mapping)
            else None
        )
        if profile is None:
            profile = limits if limits is not None else PAPER_DISPLAY
        elif limits is not None:
            # the display's own limits rule: a file may ask less, never more
            over = exceeded_limits(profile, limits)
            if over:
                raise DeviceError(
                    f"--profile asks more than the display at {url} reports: "
                    + "; ".join(over)
                    + "; lower them to the display's, or give no --profile"
                )
        return link, info, profile
    except BaseException:
        link.close()
        raise


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


class HostLoop:
    """The haptic loop over a display: read each Encoder frame, compute the answer
    (:class:`Rendering`), command it at once; deadlines, figures and the log.

    Parameters
    ----------
    link : Link
        The open display.
    rendering : Rendering or Controller
        What computes each answer (a bare controller is wrapped in :class:`Rendering`).
    """

    def __init__(
        self,
        link: Link,
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
        self.volts = 0.0
        self.sent = 0
        self.clamped = 0  # commands clamped to [0, v_max] before sending
        self.missed = self.misses_in_row = 0
        self.last_clock: int | None = None
        self.elapsed = 0.0  # display clock since the first frame, s

    def send(self, value: float) -> None:
        # every command within the limits the display reported (or a lower --profile)
        value, clamped = clamp_volts(value, self.profile.v_max)
        self.clamped += clamped
        self.link.send(SetVoltage(self.sent & 0xFFFFFFFF, value))
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
            stream.idle_timeout_s = (
                DISPLAY_SILENCE_S if elevated else DISPLAY_SILENCE_UNELEVATED_S
            )
            stream.limit_note = (
                f"; the limit is {stream.idle_timeout_s * 1e3:g} ms for a loop "
                + ("under SCHED_FIFO" if elevated else "without real-time scheduling")
            )
        try:
            summary = self._loop(stream, duration_s, on_status, period, fd)
        finally:
            restore()
        summary["watchdog_periods"] = self.watchdog_periods
        summary["realtime"] = {
            "loop": self.where,
            **self.elevation.as_dict(),
            "spin_ms": self.spin_s * 1e3,
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
                        # bridge a lost frame with the last voltage, briefly
                        self.send(self.volts if self.misses_in_row <= HOLD_PERIODS else 0.0)
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
                self.last_clock = msg.clock
                x = msg.position * self.profile.resolution
                step = self.step(x, msg.volts, dt)
                self.volts = step.volts
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
                "frames_bad": self.link.decoder.bad_frames,
                "missed_periods": self.missed,
                "watchdog_frames": f.watchdog,
                "loop_rate_hz": f.loop_rate(),
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
            "frames_bad": self.link.decoder.bad_frames,
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


#: The loop's former name, for code that used it.
_Player = HostLoop


def silence_figures(stream: Stream) -> dict[str, float]:
    """The display's longest silence, the host's own longest stall and the limit the
    display's silence was judged against, ms."""
    return {
        "longest_silence_ms": stream.longest_silence_s * 1e3,
        "host_stall_ms": stream.host_stall_s * 1e3,
        "no_frame_limit_ms": stream.idle_timeout_s * 1e3,
    }


class PlayFigures:
    """Running figures of a play, in bounded memory: tracking, flags, energy and the
    loop's period."""

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

    def account(self, step: Step, msg: Encoder, x: float, alpha: float) -> int:
        """Fold one frame in (``x``: the encoder reading, m); return the frame's flags."""
        self.frames += 1
        e = step.xp - step.xm
        if e == e:
            self.sum_e2 += e * e
            self.max_e = max(self.max_e, abs(e))
        if step.ap == step.ap:
            self.max_a = max(self.max_a, abs(step.ap))
        if self.prev_x is not None:
            # work done on the piston by the solenoid over the last period (> 0: created)
            self.work -= alpha * self.prev_volts**2 * (x - self.prev_x)
        self.prev_x, self.prev_volts = x, msg.volts
        self.x_lo, self.x_hi = min(self.x_lo, step.xp), max(self.x_hi, step.xp)
        flags = msg.flags | step.flags
        self.saturated += bool(flags & SATURATED)
        self.unrenderable += bool(flags & UNRENDERABLE)
        self.nonfinite += bool(flags & NONFINITE)
        self.watchdog += bool(flags & FLAG_WATCHDOG)
        self.limit += bool(flags & FLAG_LIMIT)
        return flags

    def summary(self, ctrl: Controller, profile: DisplayProfile) -> dict[str, Any]:
        """The figures as a dict (see :func:`play`)."""
        n = max(self.frames, 1)
        if self.x_hi >= self.x_lo:
            depths = np.linspace(self.x_lo, self.x_hi, 51)
            k_min = min(ctrl.local_stiffness(float(x)) for x in depths)
        else:
            k_min = ctrl.local_stiffness(0.0)
        return {
            "frames": self.frames,
            "tracking_rms_m": math.sqrt(self.sum_e2 / n),
            "tracking_max_m": self.max_e,
            "tracking_bound_m": tracking_bound(
                ctrl.gains.M, profile.Mp, self.max_a, k_min, profile.resolution
            ),
            "max_accel_m_s2": self.max_a,
            "saturated_fraction": self.saturated / n,
            "unrenderable_fraction": self.unrenderable / n,
            "nonfinite_frames": self.nonfinite,
            "watchdog_frames": self.watchdog,
            "limit_frames": self.limit,
            "actuator_work_j": self.work,
            "loop_rate_hz": self.loop_rate(),
            "period_p99_ms": self.percentile(99) * 1e3,
            "period_p50_ms": self.percentile(50) * 1e3,
            "period_max_ms": self.max_period * 1e3,
            "gains": asdict(ctrl.gains),
        }


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
    faults = summary.get("faults") or []
    lines.extend(f"FAULT: {f}" for f in faults)
    if faults:
        lines.append("the display did not render the tissue as checked (docs/rendering.md)")
    return lines
