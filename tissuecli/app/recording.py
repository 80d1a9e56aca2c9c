"""What every recording shares, whichever protocol the device speaks: the status the
live line shows, the blocks of samples listeners get, the result, the options, and the
online identification that listens to them."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..core.calibration import Calibration
from ..core.clock import ClockFaults, ClockMap
from ..core.errors import DeviceError
from ..hw.realtime import StopFlag


@dataclass
class RecordStatus:
    """What the live status line shows."""

    elapsed_s: float = 0.0
    samples: int = 0
    rate_hz: float = 0.0
    bad_frames: int = 0
    lost_frames: int = 0
    file_bytes: int = 0
    faults: ClockFaults = field(default_factory=ClockFaults)
    #: the online identification's current estimate (an
    #: :class:`~tissuecli.identify.online.OnlineEstimate`), None before it has one or
    #: without identification
    estimate: Any = None


@dataclass(frozen=True)
class SampleBlock:
    """Samples just handed to the writer, shape ``(n,)`` each, SI.

    Attributes
    ----------
    time : ndarray
        Device time on the repaired time base, s (not yet drift-corrected).
    position : ndarray
        Jaw closure, m.
    force : ndarray
        Grasp force, N.
    host_time : ndarray
        Host monotonic time each sample's frame arrived, s from the start of the stream.
    """

    time: NDArray[np.float64]
    position: NDArray[np.float64]
    force: NDArray[np.float64]
    host_time: NDArray[np.float64]


@dataclass
class RecordResult:
    """Summary of a finished recording.

    ``faults`` holds what the time base check found (clock jumps and steps, sequence
    restarts, rejected frames, clock wraps); ``clock_map`` the device-to-host map and
    ``time_rescaled`` whether the stored time was put on host seconds by it (only when
    its drift is resolved, see :attr:`ClockMap.resolved`).
    """

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
    faults: ClockFaults = field(default_factory=ClockFaults)
    time_rescaled: bool = False
    #: the online identification's last estimate (None without one) and why it
    #: stopped, if it did
    estimate: Any = None
    identify_note: str = ""


@dataclass(frozen=True)
class RecordOptions:
    """What a recording takes whatever the device speaks (:func:`record`'s keywords but
    the text logger's reading): the binary and the text recorders read it alike."""

    duration_s: float | None = None
    tissue: str = ""
    note: str = ""
    calibration: Calibration | None = None
    baudrate: int | None = None
    stop: StopFlag = field(default_factory=StopFlag)
    on_status: Callable[[RecordStatus], None] | None = None
    status_interval_s: float = 0.5
    flush_interval_s: float = 0.25
    idle_timeout_s: float = 2.0
    on_samples: Callable[[SampleBlock], None] | None = None
    identify: bool = True
    forgetting_s: float = 5.0


def check_not_stopped(stop: StopFlag, url: str) -> None:
    if stop:
        raise stopped_by(
            DeviceError(
                f"stopped by signal before recording from {url} began; nothing was recorded"
            ),
            stop,
        )


def stopped_by(error: DeviceError, stop: StopFlag) -> DeviceError:
    """``error`` with the exit status of the signal that ended the run, if one did."""
    if stop:
        error.exit_code = stop.exit_code
    return error


class Online:
    """The online identification as a sample listener: made before the acquisition
    loop (with the device's rate; at the first block, from the rate of its stamps, for
    a device that does not tell it), fed on the samples' time stamps (lost frames
    become holes) in batches of at least :data:`ONLINE_BATCH_S`, and switched off by
    any error.

    Everything slow is kept out of the loop: the modules the fit and its first
    estimate load (SciPy's special functions among them, a few hundred ms) are loaded
    by :meth:`prepare`, and the fit is fed in batches because an update costs much
    the same whatever its size (fed every block, a few samples at 10 kHz, it took a
    fifth of the loop's core; in batches of 0.05 s, about a twentieth).
    """

    def __init__(self, rate_hz: float, forgetting_s: float) -> None:
        self.rate_hz, self.forgetting_s = rate_hz, forgetting_s
        self.fit: Any = None
        self.note = ""
        self.pending: list[SampleBlock] = []

    def prepare(self) -> None:
        """Load what the fit needs and make it, if the rate is known; before the loop."""
        try:
            from ..identify.online import OnlineFit
            from ..identify.orthant import normal_cdf

            normal_cdf(np.zeros(1))  # the first estimate's SciPy import, here
            if math.isfinite(self.rate_hz) and self.rate_hz > 0:
                self.fit = OnlineFit(rate_hz=self.rate_hz, forgetting_s=self.forgetting_s)
        except Exception as exc:  # noqa: BLE001  (identification must never cost a recording)
            self.note = f"online identification stopped: {exc}"

    def __call__(self, block: SampleBlock) -> None:
        if self.note or block.time.size == 0:
            return
        self.pending.append(block)
        if block.time[-1] - self.pending[0].time[0] >= ONLINE_BATCH_S:
            self.feed()

    def feed(self) -> None:
        """Hand the pending blocks to the fit in one update."""
        blocks, self.pending = self.pending, []
        if self.note or not blocks:
            return
        try:
            t, x, f = (
                np.concatenate([getattr(b, k) for b in blocks])
                for k in ("time", "position", "force")
            )
            if self.fit is None:
                rate = self.rate_hz
                if not (math.isfinite(rate) and rate > 0):
                    if t.size < 2:
                        self.pending = blocks  # too few stamps to tell the rate yet
                        return
                    rate = 1.0 / float(np.median(np.diff(t)))
                from ..identify.online import OnlineFit

                self.fit = OnlineFit(rate_hz=rate, forgetting_s=self.forgetting_s)
            self.fit.update(x, f, time=t)
        except Exception as exc:  # noqa: BLE001  (identification must never cost a recording)
            self.note = f"online identification stopped: {exc}"

    def estimate(self) -> Any:
        self.feed()
        if self.fit is None or self.note:
            return None
        try:
            return self.fit.estimate()
        except Exception as exc:  # noqa: BLE001
            self.note = f"online identification stopped: {exc}"
            return None


#: the online identification is fed samples in batches spanning at least this, s
ONLINE_BATCH_S = 0.05
