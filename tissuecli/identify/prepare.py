"""From a session to what the estimators fit: validated, on its sample grid, with lost
frames and clipped samples as holes, and differentiated without looking through them."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from ..core.errors import FitError
from ..core.plausible import unit_warnings
from ..core.session import Session
from ..core.timebase import sample_clock
from .contact import Contact, find_contact, quantisation_step
from .derivatives import Differentiator, Frozen, Kinematics
from .derivatives.staircase import staircase
from .design import held_closure
from .spectrum import convolve_valid, white_noise_sd

Array = NDArray[np.float64]

MIN_SAMPLES = 200


def longest_gapless(session: Session) -> tuple[Session, list[str]]:
    """The longest stretch without gaps (lost frames), and a warning if that is not all of it.

    The derivative filters need evenly spaced samples; rather than refuse a
    session with a few lost frames, fit its longest gap-free stretch and say so.
    """
    steps = np.diff(session.time)
    if steps.size == 0:
        return session, []
    dt = float(np.median(steps))
    cuts = np.flatnonzero(np.abs(steps - dt) > 0.25 * dt) + 1
    if cuts.size == 0:
        return session, []
    edges = np.concatenate([[0], cuts, [len(session)]])
    i = int(np.argmax(np.diff(edges)))
    a, b = int(edges[i]), int(edges[i + 1])
    part = session.replace(session.time[a:b], session.force[a:b], session.position[a:b])
    return part, [
        f"the session has {cuts.size} gap(s) (lost frames); fitted the longest gap-free "
        f"stretch, {session.time[a]:.3f}-{session.time[b - 1]:.3f} s "
        f"({100 * (b - a) / len(session):.0f} % of the samples)"
    ]


#: runs of at most this many missing samples are bridged by linear interpolation (the
#: error, h^2 x''/8 over two periods, is far below sensor noise at forceps rates)
BRIDGE_SAMPLES = 2


@dataclass
class Prepared:
    """A session made ready to fit (see :func:`prepare`).

    Attributes
    ----------
    session : Session
        What is fitted, on a regular grid; holes hold interpolated stand-ins.
    kinematics : Kinematics
    warnings : list of str
        Says what the time base, lost frames, clipping and grasp selection did.
    contact : Contact
        The grasps found.
    measured_fraction : float
        Fraction of the grid that holds measurements rather than bridged stand-ins: one
        sample of the fit counts this much.
    trusted : ndarray of bool, shape (n,)
        Grid samples that hold measurements, neither lost nor clipped, in contact or
        not: what the sensors' noise is read from.
    rules : GraspRules or None
        How the grasps were fitted (:func:`grasp_rules`); None where every sample was.
    rebuilt : ndarray, shape (n,), or None
        The closure the kinematics are formed from where it is not the session's own
        (a coarse ADC's staircase rebuilt through its level crossings, m); None: the
        session's.
    rebuilt_sd : float or None
        The SD of the white noise a filter averages alike with the rebuilt closure's
        error (m; :func:`~tissuecli.identify.derivatives.staircase.staircase`).
    """

    session: Session
    kinematics: Kinematics
    warnings: list[str]
    contact: Contact
    measured_fraction: float
    trusted: NDArray[np.bool_]
    rules: GraspRules | None = None
    rebuilt: Array | None = None
    rebuilt_sd: float | None = None

    @property
    def closure(self) -> Array:
        """The closure (m, shape (n,)) the kinematics and every column are formed from."""
        return self.session.position if self.rebuilt is None else self.rebuilt


def prepare(
    session: Session,
    diff: Differentiator,
    grasps: str | Sequence[int] = "all",
    *,
    refuse_constant: bool = True,
    closure: str = "read",
) -> Prepared:
    """Validate a session, put it on its sample grid, check that it can identify anything,
    and differentiate it without looking through holes.

    Stamps are put on their regular clock, or resampled across short steps if
    irregular (:func:`on_grid`). Lost frames and long gaps become holes in the
    sample grid (filled by interpolation so the filters run, but marked), and so
    do samples at either end of the ADC, when the session knows its ADC: a clipped
    value is not a measurement. Filtered samples whose window holds a hole are
    left out of the fit, so nothing else is lost; but runs of at most
    :data:`BRIDGE_SAMPLES` missing samples (a lossy link's scattered losses) are
    bridged by interpolation and fitted, at a weight lowered by the measured
    fraction. A grid that cannot be built (far more missing than recorded) falls
    back to the longest gap-free stretch.

    Where the session alternates grasps with free jaw motion
    (:func:`~tissuecli.identify.contact.find_contact`), only filtered samples whose
    window touches a chosen grasp are fitted, the tissue's columns gated on the raw
    grid by the samples in contact (:func:`fit_grasps`): ``grasps="all"`` (every
    grasp), ``"none"`` (every sample, contact or not) or 1-based grasp numbers. With
    every grasp, the filtered samples of jaws near their most open are fitted too
    where they read an offset (:func:`open_limit`), the tissue's columns zero there:
    they read the force sensor's offset alone.

    ``refuse_constant=False`` lets jaws that never move through (to predict a hold: a
    law with memory has a force to give there, though nothing can be identified).

    ``closure="rebuilt"`` forms the kinematics from a coarse ADC's staircase rebuilt
    through the times the closure crosses each level
    (:func:`~tissuecli.identify.derivatives.staircase.staircase`), where the closure is
    one, with the filter chosen on the closure as read; ``"read"`` from the closure as
    read. A staircase's error is no white noise: where the jaws move slowly or turn, it
    holds one level while the closure moves by up to a step, an error the filter passes
    whole, and a slow 8-bit squeeze's speed column was off by 5 % of its RMS (2 % from
    the rebuilt closure), enough for a relaxation branch to follow it. Grasps and clipping
    are read on the closure as read.

    Returns
    -------
    Prepared
    """
    if closure not in ("read", "rebuilt"):
        raise FitError(f"closure {closure[:30]!r}: choose read or rebuilt")
    session.validate()
    n = len(session)
    if n < MIN_SAMPLES:
        raise FitError(f"session has {n} samples; at least {MIN_SAMPLES} are needed to fit")
    warnings: list[str] = unit_warnings(session)
    grid = on_grid(session)
    if grid is not None and grid.note:
        warnings.append(grid.note)
    slow = np.zeros(0, bool)
    if grid is None:
        session, stretch = longest_gapless(session)
        warnings += stretch
        if len(session) < MIN_SAMPLES:
            raise FitError(
                f"the session's sample times do not fall on one grid and its longest gap-free "
                f"stretch has {len(session)} samples; at least {MIN_SAMPLES} are needed to fit"
            )
        valid = np.ones(len(session), bool)
        lost = 0
    else:
        session, valid, slow = grid.session, grid.measured.copy(), grid.slow
        lost = int(np.count_nonzero(~valid & ~slow))
    x, f = (
        (session.position, session.force)
        if np.all(valid)
        else (u[valid] for u in (session.position, session.force))
    )
    # constant relative to the closure's own size, so that no choice of unit (um, km)
    # turns motion into a constant; a millionth is float32 rounding, not motion
    if refuse_constant and np.ptp(x) <= 1e-6 * float(np.max(np.abs(x))):
        raise FitError(
            "jaw position is constant: nothing to identify; the jaws must move "
            "while the forceps records"
        )
    if refuse_constant and np.ptp(f) <= 0:
        raise FitError("force is constant: check the force sensor and its calibration")
    present = valid.copy()
    bridged = _short_runs(~present, BRIDGE_SAMPLES)
    if slow.size:
        bridged |= slow
    valid |= bridged
    clipped = adc_ends(session)
    for _, mask in clipped:
        valid &= ~mask
    trusted = valid & present
    contact = find_contact(session)
    chosen = _chosen_grasps(contact, grasps)
    by_grasp = not contact.all_contact and grasps != "none"
    if by_grasp and not contact.grasps:
        warnings.append(
            f"no grasp stands above the free-jaw force of {contact.baseline_n:.4g} N: "
            "fitted every sample, as with --grasps none"
        )
        contact = replace(contact, kept_to_grasps=False)
        by_grasp = False
    # what to fit, from the most careful choice to every sample: detection that finds
    # too little to fit falls back to fitting more, with a note, never to a refusal
    stages: list[tuple[NDArray[np.bool_], bool, str]] = []
    if by_grasp:
        stages.append((valid & chosen, True, ""))
    if grasps == "all" or not by_grasp:
        stages.append(
            (
                valid.copy(),
                False,
                "the grasps found leave too few filtered samples to fit: fitted every "
                "sample, contact or not"
                if by_grasp
                else "",
            )
        )
        if clipped and not lost:
            stages.append(
                (
                    np.ones_like(valid),
                    False,
                    "too few filtered samples have a window free of clipped samples: fitted "
                    "every sample, clipped ones included",
                )
            )
        elif lost:
            stages.append(
                (
                    present | bridged,
                    False,
                    "too few filtered samples have a window free of lost or clipped "
                    "samples: fitted every sample that arrived, clipped ones included",
                )
            )
    kin, kept, note, mask = _differentiate(diff, session, stages)
    formed, rebuilt, rebuilt_sd = session, None, None
    if closure == "rebuilt":
        stair = staircase(session.position, kin.dt, valid=trusted)
        if stair is not None:
            rebuilt, rebuilt_sd = stair
            formed = session.replace(session.time, session.force, rebuilt)
            kin = Frozen(kin)(formed.time, rebuilt, formed.force, mask)
    if by_grasp and not kept:
        contact = replace(contact, kept_to_grasps=False)
    by_grasp = kept
    if note:
        warnings.append(note)
    if lost:
        arrived = present | slow if slow.size else present
        gaps = int(np.count_nonzero(np.diff(arrived.astype(np.int8)) == 1))
        short = int(np.count_nonzero(bridged & ~arrived))
        bridge_note = (
            f"; the {short} sample(s) missing in runs of at most {BRIDGE_SAMPLES} are "
            "bridged by linear interpolation, the fit leaving out the filtered samples "
            "whose window spans a longer gap"
            if short
            else ": the fit leaves out the filtered samples whose window spans one"
        )
        warnings.append(f"the session has {gaps} gap(s) ({lost} missing sample(s)){bridge_note}")
    for message, mask in clipped:
        warnings.append(
            f"{message} in {100 * np.mean(mask[present]):.1f} % of samples: clipped values are "
            "not measurements, so the fit leaves out the filtered samples whose window holds "
            "one; grasp more gently or widen the sensor range"
        )
    # filtered samples inside the fitted grasps, had nothing been lost or clipped
    fitted = chosen if by_grasp else np.ones_like(valid)
    full = int(np.count_nonzero(convolve_valid((~fitted).astype(float), np.ones(kin.window)) < 0.5))
    if (lost or clipped) and 0 < kin.time.size < full:
        warnings.append(
            f"{100 * (full - kin.time.size) / full:.1f} % of the filtered samples were left "
            "out for lost or clipped samples in their window"
        )
    measured = 1.0 - float(np.count_nonzero(bridged)) / len(session)
    rules = None
    if by_grasp:
        rules = grasp_rules(session, valid, trusted, chosen, contact.mask, kin, grasps == "all")
        kin = fit_grasps(rules, Frozen(kin), formed, valid, chosen, contact.mask)
    return Prepared(session, kin, warnings, contact, measured, trusted, rules, rebuilt,
                    rebuilt_sd)  # fmt: skip


#: jaws read open where their smoothed closure lies below the least closure seen in
#: contact by this many of its noise SDs (and one quantisation step)
OPEN_SD = 4.0
#: and within this fraction of the way from the most open closure to that of contact
REST_FRACTION = 0.2
#: and a quarter of a filter's width from every grasp: with the whole window free on
#: top of it, a grasp's edge read late by the detector lies in the window's outer tail
#: at most (a Gaussian's is 7 SDs wide, its weight beyond 3 SDs 0.3 %)
OPEN_MARGIN = 0.25
#: open jaws are fitted only where their mean force stands beyond this many standard
#: errors from zero (an offset to measure)
OPEN_SE = 4.0
#: a steady force dithers its ADC where the bias of its mean lies within this fraction
#: of the mean's standard error (:func:`_dithered`)
DITHER_SE = 0.25
#: free jaws are fitted only where they give at least this many filtered outputs
MIN_OPEN_ROWS = 32


@dataclass(frozen=True)
class GraspRules:
    """How a session's grasps are fitted: what :func:`grasp_rules` reads once from the
    whole session, and :func:`fit_grasps` applies to it, or to any stretch of it (a
    long session's blocks, :class:`~tissuecli.identify.stream.StreamedFit`), alike.

    Attributes
    ----------
    x_floor : float
        The closure's low end over the session, free jaws included (m): where contact
        may begin (:attr:`Kinematics.x_floor`).
    closed_m : float or None
        Jaws closed at least this far hold the tissue, whatever the detector read
        (:func:`touching_by_closure`, m); None: the contact flags alone.
    open_m : float or None
        Jaws a quarter of a filter's width from every grasp whose smoothed closure lies
        below this are open (:func:`open_limit`, m); None: none are read open.
    open_fitted : bool
        The open jaws are fitted, their tissue columns zero, for the sensor's offset
        (:func:`fit_grasps`).
    edges : bool
        The windows across a grasp's edges are fitted: the free jaws' force beside the
        grasps dithers its ADC.
    free_level_n : float or None
        The free jaws' level (N) taken off the force at a grasp's edges, where the
        open jaws are not fitted; None: none to take off.
    """

    x_floor: float
    closed_m: float | None
    open_m: float | None
    open_fitted: bool
    edges: bool
    free_level_n: float | None


def grasp_rules(
    session: Session,
    valid: NDArray[np.bool_],
    trusted: NDArray[np.bool_],
    chosen: NDArray[np.bool_],
    contact: NDArray[np.bool_],
    kin: Kinematics,
    read_open: bool = True,
) -> GraspRules:
    """What the fit of the ``chosen`` grasps (of the ``contact`` flags) decides over the
    whole ``session`` (:class:`GraspRules`), ``kin`` filtered inside the grasps (its
    kernels are the fit's); ``read_open``: the jaws near their most open are read for
    the sensor's offset (every grasp chosen). See :func:`fit_grasps`."""
    x = session.position
    seen = x[trusted] if np.any(trusted) else x
    open_m = open_limit(session, contact, kin) if read_open else None
    free = None if open_m is None else valid & open_mask(x, contact, kin.kernels[0], open_m)
    closed_m = closed_from(x, contact, valid)
    touching = _touching(x, contact, closed_m, free)
    w = kin.window
    open_fitted = (
        free is not None
        and _offset_readable(session, free, w)
        and np.count_nonzero(convolve_valid(free.astype(float), np.ones(w)) > w - 0.5)
        >= MIN_OPEN_ROWS
    )
    chosen = chosen & valid
    near = _near(chosen, w)
    # the free jaws' steady force, read by an ADC its noise does not dither, is off the
    # offset by up to half a step in every sample alike: the windows across a grasp's
    # edges would pin the offset there (and the spring's intercept with it)
    edges = _dithered(session.force[valid & ~contact & near], quantisation_step(session.force))
    around = valid & (near if edges else chosen) & ~(contact & ~chosen)
    free_near = around & ~touching
    level = float(np.median(session.force[free_near])) if free_near.any() else None
    return GraspRules(float(np.percentile(seen, 2)), closed_m, open_m, bool(open_fitted),
                      bool(edges), level)  # fmt: skip


def fit_grasps(
    rules: GraspRules,
    diff: Frozen,
    session: Session,
    valid: NDArray[np.bool_],
    chosen: NDArray[np.bool_],
    contact: NDArray[np.bool_],
) -> Kinematics:
    """The kinematics a fit of the ``chosen`` grasps fits (:func:`fit_grasps`), by
    ``rules`` (:func:`grasp_rules`, of this session or of the session this is a stretch
    of), filtered by ``diff``: every output whose window touches a chosen grasp and
    holds only ``valid`` samples, and no sample of a grasp not chosen (of the
    ``contact`` flags), each tissue column gated on the raw grid by the samples where
    the jaws hold the tissue (:func:`touching_by_closure`), so each tissue column is
    zero on the free samples of a window, as the tissue's force is.

    The jaws close onto the tissue and leave it at a grasp's edges, where the speed is:
    a fit kept wholly inside the grasps loses that half window at each edge, and with it
    most of what damping's force tells. The free samples of those windows read the free
    jaws' level (their median), which is taken off the force before it is filtered, and
    the law's offset holds in contact alone (:attr:`Kinematics.offset_gated`): an
    offset in contact may be the sensor's or a preload (a spring touched short of zero
    closure), the free jaws read the sensor's alone.

    Where the rules fit the open jaws (:func:`open_mask`), the outputs whose window lies
    wholly in them are added too, in time order: the tissue's columns are zero there
    and the force is the sensor's offset, so a law's offset is measured where nothing
    else can stand in for it (inside the grasps a spring's intercept trades with it).
    They are not fitted when they give fewer than :data:`MIN_OPEN_ROWS` outputs, read
    zero within :data:`OPEN_SE` standard errors of their mean (no offset to measure), or
    are read by an ADC their noise does not dither
    (:func:`_dithered`).

    Raises
    ------
    FitError
        Where too few outputs are left to filter (see :class:`Differentiator`).
    """
    x = session.position
    k0 = diff.fitted.kernels[0]
    w = k0.size
    free = None if rules.open_m is None else valid & open_mask(x, contact, k0, rules.open_m)
    touching = _touching(x, contact, rules.closed_m, free)
    chosen = chosen & valid
    # within a window's width of a chosen grasp: every sample an output touching it reads
    near = _near(chosen, w) if rules.edges else chosen
    around = valid & near & ~(contact & ~chosen)
    extra = free if rules.open_fitted else None
    mask = around if extra is None else around | extra
    force = session.force
    if extra is None and rules.free_level_n is not None:
        # the free samples of the windows across the edges read the free jaws' level
        # (with open jaws, the offset is that level itself)
        force = force - np.where(touching, 0.0, rules.free_level_n)
    both = diff(session.time, x, force, mask)
    rows = np.arange(both.time.size) if both.rows is None else both.rows
    ones = np.ones(w)
    kept = convolve_valid(chosen.astype(float), ones)[rows] > 0.5
    if extra is not None:
        kept |= convolve_valid(extra.astype(float), ones)[rows] > w - 0.5
    out = both.outputs(np.flatnonzero(kept))
    # a relaxation branch is strained only in contact: held across free jaw motion
    return replace(out, force_raw=session.force[out.keep], drive=held_closure(x, ~contact),
                   x_floor=rules.x_floor, touching=touching,
                   offset_gated=extra is None)  # fmt: skip


def open_limit(session: Session, contact: NDArray[np.bool_], kin: Kinematics) -> float | None:
    """The smoothed closure below which jaws away from every grasp are surely free of the
    tissue (m; :func:`open_mask`): within :data:`REST_FRACTION` of the way from the
    session's most open to the least closure of any grasp (less :data:`OPEN_SD` noise
    SDs and a quantisation step); None where no closure in contact is seen.

    The closure test guards against contact too weak for the grasp detector (a soft
    tissue, or a noisy session's loose grasp, a few noise SDs above the free level):
    the tissue is touched at one closure, below the least the detector saw in contact
    by however much contact it missed; jaws opened most of the way from there to their
    widest touch nothing, whatever the force reads there."""
    x = session.position
    if not contact.any():
        return None
    smooth = convolve_valid(x, kin.kernels[0])
    h = (x.size - smooth.size) // 2
    inside = contact[h : h + smooth.size]
    if not inside.any():
        return None
    margin = OPEN_SD * white_noise_sd(x) * float(np.linalg.norm(kin.kernels[0]))
    margin += quantisation_step(x)
    top = float(np.min(smooth[inside])) - margin
    lowest = float(np.min(smooth))
    # contact too weak for the detector lies just above the true touch, which is below
    # the least closure the detector saw in contact: only the jaws near their most open
    # are taken, however weak the contact it missed
    return min(top, lowest + max(margin, REST_FRACTION * (top - lowest)))


def open_mask(
    x: Array, contact: NDArray[np.bool_], kernel: Array, limit: float
) -> NDArray[np.bool_]:
    """Samples a quarter of ``kernel``'s width (:data:`OPEN_MARGIN`) from every sample in
    ``contact`` whose closure ``x`` (m), smoothed by ``kernel``, lies below ``limit``
    (:func:`open_limit`), shape (n,)."""
    reach = max(1, int(OPEN_MARGIN * kernel.size))
    near = np.convolve(contact.astype(float), np.ones(2 * reach + 1), mode="same") > 0.5
    if near.all() or x.size < kernel.size:
        return np.zeros(x.size, bool)
    smooth = convolve_valid(x, kernel)
    h = (x.size - smooth.size) // 2
    xs = np.full(x.size, np.inf)
    xs[h : h + smooth.size] = smooth
    return ~near & (xs < limit)


def _near(chosen: NDArray[np.bool_], window: int) -> NDArray[np.bool_]:
    """Samples within a window's width of a ``chosen`` one: every sample an output
    whose window touches one reads."""
    return np.convolve(chosen.astype(float), np.ones(2 * window - 1), mode="same") > 0.5


def closed_from(x: Array, contact: NDArray[np.bool_], valid: NDArray[np.bool_]) -> float | None:
    """The least closure of any grasp (m): the 1st percentile of ``x`` over the
    ``valid`` samples in ``contact`` (against noise); None where there are none."""
    inside = contact & valid
    return float(np.percentile(x[inside], 1.0)) if inside.any() else None


def _touching(
    x: Array,
    contact: NDArray[np.bool_],
    closed_m: float | None,
    free: NDArray[np.bool_] | None,
) -> NDArray[np.bool_]:
    """:func:`touching_by_closure` from its threshold ``closed_m`` (:func:`closed_from`)."""
    out = contact.copy() if closed_m is None else contact | (x >= closed_m)
    return out if free is None else out & ~free


def touching_by_closure(
    session: Session,
    contact: NDArray[np.bool_],
    valid: NDArray[np.bool_],
    free: NDArray[np.bool_] | None = None,
) -> NDArray[np.bool_]:
    """The samples where the jaws hold the tissue, shape (n,): those of the grasps found
    (``contact``), and those closed at least as far as the least closure of any grasp
    (its 1st percentile over the ``valid`` samples, against noise), but for the ``free``
    jaws. The tissue is touched at one closure; the detector reads contact from the
    force standing clear of its noise, so a soft grasp's ends and its weak stretches
    are read free, their tissue force small but not zero, and a column gated by the
    detector alone would set it to zero beside each grasp."""
    closed = closed_from(session.position, contact, valid)
    if closed is None:
        return contact.copy()
    return _touching(session.position, contact, closed, free)


def _offset_readable(session: Session, free: NDArray[np.bool_], window: int) -> bool:
    """Whether the ``free`` jaws measure an offset (:func:`fit_grasps`)."""
    if np.count_nonzero(free) < MIN_OPEN_ROWS + window:
        return False
    # the open jaws measure the offset: where their force is zero within its noise
    # they tell nothing the grasps need, and the fit keeps to the grasps
    level = session.force[free]
    noise = _steady_noise(level)
    if abs(float(np.mean(level))) <= OPEN_SE * noise / np.sqrt(level.size):
        return False
    # a steady force read through an ADC whose noise does not dither it is off by up to
    # half a step in every sample alike, an error no count of samples averages away:
    # the open jaws would pin the offset there, tens of its standard errors off, and
    # the spring's intercept with it (inside the grasps the force sweeps the steps)
    return _dithered(level, quantisation_step(session.force))


def _steady_noise(level: NDArray[np.float64]) -> float:
    """The noise SD (N) of a steady force ``level``, shape (m,), from its first
    differences (a steady level has no drift for them to read)."""
    return float(np.std(np.diff(level))) / np.sqrt(2.0)


def _dithered(level: NDArray[np.float64], step: float) -> bool:
    """Whether a steady force's noise dithers the ADC's ``step`` (N) enough for its mean:
    True when too few samples to tell.

    A Gaussian noise of SD ``s`` before an ADC of ``step`` leaves the mean of what the
    ADC reads off its own by at most ``step / pi exp(-2 pi^2 s^2 / step^2)`` (the first
    term of the quantiser's characteristic function; Widrow & Kollar, *Quantization
    Noise*, 2008, ch. 5). The force is dithered where that bias lies within
    :data:`DITHER_SE` of the level's standard error ``s / sqrt(m)``: a level read by
    many samples needs more noise than one read by few. ``s`` is the SD read after the
    ADC less its own rounding, ``step^2 / 12``."""
    if level.size < 8:
        return True
    if step <= 0:
        return True
    sd = math.sqrt(max(_steady_noise(level) ** 2 - step**2 / 12.0, 0.0))
    bias = step / math.pi * math.exp(-2.0 * (math.pi * sd / step) ** 2)
    return bias <= DITHER_SE * sd / math.sqrt(level.size)


def _differentiate(
    diff: Differentiator,
    session: Session,
    stages: list[tuple[NDArray[np.bool_], bool, str]],
) -> tuple[Kinematics, bool, str, NDArray[np.bool_]]:
    """Differentiate with the first of ``stages`` (mask of samples to trust, whether it
    keeps to the grasps, note) that leaves enough filtered samples, and say which mask;
    the last (most lenient) one's error if none does."""
    error: FitError | None = None
    for mask, by_grasp, note in stages:
        try:
            kin = diff(session.time, session.position, session.force, mask)
            return kin, by_grasp, note, mask
        except FitError as e:
            error = e
    assert error is not None
    raise error


def _short_runs(mask: NDArray[np.bool_], longest: int) -> NDArray[np.bool_]:
    """The runs of True in ``mask`` of at most ``longest`` samples, away from the ends."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(np.int8), [0]])))
    out = np.zeros_like(mask)
    for start, stop in zip(edges[::2], edges[1::2], strict=True):
        if 0 < start and stop < mask.size and stop - start <= longest:
            out[start:stop] = True
    return out


def _chosen_grasps(contact: Contact, grasps: str | Sequence[int]) -> NDArray[np.bool_]:
    """In-contact samples of the chosen grasps."""
    if isinstance(grasps, str):
        if grasps not in ("all", "none"):
            raise FitError(f"--grasps {grasps[:20]!r}: give all, none or grasp numbers such as 1,3")
        return contact.mask.copy()
    mask = np.zeros_like(contact.mask)
    for number in grasps:
        if not 1 <= number <= len(contact.grasps):
            raise FitError(
                f"--grasps {number}: the session has {len(contact.grasps)} grasp(s); "
                "fit --grasps all or choose among them"
            )
        g = contact.grasps[number - 1]
        mask[g.start : g.stop] = True
    return mask


#: an irregular session is resampled across steps up to this many periods; longer ones
#: are holes (a filter cannot see across them, and interpolation would invent motion)
SHORT_GAP_PERIODS = 3.0
#: a grid with more than this many points per recorded sample is not built
MAX_GRID_PER_SAMPLE = 10
#: a logger's slow rhythm: at least this many long steps in a row, each within a factor
#: SLOW_SPREAD of their median, is a stretch logged slowly (an adaptive or event-driven
#: logger's holds), not lost samples; lost frames come alone or in a burst of one length
SLOW_RUN = 3
SLOW_SPREAD = 2.0


@dataclass(frozen=True)
class Grid:
    """A session on a regular sample grid (see :func:`on_grid`).

    Attributes
    ----------
    session : Session
        On the grid; grid points without a measurement hold interpolated stand-ins.
    measured : ndarray of bool, shape (n,)
        Grid points that hold a measurement.
    slow : ndarray of bool, shape (n,)
        Grid points between the samples of a stretch the logger recorded slowly: their
        linear interpolation is fitted (the signal there changes slowly, or the logger
        would have logged faster), at the lowered weight of a stand-in.
    note : str
        What was done to the time base ("" if nothing).
    """

    session: Session
    measured: NDArray[np.bool_]
    slow: NDArray[np.bool_]
    note: str


def slow_steps(steps: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Which steps (in periods, shape (m,)) belong to a stretch logged slowly: runs of at
    least :data:`SLOW_RUN` steps longer than :data:`SHORT_GAP_PERIODS` periods, each
    within :data:`SLOW_SPREAD` of the run's median step. A lost burst or a pause is one
    long step, and stays a hole."""
    long = steps > 1.5
    out = np.zeros(steps.size, bool)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], long.astype(np.int8), [0]])))
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        if b - a < SLOW_RUN:
            continue
        run = steps[a:b]
        middle = float(np.median(run))
        if middle <= SHORT_GAP_PERIODS:
            continue  # short steps are bridged anyway
        alike = (run <= SLOW_SPREAD * middle) & (run >= middle / SLOW_SPREAD)
        out[a:b] = alike
    return out


def _slow_note(steps_s: NDArray[np.float64], slow: NDArray[np.bool_], dt: float) -> str:
    runs = int(np.count_nonzero(np.diff(np.concatenate([[0], slow.astype(np.int8)])) == 1))
    return (
        f"{runs} stretch(es) logged slowly (every {1e3 * float(np.median(steps_s[slow])):.4g} "
        f"ms against {1e3 * dt:.4g} ms elsewhere) resampled onto the grid by linear "
        "interpolation and fitted"
    )


def on_grid(session: Session) -> Grid | None:
    """The session on a regular sample grid.

    Stamps that follow a regular clock (:func:`~tissuecli.core.timebase.sample_clock`:
    quantised or jittered stamps, lost samples) are put on it; lost samples get
    interpolated stand-ins and are not measured. Irregular stamps are resampled onto a
    grid at their median step (at their fast step when a logger alternates two rates
    and that grid stays small): a grid point between samples at most
    :data:`SHORT_GAP_PERIODS` periods apart is interpolated, one inside a longer gap
    is a hole. Either way, stretches a logger recorded slowly (:func:`slow_steps`:
    adaptive or event-driven logging, slow during holds) are resampled, not holes.
    None when the grid would be more than :data:`MAX_GRID_PER_SAMPLE` times the samples.
    """
    t = session.time
    n = len(session)
    numbers, clock, base = sample_clock(t)
    if numbers is not None:
        if np.all(np.diff(numbers) == 1):
            exact = base.residual_max_s <= 1e-6 / base.rate_hz
            if exact:
                return Grid(session, np.ones(n, bool), np.zeros(n, bool), "")
            note = f"time stamps put back on their clock: {base.describe()}"
            return Grid(
                session.replace(clock, session.force, session.position),
                np.ones(n, bool),
                np.zeros(n, bool),
                note,
            )
        if numbers[-1] + 1 > MAX_GRID_PER_SAMPLE * numbers.size:
            return None
        grid = np.arange(numbers[-1] + 1)
        measured = np.zeros(grid.size, bool)
        measured[numbers] = True
        filled = session.replace(
            *(np.interp(grid, numbers, u) for u in (clock, session.force, session.position))
        )
        steps = np.diff(numbers).astype(float)
        slow_step = slow_steps(steps)
        slow = np.zeros(grid.size, bool)
        for i in np.flatnonzero(slow_step):
            slow[numbers[i] + 1 : numbers[i + 1]] = True
        notes = [] if base.residual_max_s <= 1e-6 / base.rate_hz else [base.describe()]
        if np.any(slow_step):
            notes.append(_slow_note(steps / base.rate_hz, slow_step, 1.0 / base.rate_hz))
        return Grid(filled, measured, slow, "; ".join(notes))
    steps = np.diff(t)
    dt = 1.0 / base.rate_hz
    fast = float(np.percentile(steps, 10))
    if 0 < fast < dt / SHORT_GAP_PERIODS:
        # two rhythms (fast ramps, slow holds): the median step would undersample the
        # ramps; the fast step keeps them, if that grid is not too large
        if (t[-1] - t[0]) / fast + 1 <= MAX_GRID_PER_SAMPLE * n:
            fast_steps = steps[steps <= 1.5 * fast]
            dt = float(np.mean(fast_steps))
    size = int(np.floor((t[-1] - t[0]) / dt)) + 1
    if size > MAX_GRID_PER_SAMPLE * t.size:
        return None
    grid_t = t[0] + dt * np.arange(size)
    after = np.clip(np.searchsorted(t, grid_t, side="right"), 1, t.size - 1)
    span = t[after] - t[after - 1]
    slow_step = slow_steps(steps / dt)
    slow = slow_step[after - 1] & (span > SHORT_GAP_PERIODS * dt)
    valid = (span <= SHORT_GAP_PERIODS * dt) | slow
    resampled = session.replace(
        grid_t, np.interp(grid_t, t, session.force), np.interp(grid_t, t, session.position)
    )
    holes = int(np.count_nonzero(~valid))
    note = (
        f"irregular time stamps resampled onto a {1.0 / dt:.6g} Hz grid by linear "
        f"interpolation across steps up to {SHORT_GAP_PERIODS:g} periods"
        + (f"; {_slow_note(steps, slow_step, dt)}" if np.any(slow_step) else "")
        + (f"; {holes} grid point(s) inside longer gaps are holes" if holes else "")
    )
    # resampled points are stand-ins, but the grid is the session's own here: only
    # the slowly logged stretches count as bridged
    return Grid(resampled, valid & ~slow, slow, note)


def adc_ends(session: Session) -> list[tuple[str, NDArray[np.bool_]]]:
    """Samples at either end of the ADC, per channel that has any, when the session
    knows its ADC (as recordings do): ``(description, mask)``."""
    adc = session.adc
    if adc is None:
        return []
    out = []
    for channel, values in (("force", session.force), ("position", session.position)):
        ends, half = adc.ends(channel), adc.step(channel) / 2
        mask = (np.abs(values - ends[0]) < half) | (np.abs(values - ends[1]) < half)
        if np.any(mask):
            where = f"({ends[0]:.4g} or {ends[1]:.4g})"
            out.append((f"{channel} is at an end of the {adc.bits}-bit ADC {where}", mask))
    return out
