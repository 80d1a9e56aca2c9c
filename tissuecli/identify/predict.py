"""The force a fitted tissue predicts for a session it did not see, with its 95 %
predictive band: how a researcher validates a law on another grasp.

A user compares a prediction with the force they measured. So by default the law is
applied, sample by sample, to the best estimate of the kinematics at that sample
(Savitzky-Golay position, speed and acceleration, whose polynomial fit follows the
motion without the lag or the flattening of a low-pass filter), and the measured
force is left as recorded. Filtering both as a fit does (``filtered=True``) compares
like with like, but predicts a smoothed force: what the filter removed is lost, and
on held-out data of known law that put the prediction 2-20 times further from the
true force than the measured force's noise floor.

Five things make the law's force the best estimate of the true one:

- **Each derivative its own smoothing.** Position noise reaches the law through x, xdot
  and xddot, amplified by the derivative's order, and a law weighs each by its own
  coefficient: one window for all three left the acceleration's noise (times M) or the
  speed's (times S) several times the force's noise floor. Each order's Savitzky-Golay
  window is chosen where the law's force agrees best with the measured force. The
  force's noise is independent of the position's, so that agreement is the distance to
  the true force plus a constant: a measure of the prediction's error that needs no
  truth. An estimator chooses on the force it was fitted to (a held-out part's own
  force is never read); a parameter file with another recording chooses on that
  recording.
- **A coarse ADC's staircase read by its crossings.** At 8-10 bits and kilohertz rates
  the closure holds a level for tens of samples, a sawtooth of one step that no
  window averages out; each derivative may read instead the closure rebuilt through
  the times it crosses each level
  (:func:`~tissuecli.identify.derivatives.staircase.staircase`), chosen, as the window
  is, where the law agrees best with the measured force.
- **Free jaws carry no tissue.** Where the session alternates grasps with free jaw
  motion (:func:`~tissuecli.identify.contact.find_contact`, as a fit finds them), the
  tissue's terms are zero outside the grasps and the force is the law's offset alone
  (the sensor's): the law was fitted in contact and says nothing of open jaws.
- **Breaks in the motion.** A ramp that starts or stops steps the acceleration (a
  constant-speed ramp kinks the closure), and a centred window across the step spreads
  it over the whole window, which a law's inertia carries into the force. Where a
  window's residual shows a break, the window bends there (a polynomial with a kink
  in its slope and a step in its curvature at the break, averaged over the break's
  likely places); whether that helps each derivative is chosen as the windows are.
- **Dry friction at a turn.** Near zero speed the estimated speed has either sign; the
  friction column is the mean of its two directions over the speed estimate's error
  (:meth:`~tissuecli.core.terms.Term.expected`), not the sign of the estimate.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..core.errors import FitError
from ..core.session import Session
from ..core.terms import Term
from ..core.timebase import sample_clock
from ..core.tissue import Tissue
from .contact import find_contact
from .derivatives import Differentiator, SavitzkyGolay, differentiator
from .derivatives.staircase import staircase
from .design import design, held_closure, position_noise_sd
from .prepare import BRIDGE_SAMPLES, _short_runs, on_grid, prepare, touching_by_closure
from .spectrum import convolve_valid, white_noise_sd

Array = NDArray[np.float64]

#: two-sided 95 % quantile of the normal distribution
Z95 = 1.959963984540054


@dataclass(frozen=True)
class Prediction:
    """Predicted and measured force at every sample of a session.

    Attributes
    ----------
    time : ndarray, shape (n,)
        s, the session's own stamps, one per sample given.
    force : ndarray, shape (n,)
        The measured force, N: as recorded, or filtered as in a fit when
        ``filtered`` (NaN where the filter cannot reach).
    predicted, lower, upper : ndarray, shape (n,)
        The law's force (posterior mean) and its 95 % predictive band, N: the
        coefficients' uncertainty carried through the law, plus the noise; NaN where
        the kinematics cannot be estimated (a gap in the stamps, the filter's edges
        when ``filtered``).
    filtered : bool
        Whether forces are the fit's filtered ones.
    """

    time: Array
    force: Array
    predicted: Array
    lower: Array
    upper: Array
    filtered: bool = False

    @property
    def known(self) -> NDArray[np.bool_]:
        """Samples with both a prediction and a measurement."""
        return np.isfinite(self.predicted) & np.isfinite(self.force)

    @property
    def count(self) -> int:
        """Samples predicted."""
        return int(np.count_nonzero(self.known))

    @property
    def rms_n(self) -> float:
        """RMS of measured minus predicted, N, over the predicted samples."""
        k = self.known
        return float(np.sqrt(np.mean((self.force[k] - self.predicted[k]) ** 2)))

    @property
    def force_sd_n(self) -> float:
        """SD of the measured force over the predicted samples, N."""
        return float(np.std(self.force[self.known]))

    @property
    def r2(self) -> float:
        """Coefficient of determination of the prediction."""
        k = self.known
        total = self.force[k] - np.mean(self.force[k])
        resid = self.force[k] - self.predicted[k]
        return 1.0 - float(resid @ resid) / max(float(total @ total), 1e-300)

    @property
    def inside(self) -> float:
        """Fraction of measured samples inside the band."""
        k = self.known
        return float(np.mean((self.force[k] >= self.lower[k]) & (self.force[k] <= self.upper[k])))


def predict_band(
    tissue: Tissue,
    session: Session,
    *,
    cov: Array | None = None,
    noise_sd: float | None = None,
    differentiator_name: str | Differentiator = "gaussian",
    filtered: bool = False,
    smoother: Differentiator | None = None,
    tune: NDArray[np.bool_] | None = None,
) -> Prediction:
    """Predict the force of every sample of ``session`` (all of it: grasps and free
    motion alike) with ``tissue``'s law; a law with memory starts from rest at the
    session's first sample.

    Parameters
    ----------
    tissue : Tissue
    session : Session
    cov : ndarray, shape (p, p), optional
        Covariance of the coefficients (SI); none: the band holds the noise alone.
    noise_sd : float, optional
        SD of the fit's residual, N; none: the band holds the coefficients' uncertainty
        alone. Unfiltered, the measured force's own noise
        (:func:`~tissuecli.identify.spectrum.white_noise_sd`) is added to it.
    differentiator_name : str or Differentiator
        As the fit used (``gaussian`` by default), for ``filtered``.
    filtered : bool
        Predict the force filtered as in a fit, and filter the measured force alike.
    smoother : Differentiator, optional
        The kinematics estimate of the unfiltered prediction, one window for every
        order; by default a Savitzky-Golay window chosen for each order (see the
        module's docstring).
    tune : ndarray of bool, shape (n,), optional
        The samples of ``session`` whose measured force chooses those windows (the
        fitted part of a session whose end is held out); by default every sample.

    Returns
    -------
    Prediction
        One value per sample of ``session``.

    Raises
    ------
    FitError
        If the session cannot be put on a sample grid or is too short to differentiate.
    """
    if filtered:
        d = differentiator_name
        diff = differentiator(d) if isinstance(d, str) else d
        ready = prepare(session, diff, "none", refuse_constant=False)
        kin, grid = ready.kinematics, ready.session
        detected = _free_jaws(grid)
        if detected.any():
            # the tissue's force is zero on free jaws: its columns gated on the raw grid
            # and filtered as the force is, as a fit kept to the grasps forms them
            touching = touching_by_closure(grid, ~detected, ready.trusted)
            kin = replace(kin, touching=touching,
                          drive=held_closure(grid.position, ~detected))  # fmt: skip
        A_rows = design(tissue.law, kin, grid.position)
        rows = np.arange(len(grid))[kin.keep]
        A = np.full((len(grid), A_rows.shape[1]), np.nan)
        A[rows] = A_rows
        measured = np.full(len(grid), np.nan)
        measured[rows] = kin.force
        predicted_grid, measured_grid = A @ tissue.coef, measured
        noise = noise_sd
    else:
        grid, usable = _grid(session)
        detected = _free_jaws(grid)
        past = detected & _past_contact_point(tissue, grid.position)
        free = detected & ~past
        judged = _on_grid_mask(session, grid, tune)

        def regressors(free: NDArray[np.bool_]) -> Array:
            if smoother is not None:
                return _raw_design(tissue, grid, usable, smoother, free)
            return _tuned_design(tissue, grid, usable, free, judged & ~detected)

        A = regressors(free)
        kept = _kept_free(tissue)
        if past.any() and not _law_reads_contact(A, tissue.coef, kept, grid.force, past & judged):
            free = detected  # terms with memory are held across these samples too
            A = regressors(free)
        if free.any():
            touched = _touching_by_closure(A, tissue.coef, kept, grid, free)
            if touched.any():
                free = free & ~touched
                if any(t.memory for t in tissue.law.terms):
                    A = regressors(free)  # the branches see the closure where it touches
        A[free] *= kept
        predicted_grid, measured_grid = A @ tissue.coef, grid.force
        noise = None
        if noise_sd is not None:
            noise = float(np.hypot(noise_sd, white_noise_sd(grid.force[usable])))
    var = np.zeros(len(grid))
    if cov is not None:
        if cov.shape != (A.shape[1], A.shape[1]):
            raise FitError(f"the covariance is {cov.shape}, the law has {A.shape[1]} terms")
        var = var + np.einsum("ij,jk,ik->i", A, cov, A)
    if noise is not None:
        var = var + noise**2
    half = Z95 * np.sqrt(np.clip(var, 0.0, None))
    at = _samples_on(session, grid)
    predicted = at(predicted_grid)
    force = session.force.astype(float) if not filtered else at(measured_grid)
    return Prediction(
        session.time.astype(float),
        force,
        predicted,
        predicted - at(half),
        predicted + at(half),
        filtered,
    )


def _grid(session: Session) -> tuple[Session, NDArray[np.bool_]]:
    """The session on its sample grid, and which grid points can be trusted for the
    kinematics (measured, bridged or logged slowly)."""
    session.validate()
    grid = on_grid(session)
    if grid is None:
        raise FitError(
            "the session's sample times do not fall on one grid (far more missing than "
            "recorded): predict a gap-free part of it"
        )
    usable = grid.measured | grid.slow
    usable |= _short_runs(~usable, BRIDGE_SAMPLES)
    return grid.session, usable


def _raw_design(
    tissue: Tissue,
    grid: Session,
    usable: NDArray[np.bool_],
    smoother: Differentiator,
    free: NDArray[np.bool_] | None = None,
) -> Array:
    """The law's regressors at the best estimate of each grid sample's kinematics,
    shape (n, p); NaN rows where the smoother's window holds a hole. Terms with memory
    are driven by the closure held across the ``free`` samples."""
    t, x = grid.time, grid.position
    n = x.size
    dt = float(np.median(np.diff(t)))
    (k0, k1, k2), _, _ = smoother.kernels(x, dt, usable)
    w = k0.size
    if w > n:
        raise FitError(
            f"{n} samples are too few for a {w}-sample smoother; predict a longer session"
        )
    h = w // 2
    # centred windows; at the ends the nearest full window's polynomial, as
    # scipy's savgol_filter(mode="interp") does
    est = []
    for k in (k0, k1, k2):
        mid = convolve_valid(x, k)
        est.append(np.concatenate([np.full(h, np.nan), mid, np.full(h, np.nan)]))
    xs, vs, acc = _ends(est, x, dt, w, smoother, position_noise_sd(x, 1.0 / dt, usable))
    held = held_closure(xs, free) if free is not None else xs
    A = np.column_stack([term.series(dt, held if term.memory else xs, vs, acc)
                         for term in tissue.law.terms])  # fmt: skip
    bad = np.convolve((~usable).astype(float), np.ones(w), mode="same") > 0.5
    A[bad] = np.nan
    return A


def _ends(
    est: list[Array], x: Array, dt: float, w: int, smoother: Differentiator, sigma_x: float
) -> tuple[Array, Array, Array]:
    """Fill the half windows at either end with the end windows' polynomials (their
    value, slope and curvature, each of the degree :func:`_end_values` chooses for
    position noise of SD ``sigma_x``, m), so every sample has kinematics."""
    h = w // 2
    order = int(getattr(smoother, "polyorder", 3))
    out = [u.copy() for u in est]
    for lo, where in ((0, np.arange(h)), (x.size - w, np.arange(x.size - h, x.size))):
        u = (where - (lo + h)) / max(h, 1)
        for k in range(3):
            values = _end_values(x[lo : lo + w], u, order, k, sigma_x)
            out[k][where] = values / (max(h, 1) * dt) ** k
    return out[0], out[1], out[2]


def _free_jaws(grid: Session) -> NDArray[np.bool_]:
    """Grid samples with the jaws free of the tissue: outside every grasp where the
    session alternates grasps with free motion, none where it is one contact."""
    contact = find_contact(grid)
    if contact.all_contact or not contact.grasps:
        return np.zeros(len(grid), bool)
    return ~contact.mask


def _past_contact_point(tissue: Tissue, x: Array) -> NDArray[np.bool_]:
    """Samples whose closure ``x`` (m) is past the contact point of a term that declares
    one (a Hunt-Crossley contact): the law's own, fitted, statement of where the tissue
    is touched. The grasp detector reads contact from the force standing clear of the
    noise, so it misses the first small force past that point (and reads a session in
    contact throughout as grasps where the closure dips short of it); the law's contact
    terms are zero short of their point by themselves and need no detector there."""
    out = np.zeros(x.size, bool)
    for term in tissue.law.terms:
        for name, parameter in zip(term.shapes, term.parameters, strict=True):
            if parameter.kind == "x0" and name in term.shape:
                out |= x > term.shape[name]
    return out


def _law_reads_contact(
    A: Array, coef: Array, kept: Array, force: Array, where: NDArray[np.bool_]
) -> bool:
    """Whether the law's force at the samples ``where`` (read free by the grasp detector,
    past the law's contact point) is closer to the measured ``force`` than the free
    jaws' (the tissue's terms zero, ``kept`` the rest): the test that the law's contact
    point holds there. A law whose contact point falls short of the true touch (a
    relaxation session fitted by a contact law, x0 below zero closure) puts a force
    on free jaws that read the sensor's offset, and is set aside; with no such sample
    to judge by, the detector stands."""
    rows = where & np.all(np.isfinite(A), axis=1) & np.isfinite(force)
    if not rows.any():
        return False
    law = A[rows] @ coef
    free = A[rows] @ (coef * kept)
    return float(np.sum((force[rows] - law) ** 2)) < float(np.sum((force[rows] - free) ** 2))


#: a closure threshold for contact on samples read free is taken where it lowers their
#: sum of squares by more than this many times the noise variance times ln(samples)
#: (a BIC for one parameter, times four)
TOUCH_BIC = 4.0


def _touching_by_closure(
    A: Array, coef: Array, kept: Array, grid: Session, free: NDArray[np.bool_]
) -> NDArray[np.bool_]:
    """Samples the grasp detector read free whose force the law explains, as contact:
    those whose closure is at or past one threshold, chosen by least squares.

    The detector reads contact from the force standing clear of its noise, so a grasp's
    loose part (a noisy session's light taps, a soft law at small closure) is read
    free, and its force predicted as the sensor's offset alone. The tissue is touched
    past one closure, though: over the samples read free (whose force, as the
    detector's, is read to tell where the jaws touch), the threshold c that best splits
    them into contact (closure >= c, the law's force) and free jaws (below, the
    offset's) is taken, where it beats reading them all free by :data:`TOUCH_BIC` times
    the noise variance times ln(samples); none otherwise. A law with memory is formed
    again with its branches driven through the samples so touched."""
    rows = free & np.all(np.isfinite(A), axis=1) & np.isfinite(grid.force)
    if np.count_nonzero(rows) < 8:
        return np.zeros(free.size, bool)
    x, f = grid.position[rows], grid.force[rows]
    law, off = A[rows] @ coef, A[rows] @ (coef * kept)
    order = np.argsort(x, kind="stable")
    gain = ((f - off) ** 2 - (f - law) ** 2)[order]  # what reading a sample touched saves
    saved = np.cumsum(gain[::-1])[::-1]  # reading touched every sample from each on
    k = int(np.argmax(saved))
    noise = white_noise_sd(grid.force)
    if not noise > 0 or saved[k] <= TOUCH_BIC * noise**2 * np.log(f.size):
        return np.zeros(free.size, bool)
    return free & (grid.position >= x[order][k])


def _kept_free(tissue: Tissue) -> Array:
    """1 for each term that stays with the jaws free (a sensor's offset), else 0;
    shape (p,)."""
    return np.array([0.0 if t.rendered else 1.0 for t in tissue.law.terms])


def _on_grid_mask(
    session: Session, grid: Session, tune: NDArray[np.bool_] | None
) -> NDArray[np.bool_]:
    """``tune`` (one flag per sample of ``session``) at the grid's samples, by the nearest
    sample in time; every grid sample when none."""
    if tune is None:
        return np.ones(len(grid), bool)
    tune = np.asarray(tune, bool)
    if tune.shape != session.time.shape:
        raise FitError(f"tune has {tune.size} flags for a session of {len(session)} samples")
    t = session.time
    i = np.clip(np.searchsorted(t, grid.time), 1, t.size - 1)
    nearer_left = (grid.time - t[i - 1]) <= (t[i] - grid.time)
    return tune[np.where(nearer_left, i - 1, i)]


#: candidate Savitzky-Golay smoothers for each derivative: these polynomial degrees (a
#: higher one follows a fast tap over a wider window), WINDOWS windows from the
#: shortest the degree allows to WIDEST times the window of the position's signal band
DEGREES = (3, 5, 7)
WINDOWS = 16
WIDEST = 16.0
#: the smoothers are chosen on at most this many samples (the last of those given)
TUNE_SAMPLES = 200_000

#: (degree, window in samples, source, bent): source 0 smooths the closure as read, 1
#: the closure rebuilt from its level crossings where it is a staircase
#: (:func:`~tissuecli.identify.derivatives.staircase.staircase`); bent, whether a
#: window across a break in the motion bends there (:func:`_bend_at_breaks`)
Smoother = tuple[int, int, int, bool]

#: a closure to smooth and the SD of its white noise (m)
Source = tuple[Array, float]


def _sources(grid: Session, usable: NDArray[np.bool_], dt: float) -> list[Source]:
    """The closures a smoother may read: as read, and where it is a staircase also
    rebuilt from its level crossings, each with its noise's SD (m).

    A coarse ADC's staircase leaves the position a slow sawtooth of one step that a
    polynomial smoother follows into its speed and acceleration unless its window
    spans many steps; the rebuilt closure passes through each crossing, known within a
    sample. Which of the two each derivative reads is chosen as its window is, by the
    law's agreement with the measured force, so a dithered staircase (whose crossings
    chatter) keeps the closure as read where that agrees better."""
    x = grid.position
    out: list[Source] = [(x, position_noise_sd(x, 1.0 / dt, usable))]
    rebuilt = staircase(x, dt, usable)
    if rebuilt is not None:
        out.append(rebuilt)
    return out


def _tuned_design(
    tissue: Tissue,
    grid: Session,
    usable: NDArray[np.bool_],
    free: NDArray[np.bool_],
    chooses: NDArray[np.bool_],
) -> Array:
    """The law's regressors, shape (n, p), on Savitzky-Golay kinematics with a smoother
    (degree, window and closure, :data:`Smoother`) for each derivative (x, xdot,
    xddot), chosen where the law's force is closest to the measured force over the
    ``chooses`` samples: derivative by derivative, the acceleration first, twice over.
    Tissue terms are zero on ``free`` samples."""
    t, x = grid.time, grid.position
    n = x.size
    dt = float(np.median(np.diff(t)))
    w0 = SavitzkyGolay().kernels(x, dt, usable)[0][0].size
    if w0 > n:
        raise FitError(
            f"{n} samples are too few for a {w0}-sample smoother; predict a longer session"
        )
    sources = _sources(grid, usable, dt)
    chosen: list[Smoother] = [(SavitzkyGolay().polyorder, w0, 0, False)] * 3
    ref = chooses & np.isfinite(grid.force)
    if np.count_nonzero(ref) > 4 * w0:  # enough measured force to choose on
        last = int(np.flatnonzero(ref)[-1]) + 1
        part = slice(max(0, last - TUNE_SAMPLES - 2 * int(WIDEST * w0)), last)
        chosen = _choose(tissue, grid, usable, free, ref, part, w0, sources)
    return _columns(tissue.law.terms, grid, usable, chosen, sources, free=free)


def _choose(
    tissue: Tissue,
    grid: Session,
    usable: NDArray[np.bool_],
    free: NDArray[np.bool_],
    ref: NDArray[np.bool_],
    part: slice,
    w0: int,
    sources: Sequence[Source],
) -> list[Smoother]:
    """The smoothers of :func:`_tuned_design`, chosen on the samples ``part``."""
    n = part.stop - part.start
    sub = grid.replace(grid.time[part], grid.force[part], grid.position[part])
    use, off, keep = usable[part], free[part], ref[part]
    own = [(u[part], sd) for u, sd in sources]
    kept_free = _kept_free(tissue)
    f = sub.force
    candidates = []
    for degree in DEGREES:
        least = degree + 2 + (degree + 1) % 2
        top = min(int(WIDEST * w0), n)
        if least > top:
            continue
        grid_w = {int(w) | 1 for w in np.geomspace(least, top, WINDOWS)} | {w0}
        candidates += [(degree, w, s) for s in range(len(own))
                       for w in sorted(grid_w) if least <= w <= n]  # fmt: skip
    cache: dict[Any, Any] = {}

    terms = tissue.law.terms
    # the derivatives each term's column reads: it is recomputed only when they change
    reads_of = {"x": (0,), "v": (1,), "a": (2,), "xv": (0, 1), "h": (0, 1), "1": ()}
    forces: dict[tuple[int, tuple[Smoother, ...]], Array] = {}

    def residual(smoothers: list[Smoother]) -> Array:
        """The law's force minus the measured one on the ``keep`` samples (NaN where
        the kinematics cannot reach)."""
        total = np.zeros(n)
        for j, term in enumerate(terms):
            key = (j, tuple(smoothers[k] for k in reads_of.get(term.variable, (0, 1, 2))))
            if key not in forces:
                col = _columns((term,), sub, use, smoothers, own, cache, off)[:, 0]
                col[off] *= kept_free[j]
                forces[key] = tissue.coef[j] * col
            total += forces[key]
        return (total - f)[keep]

    def error(r: Array) -> float:
        r = r[np.isfinite(r)]
        return float(np.mean(r**2)) if r.size else np.inf

    reads = {term.variable for term in tissue.law.terms}
    needed = [k for k, what in ((2, {"a"}), (1, {"v", "xv", "h"}), (0, {"x", "xv", "h"}))
              if reads & what]  # fmt: skip
    chosen: list[Smoother] = [(SavitzkyGolay().polyorder, w0, 0, False)] * 3
    best_r = residual(chosen)
    best = error(best_r)
    for _ in range(2):
        for k in needed:
            # each window as it is, and bending at the motion's breaks. A bend (two more
            # parameters about each break) must agree clearly better than a straight
            # window, or the force's noise on the part that chooses would pick it where
            # it does not help
            for c in [(*c, bent) for c in candidates for bent in (False, True)]:
                trial = [c if j == k else chosen[j] for j in range(3)]
                r = residual(trial)
                e = error(r)
                bends = c[3] and not chosen[k][3]
                if e < best and (not bends or _clearly_better(r, best_r)):
                    best, best_r, chosen = e, r, trial
    return chosen


#: blocks of the choosing samples whose means judge whether one smoother agrees clearly
#: better than another (:func:`_clearly_better`)
BLOCKS = 20


def _clearly_better(new: Array, old: Array) -> bool:
    """Whether the residuals ``new`` agree with the measured force better than ``old``
    by more than twice the standard error of the mean difference of their squares,
    that error from the means of :data:`BLOCKS` contiguous blocks (the residuals of a
    smoothed force are correlated from sample to sample; blocks far longer than that
    correlation are nearly independent)."""
    ok = np.isfinite(new) & np.isfinite(old)
    d = (new[ok] ** 2) - (old[ok] ** 2)
    if d.size < 4 * BLOCKS:
        return False
    means = np.array([b.mean() for b in np.array_split(d, BLOCKS)])
    return bool(-means.mean() > 2.0 * means.std(ddof=1) / math.sqrt(BLOCKS))


def _columns(
    terms: Sequence[Term],
    grid: Session,
    usable: NDArray[np.bool_],
    smoothers: list[Smoother],
    sources: Sequence[Source],
    cache: dict[Any, Any] | None = None,
    free: NDArray[np.bool_] | None = None,
) -> Array:
    """The regressors of ``terms`` on the kinematics of ``smoothers`` (x, xdot, xddot),
    shape (n, p), each smoothing one of the ``sources`` (a closure, m, and its noise's
    SD, m); NaN rows where a window reaches a sample not ``usable``. Terms with memory
    are driven by the closure held across the ``free`` samples
    (:func:`~tissuecli.identify.design.held_closure`)."""
    dt = float(np.median(np.diff(grid.time)))
    cache = {} if cache is None else cache
    est = []
    for k, smoother in enumerate(smoothers):
        if (k, smoother) not in cache:
            degree, w, s, bent = smoother
            x, sigma = sources[s]
            straight = (degree, w, s, False)
            if (k, straight) not in cache:
                cache[k, straight] = _smoothed(x, w, degree, k, dt, sigma)
            if bent:  # the straight estimate, bent where the motion breaks
                memo = cache.setdefault(("breaks", s), {})  # the windows' residuals
                est0, gain = cache[k, straight]
                cache[k, smoother] = (_bent(est0, x, w, degree, k, dt, memo), gain)
        est.append(cache[k, smoother])
    (xs, _), (vs, gain_v), (acc, _) = est
    # the speed estimate's error, for terms that bend on its scale (dry friction)
    var_v = (sources[smoothers[1][2]][1] * gain_v) ** 2
    held = held_closure(xs, free) if free is not None and any(t.memory for t in terms) else xs
    cols = [
        term.expected(vs, var_v) if term.variable == "v"
        else term.series(dt, held if term.memory else xs, vs, acc)
        for term in terms
    ]  # fmt: skip
    A = np.column_stack(cols)
    A[_reaches_hole(usable, max(w for _, w, _, _ in smoothers))] = np.nan
    return A


def _reaches_hole(usable: NDArray[np.bool_], w: int) -> NDArray[np.bool_]:
    """Samples whose centred window of ``w`` samples holds one not ``usable``."""
    if usable.all():
        return np.zeros(usable.size, bool)
    holes = np.concatenate([[0], np.cumsum(~usable)])
    i = np.arange(usable.size)
    lo, hi = np.clip(i - w // 2, 0, usable.size), np.clip(i + w // 2 + 1, 0, usable.size)
    return (holes[hi] - holes[lo]) > 0


@functools.lru_cache(maxsize=256)
def _fit_matrix(w: int, degree: int) -> Array:
    """The least-squares polynomial fit of ``w`` samples, shape (degree + 1, w): its
    coefficients (in the window's time over its half-width, from the centre) from the
    samples. One matrix gives every derivative's kernel and the end windows' fits."""
    h = w // 2
    u = (np.arange(w) - h) / max(h, 1)
    return np.linalg.pinv(np.vander(u, min(degree, w - 1) + 1, increasing=True))


def _smoothed(
    x: Array,
    w: int,
    degree: int,
    k: int,
    dt: float,
    sigma_x: float = 0.0,
    hinged: bool = False,
    memo: dict[Any, Array] | None = None,
) -> tuple[Array, float]:
    """The ``k``-th derivative's Savitzky-Golay estimate at every sample (centred windows;
    in the half window at either end the end window's polynomial, its degree chosen by
    :func:`_end_values` for position noise of SD ``sigma_x``, m) and the norm of its
    kernel (the gain of white noise). With ``hinged``, a window across a break in the
    motion bends there (:func:`_bend_at_breaks`)."""
    h = w // 2
    fit = _fit_matrix(w, degree)
    scale = math.factorial(k) / (max(h, 1) * dt) ** k
    if k >= fit.shape[0]:
        return np.zeros_like(x), 0.0
    kernel = scale * fit[k][::-1]
    out = np.concatenate([np.full(h, np.nan), convolve_valid(x, kernel), np.full(h, np.nan)])
    unit = 1.0 / (max(h, 1) * dt) ** k
    for lo, where in ((0, np.arange(h)), (x.size - w, np.arange(x.size - h, x.size))):
        u = (where - (lo + h)) / max(h, 1)
        out[where] = unit * _end_values(x[lo : lo + w], u, degree, k, sigma_x)
    if hinged:
        out = _bent(out, x, w, degree, k, dt, memo)
    return out, float(np.linalg.norm(kernel))


def _bent(
    est: Array,
    x: Array,
    w: int,
    degree: int,
    k: int,
    dt: float,
    memo: dict[Any, Array] | None = None,
) -> Array:
    """A copy of the ``k``-th derivative's estimate ``est`` from ``w``-sample windows of
    ``degree`` bent at the breaks in the motion (:func:`_bend_at_breaks`), shape (n,)."""
    out = est.copy()
    fit = _fit_matrix(w, degree)
    if 0 < k < fit.shape[0]:  # a closure's own estimate barely bends at one
        scale = math.factorial(k) / (max(w // 2, 1) * dt) ** k
        _bend_at_breaks(out, x, fit, k, scale, memo)
    return out


#: a window's residual about its polynomial marks a break in the motion where it stands
#: beyond this quantile of its chi-square (scaled to the session's median window): once
#: in a thousand windows of smooth motion
BREAK_QUANTILE = 0.999


def _bend_at_breaks(
    out: Array,
    x: Array,
    fit: Array,
    k: int,
    scale: float,
    memo: dict[Any, Array] | None = None,
) -> None:
    """Replace in ``out`` the ``k``-th derivative of the samples whose centred window
    holds a break in the motion (a step in acceleration at a ramp's start, a kink in
    a constant-speed ramp) by that of a polynomial with a hinge at the break, in place.

    A centred window across a step in acceleration spreads the step over the window
    (a ramp of its full height), and a law's inertia carries that error into the
    predicted force. A centred window whose residual sum of squares about its
    polynomial is improbable for smooth motion (:data:`BREAK_QUANTILE` of a chi-square
    with the window's residual degrees of freedom, scaled so the median window is its
    median) holds a break, and each run of such windows holds one. Its place is known
    to a few samples at best: each place between two samples within a half window of
    the run is weighed by the likelihood of a window twice as long about it, fitted by
    the polynomial plus a kink in its slope and a step in its curvature there (a
    change point). Each sample whose window reaches a likely place takes the mean, over
    the places, of the derivative of its own window's polynomial and hinge. Elsewhere
    the centred window, whose noise is the least, stays. Runs too long to hold one
    break, or breaks in more than :data:`BREAKS_AT_MOST` of the windows (a window too
    wide for the motion), are left.

    Parameters
    ----------
    out : ndarray, shape (n,)
        The centred estimates, in the derivative's SI unit; changed in place.
    x : ndarray, shape (n,)
        Closure, m.
    fit : ndarray, shape (d + 1, w)
        The window's polynomial fit (:func:`_fit_matrix`).
    k : int
        The derivative's order.
    scale : float
        From the ``k``-th polynomial coefficient to the derivative (``k! / (h dt)^k``).
    memo : dict, optional
        The windows' residuals, kept for the other derivatives of the same ``x``.
    """
    from scipy.special import gammaincinv  # chi-square quantiles, without scipy.stats

    d1, w = fit.shape
    n, h = x.size, w // 2
    dof = w - d1
    if dof < 2 or n < 3 * w or h < 2:
        return
    xc = x - float(np.median(x))  # sums of squares without cancellation
    memo = {} if memo is None else memo
    if ("rss", h, d1) not in memo:
        memo["rss", h, d1] = _window_rss(xc, h, d1)
    rss = memo["rss", h, d1]  # by window start
    typical = float(np.median(rss)) / (2.0 * float(gammaincinv(dof / 2, 0.5)))  # variance
    if not typical > 0:
        return
    flagged = np.flatnonzero(rss > typical * 2.0 * float(gammaincinv(dof / 2, BREAK_QUANTILE)))
    if flagged.size == 0 or flagged.size > BREAKS_AT_MOST * rss.size:
        return
    # a window centred on a kink can fit it better than its neighbours: one run of
    # windows about a break may have holes, closed here up to a window's length
    runs = np.split(flagged, np.flatnonzero(np.diff(flagged) > w) + 1)
    # the misfit of a hinge between samples c - 1 and c, on the 4 h + 1 samples about c
    if ("hinged", h, d1) not in memo:
        memo["hinged", h, d1] = _window_rss(xc, 2 * h, d1, hinged=True)
    misfit = memo["hinged", h, d1]  # by centre - 2 h
    kernels = _hinge_kernels(h, d1, k) * (scale / math.factorial(k))
    windows = np.lib.stride_tricks.sliding_window_view(x, w)  # by start
    for run in runs:
        if run[-1] - run[0] > 2 * w:
            continue  # more than one break
        lo, hi = max(int(run[0]) + h, 2 * h), min(int(run[-1]) + h, n - 2 * h - 1)
        if hi < lo:
            continue
        centres = np.arange(lo, hi + 1)
        m = misfit[centres - 2 * h]
        weight = np.exp(-(m - m.min()) / (2.0 * typical))
        likely = weight > 1e-4 * weight.max()
        places, weight = centres[likely], weight[likely] / weight[likely].sum()
        at = np.arange(max(int(places[0]) - h - 1, h), min(int(places[-1]) + h, n - h - 1) + 1)
        values = np.zeros(at.size)
        for c, p in zip(places, weight, strict=True):
            # the hinge at c - 1/2, seen from each sample's window: kernel row c - i + h
            row = np.clip(c - at + h, 0, 2 * h + 1)
            values += p * np.einsum("mw,mw->m", kernels[row], windows[at - h])
        out[at] = values


#: at most this fraction of windows may hold a break for them to be mended
BREAKS_AT_MOST = 0.2


def _window_rss(xc: Array, h: int, d1: int, hinged: bool = False) -> Array:
    """Residual sum of squares of each window of ``2 h + 1`` samples of ``xc`` about
    its least-squares polynomial of ``d1`` coefficients, shape (n - 2 h,), by the
    window's first sample; ``hinged``: about that polynomial plus a kink in its slope
    and a step in its curvature between its centre and the sample before. By
    convolutions: the polynomial part's projection is that of an orthonormal basis,
    the hinge's that of its columns made orthogonal to the polynomials."""
    w = 2 * h + 1
    u = (np.arange(w) - h) / h
    basis = np.linalg.qr(np.vander(u, d1, increasing=True))[0]  # (w, d1), orthonormal
    rss = convolve_valid(xc**2, np.ones(w))
    for q in basis.T:
        rss -= convolve_valid(xc, q[::-1]) ** 2
    if hinged:
        r = np.clip(u + 0.5 / h, 0.0, None)
        hinge = np.column_stack([r, r**2])
        hinge -= basis @ (basis.T @ hinge)
        hinge = np.linalg.qr(hinge)[0]
        for q in hinge.T:
            rss -= convolve_valid(xc, q[::-1]) ** 2
    return np.clip(rss, 0.0, None)


@functools.lru_cache(maxsize=512)
def _hinge_kernels(h: int, d1: int, k: int) -> Array:
    """The ``k``-th derivative (in the window's time over its half-width) at the centre
    of a window of ``2 h + 1`` samples, fitted by a polynomial of ``d1`` coefficients
    plus a kink in its slope and a step in its curvature between samples ``j - 1`` and
    ``j`` of the window, as weights on its samples: row ``j``, shape (2 h + 2, 2 h + 1).
    Rows 0 and 2 h + 1 put the hinge outside the window (the polynomial alone)."""
    w = 2 * h + 1
    u = (np.arange(w) - h) / h
    j = np.arange(1, w)[:, None]  # the hinges inside the window, between j - 1 and j
    r = np.clip((np.arange(w)[None, :] - j + 0.5) / h, 0.0, None)  # (w - 1, w)
    poly = np.vander(u, d1, increasing=True)
    A = np.concatenate([np.broadcast_to(poly, (w - 1, w, d1)), r[..., None], (r**2)[..., None]],
                       axis=2)  # fmt: skip
    coef = np.linalg.pinv(A)  # (w - 1, d1 + 2, w)
    # the derivative at u = 0 (sample h), on its own side of the hinge
    rc = np.clip((h - j[:, 0] + 0.5) / h, 0.0, None)[:, None]
    past = (j[:, 0] <= h).astype(float)[:, None]
    inside = coef[:, k] * math.factorial(k) if k < d1 else np.zeros((w - 1, w))
    if k == 0:
        inside = inside + coef[:, d1] * rc + coef[:, d1 + 1] * rc**2
    elif k == 1:
        inside = inside + coef[:, d1] * past + 2.0 * coef[:, d1 + 1] * rc
    elif k == 2:
        inside = inside + 2.0 * coef[:, d1 + 1] * past
    plain = np.linalg.pinv(poly)[k] * math.factorial(k) if k < d1 else np.zeros(w)
    out = np.vstack([plain, inside, plain])
    return out


#: a lower degree at a session's ends must agree with every higher one within this many
#: SDs of their difference (:func:`_end_values`): an unbiased one is set aside 0.27 % of
#: the time by each comparison
END_SDS = 3.0


def _end_values(xw: Array, u: Array, degree: int, k: int, sigma_x: float) -> Array:
    """The ``k``-th derivative (in the window's time over its half-width) at the
    off-centre points ``u`` (-1 to 1) of one end window ``xw`` of samples, shape like
    ``u``.

    A polynomial fit read off-centre amplifies noise far more than at its centre (at the
    window's edge a degree-7 fit's acceleration has some 30 times the centred noise
    gain), and the ends of a predicted session, a held-out end above all, were dominated
    by it; a lower degree has less noise there but more bias. Each end sample takes the
    lowest degree, from ``k`` up to ``degree`` (the one chosen on centred windows),
    whose estimate agrees with that of every higher degree within ``END_SDS`` SDs of
    their difference (Lepski's rule): a lower degree is taken only where the data show
    no bias in it beyond what the higher degree's extra noise would hide. The fits are
    nested least squares, so that difference's variance is exactly the difference of
    their variances. Without position noise the chosen degree is kept."""
    w = xw.size
    top = min(degree, w - 1)
    values, variances = [], []
    for d in range(k, top + 1):
        fit = _fit_matrix(w, d)
        powers = np.arange(k, d + 1)
        falling = np.array([math.factorial(j) // math.factorial(j - k) for j in powers], float)
        basis = falling * u[:, None] ** (powers - k)
        values.append(basis @ (fit[k:] @ xw))
        gram = fit[k:] @ fit[k:].T
        variances.append(sigma_x**2 * np.einsum("ij,jk,ik->i", basis, gram, basis))
    if not values:
        return np.zeros_like(u)
    chosen = values[-1].copy()
    done = np.zeros(u.size, bool)
    for i in range(len(values) - 1):  # the lowest degree first
        ok = ~done
        for j in range(i + 1, len(values)):
            spread = np.sqrt(np.clip(variances[j] - variances[i], 0.0, None))
            ok &= np.abs(values[i] - values[j]) <= END_SDS * spread
        chosen[ok] = values[i][ok]
        done |= ok
    return chosen


def _samples_on(session: Session, grid: Session) -> Callable[[Array], Array]:
    """A map from values on ``grid`` to values at ``session``'s samples: by sample
    number where the stamps follow a clock, else by time (NaN stays NaN)."""
    if len(grid) == len(session) and np.array_equal(grid.time, session.time):
        return lambda u: np.asarray(u, float)
    numbers, _, _ = sample_clock(session.time)
    if numbers is not None and numbers[-1] < len(grid):
        return lambda u: np.asarray(u, float)[numbers]
    t = grid.time

    def by_time(u: Array) -> Array:
        u = np.asarray(u, float)
        i = np.clip(np.searchsorted(t, session.time), 1, t.size - 1)
        left, right = u[i - 1], u[i]
        frac = (session.time - t[i - 1]) / (t[i] - t[i - 1])
        out = left + np.clip(frac, 0.0, 1.0) * (right - left)
        out[(session.time < t[0]) | (session.time > t[-1])] = np.nan  # off the grid
        return out

    return by_time
