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
    numbers, clock, base = sample_clock(t, where)
    if numbers is not None:
        steps = np.diff(t)
        # stamps already on the clock (to a millionth of a period) are kept exactly
        exact = base.residual_max_s <= 1e-6 / base.rate_hz and bool(np.all(steps > 0))
        return (t if exact else clock), base
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
    n = t.size
    where = lines if lines is not None else np.arange(1, n + 1)
    if n < 3:
        raise InputError(f"{n} sample(s) are too few to tell the sample rate")
    bad = np.flatnonzero(~np.isfinite(t))
    if bad.size:
        raise InputError(f"time is not a finite number at line {where[bad[0]]}")
    steps = np.diff(t)
    positive = steps[steps > 0]
    if positive.size == 0:
        raise InputError("time never increases; check the time column and its unit")
    typical = float(np.median(positive))
    # the period: the mean of ordinary steps, so 3 and 4 ms stamps give 3.25 ms, not 3
    ordinary = steps[(steps > -0.75 * typical) & (steps < 1.75 * typical)]
    dt = float(np.mean(ordinary)) if ordinary.size and np.mean(ordinary) > 0 else typical
    q = resolution(t)
    resid = np.zeros(n)
    for counting in (_step_counts, _locked_counts):  # the fast way, then the careful one
        period = dt
        for _ in range(3):  # count with the period, refit the period, count again
            k = counting(t, period, q)
            slope, offset, resid = _fit_clock(k, t)
            if not slope > 0 or abs(slope - period) <= 1e-4 * period:
                break
            period = slope
        worst = float(np.max(np.abs(resid)))
        if slope > 0 and worst <= 1.01 * 0.5 * (slope + q):
            return (
                k,
                offset + slope * k,
                TimeBase(
                    regular=True,
                    rate_hz=1.0 / slope,
                    residual_rms_s=float(np.sqrt(np.mean(resid**2))),
                    residual_max_s=worst,
                    lost=int(k[-1] + 1 - n),
                    repaired=int(np.count_nonzero(steps <= 0)),
                ),
            )
    return (
        None,
        t,
        TimeBase(
            regular=False,
            rate_hz=1.0 / typical,
            residual_rms_s=float(np.sqrt(np.mean(resid**2))),
            residual_max_s=float(np.max(np.abs(resid))),
            lost=0,
            repaired=0,
        ),
    )


def resolution(t: Array) -> float:
    """The coarsest decimal step (1, 2 or 5 times a power of ten, from 1 ns to 1 s) that
    every stamp is a whole multiple of: the logger clock's resolution (0 for stamps that
    are not quantised)."""
    for exponent in range(0, -10, -1):
        for mantissa in (5, 2, 1):
            q = mantissa * 10.0**exponent
            units = t / q
            if np.all(
                np.abs(units - np.rint(units))
                <= 1e-6 * np.maximum(1.0, np.abs(units)) * 1e-3 + 1e-9
            ):
                return q
    return 0.0


def _fit_clock(k: NDArray[np.int64], t: Array) -> tuple[float, float, Array]:
    """Least squares of ``t`` on ``k``, refit without stamps beyond 4 robust SDs: the
    slope (s per sample), the offset (s) and every stamp's residual (s)."""
    keep = np.ones(t.size, bool)
    for _ in range(3):
        slope, offset = np.polyfit(k[keep], t[keep], 1)
        resid = t - (offset + slope * k)
        mad = 1.4826 * float(np.median(np.abs(resid - np.median(resid))))
        inside = np.abs(resid) <= max(4 * mad, 1e-9 * abs(slope))
        if np.count_nonzero(inside) < max(2, t.size // 2):
            break  # no clear majority on one line: keep the fit of all stamps
        keep = inside
    return float(slope), float(offset), resid


def _limit(dt: float, q: float) -> float:
    """Longest step that is still one period: halfway to two periods, or, for a clock
    coarser than the period, one period plus half its resolution and a margin."""
    return max(1.5 * dt, dt + 0.5 * q + 0.1 * dt)


def _step_counts(t: Array, dt: float, q: float) -> NDArray[np.int64]:
    """Sample numbers from each step alone: enough for quantised stamps."""
    steps = np.diff(t)
    counts = np.where(steps < _limit(dt, q), 1, np.maximum(1, np.rint(steps / dt)))
    return np.concatenate([[0], np.cumsum(counts.astype(np.int64))])


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
