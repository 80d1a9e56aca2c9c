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

The stamps are read block by block (:class:`Stamps`: an array, or a column of a file
that the files layer reads rows of), and the sample numbers are made block by block
from the steps each time they are needed, so a recording of any length is put on its
clock in the memory of a few blocks (:func:`fit_clock`).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from .errors import InputError

Array = NDArray[np.float64]
Ints = NDArray[np.int64]


class Stamps(Protocol):
    """Stamps in file order, s, read a block of rows at a time: a NumPy array, or a
    column the files layer reads from a file. A slice gives an array, never modified."""

    def __len__(self) -> int: ...

    def __getitem__(self, rows: slice, /) -> Array: ...


class Lines(Protocol):
    """The line number in its file of each row, for messages."""

    def __getitem__(self, row: int, /) -> int: ...


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


def regularise(t: Array, lines: Lines | None = None) -> tuple[Array, TimeBase]:
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
    fit = fit_clock(t, lines)
    fit.check_order()
    return (t if fit.exact else _joined(fit.times(), t.size)), fit.base


def sample_clock(
    t: Array, lines: Lines | None = None
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
    fit = fit_clock(t, lines)
    if not fit.base.regular:
        return None, t, fit.base
    numbers = np.empty(t.size, dtype=np.int64)
    row = 0
    for k in fit.numbers():
        numbers[row : row + k.size] = k
        row += k.size
    return numbers, _joined(fit.clock(), t.size), fit.base


def _joined(blocks: Iterator[Array], n: int) -> Array:
    out = np.empty(n)
    row = 0
    for block in blocks:
        out[row : row + block.size] = block
        row += block.size
    return out


@dataclass
class ClockFit:
    """Stamps and the clock found behind them (:func:`fit_clock`); the sample numbers
    and the clock's times are made block by block when asked for.

    Attributes
    ----------
    base : TimeBase
    exact : bool
        Whether the times are the stamps themselves: stamps on the clock to a
        millionth of a period with nothing repaired, or irregular stamps (kept).
    """

    base: TimeBase
    stamps: Stamps = field(repr=False)
    lines: Lines = field(repr=False)
    counts: _Counts | None = field(default=None, repr=False)
    #: the clock: slope (s per sample), offset (s), and the first stamp (s) it was
    #: fitted from
    line: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def exact(self) -> bool:
        base = self.base
        return not base.regular or (
            base.residual_max_s <= 1e-6 / base.rate_hz and base.repaired == 0
        )

    def numbers(self) -> Iterator[Ints]:
        """Sample number of each stamp on the clock, :data:`BLOCK` rows at a time (lost
        samples skip numbers); only for a regular clock."""
        if self.counts is None:
            raise ValueError("irregular stamps have no sample numbers")
        for _, k, _ in self.counts.pairs(_Shifted(self.stamps, self.line[2])):
            yield k

    def clock(self) -> Iterator[Array]:
        """The clock's time of each sample, s, :data:`BLOCK` rows at a time: ``offset +
        slope k`` (plus the first stamp, where the clock was fitted from it). Each
        block is read before it is given, so it may be written over the stamps."""
        slope, offset, origin = self.line
        for k in self.numbers():
            clock = k.astype(np.float64)
            clock *= slope
            clock += offset
            if origin != 0.0:
                clock += origin
            yield clock

    def times(self) -> Iterator[Array]:
        """The times, s, :data:`BLOCK` rows at a time: the stamps if :attr:`exact`, else
        the clock's."""
        if not self.exact:
            yield from self.clock()
            return
        for i in range(0, len(self.stamps), BLOCK):
            yield np.asarray(self.stamps[i : i + BLOCK], dtype=float)

    def check_order(self) -> None:
        """Refuse irregular stamps that go back or repeat (a regular clock explains
        those it repairs).

        Raises
        ------
        InputError
            Naming the first line where the stamps go back or repeat.
        """
        if self.base.regular:
            return
        t, n = self.stamps, len(self.stamps)
        for i in range(0, n - 1, BLOCK):
            block = np.asarray(t[i : i + BLOCK + 1], dtype=float)
            back = np.flatnonzero(block[1:] <= block[:-1])
            if back.size:
                j = i + int(back[0])
                a, b = float(block[j - i]), float(block[j - i + 1])
                verb = "repeats" if b == a else "goes back"
                raise InputError(
                    f"time {verb} at line {self.lines[j + 1]} ({a:.9g} s then {b:.9g} s), "
                    "and the stamps do not follow a regular clock that would explain it; "
                    "sort or repair the time column"
                )


class _Count:
    """Line numbers 1, 2, ... (no file behind the stamps)."""

    def __getitem__(self, row: int) -> int:
        return int(row) + 1


class _Shifted:
    """Stamps less the first one, so that the clock's sums keep their digits (epoch
    stamps, 1.7e9 s, would leave them a few)."""

    def __init__(self, stamps: Stamps, origin: float) -> None:
        self.stamps, self.origin = stamps, origin

    def __len__(self) -> int:
        return len(self.stamps)

    def __getitem__(self, rows: slice) -> Array:
        block = np.asarray(self.stamps[rows], dtype=float)
        return block - self.origin if self.origin != 0.0 else block


def fit_clock(stamps: Stamps, lines: Lines | None = None) -> ClockFit:
    """The regular clock behind ``stamps``, if there is one, read block by block.

    The stamps are read a few times over, :data:`BLOCK` rows at a time; memory holds
    a few blocks, an even sample of a million stamps and the steps of more than one
    period (lost samples: up to :data:`MAX_GAPS` of them, beyond which the sample
    numbers are counted again at each pass, or all of them where the stamps follow the
    clock only when judged against a phase lock). Stamps given as an array are worked
    on whole, as are up to two blocks of stamps (their sample is every stamp).

    Parameters
    ----------
    stamps : Stamps, shape (n,)
        Stamps in file order, s: an array, or a column of a file read a block at a time.
    lines : optional
        Line number of each row in its file (indexable by row), for messages.

    Returns
    -------
    ClockFit

    Raises
    ------
    InputError
        Fewer than 3 stamps, a stamp that is not finite, or stamps that never increase.
    """
    n = len(stamps)
    where: Lines = lines if lines is not None else _Count()
    if n < 3:
        raise InputError(f"{n} sample(s) are too few to tell the sample rate")
    origin = float(np.asarray(stamps[0:1], dtype=float)[0])
    # the clock is fitted on times from the first stamp, and given back on the stamps' own
    t = _Shifted(stamps, origin)
    # one pass: every stamp finite; an even sample of a million steps for the typical
    # step; and whether every stamp is a whole multiple of the quantum the first stamps
    # suggest (the resolution, most often, without a pass of its own)
    stride = max(1, (n - 1) // BLOCK)
    head = t[:HEAD]
    first_q = next((q for q in QUANTA if _multiples(head, q)), None)
    fits_q = True
    # stamps in an array are worked on whole (shifted, as one copy); a recording of up
    # to two blocks is held whole (as its sample is every stamp)
    in_memory = isinstance(stamps, np.ndarray)
    held: Array | None = None
    if in_memory:
        held = np.asarray(stamps, dtype=float)
        held = held - origin if origin != 0.0 else held
        t = held  # type: ignore[assignment]
    elif stride == 1:
        held = np.empty(n)
    picks = []
    last = 0.0  # the previous block's last stamp
    for i in range(0, n, BLOCK):
        block = t[i : i + BLOCK]
        if not math.isfinite(float(np.sum(block))):
            bad = np.flatnonzero(~np.isfinite(block))
            if bad.size:
                raise InputError(f"time is not a finite number at line {where[i + int(bad[0])]}")
        if held is None:
            # the one-sample steps into every `stride`-th stamp (not the whole block)
            start = (-i) % stride
            if start == 0:
                if i:
                    picks.append(block[:1] - last)  # the step from the previous block
                start = stride
            ends = block[start::stride]
            picks.append(ends - block[start - 1 :: stride][: ends.size])
            last = block[-1]
        elif not in_memory:
            held[i : i + block.size] = block
        if first_q is not None and fits_q and i + block.size > HEAD:
            fits_q = _multiples(block[max(0, HEAD - i) :], first_q)
    if held is not None:
        t = held  # type: ignore[assignment]
    # every step, or an even sample of them: the one-sample steps into every
    # `stride`-th stamp (never steps over `stride` samples, which would make the
    # typical step of irregular stamps `stride` times too long)
    if held is not None:
        ends = held[stride::stride]
        sampled = ends - held[stride - 1 :: stride][: ends.size]  # np.diff when stride is 1
        del ends
    else:
        sampled = np.concatenate(picks)
    del picks
    up = sampled > 0
    positive = sampled if up.all() else sampled[up]  # no copy when every step is forward
    del sampled, up
    if positive.size == 0 and not _increases(t):
        raise InputError("time never increases; check the time column and its unit")
    if positive.size:
        typical = _median(positive, overwrite=True)
    else:
        typical = float(t[n - 1 : n][0] - t[0:1][0]) / (n - 1)
    del positive
    # the period: the mean of ordinary steps, so 3 and 4 ms stamps give 3.25 ms, not 3
    count = total = 0.0
    backward = 0
    # read block by block, the same pass keeps the steps that may be lost samples (any
    # step beyond 1.25 of the first stamps' median step) and an even sample of a
    # million stamps, so that the sample numbers need no pass of their own (:class:`_Steps`)
    steps_kept: _Steps | None = None
    if held is None:
        first = np.diff(head)
        first = first[first > 0]
        steps_kept = _Steps(1.25 * (_median(first, overwrite=True) if first.size else typical), n)
    for i in range(0, n - 1, BLOCK):
        block = t[i : i + BLOCK + 1]
        steps = np.diff(block)
        ordinary = steps[(steps > -0.75 * typical) & (steps < 1.75 * typical)]
        count, total = count + ordinary.size, total + float(np.sum(ordinary))
        backward += int(np.count_nonzero(steps <= 0))
        if steps_kept is not None and not steps_kept.add(i, block, steps):
            steps_kept = None  # too many: the numbers are counted by a pass
    dt = total / count if count and total > 0 else typical
    if first_q is None:
        q = 0.0
    elif fits_q:
        q = first_q
    else:
        q = _resolution(t, head, QUANTA[QUANTA.index(first_q) + 1 :])
    worst = rms = 0.0
    for counting in (_StepCounts, _LockedCounts):  # the fast way, then the careful one
        period = dt
        for _ in range(3):  # count with the period, refit the period, count again
            counts = counting(t, period, q, steps_kept)
            slope, offset, worst, rms = _fit_clock(counts, t, period)
            if not slope > 0 or abs(slope - period) <= 1e-4 * period:
                break
            period = slope
        if slope > 0 and worst <= 1.01 * 0.5 * (slope + q):
            base = TimeBase(
                regular=True,
                rate_hz=1.0 / slope,
                residual_rms_s=rms,
                residual_max_s=worst,
                lost=int(counts.last + 1 - n),
                repaired=backward,
            )
            return ClockFit(base, stamps, where, counts, (slope, offset, origin))
    base = TimeBase(
        regular=False,
        rate_hz=1.0 / typical,
        residual_rms_s=rms,
        residual_max_s=worst,
        lost=0,
        repaired=0,
    )
    return ClockFit(base, stamps, where)


#: stamps judged at once; longer recordings are worked through in blocks of this many,
#: so that a recording of any length needs a few blocks, no more
BLOCK = 1 << 20
#: the first stamps, that rule most quanta out cheaply
HEAD = 4096
#: the quanta a logger's clock may have, s, coarsest first: 1, 2 or 5 times a power of
#: ten, from 5 s to 1 ns
QUANTA = tuple(m * 10.0**e for e in range(0, -10, -1) for m in (5, 2, 1))


def _increases(t: Stamps) -> bool:
    """Whether any stamp is later than the one before it."""
    return any(bool(np.any(np.diff(t[i : i + BLOCK + 1]) > 0)) for i in range(0, len(t) - 1, BLOCK))


def resolution(t: Array) -> float:
    """The coarsest decimal step (1, 2 or 5 times a power of ten, from 1 ns to 1 s) that
    every stamp's distance from the first is a whole multiple of: the logger clock's
    resolution (0 for stamps that are not quantised).

    Distances from the first stamp, so that a PC's epoch stamps (1.7e9 s since 1970)
    are judged by their steps: a tolerance relative to the stamps themselves took every
    millisecond stamp there for a whole second. What float stamps that large cannot
    hold (a few ulps, 1e-6 s at 1.7e9 s) is tolerated, no more.
    """
    t = np.asarray(t, dtype=float)
    if t.size == 0:
        return 0.0
    return _resolution(t, t[:HEAD], QUANTA, float(t[0]))


def _resolution(t: Stamps, head: Array, quanta: tuple[float, ...], origin: float = 0.0) -> float:
    """:func:`resolution` over ``quanta`` only, the first stamps ``head`` given."""
    n = len(t)
    for q in quanta:
        # the first stamps rule most quanta out cheaply; the winner is checked on all
        if _multiples(head, q, origin) and all(
            _multiples(t[i : i + BLOCK], q, origin) for i in range(head.size, n, BLOCK)
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


#: steps of more than one period (lost samples) kept by their index, at most; beyond
#: that, the sample numbers are made from the steps again at each pass
MAX_GAPS = 1 << 16


class _Counts:
    """Sample numbers of the stamps, made block by block from the stamps' steps (each a
    whole number of periods, at least one) when they are needed.

    A subclass says how many periods each step is (:meth:`steps`); this base keeps what
    the first pass found: the last number; the steps of more than one period (lost
    samples), if few; and the numbers and stamps of an even sample of a million rows
    (for the residuals' spread), which are every row, held whole, for a recording of
    up to two blocks held in memory."""

    #: steps of more than one period: their indices and periods
    gaps: tuple[Ints, Ints] | None = None

    def __init__(self, t: Stamps, dt: float, q: float, known: _Steps | None = None) -> None:
        self.dt, self.limit = dt, _limit(dt, q)
        n = len(t)
        self.stride = max(1, n // (1 << 20))
        self.whole: tuple[Ints, Array] | None = None
        if known is not None and self.gaps is None and self.limit >= known.floor:
            self._from_steps(known, n)
            return
        whole = isinstance(t, np.ndarray)
        recording = self.gaps is None and not whole
        rows: list[Ints] = []
        counts: list[Ints] = []
        found = 0
        ks, ts = [], []
        full = np.empty(n, dtype=np.int64) if whole else None
        last = 0
        for i, k, tt, steps in self._pairs(t, recording):
            if steps is not None and recording:
                at = np.flatnonzero(steps != 1)
                found += at.size
                if found > MAX_GAPS:
                    recording = False
                    rows, counts = [], []
                else:
                    rows.append(at + max(0, i - 1))
                    counts.append(steps[at])
            if full is not None:
                full[i : i + k.size] = k
            if not whole or self.stride > 1:
                first = (-i) % self.stride
                ks.append(k[first :: self.stride].copy())  # not the whole blocks
                ts.append(tt[first :: self.stride].copy())
            last = int(k[-1])
        if recording:
            self.gaps = (
                np.concatenate(rows) if rows else np.empty(0, np.int64),
                np.concatenate(counts) if counts else np.empty(0, np.int64),
            )
        self.last = last
        if full is not None:
            self.whole = (full, t)  # type: ignore[assignment]
        if whole and self.stride == 1:
            self.sample_k, self.sample_t = self.whole
        else:
            self.sample_k, self.sample_t = np.concatenate(ks), np.concatenate(ts)

    def _from_steps(self, known: _Steps, n: int) -> None:
        """What the first pass finds, from the steps kept while the period was found:
        every step of more than one period is among them."""
        rows, steps = known.arrays()
        longer = steps >= self.limit
        rows, steps = rows[longer], steps[longer]
        counts = np.maximum(1, np.rint(steps / self.dt)).astype(np.int64)
        gaps = counts != 1
        self.gaps = (rows[gaps], counts[gaps])
        self._sampled(known, n)

    def _sampled(self, known: _Steps, n: int) -> None:
        """The last number and the sample, from the steps of more than one period and
        the stamps sampled while the period was found."""
        assert self.gaps is not None
        extra = np.concatenate(([0], np.cumsum(self.gaps[1] - 1)))
        self.last = n - 1 + int(extra[-1])
        # sample row r is numbered r plus the extra periods of the steps before it
        sampled = np.arange(0, n, self.stride, dtype=np.int64)
        self.sample_k = sampled + extra[np.searchsorted(self.gaps[0], sampled, side="left")]
        self.sample_t = np.concatenate(known.sample)

    def pairs(self, t: Stamps) -> Iterator[tuple[int, Ints, Array]]:
        """``(row, numbers, stamps)`` of each block of :data:`BLOCK` rows, in order. Each
        block of stamps is read once, before its numbers are given."""
        if self.whole is not None:
            k, held = self.whole
            for i in range(0, k.size, BLOCK):
                yield i, k[i : i + BLOCK], held[i : i + BLOCK]
            return
        for i, k, tt, _ in self._pairs(t, False):
            yield i, k, tt

    def _pairs(self, t: Stamps, steps_too: bool) -> Iterator[tuple[int, Ints, Array, Ints | None]]:
        """:meth:`pairs`, with each block's periods per step (from the step into its
        first row; None if each is one) if ``steps_too``."""
        prev_t, prev_k = 0.0, 0
        for i in range(0, len(t), BLOCK):
            tt = t[i : i + BLOCK]
            first = max(0, i - 1)  # the step into the block's first row (or second)
            size = tt.size - (i == 0)
            if self.gaps is not None:
                counts = self._from_gaps(first, size)
            else:
                if i == 0:
                    steps = np.diff(tt)
                else:
                    steps = np.empty(tt.size)
                    steps[0] = tt[0] - prev_t
                    np.subtract(tt[1:], tt[:-1], out=steps[1:])
                counts = self.steps(steps)
                del steps
            if i == 0:
                k = np.empty(tt.size, dtype=np.int64)
                k[0] = 0
                if counts is None:
                    k[1:] = np.arange(1, tt.size)
                else:
                    np.cumsum(counts, out=k[1:])
            elif counts is None:
                k = np.arange(prev_k + 1, prev_k + 1 + tt.size, dtype=np.int64)
            else:
                k = np.cumsum(counts)
                k += prev_k
            prev_t, prev_k = float(tt[-1]), int(k[-1])
            yield i, k, tt, (counts if counts is not None or not steps_too else _ONES)

    def _from_gaps(self, first: int, size: int) -> Ints | None:
        assert self.gaps is not None
        rows, periods = self.gaps
        lo, hi = np.searchsorted(rows, (first, first + size))
        if lo == hi:
            return None
        counts = np.ones(size, dtype=np.int64)
        counts[rows[lo:hi] - first] = periods[lo:hi]
        return counts

    def steps(self, steps: Array) -> Ints | None:
        """How many periods each of ``steps`` is; None if each is one."""
        raise NotImplementedError


#: a block of steps of one period each
_ONES = np.ones(0, dtype=np.int64)


class _Steps:
    """The steps of ``floor`` s or more (by index) and an even sample of a million stamps
    (every ``n // 2**20``-th, as :class:`_Counts` samples them), kept block by block."""

    def __init__(self, floor: float, n: int) -> None:
        self.floor, self.n = floor, n
        self.stride = max(1, n // (1 << 20))
        self.rows: list[Ints] = []
        self.steps: list[Array] = []
        self.sample: list[Array] = []
        self.found = 0

    def add(self, i: int, block: Array, steps: Array) -> bool:
        """Keep what stamps ``block`` (rows ``i``, ``i + 1``, ...; the first of the next
        block last) and their steps hold; False once the steps kept are too many."""
        at = np.flatnonzero(steps >= self.floor)
        self.found += at.size
        if self.found > MAX_GAPS or not self.floor > 0:
            return False
        self.rows.append(at + i)
        self.steps.append(steps[at])
        rows = block if i + BLOCK >= self.n - 1 else block[:BLOCK]
        self.sample.append(rows[(-i) % self.stride :: self.stride].copy())
        return True

    def arrays(self) -> tuple[Ints, Array]:
        if not self.rows:
            return np.empty(0, np.int64), np.empty(0)
        return np.concatenate(self.rows), np.concatenate(self.steps)


class _StepCounts(_Counts):
    """Sample numbers from each step alone: enough for quantised stamps."""

    def steps(self, steps: Array) -> Ints | None:
        gaps = np.flatnonzero(steps >= self.limit)  # few: lost samples
        if not gaps.size:
            return None
        counts = np.ones(steps.size, dtype=np.int64)
        counts[gaps] = np.maximum(1, np.rint(steps[gaps] / self.dt)).astype(np.int64)
        return counts


class _LockedCounts(_Counts):
    """Sample numbers judged against a clock that follows the stamps (a first-order phase
    lock), so that jitter in two successive stamps never adds or loses a sample.

    The lock runs once over the stamps; the steps that are not one period (lost
    samples) are kept, by the step's index, and the numbers made from them."""

    def __init__(self, t: Stamps, dt: float, q: float, known: _Steps | None = None) -> None:
        limit = _limit(dt, q)
        gain = 0.05  # phase correction per sample: follows drift, averages jitter
        rows: list[int] = []
        counts: list[int] = []
        clock: float | None = None
        for i in range(0, len(t), BLOCK):
            stamps = t[i : i + BLOCK].tolist()
            if clock is None:
                clock = stamps[0]
                stamps = stamps[1:]
                j = 0  # step j ends at stamp j + 1
            else:
                j = i - 1
            for stamp in stamps:
                ahead = stamp - clock
                if ahead < limit:
                    count = 1
                else:
                    count = max(1, int(round(ahead / dt)))
                    if count != 1:
                        rows.append(j)
                        counts.append(count)
                j += 1
                clock += count * dt
                clock += gain * (stamp - clock)
        self.gaps = (np.array(rows, dtype=np.int64), np.array(counts, dtype=np.int64))
        if known is not None:
            self.dt, self.limit = dt, limit
            self.stride = max(1, len(t) // (1 << 20))
            self.whole = None
            self._sampled(known, len(t))
            return
        super().__init__(t, dt, q)


def _fit_clock(counts: _Counts, t: Stamps, period: float) -> tuple[float, float, float, float]:
    """Least squares of ``t`` on the sample numbers, refit without stamps beyond 4
    robust SDs: the slope (s per sample), the offset (s), and the largest and RMS
    residual (s). Two passes over the stamps a fit, block by block; ``period`` (s) is
    the first guess of the slope. The stamps a fit keeps are those within its bound of
    the line before it, judged again block by block, never held."""
    n = len(t)
    keep: tuple[float, float, float] | None = None  # the line and bound that keep stamps
    slope, offset = period, float(t[0:1][0])
    worst = total = 0.0
    for _ in range(3):
        slope, offset = _line(counts, t, keep, (slope, offset))
        # the spread from every stamp, or from an even sample of a million of them
        sample = _residuals(counts.sample_k, counts.sample_t, slope, offset)
        spread = sample.copy()  # the median's partial sort, then the spread, in one array
        middle = _median(spread, overwrite=True)
        np.subtract(sample, middle, out=spread)
        np.abs(spread, out=spread)
        mad = 1.4826 * _median(spread, overwrite=True)
        del spread
        bound = max(4 * mad, 1e-9 * abs(slope))
        worst = total = 0.0  # of this line's residuals: the last line's are the answer
        kept = 0
        same = keep is not None
        for i, k, tt in counts.pairs(t):
            # held whole, the sample's residuals are every row's
            whole = counts.whole is not None and counts.stride == 1
            resid = sample[i : i + BLOCK] if whole else _residuals(k, tt, slope, offset)
            total += float(resid @ resid)
            np.abs(resid, out=resid)
            worst = max(worst, float(np.max(resid)))
            inside = resid <= bound
            kept += int(np.count_nonzero(inside))
            if same and keep is not None:
                same = bool(np.array_equal(inside, _kept(k, tt, keep)))
        del sample
        if kept < max(2, n // 2):
            break  # no clear majority on one line: keep the fit of all stamps
        if keep is None and kept == n or same:
            break  # the same stamps again: the same line
        keep = (slope, offset, bound)
    return float(slope), float(offset), worst, float(np.sqrt(total / n))


def _kept(k: Ints, t: Array, keep: tuple[float, float, float]) -> NDArray[np.bool_]:
    """Which stamps lie within ``keep[2]`` of the line ``keep[:2]`` (slope, offset)."""
    resid = _residuals(k, t, keep[0], keep[1])
    np.abs(resid, out=resid)
    return resid <= keep[2]


def _median(a: Array, *, overwrite: bool = False) -> float:
    """The median of finite values ``a`` (np.median's, without its check for NaN, which
    loads numpy.ma, and with one partial sort; of ``a`` itself, reordered, if
    ``overwrite``)."""
    n = a.size
    half = n // 2
    if n > 1 << 15:
        middle = _middle(a, (half,) if n % 2 else (half - 1, half))
        if middle is not None:
            return middle[0] if n % 2 else 0.5 * (middle[0] + middle[1])
    part = a if overwrite else a.copy()
    if n % 2:
        part.partition(half)
        return float(part[half])
    part.partition((half - 1, half))
    return 0.5 * (float(part[half - 1]) + float(part[half]))


def _middle(a: Array, ranks: tuple[int, ...]) -> tuple[float, ...] | None:
    """The values of ranks ``ranks`` (adjacent, 0-based) in ``a`` sorted, found among
    the values between two quantiles of an even sample of ``a`` that surely hold them:
    two comparisons over ``a`` and a partial sort of the few values between, instead
    of a partial sort of all. None when the sample's quantiles miss them (the caller
    sorts all)."""
    n = a.size
    sample = np.sort(a[:: n // 4096])
    m = sample.size
    reach = 4 * int(math.sqrt(m)) + 8  # the ranks lie this far from their estimate
    lo = float(sample[max(0, ranks[0] * m // n - reach)])
    hi = float(sample[min(m - 1, ranks[-1] * m // n + reach)])
    # steps of stamps on a clock take a few values: the ranks often fall in one run of
    # equal values, which two counts find
    value = float(sample[min(m - 1, ranks[0] * m // n)])
    below = int(np.count_nonzero(a < value))
    if below <= ranks[0] and ranks[-1] < below + int(np.count_nonzero(a == value)):
        return tuple(value for _ in ranks)
    if lo == hi:
        return None
    below = int(np.count_nonzero(a < lo))
    between = a[(a >= lo) & (a <= hi)]
    if not (below <= ranks[0] and ranks[-1] < below + between.size) or between.size > n // 4:
        return None
    kth = tuple(r - below for r in ranks)
    between.partition(kth)
    return tuple(float(between[k]) for k in kth)


def median(a: Array) -> float:
    """The median of ``a`` as :func:`numpy.median` gives it (NaN if any value is NaN),
    without loading ``numpy.ma`` (50 ms on the first call in a process)."""
    a = np.asarray(a, dtype=float)
    if a.size == 0 or np.isnan(a).any():
        return float("nan")
    return _median(a)


def _residuals(k: NDArray[np.int64], t: Array, slope: float, offset: float) -> Array:
    """``t - (offset + slope k)``."""
    line = k * slope
    line += offset
    return np.subtract(t, line, out=line)


def _line(
    counts: _Counts,
    t: Stamps,
    keep: tuple[float, float, float] | None,
    guess: tuple[float, float],
) -> tuple[float, float]:
    """Slope and offset of the least-squares line of ``t`` on the sample numbers over
    the stamps within ``keep[2]`` of the line ``keep[:2]`` (all if None), in one pass
    block by block: the line of the residuals about ``guess`` (slope, offset), which
    are small, so that no sum of large products rounds them away, with the numbers
    about their middle."""
    slope0, offset0 = guess
    pivot = 0.5 * counts.last
    count = sk = sr = skk = skr = 0.0
    for _, kk, tt in counts.pairs(t):
        if keep is not None:
            inside = _kept(kk, tt, keep)
            kk, tt = kk[inside], tt[inside]
        dk = kk.astype(np.float64)  # exact (numbers below 2**53), and cast once
        r = dk * -slope0
        r += tt
        r -= offset0
        dk -= pivot
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
