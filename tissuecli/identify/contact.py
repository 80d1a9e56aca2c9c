"""Grasps: where the jaws hold tissue, told from free jaw motion by the force.

A forceps session alternates grasps with free motion, during which the force
sensor reads its own offset (the baseline) plus noise. The baseline is the level
of the lowest long, flat stretch of the smoothed force during which the force does not
follow the jaw closure (near the tightest closure of a grasp the force also rests low,
but rises and falls with the closure); a sample is in contact when
the smoothed force stands away from the baseline by more than 6 noise SDs (entering)
and until it comes within 3 (leaving): SDs of the smoothed force's own noise, measured
on the free stretches, where the raw noise dithers the force's quantisation (else of the
raw force's noise). Each edge then goes, within half a smoothing width of it, where
least squares best split the raw force into free jaws at the baseline on one side and
the grasp's force, a parabola, on the other. Stretches shorter than :data:`MIN_GRASP_S` are not
grasps, and gaps shorter than :data:`MIN_GAP_S` do not end one, unless the jaws are
seen resting open in them (below). When no free stretch
covers :data:`MIN_FREE_FRACTION` of the session, the whole session is one contact.

Free jaws read the sensor's offset whatever the jaws do; tissue answers the closure
*and its speed*. A soft law such as ``K x^3`` is near zero at small closure, so a
stretch at the lowest force can be tissue in contact, told apart by two signs: its
force follows the closure or the closure speed (the damping term), beyond what the
smoothed noise explains; or the force falls well below that level elsewhere for more
than :data:`BELOW_FRACTION` of the session (free jaws read the lowest level there
is; damping pulls a grasped tissue's force below it while the jaws open and turn).
Either way the stretch is not free jaw motion, unless its jaws are held still through
its middle half and its force keeps one level there: such a stretch is free whatever
its ends do (they take in the first and last few noise SDs of the grasps beside it,
whose force follows the closure). Where the lowest force has no free stretch (a damped
tissue pulls the force below the free-jaw level at every release), the level the force
rests at most often is tried for jaws held still; once such jaws cover
:data:`MIN_FREE_FRACTION` of the session, a dip below their level is a grasped tissue
pulling and no sign against them. A dip that ends with the jaws still
opening fast is the other case: a tissue pulled on jaws opening faster than it
recovers until it let go, at the end of a grasp; such dips are in contact (a force
far from the baseline either way is tissue's) and say nothing against free jaws.
Where the force alone finds no free level (a damped tissue pulling below it at every
release on a closure quantised coarser than its noise, a soft law resting at its force),
the closure tells: free jaws rest at the session's most open closure, held there with
one force level, in :data:`MIN_REST_STRETCHES` stretches or more; a squeeze in contact
throughout only passes its most open closure at a turn. Jaws seen resting so are free
however the force reads, and end the grasp before them: a damped tissue's pull on
release keeps the smoothed force off the free level for most of a short break.
The regressions run on the smoothed force taken every smoothing width, whose noise is
then nearly independent.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..core.session import Session
from .spectrum import white_noise_sd

Array = NDArray[np.float64]

#: shortest grasp and shortest break between grasps, s
MIN_GRASP_S = 0.1
MIN_GAP_S = 0.05
#: enter and leave contact at these many noise SDs above the baseline
ENTER_SD, LEAVE_SD = 6.0, 3.0
#: smoothing of the force before thresholding, s
SMOOTH_S = 0.02
#: the free stretches must cover this much of a session for it to have any
MIN_FREE_FRACTION = 0.05
#: a stretch whose force follows the closure with more than this fraction of the
#: session's overall force-closure slope, significantly, is contact resting low
FOLLOW_FRACTION = 0.02
#: a free-jaw level the smoothed force falls below (by ENTER_SD of its noise) for more
#: than this fraction of the session is no free-jaw level: the force there is tissue's
BELOW_FRACTION = 0.005
#: a dip below the free-jaw level that ends with the jaws opening at less than this
#: fraction of the dip's fastest speed (or closing) is the jaws turning in contact, not a
#: tissue letting go of jaws that go on opening
TURN_FRACTION = 0.3
#: a stretch at the lowest force whose middle half keeps the smoothed closure within
#: this many of its noise SDs is jaws held still, free: its ends take in the first and last few
#: noise SDs of the grasps beside it, whose force follows the closure
STILL_SD = 8.0
#: most bins of the histogram that finds the level the force rests at most
MAX_BINS = 4096
#: jaws resting at their most open closure this many times, at one force level, are free
#: jaws between grasps (a squeeze in contact throughout passes its smallest closure once
#: in a while, at a turn)
MIN_REST_STRETCHES = 3
#: t statistic above which a stretch's force follows the closure or its speed
FOLLOW_T = 4.0
#: jaws resting open last at least this many smoothing widths and this many samples
#: (each half of its middle then holds eight: a few at a slow rate and a quantised force
#: rest flat by chance); no more than :data:`MIN_GRASP_S`. One width suffices: the
#: stretch is read on the smoothed closure, which leaves the most open closure as soon
#: as its window takes in jaws that move, so the jaws rest half a width beyond each
#: end, and the smoothed force of its middle half reads resting jaws alone (two widths
#: cut the rests of a fast session short, 40-60 ms at 9-10 kHz, and read it as one
#: contact)
MIN_FREE_WIDTHS, MIN_FREE_SAMPLES = 1, 32
#: a force whose noise SD is at least this many quantisation steps is dithered: its
#: moving mean averages the noise down
DITHER_STEPS = 2.0
#: a grasp lasts at least this many smoothing widths (an outlier spread by the moving
#: mean stands out for one width) and this many samples; never more than MIN_GRASP_S
SPIKE_WIDTHS, MIN_GRASP_SAMPLES = 2, 4
#: a grasp's force is read as a polynomial of this degree over the half width beside
#: its edge (a parabola follows a damped or massive tissue's force falling through the
#: free-jaw level as the jaws open)
EDGE_DEGREE = 2
#: the parabola is fitted to at least this many samples beyond the candidate edges
EDGE_SAMPLES = 4 * (EDGE_DEGREE + 1)
#: edges whose sums of squares lie within this many noise variances of the best are a
#: tie (a likelihood ratio of e), settled for the free jaws
EDGE_TIE = 2.0
#: weak contact is sought by moving means this many times wider, then again, up to
#: COARSE_SCALES times; each needs this many independent widths of free samples below
#: the free-jaw level to measure its noise (the median of 16 half-normal values is
#: within about 30 % of its own: the threshold then stays above 4 SDs)
SCALE_RATIO, COARSE_SCALES, SCALE_WINDOWS = 4, 3, 16
#: a grasp's edge is pushed outward while the raw force stands about this many noise SDs
#: from the free-jaw level (free noise passes it 0.27 % of the time)
EDGE_SD = 3.0


@dataclass(frozen=True)
class Grasp:
    """One grasp: samples ``start`` (inclusive) to ``stop`` (exclusive) of the session."""

    start: int
    stop: int
    start_s: float
    end_s: float
    peak_force_n: float  # above the baseline, N

    @property
    def duration_s(self) -> float:
        return self.end_s - self.start_s


@dataclass(frozen=True)
class Contact:
    """Where a session is in contact.

    Attributes
    ----------
    grasps : tuple of Grasp
        In time order.
    mask : ndarray of bool, shape (n,)
        True on in-contact samples.
    baseline_n : float
        Force with the jaws free (the sensor's offset), N; NaN when the session has no
        free stretch.
    noise_n : float
        SD of the force noise, N.
    all_contact : bool
        The session has no free stretch: it is one contact from start to end.
    kept_to_grasps : bool
        The fit kept to the grasps found; False where they left too few samples to fit
        and every sample was fitted instead (set by the fit, not by detection).
    level_sd_n : float
        SD of the smoothed force where the jaws are free, N: what the thresholds are
        set in (NaN when the session has no free stretch).
    rested : bool
        The free-jaw level was read from jaws resting open (the force alone found none).
    scale_sd_n : tuple of float
        Noise SD of each wider moving mean weak contact was sought with, N.
    """

    grasps: tuple[Grasp, ...]
    mask: NDArray[np.bool_]
    baseline_n: float
    noise_n: float
    all_contact: bool
    kept_to_grasps: bool = True
    level_sd_n: float = float("nan")
    rested: bool = False
    scale_sd_n: tuple[float, ...] = ()

    def describe(self) -> str:
        if self.all_contact:
            return "no free jaw motion found: the whole session is one contact"
        durations = [g.duration_s for g in self.grasps]
        if not durations:
            return f"no grasp found (baseline {self.baseline_n:.4g} N)"
        return (
            f"{len(self.grasps)} grasp(s) of {min(durations):.2f}-{max(durations):.2f} s, "
            f"peak {max(g.peak_force_n for g in self.grasps):.3g} N above a baseline of "
            f"{self.baseline_n:.4g} N; {100 * np.mean(self.mask):.0f} % of the samples in contact"
        )


def find_contact(session: Session, levels: Contact | None = None) -> Contact:
    """Find the grasps of a session (on a regular or nearly regular sample grid).

    ``levels``: the contact found on a whole session this is a stretch of (a long
    session's block, :class:`~tissuecli.identify.stream.StreamedFit`), whose free-jaw
    level and noise are read here rather than from the stretch alone, so that the
    stretch's grasps are the whole session's."""
    f = session.force
    n = f.size
    dt = float(np.median(np.diff(session.time))) if n > 1 else 1.0
    known = levels if levels is not None and not levels.all_contact else None
    noise = known.noise_n if known is not None else _noise_sd(f)
    width = max(1, int(round(SMOOTH_S / dt)))
    smooth = _moving_mean(f, width)
    closure = _moving_mean(session.position, width)
    # jaws held still, told from a slow turn only where the position's noise resolves
    # its steps (a closure quantised coarser than its noise stays on one step through
    # both)
    step_d = np.diff(session.position)
    resolved = step_d.size > 0 and float(np.median(np.abs(step_d - np.median(step_d)))) > 0
    still = STILL_SD * _noise_sd(session.position) / np.sqrt(width) if resolved else -1.0
    rests = np.zeros(n, bool)  # jaws seen resting open: free, whatever the force does
    q = quantisation_step(session.position) if not resolved else 0.0
    if known is not None:
        baseline, free = known.baseline_n, 1.0
        if known.rested:
            tol = max(still, q)
            rests = _open_rest(smooth, closure, noise, dt, width, tol, known.baseline_n)[2]
    else:
        baseline, free = _baseline(smooth, closure, noise, dt, width, still)
    rested = known is not None and known.rested
    if free < MIN_FREE_FRACTION:
        # the force alone found no free level: jaws resting open between grasps, told by
        # the closure (a damped tissue pulls the force below the free level on release,
        # and a soft law rests at the free level's force at small closure)
        baseline, free, rests = _open_rest(smooth, closure, noise, dt, width, max(still, q))
        rested = True
    if free < MIN_FREE_FRACTION:
        return Contact(
            grasps=(
                Grasp(0, n, float(session.time[0]), float(session.time[-1]), float(np.ptp(f))),
            ),
            mask=np.ones(n, bool),
            baseline_n=float("nan"),
            noise_n=noise,
            all_contact=True,
        )
    # free jaws read the baseline: a force far from it either way is tissue's (one that
    # pulls on jaws opening faster than it recovers reads below)
    above = smooth - baseline
    mask = _hysteresis(np.abs(above), ENTER_SD * noise, LEAVE_SD * noise)
    # the thresholds in the smoothed force's own noise, measured where the jaws are free,
    # where the noise dithers the force's quantisation (a moving mean of a force quantised
    # coarser than that is a staircase whose error does not average out)
    dithered = noise >= DITHER_STEPS * quantisation_step(f)
    if known is not None:
        level_sd = known.level_sd_n
    else:
        level_sd = _free_sd(above, mask, noise, width) if dithered else noise
    if level_sd < noise:
        mask = _hysteresis(np.abs(above), ENTER_SD * level_sd, LEAVE_SD * level_sd)
    # a break shorter than MIN_GAP_S ends no grasp, unless the jaws are seen resting open
    # in it (a fast session's rests last 20-60 ms, and a damped tissue's pull on release
    # keeps the smoothed force off the free level for part of its break)
    mask = _close_gaps(mask, int(round(MIN_GAP_S / dt)), keep=rests)
    mask = _sharpen(mask, f - baseline, width, noise)
    scale_sd: tuple[float, ...] = ()
    if dithered:
        # contact too weak for the moving mean of one width, seen by longer ones
        weak, scale_sd = _weak_contact(f - baseline, mask, noise, width,
                                       None if known is None else known.scale_sd_n)  # fmt: skip
        mask |= weak
        mask = _close_gaps(mask, int(round(MIN_GAP_S / dt)), keep=rests)
        mask = _extend(mask, f - baseline, noise, width)
    mask &= ~rests
    grasps = []
    shortest = _min_grasp(dt, width)
    for start, stop in _runs(mask):
        if stop - start < shortest and not _cut_by_end(start, stop, f - baseline, noise, width):
            mask[start:stop] = False
            continue
        grasps.append(
            Grasp(
                start,
                stop,
                float(session.time[start]),
                float(session.time[stop - 1]),
                float(np.max(above[start:stop])),
            )
        )
    return Contact(tuple(grasps), mask, float(baseline), noise, all_contact=False,
                   level_sd_n=level_sd, rested=rested, scale_sd_n=scale_sd)  # fmt: skip


def _extend(mask: NDArray[np.bool_], above: Array, noise: float, width: int) -> NDArray[np.bool_]:
    """Each grasp's edges pushed outward over the raw force ``above`` the free-jaw level
    that still stands out of its noise (SD ``noise``, N), by at most a smoothing width.

    A grasp that ends by a fast release (or starts by a fast squeeze) falls to the level
    within a width: the moving mean crosses its threshold, and the steepest step lies
    part of the way down the ramp, so the ramp's foot (several noise SDs of force) was
    read free. Outward from each edge, the edge goes where the sum of
    ``above**2 - EDGE_SD**2 * noise**2`` over the samples it takes in is largest: a
    sample of free jaws adds ``-(EDGE_SD**2 - 1) noise**2`` on average, and one
    ``EDGE_SD`` noise SDs from the level or more adds at least nothing, so the edge
    stops where the force comes within about ``EDGE_SD`` SDs of the level. Free noise
    takes in a sample with the probability that it lies beyond ``EDGE_SD`` SDs: 0.27 %
    an edge at 3. (At 2, 4.6 %: one free sample in contact at a sharp edge, where a
    damped law's force jumps, cost more than a ramp's foot read free.)
    """
    if width <= 1 or not noise > 0:
        return mask
    out = mask.copy()
    gain = above**2 - (EDGE_SD * noise) ** 2
    runs = _runs(mask)
    for k, (start, stop) in enumerate(runs):
        lo = runs[k - 1][1] if k else 0
        hi = runs[k + 1][0] if k + 1 < len(runs) else mask.size
        after = gain[stop : min(stop + width, hi)]
        if after.size:
            total = np.cumsum(after)
            if total.max() > 0:
                out[stop : stop + int(np.argmax(total)) + 1] = True
        before = gain[max(start - width, lo) : start][::-1]
        if before.size:
            total = np.cumsum(before)
            if total.max() > 0:
                out[start - int(np.argmax(total)) - 1 : start] = True
    return out


def _cut_by_end(start: int, stop: int, above: Array, noise: float, width: int) -> bool:
    """Whether a run too short for a grasp is one cut by the recording's start or end:
    it touches it, lasts a smoothing width, and the mean of its own raw force ``above``
    the free-jaw level lies beyond :data:`ENTER_SD` of its noise SD
    (``noise / sqrt(stop - start)``). The moving mean repeats the end sample to fill its
    window there, so the run alone is no evidence: one noisy last sample counts half."""
    if not (start == 0 or stop == above.size) or stop - start < max(width, MIN_GRASP_SAMPLES):
        return False
    mean = float(np.mean(above[start:stop]))
    return abs(mean) > ENTER_SD * noise / np.sqrt(stop - start)


def _min_grasp(dt: float, width: int) -> int:
    """Fewest samples in a grasp: :data:`SPIKE_WIDTHS` smoothing widths and
    :data:`MIN_GRASP_SAMPLES`, no more than :data:`MIN_GRASP_S`.

    The hysteresis enters at :data:`ENTER_SD` SDs of the smoothed noise, which white
    noise passes about twice in a billion independent widths: a run that reaches it is
    no noise, however short. What a length rule must still reject is an outlier: one
    sample spread by the moving mean stands above the level for one width at most.
    (A fixed 0.1 s dropped short strong contact: a grasp cut by the end of the
    recording, a quick tap.)"""
    fixed = int(np.ceil(MIN_GRASP_S / dt - 1e-9))
    return max(min(fixed, max(SPIKE_WIDTHS * width, MIN_GRASP_SAMPLES)), 2)


def _weak_contact(
    above: Array,
    mask: NDArray[np.bool_],
    noise: float,
    width: int,
    known: tuple[float, ...] | None = None,
) -> tuple[NDArray[np.bool_], tuple[float, ...]]:
    """Contact too weak for the moving mean of ``width`` samples, found by moving means
    :data:`SCALE_RATIO`, ``SCALE_RATIO**2``, ... times wider (at most
    :data:`COARSE_SCALES` of them): samples where the mean of the raw force ``above``
    the free-jaw level stands beyond :data:`ENTER_SD` SDs of that mean's own noise.

    A grasp resting a noise SD above the level for a few hundred samples (a soft law at
    small closure, a relaxed hold, a weak grasp in a noisy session) is far outside the
    noise of a mean over many samples, though no single width of it is. Each wider
    mean sees the force with the contact found so far set to the level, so a strong
    grasp is not spread past its edges; and a stretch first found at a width ``w`` is
    one the mean over ``w / SCALE_RATIO`` did not reach, so its level is under
    ``ENTER_SD * SCALE_RATIO ** 0.5`` SDs of the mean over ``w``: that mean passes the
    threshold only where more than half its window lies on it, inside the stretch.

    The noise SD of each mean is measured where the jaws are free (:func:`_scale_sd`);
    a scale whose free samples are too few to measure it, or longer than a sixteenth of
    the session, is not used. The false-alarm rate is that of the fine scale (about
    2e-9 per independent window at 6 SDs) per scale.

    Returns the contact found and the noise SD of each scale used (N); ``known``: those
    of the whole session this is a stretch of, used as they are.
    """
    found = mask.copy()
    out = np.zeros_like(mask)
    n = above.size
    w = width
    sds: list[float] = []
    for k in range(COARSE_SCALES if known is None else len(known)):
        w *= SCALE_RATIO
        if known is None and 16 * w > n:
            break
        smooth, count = _window_mean(np.where(found, 0.0, above), w)
        sd = _scale_sd(smooth, found, noise, w) if known is None else known[k]
        if sd is None:
            break
        sds.append(sd)
        # near the ends the window holds fewer samples, and its mean more noise
        new = (np.abs(smooth) > ENTER_SD * sd * np.sqrt(w / count)) & ~found
        out |= new
        found |= new
    return out, tuple(sds)


def _window_mean(f: Array, w: int) -> tuple[Array, Array]:
    """The mean of the samples within a centred window of ``w`` at each sample, and how
    many it holds (fewer near the ends: no sample is repeated to fill the window)."""
    csum = np.concatenate([[0.0], np.cumsum(f)])
    i = np.arange(f.size)
    lo = np.clip(i - w // 2, 0, f.size)
    hi = np.clip(i - w // 2 + w, 0, f.size)
    count = (hi - lo).astype(float)
    return (csum[hi] - csum[lo]) / count, count


def _scale_sd(smooth: Array, found: NDArray[np.bool_], noise: float, w: int) -> float | None:
    """SD of a moving mean ``w`` samples wide of the force above the free-jaw level,
    where the jaws are free (away from ``found`` by a width): robustly from the half
    below the level, as :func:`_free_sd`, between ``noise / sqrt(w)`` (white noise) and
    ``noise``. None where fewer than :data:`SCALE_WINDOWS` independent widths of free
    samples lie below the level (too few to measure it)."""
    away = ~found.copy()
    for start, stop in _runs(found):
        away[max(start - w, 0) : stop + w] = False
    below = smooth[away & (smooth < 0)]
    if below.size < SCALE_WINDOWS * w:
        return None
    sd = float(np.median(-below)) / 0.6745
    return float(np.clip(sd, noise / np.sqrt(w), noise))


def _free_sd(above: Array, mask: NDArray[np.bool_], noise: float, width: int) -> float:
    """SD of the smoothed force ``above`` the free-jaw level where the jaws are free (N):
    within :data:`LEAVE_SD` noise SDs of the level and a smoothing width away from
    ``mask``, robustly: from the median distance below the level (a half-normal's).

    White noise gives ``noise / sqrt(width)``; drift, hum or a sensor's slow noise more.
    Bounded by those two: a moving mean cannot make the noise larger, and fewer than
    two widths of free samples below the level are not enough to measure it (then
    ``noise``).
    """
    if width <= 1:
        return noise
    away = ~mask & (np.abs(above) <= LEAVE_SD * noise)  # a grasp too weak for ``mask``
    for start, stop in _runs(mask):
        away[max(start - width, 0) : stop + width] = False
    # the half below the level: free noise is symmetric about it, while a grasp too weak
    # for ``mask`` (or a soft law at small closure) pushes the force up
    below = above[away & (above < 0)]
    if below.size < 2 * width:
        return noise
    sd = float(np.median(-below)) / 0.6745  # median of a half-normal
    return float(np.clip(sd, noise / np.sqrt(width), noise))


def _sharpen(
    mask: NDArray[np.bool_], above: Array, width: int, noise: float = 0.0
) -> NDArray[np.bool_]:
    """Each grasp's edges where the raw force ``above`` the free-jaw level leaves it (or
    comes back to it), by least squares.

    The moving mean spreads a grasp's first rise (and last fall) over its width, so a
    threshold on it places the edges up to half a width outside. Within half a width
    of each edge, the edge goes to the place that best splits the span around it into
    free jaws, at the level, on one side, and contact on the other, its force a
    straight line (a ramp) over up to a width. A step between the means of the half
    widths either side (the rule before) put the release late wherever the force
    crosses the level as it falls: a damped tissue pulls below it while the jaws open,
    and the half width before the release then averages out near the level. ``noise``
    (N, the raw force's noise SD) sets what counts as a tie (:data:`EDGE_TIE`).
    """
    h = width // 2
    if h < 2:
        return mask
    out = mask.copy()
    runs = _runs(mask)
    for k, (start, stop) in enumerate(runs):
        lo = runs[k - 1][1] if k else 0
        hi = runs[k + 1][0] if k + 1 < len(runs) else mask.size
        for edge, rising in ((start, True), (stop, False)):
            first, last = max(edge - h, lo), min(edge + h, hi)  # the candidate edges
            # the grasp's side holds enough samples for its parabola at every candidate
            # (at a few hundred Hz half a width is three samples)
            reach = max(h, EDGE_SAMPLES)
            if rising:
                span = (max(first - h, lo), min(last + reach, hi))
            else:
                span = (max(first - reach, lo), min(last + h, hi))
            best = _split(above[span[0] : span[1]], first - span[0], last - span[0], rising,
                          EDGE_TIE * noise**2)  # fmt: skip
            if best is None:
                continue
            best += span[0]
            if rising:
                out[min(best, edge) : max(best, edge)] = best < edge
            else:
                out[min(best, edge) : max(best, edge)] = best > edge
    return out


def _split(y: Array, first: int, last: int, rising: bool, tie: float = 0.0) -> int | None:
    """The index c in ``first..last`` that best splits ``y`` into free samples at zero
    and contact samples on a parabola (:data:`EDGE_DEGREE`): ``y[:c]`` free and
    ``y[c:]`` contact when ``rising``, the other way round when not; None when no split
    leaves more samples on the curve than it has coefficients. Of the splits within
    ``tie`` (a sum of squares) of the best, the one with the least contact."""
    n = y.size
    p = EDGE_DEGREE + 1
    t = (np.arange(n) - 0.5 * n) / max(n, 1)  # centred and scaled: sums keep precision
    zero = np.zeros(1)
    powers = [np.concatenate([zero, np.cumsum(t**k)]) for k in range(2 * p - 1)]
    moments = [np.concatenate([zero, np.cumsum(y * t**k)]) for k in range(p)]
    squares = np.concatenate([zero, np.cumsum(y * y)])
    c = np.arange(max(first, 0), min(last, n) + 1)
    i, j = (c, np.full(c.size, n)) if rising else (np.zeros(c.size, np.intp), c)
    ok = j - i > p
    if not ok.any():
        return None
    c, i, j = c[ok], i[ok], j[ok]
    G = np.stack([np.stack([powers[a + b][j] - powers[a + b][i] for b in range(p)], -1)
                  for a in range(p)], -2)  # fmt: skip
    r = np.stack([m[j] - m[i] for m in moments], -1)
    try:
        beta = np.linalg.solve(G, r[..., None])[..., 0]
    except np.linalg.LinAlgError:
        return None
    curve = (squares[j] - squares[i]) - np.einsum("ka,ka->k", beta, r)  # its residual SS
    free = squares[c] if rising else squares[n] - squares[c]
    cost = curve + free
    # where the force fades into the level (a soft law at its contact point) the place
    # is not told by the data: the least contact within a tie, as free jaws read in
    # contact take a law's force where there is none
    near = np.flatnonzero(cost <= float(np.min(cost)) + tie)
    return int(c[near[-1] if rising else near[0]])


def _min_free(dt: float, width: int) -> int:
    """Fewest samples in a free stretch: :data:`MIN_FREE_WIDTHS` smoothing widths and
    :data:`MIN_FREE_SAMPLES`, no more than :data:`MIN_GRASP_S` (a session sampled fast
    and cut short has free stretches of a few tenths of a second or less)."""
    fixed = int(np.ceil(MIN_GRASP_S / dt - 1e-9))
    return max(min(fixed, max(MIN_FREE_WIDTHS * width, MIN_FREE_SAMPLES)), 2)


def _noise_sd(f: Array) -> float:
    """Force noise SD from second differences (robust to the signal's slow changes)."""
    if f.size < 3:
        return 0.0
    sd = white_noise_sd(f)
    # a quantised signal whose noise does not dither its steps: half a step, as a
    # mostly constant one gives
    q = quantisation_step(f)
    return sd if sd >= q / np.sqrt(12) or q == 0 else q / 2


def _moving_mean(f: Array, width: int) -> Array:
    if width <= 1:
        return f.astype(float)
    kernel = np.ones(width) / width
    padded = np.pad(f.astype(float), (width // 2, width - 1 - width // 2), mode="edge")
    return np.convolve(padded, kernel, mode="valid")


def _baseline(
    smooth: Array, closure: Array, noise: float, dt: float, width: int = 1, still: float = 0.0
) -> tuple[float, float]:
    """The lowest level the smoothed force rests at for long stretches (free jaws), and
    the fraction of the session spent within a few noise SDs of it (0 when there is no
    such level: the session is in contact throughout).

    ``width`` is the moving mean's width in samples: the smoothed noise has SD
    ``noise / sqrt(width)`` and is nearly independent ``width`` samples apart.
    ``still`` (m): jaws whose smoothed closure moves less than this are held still.

    The floor is the force's 2nd percentile; where no free stretch rests there (a
    damped tissue pulls the force below the free-jaw level at every release), the
    level the force rests at most often in its lower half, if the jaws are held still
    there.
    """
    level, free = _baseline_at(float(np.percentile(smooth, 2)), smooth, closure, noise, dt,
                               width, still)  # fmt: skip
    if free > 0 or still <= 0:
        return level, free
    step = max(width, 1)
    lo, mid = np.percentile(smooth, [2, 50])
    bin_n = max(noise / np.sqrt(step), 1e-12 * max(abs(mid), 1.0))
    if not mid > lo + bin_n:
        return level, free
    bins = int(min(np.ceil((mid - lo) / bin_n), MAX_BINS))  # noiseless: a bounded count
    counts, edges = np.histogram(smooth, bins=bins, range=(lo, mid))
    mode = 0.5 * float(edges[int(np.argmax(counts))] + edges[int(np.argmax(counts)) + 1])
    rest, free_rest = _baseline_at(mode - 0.5 * ENTER_SD * noise, smooth, closure, noise,
                                   dt, width, still, only_still=True)  # fmt: skip
    return (rest, free_rest) if free_rest > 0 else (level, free)


def _open_rest(
    smooth: Array,
    closure: Array,
    noise: float,
    dt: float,
    width: int,
    tol: float,
    known: float | None = None,
) -> tuple[float, float, NDArray[np.bool_]]:
    """The free-jaw level from jaws resting at their most open closure between grasps,
    the fraction of the session they rest there (0 when they do not), and where they
    rest (True on those samples; none when they do not).

    Free jaws rest open, at the session's smallest closure, in stretches of one force
    level, again and again; a squeeze in contact throughout passes its smallest closure
    at a turn. So: stretches of at least :func:`_min_free` samples whose smoothed closure stays
    within ``tol`` (m; its noise or quantisation step) of the smallest, held there
    through their middle half with the force flat, at least :data:`MIN_REST_STRETCHES`
    of them at one level (within :data:`ENTER_SD` noise SDs), covering
    :data:`MIN_FREE_FRACTION` of the session. With the ``known`` level (N) of the whole
    session a stretch of it is part of, each such stretch at that level is a rest,
    however few the stretch holds.
    """
    none = np.zeros(smooth.size, bool)
    if not tol > 0 or smooth.size < 2:
        return float("nan"), 0.0, none
    step = max(width, 1)
    low = float(np.percentile(closure, 1))
    at_open = closure <= low + 2 * tol
    levels, rest = [], np.zeros_like(at_open)
    for start, stop in _runs(at_open):
        quarter = (stop - start) // 4
        middle = slice(start + quarter, stop - quarter)
        # a quantised closure's moving mean spans one step exactly: within tol, not past it
        if stop - start < _min_free(dt, width) or np.ptp(closure[middle]) > tol * (1 + 1e-9):
            continue
        if not _flat(smooth[middle], noise, step):
            continue
        level = float(np.median(smooth[middle]))
        if known is not None and abs(level - known) > ENTER_SD * noise:
            continue
        levels.append(level)
        rest[start:stop] = True
    if known is not None:
        return known, float(np.mean(rest)), rest
    if len(levels) < MIN_REST_STRETCHES:
        return float("nan"), 0.0, none
    level = float(np.median(levels))
    if np.max(np.abs(np.array(levels) - level)) > ENTER_SD * noise:
        return float("nan"), 0.0, none  # the force rests at different levels: tissue's
    return level, float(np.mean(rest)), rest


def quantisation_step(x: Array) -> float:
    """The smallest nonzero step between successive samples (a quantised signal's step)."""
    d = np.abs(np.diff(x))
    d = d[d > 0]
    return float(np.min(d)) if d.size else 0.0


def _baseline_at(
    floor: float,
    smooth: Array,
    closure: Array,
    noise: float,
    dt: float,
    width: int,
    still: float,
    only_still: bool = False,
) -> tuple[float, float]:
    """:func:`_baseline` from the stretches within ``ENTER_SD`` noise SDs above
    ``floor`` (N); ``only_still``: only those whose jaws are held still are free."""
    band = max(ENTER_SD * noise, 1e-12 * max(abs(floor), 1.0))
    near = smooth <= floor + band
    step = max(width, 1)
    speed = np.gradient(closure, dt)
    overall = _follow(closure[::step], speed[::step], smooth[::step])
    long_free = np.zeros_like(near)
    held = np.zeros_like(near)  # free stretches whose jaws are held still
    for start, stop in _runs(near):
        # a soft law near zero force at a squeeze's turn rests as long as free jaws do in
        # a fast session cut short: here, by the force alone, a free stretch is long
        if (stop - start) * dt < MIN_GRASP_S:
            continue
        cut = slice(start, stop, step)
        quarter = (stop - start) // 4
        middle = slice(start + quarter, stop - quarter)
        if np.ptp(closure[middle]) <= still and _flat(smooth[middle], noise, step):
            held[start:stop] = True  # free, whatever the grasps beside it add at its ends
        elif only_still or _follows(_follow(closure[cut], speed[cut], smooth[cut]), overall):
            continue  # the force follows the closure or its speed: a grasp at its loosest
        long_free[start:stop] = True
    if not np.any(long_free):
        return floor, 0.0
    level = float(np.median(smooth[long_free]))
    # free jaws read the lowest level there is: a force well below it for long is tissue,
    # unless each dip ends with the jaws still opening fast: a tissue that pulls on jaws
    # opening faster than it recovers, until it lets go (a grasp's release). A tissue in
    # contact throughout dips while damping outweighs its spring, until the jaws turn.
    # Jaws held still at the level for MIN_FREE_FRACTION of the session are free jaws
    # seen: a dip elsewhere is then a grasped tissue pulling, not a sign against them.
    if np.mean(held) >= MIN_FREE_FRACTION:
        return level, float(np.mean(long_free))
    below = smooth < level - ENTER_SD * noise / np.sqrt(step)
    turning = np.zeros_like(below)
    for start, stop in _runs(_close_gaps(below, 2 * step)):  # one dip, however noisy
        peak = float(np.max(np.abs(speed[start:stop])))
        # a release ends with the jaws still opening fast (closure falling)
        if not float(speed[stop - 1]) <= -TURN_FRACTION * peak or stop == below.size:
            turning[start:stop] = below[start:stop]
    if np.mean(turning) > BELOW_FRACTION:
        return level, 0.0
    return level, float(np.mean(long_free))


def _flat(y: Array, noise: float, width: int) -> bool:
    """Whether the smoothed force ``y`` (a moving mean ``width`` samples wide of a force
    whose noise SD is ``noise``) keeps one level: the means of its halves within
    :data:`FOLLOW_T` standard errors. A hold relaxing is not flat.

    Taken every ``width`` samples, the smoothed noise (SD ``noise / sqrt(width)``) is
    nearly independent; a stretch shorter than that gives at four points, and
    the mean of ``L`` of its samples has an SD of at most ``noise / sqrt(max(L, width))``.
    """
    if y[::width].size >= 4:
        y = y[::width]
        h = y.size // 2
        se = noise / np.sqrt(width) * np.sqrt(1.0 / h + 1.0 / (y.size - h))
    else:
        if y.size < 4:
            return False
        h_raw = y.size // 2
        se = noise * np.sqrt(1.0 / max(h_raw, width) + 1.0 / max(y.size - h_raw, width))
        y = y[:: y.size // 4]
        h = y.size // 2
    if h < 2:
        return False
    return bool(abs(float(np.mean(y[h:]) - np.mean(y[:h]))) <= FOLLOW_T * se)


def _follow(x: Array, v: Array, y: Array) -> list[tuple[float, float]]:
    """Least-squares slopes of ``y`` on closure ``x`` and speed ``v`` together, each with
    its standard error (inf for a column without spread, or too few samples)."""
    cols = [u - u.mean() for u in (x, v)]
    usable = [j for j, c in enumerate(cols) if float(c @ c) > 0]
    out = [(0.0, float("inf"))] * 2
    if not usable or y.size < len(usable) + 3:
        return out
    A = np.column_stack([cols[j] for j in usable])
    scale = np.linalg.norm(A, axis=0)
    yc = y - y.mean()
    coef, _, rank, sv = np.linalg.lstsq(A / scale, yc, rcond=None)
    if rank < len(usable):
        return [_slope(x, y), (0.0, float("inf"))]
    resid = yc - (A / scale) @ coef
    s2 = float(resid @ resid) / (y.size - len(usable) - 1)
    cov = s2 * np.linalg.pinv((A / scale).T @ (A / scale))  # rank held by lstsq, not by inv
    for k, j in enumerate(usable):
        out[j] = (float(coef[k] / scale[k]), float(np.sqrt(cov[k, k]) / scale[k]))
    return out


def _follows(stretch: list[tuple[float, float]], overall: list[tuple[float, float]]) -> bool:
    """Whether a stretch's force follows the closure or its speed significantly, the
    same way as the whole session's does and by more than :data:`FOLLOW_FRACTION` of it."""
    for (slope, se), (whole, _) in zip(stretch, overall, strict=True):
        if whole > 0 and slope > max(FOLLOW_FRACTION * whole, FOLLOW_T * se):
            return True
    return False


def _slope(x: Array, y: Array) -> tuple[float, float]:
    """Least-squares slope of ``y`` on ``x`` and its standard error (0, inf if x is flat)."""
    dx = x - x.mean()
    sxx = float(dx @ dx)
    if x.size < 3 or sxx <= 0:
        return 0.0, float("inf")
    slope = float(dx @ (y - y.mean())) / sxx
    resid = y - y.mean() - slope * dx
    return slope, float(np.sqrt(resid @ resid / (x.size - 2) / sxx))


def _hysteresis(signal: Array, enter: float, leave: float) -> NDArray[np.bool_]:
    """True from where ``signal`` exceeds ``enter`` until it falls below ``leave``."""
    high, low = signal > enter, signal < leave
    mask = np.zeros(signal.size, bool)
    state = False
    # run-wise rather than sample-wise: states change only at crossings
    change = np.flatnonzero(high | low)
    last = 0
    for i in change:
        mask[last:i] = state
        state = bool(high[i]) or (state and not low[i])
        last = i
    mask[last:] = state
    return mask


def _close_gaps(
    mask: NDArray[np.bool_], width: int, keep: NDArray[np.bool_] | None = None
) -> NDArray[np.bool_]:
    """``mask`` with its inner gaps of at most ``width`` samples filled, but for those
    holding a True sample of ``keep``."""
    out = mask.copy()
    runs = _runs(~mask)
    for start, stop in runs:
        if 0 < start and stop < mask.size and stop - start <= width:
            if keep is None or not keep[start:stop].any():
                out[start:stop] = True
    return out


def _runs(mask: NDArray[np.bool_]) -> list[tuple[int, int]]:
    """(start, stop) of every run of True."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(np.int8), [0]])))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist(), strict=True))
