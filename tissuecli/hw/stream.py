"""The skeleton every acquisition loop shares: START, poll, sequence tracking, a silent
device taken as lost, status cadence, a clean stop and a final STOP.

:func:`tissuecli.app.record.record` (forceps samples to a file) and
:func:`tissuecli.app.play.play` (display frames through the control loop) differ only
in what they do with each batch of frames and how long they wait between polls.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from types import TracebackType
from typing import Any, Protocol

from ..core.errors import DeviceLost
from .protocol import Message, SequenceTracker
from .realtime import StopFlag


class Source(Protocol):
    """What a stream reads: an open :class:`~tissuecli.hw.device.Device` (or a bare
    :class:`~tissuecli.hw.link.Link`)."""

    url: str

    def command(self, name: str) -> None: ...

    def poll(self) -> list[Any]: ...


class Stream:
    """One device streaming frames of one type, from START to STOP.

    Entering sends START; leaving always tries ``before_stop`` (the play loop's
    0 V) and then STOP, ignoring a line that is already gone. Between the two the
    owner loops::

        with Stream(link, Sample, stop=stop, idle_timeout_s=2.0) as stream:
            while stream.running():
                frames = stream.poll()
                now = time.monotonic()
                if not frames:
                    stream.check_idle(now)
                ...
                if stream.status_due(now):
                    ...

    Parameters
    ----------
    link : Source
        An open, identified device (:class:`~tissuecli.hw.device.Device`).
    frame_type : type of Message
        The frames the loop is about (Sample, Encoder); others are ignored.
    stop : StopFlag
        Set by SIGINT/SIGTERM: :meth:`running` then returns False.
    idle_timeout_s : float
        A device that sends no frame for this long is taken as lost, s.
    status_interval_s : float
        Cadence of :meth:`status_due`, s.
    before_stop : callable, optional
        Run before the final STOP (e.g. switch the solenoid off).
    track_sequence : bool
        Count losses in :attr:`seqs` for every frame received; an owner that checks
        frames itself and keeps only some (the recorder) counts its own.

    Attributes
    ----------
    seqs : SequenceTracker
        Frames lost and sequence restarts so far (if ``track_sequence``).
    reason : str
        Why the stream ended: ``"duration reached"`` unless the stop flag or a
        lost device ended it (or the owner says otherwise).
    t_start : float
        Monotonic time of START, s.
    longest_silence_s : float
        Longest time the device went without a frame while this host was running, s.
    host_stall_s : float
        Longest time this host itself did not poll (descheduled on a busy machine), s:
        such a stall is not held against the device (see :meth:`check_idle`).
    """

    def __init__(
        self,
        link: Source,
        frame_type: type[Message],
        *,
        stop: StopFlag,
        idle_timeout_s: float,
        status_interval_s: float = math.inf,
        before_stop: Callable[[], None] | None = None,
        track_sequence: bool = True,
    ) -> None:
        self.link = link
        self.frame_type = frame_type
        self.stop = stop
        self.idle_timeout_s = idle_timeout_s
        self.status_interval_s = status_interval_s
        self.before_stop = before_stop
        self.track_sequence = track_sequence
        self.seqs = SequenceTracker()
        self.reason = "duration reached"
        self.t_start = self.last_frame = self.next_status = self.last_poll = math.nan
        self.listened = math.nan
        self.longest_silence_s = self.host_stall_s = 0.0
        self.frames_seen = 0

    def __enter__(self) -> Stream:
        self.link.command("start")
        self.t_start = self.last_frame = self.last_poll = self.listened = time.monotonic()
        self.next_status = self.t_start + self.status_interval_s
        return self

    def running(self) -> bool:
        """False once the stop flag is set (the reason is then recorded)."""
        if self.stop:
            self.reason = self.stop.reason or "interrupted by signal"
            return False
        return True

    def poll(self) -> list[Message]:
        """The frames of the stream's type that have arrived (sequence numbers tracked if
        ``track_sequence``)."""
        before = time.monotonic()
        # the wait for the first frame is the loop's own choice, not a stall
        stall = before - self.last_poll if self.frames_seen else 0.0
        if stall > 0.5 * self.idle_timeout_s:
            # this host was not running (descheduled): the device's silence is counted
            # from when it could have been heard again, not held against it
            self.last_frame += stall
        self.host_stall_s = max(self.host_stall_s, stall)
        # all the device sent before this moment is read by this poll
        self.listened = before
        frames = [m for m in self.link.poll() if isinstance(m, self.frame_type)]
        now = self.last_poll = time.monotonic()
        if frames:
            self.frames_seen += len(frames)
            if self.track_sequence:
                for m in frames:
                    self.seqs.update(m.seq)  # type: ignore[attr-defined]
            if self.frames_seen > len(frames):  # silences between frames, not before
                self.longest_silence_s = max(self.longest_silence_s, before - self.last_frame)
            self.last_frame = now
        return frames

    def check_idle(self, now: float) -> None:
        """Raise :class:`DeviceLost` if no frame arrived for ``idle_timeout_s``.

        The silence is counted up to the start of the last poll, not to ``now``: only
        that poll proves the device sent nothing, and this host may have been
        descheduled for a while since it began (before the first frame too).
        """
        if min(now, self.listened) - self.last_frame > self.idle_timeout_s:
            timeout = self.idle_timeout_s
            stalled = (
                f" (this host itself was descheduled for up to {_span(self.host_stall_s)})"
                if self.host_stall_s > 0.2 * timeout
                else ""
            )
            raise DeviceLost(
                f"no {self.frame_type.__name__} frame from {self.link.url} for "
                f"{_span(timeout)}{stalled}{self.limit_note}"
            )

    #: Said after a lost device's message: how the silence limit was chosen.
    limit_note = ""

    def status_due(self, now: float) -> bool:
        """True once every ``status_interval_s``."""
        if now >= self.next_status:
            self.next_status = now + self.status_interval_s
            return True
        return False

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if isinstance(exc, DeviceLost):
            self.reason = f"device lost: {exc}"
        try:
            if self.before_stop is not None:
                self.before_stop()
            self.link.command("stop")
        except DeviceLost:
            pass


def _span(seconds: float) -> str:
    """``100 ms`` or ``2 s``."""
    return f"{seconds * 1e3:.3g} ms" if seconds < 1 else f"{seconds:.3g} s"
