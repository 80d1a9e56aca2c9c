"""A closure read by a coarse ADC at a high rate, rebuilt from its level crossings.

At 8-10 bits and kilohertz rates the closure holds one ADC level for tens of samples and
then steps: a staircase. Its error is not white noise a smoother can average out but a
sawtooth of one step peak to peak whose period is the time between steps, as slow as
the motion itself, so a polynomial smoother must span many steps before its speed, and
above all its acceleration, stop following the stairs (on an 8-bit squeeze at 8.4 kHz
the cubic Savitzky-Golay acceleration's error was 0.1-3.4 times the true
acceleration's SD over windows of 321-81 samples).

The times the closure crosses the thresholds between levels are known far better:
within a sample, where a level's value is known only within a step. Through the
crossings (the threshold's value between the two samples either side) a monotone
cubic (PCHIP) passes, and where the closure turns (it crosses one threshold twice,
there and back) a point is added at the turn, as far past the threshold as a
parabola through the nested crossings puts it. The rebuilt closure's error is then the
crossing time's (a speed times a fraction of a sample) plus the curvature between
crossings: on that squeeze its speed error was 2.7 times smaller and its
acceleration's 2.5 times smaller at 321 samples, 4.7 times at 81.

Noise on the closure before the ADC makes the reading chatter between two levels near
each crossing. Consecutive transitions across one threshold with each level held
briefly between them are taken together: an odd number is one crossing, placed where
the samples on either side of it would be were they not interleaved (their count from
its first transition); an even number touches the threshold and returns. Where the
noise is of a quarter of a step or more the reading moves every few samples and is no
staircase (:func:`staircase` says so): there the rebuilt closure was no better than the
reading, and the closure is left as read.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .base import Array

#: a closure is a staircase where it holds a level for this many samples on average
#: (the fraction of repeated values is 1 - 1 / STAIR_SAMPLES); below it the steps come
#: nearly every sample and the level crossings tell no more than the samples
STAIR_SAMPLES = 4.0

#: levels are an ADC's where every gap between distinct values is a whole number of the
#: smallest gap within this fraction of it
LEVEL_TOLERANCE = 1e-3


def adc_step(x: Array) -> float | None:
    """The smallest gap between distinct values of ``x`` (m) where every gap is a whole
    number of it (the ADC's step), else None."""
    levels = np.unique(x[np.isfinite(x)])
    if levels.size < 3:
        return None
    gaps = np.diff(levels)
    step = float(gaps.min())
    if not step > 0:
        return None
    ratio = gaps / step
    if np.max(np.abs(ratio - np.round(ratio))) > LEVEL_TOLERANCE:
        return None
    return step


def staircase(
    x: Array, dt: float, valid: NDArray[np.bool_] | None = None
) -> tuple[Array, float] | None:
    """The closure ``x`` (m, shape (n,), sampled every ``dt`` s) rebuilt from its level
    crossings where it is a staircase (its values on an ADC's levels, held
    :data:`STAIR_SAMPLES` samples or more on average); None where it is not.

    Parameters
    ----------
    x : ndarray, shape (n,)
        The closure as read, m.
    dt : float
        Sample interval, s.
    valid : ndarray of bool, shape (n,), optional
        Samples to trust; a step across untrusted ones is read at their middle.

    Returns
    -------
    closure : ndarray, shape (n,)
        The rebuilt closure, m: through every crossing; before the first and after the
        last, within half a step of the reading.
    sd : float
        The SD of the white noise a smoother would average alike, m. Each crossing's
        time is known within a sample, its value so within a speed times a sample:
        SD ``step / sqrt(12) / s`` for ``s`` samples a step, one crossing every ``s``
        samples, which a window averages as it would white noise of SD
        ``step / sqrt(12 s)`` on every sample (the reading's own sawtooth has
        ``step / sqrt(12)``, and a window does not average it down).
    None
        Where ``x`` is no staircase.
    """
    n = x.size
    ok = np.ones(n, bool) if valid is None else np.asarray(valid, bool)
    if n < 8 or not np.all(np.isfinite(x[ok])):
        return None
    step = adc_step(x[ok])
    if step is None:
        return None
    base = float(np.min(x[ok]))
    codes = np.round((x - base) / step)
    if not ok.all():
        # an untrusted sample reads as the nearer trusted one: a step across a hole is
        # read at its middle (left out, it went unread, and the rebuilt closure stayed
        # a step off until the next crossing)
        kept = np.flatnonzero(ok)
        after = np.clip(np.searchsorted(kept, np.arange(n)), 0, kept.size - 1)
        before = np.clip(after - 1, 0, kept.size - 1)
        here = np.arange(n)
        nearer = np.where(here - kept[before] <= kept[after] - here, kept[before], kept[after])
        codes = codes[np.where(ok, here, nearer)]
    moved = codes[1:] != codes[:-1]
    steps, pairs = np.count_nonzero(moved), n - 1
    if steps < 4 or pairs < STAIR_SAMPLES * steps:
        return None
    t, v = _crossings(codes, moved, dt)
    if t.size < 4:
        return None
    curve = _through(t, v)
    time = np.arange(n) * dt
    u = curve(time)
    # before the first crossing and after the last the closure goes on at the speed it
    # had there (a cubic's curvature, carried on, runs off), within the reading's step
    slope = curve.derivative()(t[[0, -1]])
    for ends, i in ((time < t[0], 0), (time > t[-1], -1)):
        line = v[i] + slope[i] * (time[ends] - t[i])
        u[ends] = np.clip(line, codes[ends] - 0.5, codes[ends] + 0.5)
    return base + step * u, step / math.sqrt(12.0 * pairs / steps)


def _through(t: Array, v: Array) -> Any:
    """A monotone cubic (PCHIP) through the points ``t`` (s), ``v`` (steps), shape (m,),
    but for the spans either side of a turn (a point beyond both its neighbours): there
    the parabola with its vertex at the turn, the shape of a smooth closure near it.

    PCHIP enters a turn at the harmonic mean of the chords about the crossing before
    it, short of the parabola's slope (three quarters of it at even spacing): through a
    slow 8-bit squeeze's turns the rebuilt speed fell short of the truth's, a misfit a
    friction term took up (paper scene 5520345, x^3+xdot+sign(xdot)+xddot 2.1 nats
    ahead of the truth, 0.5 with the parabola). Slopes from the parabola through every
    point and its neighbours as well took the rebuilt acceleration's shortfall through
    the fit's filter only from 0.6 to 0.5 %, and put predict's true law on an 8.4 kHz
    8-bit squeeze (scene 6630428) 4.6 times the noise floor off, where this is 1.3."""
    from scipy.interpolate import CubicHermiteSpline, PchipInterpolator  # only here

    slope = PchipInterpolator(t, v).derivative()(t)
    if t.size >= 3:
        i = 1 + np.flatnonzero((v[1:-1] - v[:-2]) * (v[1:-1] - v[2:]) > 0)  # the turns
        for j in (i - 1, i + 1):  # the parabola's slope at each neighbour: twice the chord
            slope[j] = 2.0 * (v[j] - v[i]) / (t[j] - t[i])
        slope[i] = 0.0
        # on the span beyond each neighbour, within three times that span's chord
        # (Fritsch and Carlson's bound for a monotone cubic): a smooth turn's parabola
        # gives at most twice it, but a reading that jumps two levels in one sample
        # put a turn one sample from its neighbour, and the cubic beyond, 20 samples
        # long, swung three steps off the readings
        for j, k in ((i - 1, i - 2), (i + 1, i + 2)):
            ok = (k >= 0) & (k < t.size)
            j, k = j[ok], k[ok]
            chord = (v[k] - v[j]) / (t[k] - t[j])
            # where the span beyond runs on the way the slope does (a span that turns
            # back or holds a level is beside another turn, whose shape governs it)
            same = (np.sign(slope[j]) == np.sign(chord)) & (chord != 0)
            bound = np.minimum(np.abs(slope[j]), 3 * np.abs(chord))
            slope[j] = np.where(same, np.sign(chord) * bound, slope[j])
    return CubicHermiteSpline(t, v, slope, extrapolate=False)


def _crossings(codes: Array, moved: NDArray[np.bool_], dt: float) -> tuple[Array, Array]:
    """The points (time from the first sample, s; value in steps) the rebuilt closure
    passes through: one per crossing of a threshold, and one at each turn between two
    crossings of the same threshold (:func:`_apex`)."""
    ch = np.flatnonzero(moved)  # a step between samples i and i + 1
    tt = (ch + 0.5) * dt
    lev = 0.5 * (codes[ch] + codes[ch + 1])  # the threshold crossed
    gaps = np.diff(ch)  # samples held between consecutive transitions
    # runs of transitions across one threshold, each level held briefly between them:
    # chatter. A level held longer is a true excursion past the threshold (a turn) and
    # starts a new run: longer than a quarter of the time between the crossings of the
    # thresholds either side (noise of a fifth of a step chatters over some 0.4 of it)
    same = lev[1:] == lev[:-1]
    fresh = np.concatenate([[True], ~same])  # a new threshold
    base_start = np.flatnonzero(fresh)
    base_stop = np.concatenate([base_start[1:], [ch.size]]) - 1
    outer = ch[np.clip(base_stop + 1, 0, ch.size - 1)] - ch[np.clip(base_start - 1, 0, ch.size - 1)]
    known = (base_start > 0) & (base_stop + 1 < ch.size)
    span = np.where(known, outer, np.inf)[np.cumsum(fresh)[:-1] - 1]  # at each gap
    first = np.concatenate([[True], ~same | (gaps > span / 4)])
    start = np.flatnonzero(first)
    stop = np.concatenate([start[1:], [ch.size]]) - 1
    cluster = np.cumsum(first) - 1
    parity = (np.arange(ch.size) - start[cluster]) % 2
    inner = cluster[:-1] == cluster[1:]  # the gap lies within one run of transitions
    # samples back on the side the run started from / on the far side, within the run
    g = gaps.astype(float)
    back = np.bincount(cluster[:-1][inner], weights=(g * (parity[:-1] == 1))[inner],
                       minlength=start.size)  # fmt: skip
    far = np.bincount(cluster[:-1][inner], weights=(g * (parity[:-1] == 0))[inner],
                      minlength=start.size)  # fmt: skip
    th = lev[start]
    crossing = (stop - start) % 2 == 0
    # the record may cut a crossing's chatter short: a first or last run that returns
    # is no turn known, and the reading's step alone bounds the closure there
    kept = crossing.copy()
    kept[1:-1] = True
    # a crossing where the run's samples would put it unmixed: after those still behind;
    # a run that returns (a turn just past the threshold, or chatter): its time beyond
    centre = 0.5 * (tt[start] + tt[stop])
    half = 0.5 * far * dt
    one, two = kept & crossing, kept & ~crossing
    t = np.concatenate([(tt[start] + back * dt)[one], (centre - half)[two], (centre + half)[two]])
    v = np.concatenate([th[one], th[two], th[two]])
    order = np.argsort(t, kind="stable")
    t, v = t[order], v[order]
    distinct = np.concatenate([[True], np.diff(t) > 0])
    t, v = t[distinct], v[distinct]
    return _apex(t, v, codes, dt)


def _apex(t: Array, v: Array, codes: Array, dt: float) -> tuple[Array, Array]:
    """The crossings ``t`` (s), ``v`` (steps) with a point added at each turn: between
    two consecutive crossings of one threshold, the closure goes past it and back.

    Near its turn a smooth closure is a parabola, whose width at a depth d below the
    apex is proportional to sqrt(d): with L the time past the threshold (between the two
    crossings) and W the time past the next threshold back (the crossings of it either
    side of the turn), the apex is ``L^2 / (W^2 - L^2)`` steps past the threshold (at
    most one: it would have crossed the next). Where only one neighbour crosses that
    threshold it gives W by symmetry, and the apex is put no further than the level's
    middle (a turn is seldom symmetric: the one side's width put an apex 0.29 step
    too far on an 8-bit slow squeeze); with neither, on the threshold. Where both sides
    cross two thresholds back, the three widths give the symmetric quartic instead
    (:func:`_quartic_apex`)."""
    m = t.size
    if m < 2:
        return t, v
    pair = np.flatnonzero(v[1:] == v[:-1])  # knots i, i + 1 enclose a turn
    if pair.size == 0:
        return t, v
    mid = 0.5 * (t[pair] + t[pair + 1])
    inside = codes[np.clip(np.round(mid / dt).astype(np.intp), 0, codes.size - 1)]
    side = np.sign(inside - v[pair])
    back = v[pair] - side  # the next threshold back
    before = (pair >= 1) & (v[np.clip(pair - 1, 0, m - 1)] == back)
    after = (pair + 2 < m) & (v[np.clip(pair + 2, 0, m - 1)] == back)
    t_before = t[np.clip(pair - 1, 0, m - 1)]
    t_after = t[np.clip(pair + 2, 0, m - 1)]
    width = np.where(
        before & after, t_after - t_before,
        np.where(before, 2 * (mid - t_before), np.where(after, 2 * (t_after - mid), np.nan)),
    )  # fmt: skip
    inner = t[pair + 1] - t[pair]
    with np.errstate(invalid="ignore", divide="ignore"):
        height = inner**2 / (width**2 - inner**2)
    # one side's width says little of an asymmetric turn: there no more than the
    # level's middle, the guess of least greatest error
    top = np.where(before & after, 1.0, 0.5)
    height = np.where(np.isfinite(height) & (width > inner), np.minimum(height, top), 0.0)
    height = np.clip(height, 0.0, None)
    # with the crossings of two thresholds back known on both sides: the quartic
    two = before & after & (pair >= 2) & (pair + 3 < m)
    two &= (v[np.clip(pair - 2, 0, m - 1)] == back - side)
    two &= (v[np.clip(pair + 3, 0, m - 1)] == back - side)
    if np.any(two):
        k = pair[two]
        deeper = _quartic_apex(inner[two], width[two], t[k + 3] - t[k - 2])
        height[two] = np.where(np.isfinite(deeper), deeper, height[two])
    t = np.concatenate([t, mid])
    v = np.concatenate([v, v[pair] + side * height])
    order = np.argsort(t, kind="stable")
    return t[order], v[order]


def _quartic_apex(inner: Array, width: Array, wider: Array) -> Array:
    """The apex (steps past the threshold) of the symmetric quartic ``depth = c tau^2 -
    e tau^4`` below it whose full widths are ``inner``, ``width`` and ``wider`` (s,
    shape (k,)) at the threshold and the next two back; NaN where it has no apex within
    a step of the threshold (c not positive).

    Three widths fix the apex h, c and e: ``c tau_j^2 - e tau_j^4 - h = j`` for the
    half widths tau_0, tau_1, tau_2, linear in them. The parabola (e = 0) of two widths
    took a closure's turns for sharper than they are: a smooth closure falls from its
    apex more slowly than a parabola as it goes deeper (a sinusoid's ``cos`` by
    ``tau^4 / 24``), its second width is wider than the parabola's, and the apex came
    out low, by 0.04 of a step on average over 423 turns of 8-bit sessions at 1 kHz and
    by 0.1-0.17 at apexes past 0.75 of a step. Through the fit's filter the rebuilt
    acceleration was 0.6-0.9 % short and M 1-2.5 SDs low.
    """
    tau = 0.5 * np.stack([inner, width, wider], axis=1)  # (k, 3)
    A = np.stack([np.full_like(tau, -1.0), tau**2, -(tau**4)], axis=2)  # (k, 3, 3)
    rhs = np.broadcast_to(np.array([0.0, 1.0, 2.0]), tau.shape)
    ok = np.abs(np.linalg.det(A)) > 0
    out = np.full(tau.shape[0], np.nan)
    if np.any(ok):
        h, c, _ = np.linalg.solve(A[ok], rhs[ok][..., None])[..., 0].T
        out[ok] = np.where((c > 0) & (h >= 0.0) & (h <= 1.0), h, np.nan)
    return out
