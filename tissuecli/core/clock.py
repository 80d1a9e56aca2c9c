"""Device clocks: a repaired time base from sequence numbers and clock stamps that need
not be trusted, and the map from device time to host time.

:class:`TimeBase` checks every frame's ``(seq, clock)`` against what the last good
frames predict and turns the stream into strictly increasing device time, counting
clock jumps, clock steps, sequence restarts, wraps, lost and rejected frames.
:func:`fit_clock_map` fits host time against device time along the lower envelope of
the arrival times, which transport latency (always positive) cannot bias.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Generic, TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

MASK32 = 0xFFFFFFFF
HALF32 = 1 << 31


class TickUnwrapper:
    """Turns a wrapping 32-bit tick counter into a monotonic int64 count.

    Trusts every stamp: one absurd stamp can count a false wrap. :class:`TimeBase`
    is what checks stamps; this remains for callers that have trusted data.
    """

    def __init__(self) -> None:
        self._last: int | None = None
        self._high = 0

    def __call__(self, ticks: ArrayLike) -> NDArray[np.int64]:
        t = np.asarray(ticks, dtype=np.int64)
        if t.size == 0:
            return t
        prev = t[0] if self._last is None else self._last
        # a step back of more than half the range is a wrap, not disorder
        steps = np.diff(np.concatenate([[prev], t]))
        wraps = np.cumsum(steps < -(1 << 31))
        out = t + (self._high + wraps) * (1 << 32)
        self._high += int(wraps[-1])
        self._last = int(t[-1])
        return out


def _signed32(x: int) -> int:
    """``x`` modulo 2**32, as the nearest signed value in [-2**31, 2**31)."""
    return ((x + HALF32) & MASK32) - HALF32


# --------------------------------------------------------------------------- time base


@dataclass
class ClockFaults:
    """What :class:`TimeBase` found in a stream of frames (counts of frames or events).

    Attributes
    ----------
    frames_lost : int
        Sequence numbers missing between kept frames of one run of the sequence.
    clock_jumps : int
        Kept frames whose clock stamp disagreed with their sequence number while the
        frames around them agreed; stamped with the time their sequence number predicts.
    clock_steps : int
        Lasting steps of the device clock with the sequence continuing; the time base
        continues across the step from the sequence numbers.
    sequence_restarts : int
        Lasting restarts of the sequence (device reset); the time base continues one
        sample period after the last good sample.
    clock_wraps : int
        Genuine 32-bit wraps of the device clock.
    frames_rejected : int
        Frames with a valid CRC dropped because their sequence number and clock fit
        neither the frames before nor those after them.
    """

    frames_lost: int = 0
    clock_jumps: int = 0
    clock_steps: int = 0
    sequence_restarts: int = 0
    clock_wraps: int = 0
    frames_rejected: int = 0

    def as_dict(self) -> dict[str, int]:
        return asdict(self)

    @property
    def any(self) -> int:
        """Number of clock and sequence faults (losses and wraps are not faults)."""
        return self.clock_jumps + self.clock_steps + self.sequence_restarts + self.frames_rejected


P = TypeVar("P")


@dataclass(frozen=True)
class Stamped(Generic[P]):
    """A frame kept by :class:`TimeBase`.

    Attributes
    ----------
    payload : object
        What the caller passed with the frame (e.g. the decoded message).
    host_s : float
        Host arrival time passed with it, s.
    device_clock : int
        The device's own stamp unwrapped to 64 bits (to the nearest 2**32 of the
        previous kept frame), ticks: what the device said, not repaired.
    ticks : float
        Repaired device time since the first kept frame, ticks.
    """

    payload: P
    host_s: float
    device_clock: int
    ticks: float


@dataclass
class _Frame(Generic[P]):
    seq: int
    clock: int
    payload: P
    host_s: float
    # whether later frames confirm this one, and how many were looked at to say so
    confirmed: bool = False
    looked_at: int = -1


@dataclass
class _Anchor:
    seq: int  # of the last good frame (its clock is trusted)
    clock: int
    device_clock: int
    ticks: float


class TimeBase(Generic[P]):
    """Repairs the time base of a stream of ``(seq, clock)`` frames it does not trust.

    Each frame is checked against the last good frame: its sequence number must
    advance by 1..``max_gap`` and its clock by the sequence step times
    ``period_ticks``, within ``jitter`` of a period plus ``drift`` of the step.
    A frame is taken as good only when ``confirm - 1`` later frames continue it the
    same way, so no single frame can move the time base of the others:

    * a frame whose clock disagrees while the frames around it agree is a **clock
      jump**: kept, stamped with the time its sequence number predicts;
    * ``confirm`` frames that agree with each other but not with the last good one
      are a lasting change, and the time base continues across it: from the
      sequence numbers if they continue (**clock step**), else one period after the
      last good sample (**sequence restart**, a device reset);
    * a frame that fits nothing (an absurd or repeated sequence number) is rejected.

    Wraps of the 32-bit clock and sequence are taken modulo 2**32, so a genuine
    wrap is just a step like any other (and counted). Kept frames come out in
    order with strictly increasing time; frames wait in a window of at most
    ``window`` until they are confirmed, so output lags input by ``confirm - 1``
    frames until :meth:`finish`.

    Parameters
    ----------
    period_ticks : float or None
        Device ticks per sample (``clock_hz / rate_hz``), at least 10; ``None``
        learns it from the first frames (median step of agreeing frames).
    limit_ticks : float
        Frames at or past this repaired time are not kept and set :attr:`done`.
    confirm : int
        Frames that must agree before a frame counts as good (>= 2).
    window : int
        Most frames held unresolved; beyond it the oldest is decided alone.
    max_gap : int
        Largest sequence step read as frames lost rather than a restart.
    jitter : float
        Tolerated clock deviation, fraction of a period (< 0.5).
    drift : float
        Tolerated clock rate error, fraction of the elapsed ticks (< 0.1).

    Attributes
    ----------
    faults : ClockFaults
        Counts so far, for kept frames only.
    done : bool
        A frame reached ``limit_ticks``.
    period_ticks : float or None
        Ticks per sample in use.
    """

    def __init__(
        self,
        period_ticks: float | None,
        *,
        limit_ticks: float = math.inf,
        confirm: int = 3,
        window: int = 32,
        max_gap: int = 1 << 24,
        jitter: float = 0.25,
        drift: float = 1e-3,
    ) -> None:
        if period_ticks is not None and not (math.isfinite(period_ticks) and period_ticks >= 10):
            raise ValueError(f"period_ticks must be finite and >= 10, got {period_ticks}")
        if confirm < 2 or window < 2 * confirm or not 0 < jitter < 0.5 or not 0 <= drift < 0.1:
            raise ValueError("need confirm >= 2, window >= 2 confirm, jitter in (0, 0.5)")
        self.period_ticks = period_ticks
        self.limit_ticks = limit_ticks
        self.confirm = confirm
        self.window = window
        self.max_gap = max_gap
        self.jitter = jitter
        self.drift = drift
        self.faults = ClockFaults()
        self.done = False
        self._pending: list[_Frame[P]] = []
        self._anchor: _Anchor | None = None
        self._last_seq = 0  # of the last kept frame, for counting losses
        self._last_ticks = -math.inf  # of the last kept frame: time must increase

    # -- checks

    def _advance(self, a_seq: int, a_clock: int, b_seq: int, b_clock: int) -> int | None:
        """Clock ticks from frame a to frame b if b continues a, else None."""
        dseq = (b_seq - a_seq) & MASK32
        if not 0 < dseq <= self.max_gap:
            return None
        assert self.period_ticks is not None
        expected = dseq * self.period_ticks
        base = round(expected)
        advance = base + _signed32(b_clock - a_clock - base)
        # the tolerance stays below a period (time increases) and far below 2**31
        tol = min(self.jitter * self.period_ticks + self.drift * expected, float(1 << 28))
        return advance if abs(advance - expected) <= tol else None

    def _chain(self, i: int) -> bool:
        """Whether ``confirm - 1`` later pending frames continue pending[i] (others skipped)."""
        a = self._pending[i]
        later = self._pending[i + 1 : i + self.window]
        # frames are only ever removed before ``a`` and added at the end, so the answer
        # changes only when more frames follow it: in a storm of absurd frames each is
        # examined once instead of once per decision
        if a.looked_at == len(later) or a.confirmed:
            return a.confirmed
        need = self.confirm - 1
        seq, clock = a.seq, a.clock
        for b in later:
            if self._advance(seq, clock, b.seq, b.clock) is not None:
                seq, clock = b.seq, b.clock
                need -= 1
                if need == 0:
                    break
        a.confirmed, a.looked_at = need == 0, len(later)
        return a.confirmed

    def _fits_anchor(self, f: _Frame[P]) -> int | None:
        a = self._anchor
        assert a is not None
        return self._advance(a.seq, a.clock, f.seq, f.clock)

    # -- input and output

    def feed(self, frames: Sequence[tuple[int, int, P, float]]) -> list[Stamped[P]]:
        """Add frames ``(seq, clock, payload, host_s)``; return those now decided and kept."""
        self._pending.extend(_Frame(s & MASK32, c & MASK32, p, h) for s, c, p, h in frames)
        return self._resolve(final=False)

    def finish(self) -> list[Stamped[P]]:
        """Decide every frame still waiting (the stream has ended); return the kept ones."""
        return self._resolve(final=True)

    @property
    def waiting(self) -> int:
        """Frames received but not yet decided."""
        return len(self._pending)

    def _resolve(self, final: bool) -> list[Stamped[P]]:
        out: list[Stamped[P]] = []
        pending = self._pending
        while pending and not self.done:
            if self.period_ticks is None and not self._learn_period():
                if len(pending) < self.window and not final:
                    break
                self._reject_head()
                continue
            if self._anchor is None:
                if not self._first_anchor(out, final):
                    break
            elif not self._take_run(out, final) and not self._decide_head(out, final):
                break
        if final:
            if not self.done:
                self.faults.frames_rejected += len(pending)
            pending.clear()
        return out

    def _first_anchor(self, out: list[Stamped[P]], final: bool) -> bool:
        """Anchor time 0 at the first frame that starts a confirmed run."""
        pending = self._pending
        start = next((i for i in range(min(len(pending), self.window)) if self._chain(i)), None)
        if start is None and final and self._short_stream():
            start = 0  # fewer frames than a confirmation needs, all agreeing
        if start is None:
            if not (final or len(pending) >= self.window):
                return False
            self._reject_head()
            return True
        for _ in range(start):
            self._reject_head()
        f = pending.pop(0)
        if self._keep(out, f, 0.0, f.clock, count_lost=False):
            self._anchor = _Anchor(f.seq, f.clock, f.clock, 0.0)
        return True

    def _short_stream(self) -> bool:
        """Whether the whole stream is fewer than ``confirm`` frames that continue each other
        (a recording stopped just after it began): nothing contradicts them."""
        p = self._pending
        return (
            self.faults.frames_rejected == 0
            and len(p) < self.confirm
            and all(
                self._advance(a.seq, a.clock, b.seq, b.clock) is not None
                for a, b in zip(p, p[1:], strict=False)
            )
        )

    def _take_run(self, out: list[Stamped[P]], final: bool) -> int:
        """Keep the frames at the head that continue the anchor, one after the other, and
        are confirmed by ``confirm - 1`` successors (all of them when the stream ended)."""
        pending = self._pending
        a = self._anchor
        assert a is not None
        seq, clock = a.seq, a.clock
        steps: list[int] = []
        for f in pending:
            adv = self._advance(seq, clock, f.seq, f.clock)
            if adv is None:
                break
            steps.append(adv)
            seq, clock = f.seq, f.clock
        n = len(steps) if final else len(steps) - (self.confirm - 1)
        for kept, adv in enumerate(steps[: max(n, 0)]):
            if a.ticks + adv <= self._last_ticks:
                return kept  # behind a stamped frame: the head rule decides
            self._continue(out, pending.pop(0), adv)
            a = self._anchor
            if self.done:
                return kept + 1
        return max(n, 0)

    def _continue(self, out: list[Stamped[P]], f: _Frame[P], adv: int) -> None:
        """Keep ``f``, which continues the anchor by ``adv`` ticks, and anchor on it."""
        a = self._anchor
        assert a is not None
        device_clock = a.device_clock + adv
        if self._keep(out, f, a.ticks + adv, device_clock, count_lost=True):
            self.faults.clock_wraps += (device_clock >> 32) - (a.device_clock >> 32)
            self._anchor = _Anchor(f.seq, f.clock, device_clock, a.ticks + adv)

    def _decide_head(self, out: list[Stamped[P]], final: bool) -> bool:
        """Decide the first pending frame when it does not simply continue the anchor;
        False if that needs frames not yet received."""
        pending = self._pending
        a = self._anchor
        assert a is not None
        head = pending[0]
        fits = self._fits_anchor(head)
        head_step = (head.seq - a.seq) & MASK32
        # a later frame that continues the anchor and is confirmed overrules the head,
        # unless the head continues the anchor too and comes first
        full = final or len(pending) >= self.window
        awaited = False  # such a frame, not yet confirmed
        for j in range(1, min(len(pending), self.window)):
            g = pending[j]
            g_step = (g.seq - a.seq) & MASK32
            if fits is not None and g_step >= head_step:
                continue
            g_adv = self._fits_anchor(g)
            if g_adv is None:
                continue
            if full or self._chain(j):
                if fits is None and 0 < head_step < g_step:
                    self._stamp(out, a.ticks + g_adv)
                else:
                    self._reject_head()
                return True
            awaited = True
        if awaited:
            return False
        if fits is not None:
            if not (full or self._chain(0)):
                return False
            if a.ticks + fits > self._last_ticks:
                self._continue(out, pending.pop(0), fits)
            else:
                self._reject_head()
            return True
        if self._chain(0):
            self._reanchor(out, head_step)
            return True
        if full:
            self._reject_head()  # fits nothing, and nothing confirms where it belongs
            return True
        return False

    def _stamp(self, out: list[Stamped[P]], before_ticks: float) -> None:
        """Keep the head, whose clock is wrong, at the time its sequence number predicts,
        if that falls between the last kept frame and ``before_ticks``."""
        a = self._anchor
        assert a is not None and self.period_ticks is not None
        f = self._pending[0]
        ticks = a.ticks + ((f.seq - a.seq) & MASK32) * self.period_ticks
        after_last = ((f.seq - a.seq) & MASK32) > ((self._last_seq - a.seq) & MASK32)
        if not (after_last and self._last_ticks < ticks < before_ticks):
            self._reject_head()
            return
        self._pending.pop(0)
        device_clock = a.device_clock + _signed32(f.clock - a.clock)
        if self._keep(out, f, ticks, device_clock, count_lost=True):
            self.faults.clock_jumps += 1

    def _reanchor(self, out: list[Stamped[P]], step: int) -> None:
        """The head starts a confirmed run that does not continue the anchor: continue the
        time base across the change and anchor on the head."""
        a = self._anchor
        assert a is not None and self.period_ticks is not None
        f = self._pending.pop(0)
        last_step = (self._last_seq - a.seq) & MASK32
        continues = 0 < step <= self.max_gap and step > last_step
        if continues:  # a clock step: the sequence numbers carry the time across
            ticks = max(a.ticks + step * self.period_ticks, self._last_ticks + self.period_ticks)
        else:  # a restart: one period after the last sample
            ticks = self._last_ticks + self.period_ticks
        device_clock = a.device_clock + _signed32(f.clock - a.clock)
        if self._keep(out, f, ticks, device_clock, count_lost=continues):
            if continues:
                self.faults.clock_steps += 1
            else:
                self.faults.sequence_restarts += 1
            self._anchor = _Anchor(f.seq, f.clock, device_clock, ticks)

    def _keep(
        self, out: list[Stamped[P]], f: _Frame[P], ticks: float, device_clock: int, count_lost: bool
    ) -> bool:
        """Emit a frame, unless it reaches the limit (which ends the stream)."""
        if ticks >= self.limit_ticks:
            self.done = True
            return False
        out.append(Stamped(f.payload, f.host_s, device_clock, ticks))
        gap = (f.seq - self._last_seq) & MASK32
        if count_lost and 0 < gap <= self.max_gap:
            self.faults.frames_lost += gap - 1
        self._last_seq = f.seq
        self._last_ticks = ticks
        return True

    def _reject_head(self) -> None:
        self._pending.pop(0)
        self.faults.frames_rejected += 1

    def _learn_period(self) -> bool:
        """Ticks per sample from the first frames: the median step of agreeing neighbours."""
        rates = []
        p = self._pending
        for a, b in zip(p, p[1:], strict=False):
            dseq = (b.seq - a.seq) & MASK32
            if 0 < dseq <= 16:
                step = _signed32(b.clock - a.clock) / dseq
                if step >= 10:
                    rates.append(step)
        if len(rates) < self.confirm:
            return False
        med = float(np.median(rates))
        agree = [r for r in rates if abs(r - med) <= 0.01 * med]
        if len(agree) < self.confirm:
            return False
        self.period_ticks = float(np.mean(agree))
        return True


# --------------------------------------------------------------------------- clock map

#: the drift must be known to this many ppm (1 sigma) before time is rescaled by it
MAX_UNCERTAINTY_PPM = 50.0
#: ... and exceed its uncertainty this many times
MIN_SIGNIFICANCE = 4.0


@dataclass(frozen=True)
class ClockMap:
    """``host_s = offset_s + slope * device_s`` along the lower envelope of the arrivals.

    ``drift_ppm`` is how fast the device clock runs relative to the host
    (positive: the device clock is fast), ``drift_uncertainty_ppm`` its standard
    error. The offset includes the smallest transport latency seen, which a one-way
    stream cannot separate from the clocks' offset.

    Attributes
    ----------
    slope : float
        Host seconds per device second.
    offset_s : float
        Host time at device time 0 along the envelope, s.
    residual_rms_s : float
        RMS scatter of the window minima about the line, s.
    drift_ppm, drift_uncertainty_ppm : float
        Device clock rate error and its standard error, ppm.
    samples : int
        Samples used.
    windows : int
        Windows of device time whose minima define the envelope.
    windows_used : int
        Of those, the ones left after late windows (bursts) are trimmed.
    latency_median_s : float
        Median arrival time above the envelope, s.
    """

    slope: float
    offset_s: float
    residual_rms_s: float
    drift_ppm: float
    drift_uncertainty_ppm: float
    samples: int
    windows: int = 0
    windows_used: int = 0
    latency_median_s: float = math.nan

    @property
    def resolved(self) -> bool:
        """Whether the drift is known well enough to rescale time by it: its uncertainty is
        below :data:`MAX_UNCERTAINTY_PPM` and :data:`MIN_SIGNIFICANCE` times below it."""
        u = self.drift_uncertainty_ppm
        return bool(
            math.isfinite(u)
            and u <= MAX_UNCERTAINTY_PPM
            and abs(self.drift_ppm) >= MIN_SIGNIFICANCE * u
        )

    def as_dict(self) -> dict[str, float | int | bool | None]:
        """The fields and ``resolved``; a value that is not finite becomes None (JSON)."""
        out: dict[str, float | int | bool | None] = {
            k: (v if not isinstance(v, float) or math.isfinite(v) else None)
            for k, v in asdict(self).items()
        }
        out["resolved"] = self.resolved
        return out


@dataclass(frozen=True)
class _Line:
    intercept: float
    slope: float
    residuals: NDArray[np.float64] = field(repr=False)


def _line(x: NDArray[np.float64], y: NDArray[np.float64]) -> _Line:
    xm, ym = x.mean(), y.mean()
    dx = x - xm
    b = float(np.dot(dx, y - ym) / np.dot(dx, dx))
    a = float(ym - b * xm)
    return _Line(a, b, y - (a + b * x))


def _late(y: NDArray[np.float64], reach: int = 10) -> NDArray[np.bool_]:
    """Window minima raised by a stall or burst: above the lowest minimum within
    ``reach`` windows on *both* sides by more than the window-to-window scatter allows.

    A lasting change of level (latency quantised to USB frames makes a staircase as the
    clocks drift) has one side at its own level, so it is not taken for a burst; nor
    are windows at the ends of the session, which have only one side.
    """
    n = y.size
    late = np.zeros(n, dtype=bool)
    if n < 2 * reach + 1:
        return late
    steps = np.abs(np.diff(y))
    scale = 1.4826 * float(np.median(steps)) / math.sqrt(2.0)
    threshold = max(4.0 * scale, 1e-5)
    for j in range(reach, n - reach):
        left = y[j - reach : j].min()
        right = y[j + 1 : j + 1 + reach].min()
        late[j] = y[j] > max(left, right) + threshold
    return late


def fit_clock_map(
    device_s: ArrayLike,
    host_s: ArrayLike,
    *,
    window_s: float = 0.05,
    min_window_samples: int = 20,
    max_windows: int = 400,
) -> ClockMap | None:
    """Fit host time against device time along the lower envelope of the arrivals.

    A sample arrives at ``offset + slope * device_s + latency`` with a latency that is
    never negative but jitters, queues behind bursts and waits for USB frames. A least
    squares line through all arrivals follows that latency (a burst at the end of a
    short session tilts it by thousands of ppm). As NTP and LSL do, only the earliest
    arrivals are used: device time is cut into windows, the minimum of
    ``host - device`` in each is kept, windows raised above both their neighbourhoods
    (a stall or burst covering a whole window) are dropped, and a line is fitted
    through the rest by least squares.

    The standard error of the slope allows for residuals correlated from window to
    window (latency quantised to USB frames makes a staircase): the number of
    windows is discounted by their lag-1 autocorrelation, ``n_eff = n (1 - r) /
    (1 + r)``. Added to it in quadrature is ``q / 2T``, with ``q`` the median spacing of
    the host's arrival times and ``T`` the span: a step of the envelope by one batch
    near an end of the session cannot be told from a late window there.

    Parameters
    ----------
    device_s, host_s : array_like, shape (n,)
        Device time (increasing) and host arrival time of each sample, s.
    window_s : float
        Shortest window of device time, s.
    min_window_samples : int
        Fewest samples per window.
    max_windows : int
        Most windows.

    Returns
    -------
    ClockMap or None
        ``None`` with fewer than 10 samples or no span of device time.
    """
    d = np.asarray(device_s, dtype=float)
    h = np.asarray(host_s, dtype=float)
    ok = np.isfinite(d) & np.isfinite(h)
    d, h = d[ok], h[ok]
    if d.size < 10:
        return None
    if not np.all(np.diff(d) >= 0):
        order = np.argsort(d, kind="stable")
        d, h = d[order], h[order]
    span = float(d[-1] - d[0])
    if not span > 0:
        return None
    y = h - d  # offset + drift * d + latency
    n_win = int(min(max_windows, d.size // min_window_samples, span / window_s))
    n_win = max(n_win, 2)
    edges = np.searchsorted(d, d[0] + span * np.arange(1, n_win) / n_win)
    bounds = np.concatenate([[0], edges, [d.size]])
    xs, ys = [], []
    for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
        if hi > lo:
            k = lo + int(np.argmin(y[lo:hi]))
            xs.append(d[k])
            ys.append(y[k])
    x, ym = np.array(xs), np.array(ys)
    keep = ~_late(ym)
    fit = _line(x[keep], ym[keep])
    fit = _Line(fit.intercept, fit.slope, ym - (fit.intercept + fit.slope * x))
    # windows at the ends have one side only: drop them only if they lie further above
    # the line than any window inside does (a staircase of USB frames stays within that)
    reach = 10
    inside = keep.copy()
    inside[:reach] = inside[x.size - reach :] = False
    if inside.sum() >= 4:
        bound = 1.5 * float(np.abs(fit.residuals[inside]).max()) + 1e-5
        ends = np.ones(x.size, dtype=bool)
        ends[reach : x.size - reach] = False
        raised = ends & keep & (fit.residuals > bound)
        if raised.any():
            keep &= ~raised
            fit = _line(x[keep], ym[keep])
            fit = _Line(fit.intercept, fit.slope, ym - (fit.intercept + fit.slope * x))
    r = fit.residuals[keep]
    xk = x[keep]
    n = int(keep.sum())
    uncertainty = math.inf
    if n >= 4:
        r0 = r - r.mean()
        denom = float(np.dot(r0, r0))
        rho = float(np.dot(r0[:-1], r0[1:]) / denom) if denom > 0 else 0.0
        rho = min(max(rho, 0.0), 0.99)
        # at least 3: residuals that are one smooth pattern (n_eff -> 0) leave the
        # error of a line through a ramp of their size, sqrt(12) rms / T
        n_eff = max(n * (1.0 - rho) / (1.0 + rho), 3.0)
        sxx = float(np.sum((xk - xk.mean()) ** 2))
        # floor the scatter at 1 us: host clocks resolve no better in practice
        s2 = max(float(np.dot(r, r)), 1e-12 * n) / (n_eff - 2.0)
        uncertainty = math.sqrt(s2 / sxx)
    # the host sees arrivals in batches, so a level of the envelope is known only to
    # their spacing q; a step of q hidden near an end of the span tilts the line by q / T
    batches = np.diff(np.unique(h))
    quantum = float(np.median(batches)) if batches.size else 0.0
    uncertainty = math.hypot(uncertainty, quantum / (2.0 * span))
    slope = 1.0 + fit.slope
    if not (slope > 0 and math.isfinite(slope)):
        # arrivals all in one batch (a host descheduled through a short recording): the
        # host's stamps say nothing about the device's rate
        return None
    latency = y - (fit.intercept + fit.slope * d)
    return ClockMap(
        slope=slope,
        offset_s=fit.intercept,
        residual_rms_s=float(np.sqrt(np.mean(r**2))),
        drift_ppm=float((1.0 / slope - 1.0) * 1e6),
        drift_uncertainty_ppm=float(uncertainty / slope**2 * 1e6),
        samples=int(d.size),
        windows=int(x.size),
        windows_used=n,
        latency_median_s=float(np.median(latency)),
    )


def fit_clock_map_lsq(device_s: ArrayLike, host_s: ArrayLike) -> ClockMap | None:
    """Least squares of host time on every arrival: the estimator :func:`fit_clock_map`
    replaces, kept for comparison (benchmarks/clock_faults.py). Latency biases it."""
    d = np.asarray(device_s, dtype=float)
    h = np.asarray(host_s, dtype=float)
    if d.size < 10 or np.ptp(d) <= 0:
        return None
    fit = _line(d, h - d)
    slope = 1.0 + fit.slope
    return ClockMap(
        slope=slope,
        offset_s=fit.intercept,
        residual_rms_s=float(np.sqrt(np.mean(fit.residuals**2))),
        drift_ppm=float((1.0 / slope - 1.0) * 1e6),
        drift_uncertainty_ppm=math.nan,
        samples=int(d.size),
    )
