"""The ``live`` service: feel the tissue while it is grasped.

The forceps is recorded exactly as ``record`` does (the same crash-safe file and
acquisition loop, :func:`tissuecli.app.record.record`, in the calling thread), and its
online identification (the recorder's own :class:`~tissuecli.identify.online.OnlineFit`)
is rendered on the display by the haptic loop of ``play``, in a thread of its own with
elevated scheduling. The display stays at 0 V until the estimate is confident; each
new estimate is handed over through :meth:`Controller.retarget` (a blend that creates
no energy) and every voltage through a
:class:`~tissuecli.render.passivity.PassivityController`. Confidence lost, the
forceps silent or either device gone: 0 V.
"""

from __future__ import annotations

import math
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from datetime import datetime, timezone
from typing import Any

import numpy as np

from ..core.errors import DeviceLost, InputError
from ..core.tissue import Tissue
from ..hw.link import DEFAULT_BAUD
from ..hw.protocol import Encoder
from ..hw.realtime import StopFlag
from ..hw.stream import Stream
from ..render.check import check
from ..render.controller import Controller, Step
from ..render.passivity import PassivityController
from ..render.profile import DisplayProfile
from .play import _jsonable, _open_display, _Player
from .record import RecordStatus, SampleBlock, record

#: The forceps silent this long (no sample block) and the display goes to 0 V, s.
FORCEPS_SILENCE_S = 0.1
#: The display silent this long is taken as lost, s: longer than ``play``'s 0.1 s, as
#: the recorder shares the machine (the display's own watchdog cuts the solenoid after
#: 5 periods without a command whatever the host does).
DISPLAY_SILENCE_S = 0.5
#: A new estimate is handed to the display when a coefficient moved by more than this
#: fraction of its value (or the law changed), at most every RETARGET_INTERVAL_S.
RETARGET_CHANGE = 0.05
RETARGET_INTERVAL_S = 0.25
#: A grasp starts when the force first exceeds this, N (the delay to first rendering
#: is counted from there).
GRASP_START_N = 0.1
#: The interpreter's switch interval while both loops run, s (Python's default 5 ms is
#: five periods of the haptic loop).
SWITCH_INTERVAL_S = 2e-4


class _LivePlayer(_Player):
    """``play``'s loop with a tissue that arrives (and changes) while it runs."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.pending: tuple[Tissue, Any] | None = None  # (tissue, gains), from the recorder
        self.active = False  # a confident, renderable estimate and a live forceps
        self.last_sample = math.inf  # monotonic time of the last forceps block
        self.pc = PassivityController(self.profile, 1.0 / self.period)
        self.first_render: float | None = None
        self.rendered: Tissue | None = None
        cap = 1 << 16
        self.trace = np.zeros((cap, 4))  # xp, vp, ap, observed force of rendered frames
        self.n_trace = 0

    def step(self, x: float, volts: float, dt: float) -> Step:
        pending = self.pending
        if pending is not None:
            self.pending = None
            tissue, gains = pending
            if self.ctrl is None:
                self.ctrl = Controller(tissue, self.profile, 1.0 / self.period, gains)
            else:
                self.ctrl.retarget(tissue)
            self.rendered = tissue
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

    def summary(self, stream: Stream) -> dict[str, Any]:
        if self.ctrl is None:  # nothing was ever rendered: no controller figures
            return {"duration_s": self.elapsed, "frames": self.figures.frames}
        return super().summary(stream)


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
    loop: str = "elevated",
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
    loop : str
        The haptic loop's kind (:data:`tissuecli.app.play.LOOPS`).
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
        (grasp start to the first voltage rendered), ``offline`` (the law fitted to the
        recording) and ``tracking_rms_n`` (RMS of the force the display rendered minus
        what that law gives at the display's motion), ``stop_reason``.
    """
    _check_args(duration_s)
    if session is None:
        session = "live-" + datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S")
    stop = stop if stop is not None else StopFlag()
    link, info, profile = _open_display(display_url, baudrate, rate_hz, profile)
    player = _LivePlayer(
        link, None, profile, rate_hz, float(info.get("clock_hz", 1e6)), None, loop, on_message
    )  # type: ignore[arg-type]
    haptic_stop = StopFlag()
    stream = Stream(
        link,
        Encoder,
        stop=haptic_stop,
        idle_timeout_s=DISPLAY_SILENCE_S,
        before_stop=lambda: player.send(0.0),
    )
    box: dict[str, Any] = {}

    def haptic() -> None:
        try:
            box["summary"] = player.run(stream, None, None)
        except BaseException as exc:  # handed over below
            box["error"] = exc
            stop.set(signal.SIGTERM)  # the display gone: end the recording too

    grasp: dict[str, float] = {}
    state: dict[str, Any] = {"estimate": None, "handed": None, "at": -math.inf, "note": ""}

    def on_samples(block: SampleBlock) -> None:
        now = time.monotonic()
        player.last_sample = now
        if "start" not in grasp:
            above = np.nonzero(block.force > GRASP_START_N)[0]
            if above.size:
                grasp["start"] = now - float(block.host_time[-1] - block.host_time[above[0]])

    def on_record_status(status: RecordStatus) -> None:
        est = status.estimate
        state["estimate"] = est
        if est is None or not est.confident:
            player.active = False
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
                player.pending = (tissue, verdict.gains)
                state["handed"], state["at"], state["note"] = est, now, ""
            else:
                state["note"] = "not renderable: " + "; ".join(verdict.reasons)
        player.active = state["handed"] is not None and not state["note"]
        if on_status is not None and now >= state.get("next", 0.0):
            state["next"] = now + 1.0
            on_status(
                {
                    "elapsed_s": status.elapsed_s,
                    "samples": status.samples,
                    "estimate": est.describe(),
                    "rendering": player.active,
                    "energy_j": player.pc.energy_j,
                }
            )

    thread = threading.Thread(target=haptic, name="haptic loop", daemon=True)
    result = None
    # the recorder and the online fit share the interpreter with the haptic loop: hand it
    # the interpreter every 0.2 ms instead of every 5 ms
    switch = sys.getswitchinterval()
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    try:
        thread.start()
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
    except DeviceLost:
        player.active = False
        raise
    finally:
        player.active = False
        haptic_stop.set(0)
        thread.join(5.0)
        link.close()
        sys.setswitchinterval(switch)
    if "error" in box:
        raise box["error"]
    render = _jsonable(box.get("summary", {}))
    summary: dict[str, Any] = {
        "recording": {
            "path": result.path,
            "session": result.session,
            "samples": result.samples,
            "duration_s": result.duration_s,
        },
        "estimate": state["estimate"].as_dict() if state["estimate"] is not None else None,
        "rendered": player.rendered.describe() if player.rendered is not None else None,
        "render": render,
        "passivity": player.pc.summary(),
        "first_render_delay_s": (
            player.first_render - grasp["start"]
            if player.first_render is not None and "start" in grasp
            else None
        ),
        "stop_reason": result.stop_reason,
        "note": state["note"],
    }
    if fit_offline:
        summary.update(_offline_score(out, session, player))
    return _jsonable(summary)


def _offline_score(out: Any, session: str, player: _LivePlayer) -> dict[str, Any]:
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
    scored: dict[str, Any] = {"offline": tissue.describe(), "tracking_rms_n": None}
    n = player.n_trace
    if n:
        xp, vp, ap, f = player.trace[:n].T
        err = f - tissue.force(xp, vp, ap)
        scored["tracking_rms_n"] = float(np.sqrt(np.mean(err**2)))
        scored["rendered_frames"] = n
    return scored


def summary_lines(summary: dict[str, Any]) -> list[str]:
    """The summary of :func:`live` as a few lines for people."""
    rec, pas, ren = summary["recording"], summary["passivity"], summary.get("render") or {}
    delay = summary.get("first_render_delay_s")
    rms = summary.get("tracking_rms_n")
    lines = [
        f"recorded {rec['samples']} samples ({rec['duration_s']:.2f} s) to {rec['path']}, "
        f"session {rec['session']}",
        f"online estimate: {summary.get('estimate') and summary['estimate']['law']} "
        f"{summary.get('rendered') or 'never rendered'}",
        "first rendering "
        + (f"{delay:.2f} s after the grasp began" if delay is not None else "never"),
        f"display loop {ren.get('loop_rate_hz') or 0:.1f} Hz, watchdog frames "
        f"{ren.get('watchdog_frames', 0)}; scheduling "
        f"{(ren.get('realtime') or {}).get('scheduler', 'n/a')}",
        f"passivity: energy observed {pas['energy_observed_j'] * 1e3:.3f} mJ (min "
        f"{pas['energy_min_j'] * 1e3:.3f}), dissipated {pas['energy_dissipated_j'] * 1e3:.3f} "
        f"mJ on {pas['acting_frames']} frames",
        f"offline law: {summary.get('offline')}; rendered force vs offline law: RMS "
        + (f"{rms:.3f} N" if rms is not None else "n/a"),
        f"stopped: {summary.get('stop_reason', '')}",
    ]
    if summary.get("note"):
        lines.append(summary["note"])
    return lines


def _check_args(duration_s: float | None) -> None:
    if duration_s is not None and not duration_s > 0:
        raise InputError("--duration must be a positive number of seconds")
