"""The ``live`` service: feel the tissue while it is grasped.

The forceps is recorded exactly as ``record`` does (the same crash-safe file and
acquisition loop, :func:`tissuecli.app.record.record`, in the calling thread), and its
online identification (the recorder's own :class:`~tissuecli.identify.online.OnlineFit`)
is rendered on the display by the haptic loop of ``play``, in a process of its own
(:class:`HapticLoop`: an interpreter the recorder and the fit do not share) with
elevated scheduling. The display stays at 0 V until the estimate is confident; each
new estimate is handed over (:mod:`tissuecli.render.handover`) and blended in through
:meth:`Controller.retarget` (a blend that creates no energy), and every voltage goes
through a :class:`~tissuecli.render.passivity.PassivityController`. Confidence lost,
the forceps silent, either device or this process gone: 0 V.
"""

from __future__ import annotations

import math
import os
import signal
import time
from collections.abc import Callable
from dataclasses import replace
from datetime import datetime, timezone
from typing import Any

import numpy as np

from ..core.errors import (
    DeviceError,
    DeviceLost,
    InputError,
    RenderError,
    worst_fault,
)
from ..core.tissue import Tissue
from ..hw.link import DEFAULT_BAUD
from ..hw.protocol import Encoder
from ..hw.realtime import LoopProcess, Parent, StopFlag
from ..hw.stream import Stream
from ..render.check import check
from ..render.controller import Controller, Step
from ..render.handover import TISSUE, read_tissue_message, tissue_message
from ..render.law import Gains
from ..render.passivity import PassivityController
from ..render.profile import DisplayProfile
from .faults import live_faults
from .loopstats import jsonable
from .play import HostLoop, Rendering, open_display, watchdog_periods
from .record import RecordStatus, SampleBlock, record

#: The forceps silent this long (no sample block) and the display goes to 0 V, s.
FORCEPS_SILENCE_S = 0.1
#: The recorder tells the loop the forceps is alive at most this often, s (a message
#: per sample block would be needless work for the loop).
HEARTBEAT_S = 0.02
#: The display silent this long is taken as lost, s: longer than ``play``'s 0.1 s, as
#: the recorder shares the machine (the display's own watchdog cuts the solenoid after
#: 5 periods without a command whatever the host does).
DISPLAY_SILENCE_S = 0.5
#: How long the loop process may take to start and open the display, s.
OPEN_TIMEOUT_S = 30.0
#: A new estimate is handed to the display when a coefficient moved by more than this
#: fraction of its value (or the law changed), at most every RETARGET_INTERVAL_S.
RETARGET_CHANGE = 0.05
RETARGET_INTERVAL_S = 0.25
#: A grasp starts when the force first exceeds this, N (the delay to first rendering
#: is counted from there).
GRASP_START_N = 0.1


class LiveRendering(Rendering):
    """``live``'s computation in the haptic loop: a tissue that arrives (and changes)
    while the loop runs, handed over by the process that started it, rendered behind a
    passivity controller; 0 V until it is confident and whenever the forceps is silent.

    Parameters
    ----------
    profile : DisplayProfile
        The display's constants.
    rate_hz : float
        The loop's rate, Hz.
    """

    def __init__(self, profile: DisplayProfile, rate_hz: float) -> None:
        super().__init__(None)  # a controller once a tissue arrives
        self.profile, self.rate_hz = profile, rate_hz
        self.active = False  # a confident, renderable estimate
        self.last_sample = -math.inf  # monotonic time of the forceps' last block
        self.pc = PassivityController(profile, rate_hz)
        self.first_render: float | None = None
        self.rendered: Tissue | None = None
        self.handovers = 0
        self.refused = ""
        cap = 1 << 16
        self.trace = np.zeros((cap, 4))  # xp, vp, ap, observed force of rendered frames
        self.n_trace = 0

    def handle(self, message: Any) -> None:
        kind = message[0]
        if kind == TISSUE:
            tissue, gains = read_tissue_message(message)
            if self.ctrl is None:
                self.ctrl = Controller(tissue, self.profile, self.rate_hz, gains)
            else:
                try:
                    self.ctrl.retarget(tissue)
                except RenderError as exc:  # keep rendering the law it has
                    self.refused = str(exc)
                    return
            self.rendered = tissue
            self.handovers += 1
        elif kind == "active":
            self.active = bool(message[1])
        elif kind == "forceps":
            self.last_sample = float(message[1])

    def step(self, x: float, volts: float, dt: float) -> Step:
        fresh = time.monotonic() - self.last_sample < FORCEPS_SILENCE_S
        if self.ctrl is None:
            self.pc.observe(x, volts)
            return Step(0.0, 0, x, 0.0, 0.0, x, 0.0, math.nan, math.nan)
        step = self.ctrl.update(x, volts, dt)
        if not (self.active and fresh):
            self.pc.observe(x, volts)
            self.pc.act(0.0, 0.0, dt)
            return replace(step, volts=0.0)
        pc = self.pc.update(x, volts, step.volts, step.vp + 1.5 * dt * step.ap, dt)
        self.ctrl.extra_damping = self.pc.damping
        if self.first_render is None and pc.volts > 0.0:
            self.first_render = time.monotonic()
        if step.force == step.force:
            if self.n_trace == self.trace.shape[0]:  # a minute more, rarely
                self.trace = np.concatenate([self.trace, np.zeros((60_000, 4))])
            self.trace[self.n_trace] = (step.xp, step.vp, step.ap, step.force)
            self.n_trace += 1
        return replace(step, volts=pc.volts)


def _live_loop(
    parent: Parent,
    display_url: str,
    baudrate: int,
    rate_hz: float,
    profile: DisplayProfile | None,
    realtime: bool,
) -> dict[str, Any]:
    """The haptic loop of ``live``, in its own process: open the display, tell the
    parent its profile, render what it hands over until it stops or goes."""
    link = open_display(display_url, baudrate=baudrate, rate_hz=rate_hz, profile=profile)
    info, profile = link.info or {}, link.profile
    try:
        parent.send(("opened", profile))
        rendering = LiveRendering(profile, rate_hz)
        loop = HostLoop(
            link,
            rendering,
            profile,
            rate_hz,
            float(info.get("clock_hz", 1e6)),
            None,
            realtime,
            lambda m: parent.send(("message", m)),
            parent,
        )
        loop.where = "process"
        loop.watchdog_periods = watchdog_periods(info)
        stream = Stream(
            link,
            Encoder,
            stop=parent.stop,
            idle_timeout_s=DISPLAY_SILENCE_S,
            status_interval_s=1.0,
            before_stop=lambda: loop.send(0.0, modelled=False),  # no model to render from
        )
        render = loop.run(
            stream, None, lambda s: parent.send(("status", {"energy_j": rendering.pc.energy_j}))
        )
    finally:
        link.close()
    return {
        "render": jsonable(render),
        "passivity": rendering.pc.summary(),
        "first_render": rendering.first_render,
        "rendered": (
            {**rendering.rendered.describe(), "units": rendering.rendered.law.units}
            if rendering.rendered is not None
            else None
        ),
        "handovers": rendering.handovers,
        "refused": rendering.refused,
        "trace": rendering.trace[: rendering.n_trace].copy(),
    }


class HapticLoop:
    """The haptic loop of ``live`` in a process of its own, seen from the recorder's.

    Starting it opens the display (:attr:`profile` is what it reports). Then
    :meth:`render` hands over a tissue, :meth:`set_active` switches rendering on and
    off (0 V while off), :meth:`forceps_alive` says the forceps has just sent samples
    (0 V when it has not for :data:`FORCEPS_SILENCE_S`), :meth:`poll` collects what the
    loop said, and :meth:`finish` stops it and returns its figures. If this process
    dies, the loop sees its pipe close and sends 0 V.

    Parameters
    ----------
    display_url : str
        The display's port.
    rate_hz : float
        Its loop rate, Hz.
    profile : DisplayProfile, optional
        Its constants (default: what it reports).
    baudrate : int
        Line rate, bit/s.
    realtime : bool
        Ask for SCHED_FIFO, locked memory and one CPU in the loop process.
    stop : StopFlag, optional
        Watched while the display opens.
    on_message : callable, optional
        Told once if elevated scheduling is refused.
    """

    def __init__(
        self,
        display_url: str,
        rate_hz: float = 1000.0,
        profile: DisplayProfile | None = None,
        baudrate: int = DEFAULT_BAUD,
        realtime: bool = True,
        stop: StopFlag | None = None,
        on_message: Callable[[str], None] | None = None,
    ) -> None:
        self.on_message = on_message
        self.energy_j = 0.0
        self.active = False
        self.last_beat = -math.inf
        self.result: dict[str, Any] | None = None
        self.error: BaseException | None = None
        self.proc = LoopProcess(
            _live_loop, (display_url, baudrate, rate_hz, profile, realtime), "haptic loop"
        ).start()
        opened: DisplayProfile | None = None
        deadline = time.monotonic() + OPEN_TIMEOUT_S
        try:
            while opened is None:
                if stop or time.monotonic() > deadline:
                    self.proc.wait(timeout_s=0.0)
                    why = "interrupted" if stop else f"not within {OPEN_TIMEOUT_S:g} s"
                    raise DeviceError(f"the display at {display_url} did not start its loop: {why}")
                for message in self.proc.receive(0.05):
                    if message[0] == "opened":
                        opened = message[1]
                    else:
                        self._take(message)
                if self.error is not None:
                    raise self.error
                if self.proc.ended and opened is None:
                    self.proc.wait(timeout_s=0.0)  # raises why it ended
        except BaseException:
            self.proc.kill()
            raise
        self.profile: DisplayProfile = opened

    def _take(self, message: Any) -> None:
        kind = message[0]
        if kind == "status":
            self.energy_j = float(message[1]["energy_j"])
        elif kind == "message" and self.on_message is not None:
            self.on_message(message[1])
        elif kind == "done":
            self.result = message[1]
        elif kind == "error":
            self.error = message[1]

    def poll(self) -> bool:
        """Collect what the loop said, without waiting; False once it has ended."""
        for message in self.proc.receive(0.0):
            self._take(message)
        return not (self.proc.ended or self.result is not None or self.error is not None)

    def render(self, tissue: Tissue, gains: Gains) -> None:
        """Hand ``tissue`` over, to be rendered with ``gains`` (the first one's stay)."""
        self.proc.send(tissue_message(tissue, gains))

    def set_active(self, active: bool) -> None:
        if active != self.active:
            self.active = active
            self.proc.send(("active", active))

    def forceps_alive(self, now: float | None = None) -> None:
        """The forceps sent samples at ``now`` (monotonic s, default now)."""
        now = time.monotonic() if now is None else now
        if now - self.last_beat >= HEARTBEAT_S:
            self.last_beat = now
            self.proc.send(("forceps", now))

    def finish(self) -> dict[str, Any]:
        """Stop the loop (0 V, STOP) and return its figures; raise what ended it, if
        something did (the display lost)."""
        self.set_active(False)
        if self.result is None and self.error is None:
            try:
                self.result = self.proc.wait(on_message=self._take, timeout_s=0.0)
            except BaseException as exc:  # noqa: BLE001  (raised below, once)
                self.error = exc
        else:
            self.proc.join()
        if self.error is not None:
            raise self.error
        assert self.result is not None
        return self.result


def live(
    forceps_url: str,
    display_url: str,
    out: str | os.PathLike[str],
    session: str | None = None,
    duration_s: float | None = None,
    *,
    rate_hz: float = 1000.0,
    profile: DisplayProfile | None = None,
    forgetting_s: float = 5.0,
    baudrate: int = DEFAULT_BAUD,
    stop: StopFlag | None = None,
    realtime: bool = True,
    on_status: Callable[[dict[str, Any]], None] | None = None,
    on_message: Callable[[str], None] | None = None,
    fit_offline: bool = True,
) -> dict[str, Any]:
    """Record from the forceps, identify online and render the estimate on the display.

    Parameters
    ----------
    forceps_url, display_url : str
        The two devices' ports.
    out : path
        HDF5 file the session is recorded to (as by ``record``).
    session : str, optional
        Session name (default ``live-<UTC time>``).
    duration_s : float, optional
        Seconds to record (device time); default until ``stop``.
    rate_hz : float
        The display's loop rate, Hz.
    profile : DisplayProfile, optional
        The display's constants (default: what it reports).
    forgetting_s : float
        Forgetting time of the online identification, s.
    stop : StopFlag, optional
        Set by SIGINT/SIGTERM: both loops end cleanly.
    realtime : bool
        Ask for elevated scheduling in the haptic loop's process (``--no-realtime``).
    on_status : callable, optional
        Called about once a second with the running figures.
    on_message : callable, optional
        Told once if elevated scheduling is refused.
    fit_offline : bool
        Fit the recording afterwards and score the rendering against that law.

    Returns
    -------
    dict
        ``recording`` (path, session, samples, duration_s), ``estimate`` (the last
        online estimate), ``render`` (the haptic loop's figures as ``play`` gives
        them), ``passivity`` (energy observed, dissipated), ``first_render_delay_s``
        (grasp start to the first voltage rendered), ``handovers`` (estimates handed to
        the loop), ``offline`` (the law fitted to the recording) and ``tracking_rms_n``
        (RMS of the force the display rendered minus what that law gives at the
        display's motion), ``stop_reason``.
    """
    _check_args(duration_s)
    if session is None:
        session = "live-" + datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S")
    stop = stop if stop is not None else StopFlag()
    haptic = HapticLoop(display_url, rate_hz, profile, baudrate, realtime, stop, on_message)
    profile = haptic.profile

    grasp: dict[str, float] = {}
    state: dict[str, Any] = {"estimate": None, "handed": None, "at": -math.inf, "note": ""}

    def on_samples(block: SampleBlock) -> None:
        now = time.monotonic()
        haptic.forceps_alive(now)
        if "start" not in grasp:
            above = np.nonzero(block.force > GRASP_START_N)[0]
            if above.size:
                grasp["start"] = now - float(block.host_time[-1] - block.host_time[above[0]])

    def on_record_status(status: RecordStatus) -> None:
        if not haptic.poll():
            stop.set(signal.SIGTERM)  # the display gone: end the recording too
        est = status.estimate
        state["estimate"] = est
        if est is None or not est.confident:
            haptic.set_active(False)
            return
        now = time.monotonic()
        handed = state["handed"]
        changed = (
            handed is None
            or handed.law != est.law
            or bool(np.any(np.abs(est.mean - handed.mean) > RETARGET_CHANGE * np.abs(handed.mean)))
        )
        if changed and now - state["at"] >= RETARGET_INTERVAL_S:
            tissue = est.tissue()
            verdict = check(tissue, profile, rate_hz)
            if verdict.renderable:
                haptic.render(tissue, verdict.gains)
                state["handed"], state["at"], state["note"] = est, now, ""
            else:
                state["note"] = "not renderable: " + "; ".join(verdict.reasons)
        haptic.set_active(state["handed"] is not None and not state["note"])
        if on_status is not None and now >= state.get("next", 0.0):
            state["next"] = now + 1.0
            on_status(
                {
                    "elapsed_s": status.elapsed_s,
                    "samples": status.samples,
                    "estimate": est.describe(),
                    "rendering": haptic.active,
                    "energy_j": haptic.energy_j,
                }
            )

    try:
        result = record(
            forceps_url,
            out,
            session,
            duration_s=duration_s,
            stop=stop,
            on_status=on_record_status,
            status_interval_s=0.05,
            on_samples=on_samples,
            forgetting_s=forgetting_s,
        )
    except BaseException:
        try:
            haptic.finish()
        except Exception:  # noqa: BLE001  (the recorder's error is the one to report)
            pass
        raise
    try:
        loop = haptic.finish()
    except DeviceLost as exc:  # the display went: the recording is complete up to then
        raise DeviceLost(
            f"the display was lost ({exc}); the recording stopped with it and its "
            f"{result.samples} samples are saved in {result.path}, session {result.session}"
        ) from None
    first = loop["first_render"]
    summary: dict[str, Any] = {
        "recording": {
            "path": result.path,
            "session": result.session,
            "samples": result.samples,
            "duration_s": result.duration_s,
            "lost_frames": result.lost_frames,
            "bad_frames": result.bad_frames,
            "rejected_frames": result.faults.frames_rejected,
        },
        "estimate": state["estimate"].as_dict() if state["estimate"] is not None else None,
        "rendered": loop["rendered"],
        "handovers": loop["handovers"],
        "render": loop["render"],
        "passivity": loop["passivity"],
        "first_render_delay_s": (
            first - grasp["start"] if first is not None and "start" in grasp else None
        ),
        "stop_reason": result.stop_reason,
        "note": state["note"] or loop["refused"],
    }
    if fit_offline:
        summary.update(_offline_score(out, session, loop["trace"]))
    classified = live_faults(summary, rate_hz)
    summary["faults"] = [text for _, text in classified]
    summary["exit_code"] = worst_fault({code for code, _ in classified})
    return jsonable(summary)


def _offline_score(out: Any, session: str, trace: np.ndarray) -> dict[str, Any]:
    """The law fitted to the whole recording, and the RMS of the force the display
    rendered against that law's force at the display's own motion."""
    from ..formats.sessions import read_session
    from ..identify import fit_session

    try:
        outcome = fit_session(read_session(out, session), forms="paper")
    except Exception as exc:  # noqa: BLE001  (a summary without the score, saying why)
        return {"offline": None, "offline_note": f"offline fit failed: {exc}"}
    best = outcome.bayes.best_ if outcome.bayes is not None else None
    if best is None or best.posterior is None:
        return {"offline": None}
    tissue = Tissue(best.model, *(float(c) for c in best.posterior.mean))
    scored: dict[str, Any] = {
        "offline": {**tissue.describe(), "units": tissue.law.units},
        "tracking_rms_n": None,
    }
    n = len(trace)
    if n:
        xp, vp, ap, f = trace.T
        err = f - tissue.force(xp, vp, ap)
        scored["tracking_rms_n"] = float(np.sqrt(np.mean(err**2)))
        scored["rendered_frames"] = n
    return scored


def _check_args(duration_s: float | None) -> None:
    if duration_s is not None and not duration_s > 0:
        raise InputError("--duration must be a positive number of seconds")
