"""Time stamps as loggers write them: regular samples stamped by a coarse clock (a
microcontroller's milliseconds) or with jitter (host arrival times), lost samples, and
duplicate stamps, put back on the sample clock they came from.

A regular sampler stamps sample ``i`` at ``t0 + k_i dt`` plus quantisation or jitter
smaller than half a period, where ``k_i`` counts samples including lost ones. So the
sample counts ``k_i`` follow from the steps (each step is a whole number of periods,
at least one), and ``t0``, ``dt`` from a least-squares line through ``(k_i, t_i)``,
refined without outliers. When every stamp lies within half a period of that line,
the line is the time base: the stamps' noise is gone and lost samples are gaps of
whole periods. Otherwise the stamps are irregular and are kept as they are.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .errors import InputError

Array = NDArray[np.float64]


@dataclass(frozen=True)
class TimeBase:
    """What the stamps turned out to be.

    Attributes
    ----------
    regular : bool
        Whether the stamps are a regular clock plus quantisation or jitter.
    rate_hz : float
        Samples per second of the fitted clock (or from the median step, if irregular).
    residual_rms_s, residual_max_s : float
        Stamps about the fitted clock, s.
    lost : int
        Samples missing between stamps (gaps of whole periods).
    repaired : int
        Repeated or backward stamps that the clock explains (a coarse clock that stamps
        two samples alike, jitter that swaps two arrivals).
    """

    regular: bool
    rate_hz: float
    residual_rms_s: float
    residual_max_s: float
    lost: int
    repaired: int

    def describe(self) -> str:
        """One line for people."""
        if not self.regular:
            return (
                f"irregular time stamps (median rate {self.rate_hz:.6g} Hz, "
                f"{self.residual_max_s * 1e3:.3g} ms from a regular clock); kept as stamped"
            )
        text = (
            f"regular clock at {self.rate_hz:.6g} Hz, stamps within "
            f"{self.residual_max_s * 1e3:.3g} ms (RMS {self.residual_rms_s * 1e3:.3g} ms)"
        )
        if self.lost:
            text += f", {self.lost} lost sample(s)"
        if self.repaired:
            text += f", {self.repaired} repeated or backward stamp(s) repaired"
        return text


def regularise(t: Array, lines: NDArray[np.int64] | None = None) -> tuple[Array, TimeBase]:
    """Put stamps ``t`` (s, shape (n,)) on the regular clock they came from, if they did.

    Parameters
    ----------
    t : ndarray, shape (n,)
        Stamps in file order, s.
    lines : ndarray of int, shape (n,), optional
        Line numbers of the samples in their file, for messages.

    Returns
    -------
    time : ndarray, shape (n,)
        Strictly increasing times: the fitted clock's, or the stamps themselves.
    base : TimeBase

    Raises
    ------
    InputError
        If the stamps are not finite, or go backwards (or repeat) by more than a
        regular clock explains; the message names the line.
    """
    t = np.asarray(t, dtype=float)
    where = lines if lines is not None else np.arange(1, t.size + 1)
    numbers, line, base = _clock_line(t, where)
    if numbers is not None:
        # stamps already on the clock (to a millionth of a period) are kept exactly; the
        # clock's times are made only when they differ
        exact = base.residual_max_s <= 1e-6 / base.rate_hz and base.repaired == 0
        return (t if exact else _clock(numbers, line)), base
    back = np.flatnonzero(np.diff(t) <= 0)
    if back.size:
        i = int(back[0])
        verb = "repeats" if t[i + 1] == t[i] else "goes back"
        raise InputError(
            f"time {verb} at line {where[i + 1]} ({t[i]:.9g} s then {t[i + 1]:.9g} s), and "
            "the stamps do not follow a regular clock that would explain it; sort or "
            "repair the time column"
        )
    return t, base


def sample_clock(
    t: Array, lines: NDArray[np.int64] | None = None
) -> tuple[NDArray[np.int64] | None, Array, TimeBase]:
    """The regular clock behind stamps ``t``, if there is one.

    Returns
    -------
    numbers : ndarray of int, shape (n,), or None
        Sample number of each stamp on the clock (lost samples skip numbers); None
        when the stamps follow no regular clock.
    clock : ndarray, shape (n,)
        The clock's time of each sample, s (the stamps themselves if irregular).
    base : TimeBase
    """
    t = np.asarray(t, dtype=float)
    numbers, line, base = _clock_line(t, lines)
    return numbers, (t if numbers is None else _clock(numbers, line)), base


def _clock(numbers: NDArray[np.int64], line: tuple[float, float, float]) -> Array:
    """The clock's time of each sample number, s: ``line[1] + line[0] numbers``, then
    plus ``line[2]`` (the first stamp, where the clock was fitted from it)."""
    clock = numbers.astype(np.float64)
    clock *= line[0]
    clock += line[1]
    if line[2] != 0.0:
        clock += line[2]
    return clock


def _clock_line(
    t: Array, lines: NDArray[np.int64] | None = None
) -> tuple[NDArray[np.int64] | None, tuple[float, float, float], TimeBase]:
    """:func:`sample_clock` without the clock's times: the sample numbers (None if
    irregular), the clock's line (slope s per sample, offset s, and the first stamp it
    was fitted from, s) and the time base."""
    n = t.size
    where = lines if lines is not None else np.arange(1, n + 1)
    if n < 3:
        raise InputError(f"{n} sample(s) are too few to tell the sample rate")
    bad = np.flatnonzero(~np.isfinite(t))
    if bad.size:
        raise InputError(f"time is not a finite number at line {where[bad[0]]}")
    origin = float(t[0])
    if origin != 0.0:
        # the clock is fitted on times from the first stamp (epoch stamps, 1.7e9 s,
        # would leave the line's sums a few digits), and given back on the stamps' own
        numbers, (slope, offset, _), base = _clock_line(t - origin, where)
        return numbers, (slope, offset, origin), base
    # every step, or an even sample of a million of them on a long recording
    stride = max(1, (n - 1) // BLOCK)
    sampled = t[stride::stride] - t[: n - stride : stride] if stride > 1 else np.diff(t)
    positive = sampled[sampled > 0]
    if positive.size == 0 and not np.any(t[1:] > t[:-1]):
        raise InputError("time never increases; check the time column and its unit")
    typical = _median(positive) if positive.size else float(t[-1] - t[0]) / (n - 1)
    # the period: the mean of ordinary steps, so 3 and 4 ms stamps give 3.25 ms, not 3
    count = total = 0.0
    backward = 0
    for i in range(0, n - 1, BLOCK):
        steps = np.diff(t[i : i + BLOCK + 1])
        ordinary = steps[(steps > -0.75 * typical) & (steps < 1.75 * typical)]
        count, total = count + ordinary.size, total + float(np.sum(ordinary))
        backward += int(np.count_nonzero(steps <= 0))
    dt = total / count if count and total > 0 else typical
    q = resolution(t)
    worst = rms = 0.0
    for counting in (_step_counts, _locked_counts):  # the fast way, then the careful one
        period = dt
        for _ in range(3):  # count with the period, refit the period, count again
            k = None  # the last try's numbers go before the next are made
            k = counting(t, period, q)
            slope, offset, worst, rms = _fit_clock(k, t, period)
            if not slope > 0 or abs(slope - period) <= 1e-4 * period:
                break
            period = slope
        if slope > 0 and worst <= 1.01 * 0.5 * (slope + q):
            return (
                k,
                (slope, offset, 0.0),
                TimeBase(
                    regular=True,
                    rate_hz=1.0 / slope,
                    residual_rms_s=rms,
                    residual_max_s=worst,
                    lost=int(k[-1] + 1 - n),
                    repaired=backward,
                ),
            )
    return (
        None,
        (0.0, 0.0, 0.0),
        TimeBase(
            regular=False,
            rate_hz=1.0 / typical,
            residual_rms_s=rms,
            residual_max_s=worst,
            lost=0,
            repaired=0,
        ),
    )


#: stamps judged at once; longer arrays are worked through in blocks of this many, so
#: that a long recording needs a few arrays of its own length, no more
BLOCK = 1 << 20


def resolution(t: Array) -> float:
    """The coarsest decimal step (1, 2 or 5 times a power of ten, from 1 ns to 1 s) that
    every stamp's distance from the first is a whole multiple of: the logger clock's
    resolution (0 for stamps that are not quantised).

    Distances from the first stamp, so that a PC's epoch stamps (1.7e9 s since 1970)
    are judged by their steps: a tolerance relative to the stamps themselves took every
    millisecond stamp there for a whole second. What float stamps that large cannot
    hold (a few ulps, 1e-6 s at 1.7e9 s) is tolerated, no more.
    """
    if t.size == 0:
        return 0.0
    origin = float(t[0])
    head = t[:4096]
    for exponent in range(0, -10, -1):
        for mantissa in (5, 2, 1):
            q = mantissa * 10.0**exponent
            # the first stamps rule most steps out cheaply; the winner is checked on all
            if _multiples(head, q, origin) and all(
                _multiples(t[i : i + BLOCK], q, origin) for i in range(head.size, t.size, BLOCK)
            ):
                return q
    return 0.0


def _multiples(t: Array, q: float, origin: float = 0.0) -> bool:
    units = t - origin
    units /= q
    off = np.rint(units)
    np.subtract(units, off, out=off)
    np.abs(off, out=off)
    # the tolerance is at least 2e-9 of a step: most stamps pass that at once, and only
    # the others are judged against the whole of it
    near = off <= 2e-9
    if near.all():
        return True
    far = np.flatnonzero(~near)
    units, off = units[far], off[far]
    # rounding of decimal stamps and unit factors, and the ulps of large stamps
    ulps = 3.0 * np.finfo(np.float64).eps * (abs(origin) + np.abs(units) * q) / q
    tolerance = 1e-9 * np.maximum(1.0, np.abs(units)) + 1e-9 + ulps
    return bool(np.all(off <= tolerance))


def _fit_clock(k: NDArray[np.int64], t: Array, period: float) -> tuple[float, float, float, float]:
    """Least squares of ``t`` on ``k``, refit without stamps beyond 4 robust SDs: the
    slope (s per sample), the offset (s), and the largest and RMS residual (s). The
    residuals are worked out block by block, never held whole; ``period`` (s) is the
    first guess of the slope."""
    keep: NDArray[np.bool_] | None = None
    slope, offset = period, float(t[0])
    stride = max(1, t.size // (1 << 20))
    worst = total = 0.0
    for _ in range(3):
        slope, offset = _line(k, t, keep, (slope, offset))
        # the spread from every stamp, or from an even sample of a million of them
        sample = _residuals(k[::stride], t[::stride], slope, offset)
        spread = sample - _median(sample)
        np.abs(spread, out=spread)
        mad = 1.4826 * _median(spread)
        del spread
        bound = max(4 * mad, 1e-9 * abs(slope))
        inside = np.empty(t.size, dtype=bool)
        worst = total = 0.0  # of this line's residuals: the last line's are the answer
        for i in range(0, t.size, BLOCK):
            resid = (
                sample
                if stride == 1 and t.size <= BLOCK
                else _residuals(k[i : i + BLOCK], t[i : i + BLOCK], slope, offset)
            )
            total += float(resid @ resid)
            np.abs(resid, out=resid)
            worst = max(worst, float(np.max(resid)))
            np.less_equal(resid, bound, out=inside[i : i + BLOCK])
        del sample
        kept = np.count_nonzero(inside)
        if kept < max(2, t.size // 2):
            break  # no clear majority on one line: keep the fit of all stamps
        if keep is None and kept == t.size or keep is not None and np.array_equal(inside, keep):
            break  # the same stamps again: the same line
        keep = inside
    return float(slope), float(offset), worst, float(np.sqrt(total / t.size))


def _median(a: Array) -> float:
    """The median of finite values ``a`` (np.median's, without its check for NaN, which
    loads numpy.ma, and with one partial sort)."""
    n = a.size
    half = n // 2
    if n % 2:
        return float(np.partition(a, half)[half])
    part = np.partition(a, (half - 1, half))
    return 0.5 * (float(part[half - 1]) + float(part[half]))


def _residuals(k: NDArray[np.int64], t: Array, slope: float, offset: float) -> Array:
    """``t - (offset + slope k)``."""
    line = k * slope
    line += offset
    return np.subtract(t, line, out=line)


def _line(
    k: NDArray[np.int64],
    t: Array,
    keep: NDArray[np.bool_] | None,
    guess: tuple[float, float],
) -> tuple[float, float]:
    """Slope and offset of the least-squares line of ``t`` on ``k`` over the stamps
    `keep` marks (all if None), in one pass block by block: the line of the residuals
    about ``guess`` (slope, offset), which are small, so that no sum of large products
    rounds them away, with ``k`` about its middle."""
    slope0, offset0 = guess
    pivot = 0.5 * (float(k[0]) + float(k[-1]))
    count = sk = sr = skk = skr = 0.0
    for i in range(0, t.size, BLOCK):
        kk, tt = k[i : i + BLOCK], t[i : i + BLOCK]
        if keep is not None:
            kk, tt = kk[keep[i : i + BLOCK]], tt[keep[i : i + BLOCK]]
        r = kk * -slope0
        r += tt
        r -= offset0
        dk = kk - pivot
        count += dk.size
        sk += float(np.sum(dk))
        sr += float(np.sum(r))
        skk += float(dk @ dk)
        skr += float(dk @ r)
    kbar, rbar = sk / count, sr / count
    sxx = skk - sk * kbar
    ds = (skr - sk * rbar) / sxx if sxx > 0 else 0.0
    return slope0 + ds, offset0 + rbar - ds * (kbar + pivot)


def _limit(dt: float, q: float) -> float:
    """Longest step that is still one period: halfway to two periods, or, for a clock
    coarser than the period, one period plus half its resolution and a margin."""
    return max(1.5 * dt, dt + 0.5 * q + 0.1 * dt)


def _step_counts(t: Array, dt: float, q: float) -> NDArray[np.int64]:
    """Sample numbers from each step alone: enough for quantised stamps."""
    k = np.empty(t.size, dtype=np.int64)
    k[0] = 0
    limit = _limit(dt, q)
    for i in range(0, t.size - 1, BLOCK):
        steps = np.diff(t[i : i + BLOCK + 1])
        counts = np.ones(steps.size, dtype=np.int64)
        gaps = np.flatnonzero(steps >= limit)  # few: lost samples
        counts[gaps] = np.maximum(1, np.rint(steps[gaps] / dt)).astype(np.int64)
        np.cumsum(counts, out=k[i + 1 : i + 1 + counts.size])
        k[i + 1 : i + 1 + counts.size] += k[i]
    return k


def _locked_counts(t: Array, dt: float, q: float) -> NDArray[np.int64]:
    """Sample numbers judged against a clock that follows the stamps (a first-order phase
    lock), so that jitter in two successive stamps never adds or loses a sample."""
    k = np.empty(t.size, dtype=np.int64)
    k[0] = 0
    clock = float(t[0])
    limit = _limit(dt, q)
    gain = 0.05  # phase correction per sample: follows drift, averages jitter
    for i in range(1, t.size):
        ahead = float(t[i]) - clock
        count = 1 if ahead < limit else max(1, int(round(ahead / dt)))
        k[i] = k[i - 1] + count
        clock += count * dt
        clock += gain * (float(t[i]) - clock)
    return k
