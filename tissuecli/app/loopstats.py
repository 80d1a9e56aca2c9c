"""The haptic loop's figures: tracking, flags, energy and the loop's period, kept in
bounded memory while the loop runs (:class:`PlayFigures`), the stream's silences
(:func:`silence_figures`) and the summary made JSON (:func:`jsonable`).

The loop (:class:`~tissuecli.app.play.HostLoop`) counts through these; the fault rules
(:mod:`tissuecli.app.faults`) judge them and :mod:`tissuecli.app.summaries` prints them.
"""

from __future__ import annotations

import math
from dataclasses import asdict
from typing import Any

import numpy as np

from ..core.flags import (
    FLAG_LIMIT,
    FLAG_MODEL,
    FLAG_STALE,
    FLAG_WATCHDOG,
    NONFINITE,
    SATURATED,
    UNRENDERABLE,
)
from ..hw.protocol import Encoder
from ..hw.stream import Stream
from ..render.controller import Controller, Step, tracking_bound
from ..render.profile import DisplayProfile


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
        self.stale = self.stale_run = self.stale_run_max = 0
        self.reports_stale = False  # the display raises FLAG_STALE (it says so)
        # periods rendered from the local model of a late answer (FLAG_MODEL), and the
        # longest run of late answers of either kind
        self.modelled = self.late_run = self.late_run_max = 0
        self.reports_model = False  # the display renders from SetModel (it says so)
        self.sum_e2 = self.max_e = self.max_a = self.work = 0.0
        self.x_lo, self.x_hi = math.inf, -math.inf
        self.hist = [0] * 1001
        self.max_period = 0.0
        self.first_send: float | None = None
        # the frames the host ran through the loop, and when (its own clock): its pace
        self.first_batch: float | None = None
        self.batch_frames = 0
        self.last_batch = 0.0
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

    def handled(self, now: float, frames: int) -> None:
        """``frames`` frames run through the loop in one poll, ending at ``now`` (s)."""
        if self.first_batch is None:
            self.first_batch = now
        else:
            self.batch_frames += frames
        self.last_batch = now

    def frame_rate(self) -> float:
        """Frames the host ran through the loop per second of its own clock, after the
        first poll that brought any; 0 before two such polls."""
        span = self.last_batch - (self.first_batch or 0.0)
        return self.batch_frames / span if self.batch_frames and span > 0 else 0.0

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

    def rates(self) -> dict[str, Any]:
        """The loop's pace and the display's late answers, for the summary.

        ``loop_rate_hz`` is the rate at which the host ran the display's frames through
        the loop (its own clock); ``answer_rate_hz`` the rate at which it answered, once
        per poll that brought frames, so frames that reach it together are answered once
        (by the answer to the newest); ``unanswered_frames`` counts those others.
        ``stale_frames`` are the periods the display ran on a command that was not the
        answer to its previous frame (``FLAG_STALE``: a late answer, whichever way it was
        late), ``stale_run_max`` the longest run of them; None if the display does not
        report it. From a display that renders late answers from their local model
        (``"local_model": true``), ``modelled_frames`` are the periods it did so
        (``FLAG_MODEL``), ``stale_frames`` those beyond the model's horizon, and
        ``late_run_max`` the longest run of late answers of either kind (None
        otherwise).
        """
        return {
            "loop_rate_hz": self.frame_rate(),
            "answer_rate_hz": self.loop_rate(),
            "unanswered_frames": self.frames - self.sends,
            "stale_frames": self.stale if self.reports_stale else None,
            "stale_run_max": self.stale_run_max if self.reports_stale else None,
            "modelled_frames": self.modelled if self.reports_model else None,
            "late_run_max": self.late_run_max if self.reports_model else None,
        }

    def loop_rate(self) -> float:
        """Answers per second, once per poll that brought frames (its own clock)."""
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
        if flags & FLAG_STALE:
            self.stale += 1
            self.stale_run += 1
            self.stale_run_max = max(self.stale_run_max, self.stale_run)
        else:
            self.stale_run = 0
        if flags & (FLAG_STALE | FLAG_MODEL):
            self.modelled += bool(flags & FLAG_MODEL)
            self.late_run += 1
            self.late_run_max = max(self.late_run_max, self.late_run)
        else:
            self.late_run = 0
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
            **self.rates(),
            "period_p99_ms": self.percentile(99) * 1e3,
            "period_p50_ms": self.percentile(50) * 1e3,
            "period_max_ms": self.max_period * 1e3,
            "gains": asdict(ctrl.gains),
        }


def jsonable(value: Any) -> Any:
    """NaN and infinities (a figure with no data) become None, so the summary is JSON."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    return value
