"""Peer estimators of the tissue law, and the Cramér-Rao bound, for benchmarks.

Usage::

    pip install -e ".[bench]"
    python benchmarks/peers.py --bits 8,12 --duration 10

Every peer takes a :class:`~tissuecli.session.Session` and returns a
:class:`PeerResult`: the chosen form, ``(K, S, M)`` in SI for that form and the
wall-clock time, so that a harness can put them next to
:class:`~tissuecli.identify.BayesianFit` on the same sessions.

PySINDy (:func:`pysindy_fit`)
    PySINDy's core API (``ps.SINDy``) fits ``dx/dt = Theta(x) Xi``: a state's
    derivative on a library of candidate functions of the state. The tissue
    law has a different shape, ``F = Theta(x, xdot, xddot) Xi``, with the
    measured force, not a derivative, on the left. So PySINDy's parts are used
    directly, each for what it is documented to do:

    1. ``ps.SmoothedFiniteDifference`` (its default smoother, a Savitzky-Golay
       filter of order 3, then second-order central differences) gives xdot
       (``d=1``) and xddot (``d=2``) from position; the library is evaluated
       on its smoothed position ``smoothed_x_``, exactly as ``SINDy.fit`` does.
       The window is ``window_s`` (0.1 s: 101 samples at 1 kHz).
    2. A ``ps.GeneralizedLibrary`` of two ``ps.CustomLibrary`` and one
       ``ps.IdentityLibrary``, each restricted to one input
       (``inputs_per_library``), builds exactly the five candidate terms
       ``[x, x^3, xdot, xdot|xdot|, xddot]``.
    3. The sparse regression ``ps.STLSQ`` is fitted on that feature matrix with
       the measured force as target (``optimizer.fit(Theta, F)``), with
       ``normalize_columns=True``: each coefficient is then the L2 norm of its
       term's contribution over the record, so one threshold applies to all
       five terms whatever their units (x^3 in m^3 is a million times smaller
       than x in m). The threshold is ``threshold`` (0.2 %) times the norm of
       the force: a term contributing less than that is dropped. After
       thresholding, STLSQ refits the surviving terms by least squares
       (``unbias=True``).

    The force is not filtered (SINDy filters only the state it differentiates)
    and the edges, half a window at each end, are trimmed. The chosen
    stiffness form is whichever of x and x^3 has the larger contribution after
    thresholding, and likewise xdot and xdot|xdot| for damping; a term zeroed
    by the threshold contributes nothing, so the survivor of a pair is chosen
    (if both were zeroed, the larger in the first, unthresholded, least-squares
    solution). ``params`` are the STLSQ coefficients of the chosen terms and of
    xddot; a coefficient zeroed by the threshold is reported as 0.

lmfit with emcee (:func:`lmfit_emcee_fit`)
    As a user of lmfit would do it: kinematics from ``scipy.signal.savgol_filter``
    (order 3, the same 0.1 s window, ``deriv=0, 1, 2`` with ``delta`` set to the
    sample interval), edges trimmed, raw force as data; a residual function
    ``F - (K f0(x) + S f1(xdot) + M xddot)`` with ``K, S, M >= 0`` (``min=0``)
    for each of the four forms, fitted by ``Minimizer.minimize(method="leastsq")``
    from starting values that make each term alone explain a third of the RMS
    force. The form with the lowest BIC (as lmfit reports it) is chosen, and
    only that form is sampled by ``Minimizer.emcee(steps, burn, thin,
    is_weighted=False)``, with ``__lnsigma`` (the unknown noise level) started
    at the least-squares residual SD as lmfit's documentation shows. ``params``
    are the emcee medians (lmfit's ``result.params`` after ``emcee``).

Cramér-Rao bound (:func:`cramer_rao`)
    For the linear-Gaussian model ``F = A beta + e``, ``A = [f0(x), f1(xdot),
    xddot]`` at the exact kinematics, with white force noise of SD ``sigma``
    (analogue noise and the ADC step / sqrt(12) combined), the Fisher
    information of ``beta = (K, S, M)`` is ``A^T A / sigma^2`` and its inverse
    bounds the covariance of any unbiased estimator. It ignores position noise
    and quantisation: every estimator here must differentiate noisy positions,
    so the bound is a floor none of them can beat, but not always one they can
    reach.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import time
import warnings
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray
from scipy.signal import savgol_filter

from tissuecli.core.session import Session
from tissuecli.core.terms import Law, paper_laws
from tissuecli.core.tissue import Tissue
from tissuecli.identify import BayesianFit
from tissuecli.identify.prepare import longest_gapless
from tissuecli.sim.synth import ForcepsModel, Sensors, synthesize

if TYPE_CHECKING:
    import lmfit

Array = NDArray[np.float64]

#: Candidate terms of the PySINDy library, in column order.
TERMS = ("x", "x^3", "xdot", "xdot|xdot|", "xddot")
#: Savitzky-Golay window (s) and polynomial order shared by both peers.
WINDOW_S = 0.1
POLYORDER = 3


@dataclass
class PeerResult:
    """What a peer estimator returns.

    Attributes
    ----------
    name : str
        The peer, e.g. ``"pysindy-stlsq"`` or ``"lmfit-emcee"``.
    model : str
        The chosen form, ``"x,xdot"`` style, or ``""`` if the peer does not choose.
    params : ndarray, shape (3,)
        ``(K, S, M)`` in SI for that form; nan where the peer gives no value.
    seconds : float
        Wall-clock time of the whole fit, differentiation included.
    note : str
        Anything the reader of a comparison should know about this run.
    """

    name: str
    model: str
    params: Array
    seconds: float
    note: str = ""


def _kinematics_input(session: Session, window_s: float) -> tuple[Session, float, int, str]:
    """The longest gap-free stretch, its sample interval, an odd window length and a note."""
    session.validate()
    part, warn = longest_gapless(session)
    dt = float(np.median(np.diff(part.time)))
    window = max(int(round(window_s / dt)) | 1, (POLYORDER + 2) | 1)
    if len(part) < 2 * window:
        raise ValueError(
            f"{len(part)} samples are too few for a {window}-sample Savitzky-Golay window"
        )
    return part, dt, window, "; ".join(warn)


def pysindy_fit(
    session: Session,
    *,
    seed: int = 0,
    window_s: float = WINDOW_S,
    threshold: float = 0.002,
) -> PeerResult:
    """Sparse regression of force on five candidate terms with PySINDy (STLSQ).

    Parameters
    ----------
    session : Session
        Time (s), force (N) and position (m).
    seed : int
        Accepted for a uniform interface; STLSQ is deterministic.
    window_s : float
        Savitzky-Golay window of ``ps.SmoothedFiniteDifference``, in s.
    threshold : float
        STLSQ threshold as a fraction of the force's L2 norm (columns are
        normalised, so coefficients are L2 norms of each term's contribution).

    Returns
    -------
    PeerResult
        ``name="pysindy-stlsq"``; ``note`` lists the terms STLSQ kept.
    """
    import pysindy as ps

    del seed  # deterministic
    t0 = time.perf_counter()
    part, dt, window, note = _kinematics_input(session, window_s)
    x = part.position[:, None]

    def sfd(order: int) -> ps.SmoothedFiniteDifference:
        # a fresh dict each time: pysindy adds "axis" to the one it is given
        kws = {"window_length": window, "polyorder": POLYORDER}
        return ps.SmoothedFiniteDifference(d=order, smoother_kws=kws)

    velocity = sfd(1)
    v = velocity(x, t=dt)[:, 0]
    a = sfd(2)(x, t=dt)[:, 0]
    xs = np.asarray(velocity.smoothed_x_)[:, 0]

    library = ps.GeneralizedLibrary(
        [
            ps.CustomLibrary([lambda u: u, lambda u: u**3], [lambda u: u, lambda u: f"{u}^3"]),
            ps.CustomLibrary(
                [lambda u: u, lambda u: u * np.abs(u)], [lambda u: u, lambda u: f"{u}|{u}|"]
            ),
            ps.IdentityLibrary(),
        ],
        inputs_per_library=[[0], [1], [2]],
    )
    theta = np.asarray(library.fit_transform(np.column_stack([xs, v, a])))
    names = tuple(library.get_feature_names(["x", "xdot", "xddot"]))
    if names != TERMS:
        raise RuntimeError(f"unexpected PySINDy library {names}; expected {TERMS}")
    h = window // 2
    theta, force = theta[h:-h], part.force[h:-h]

    optimizer = ps.STLSQ(threshold=threshold * float(np.linalg.norm(force)), normalize_columns=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "eliminated all coefficients" is handled below
        optimizer.fit(theta, force)
    coef = np.asarray(optimizer.coef_)[0]
    norms = np.linalg.norm(theta, axis=0)
    contribution = np.abs(coef) * norms
    first = np.abs(np.asarray(optimizer.history_[0])[0]) * norms  # plain least squares

    def pick(i: int, j: int) -> int:
        if contribution[i] == 0 and contribution[j] == 0:
            return i if first[i] >= first[j] else j
        return i if contribution[i] >= contribution[j] else j

    i0, i1 = pick(0, 1), pick(2, 3)
    model = Law.paper("x" if i0 == 0 else "x^3", "xdot" if i1 == 2 else "xdot^2")
    kept = [t for t, c in zip(TERMS, coef, strict=True) if c != 0]
    notes = [f"STLSQ kept {', '.join(kept) or 'nothing'}", f"window {window} samples"]
    if note:
        notes.append(note)
    return PeerResult(
        name="pysindy-stlsq",
        model=model.name,
        params=np.array([coef[i0], coef[i1], coef[4]], dtype=float),
        seconds=time.perf_counter() - t0,
        note="; ".join(notes),
    )


def _residual(p: lmfit.Parameters, model: Law, x: Array, v: Array, a: Array, f: Array) -> Array:
    """Unweighted residual ``F - (K f0(x) + S f1(xdot) + M xddot)`` for lmfit (N)."""
    coef = [p[name].value for name in "KSM"]
    return f - model.force(coef, x, v, a)


def lmfit_emcee_fit(
    session: Session,
    *,
    steps: int = 2000,
    seed: int = 0,
    burn: int | None = None,
    thin: int = 10,
    nwalkers: int = 100,
    window_s: float = WINDOW_S,
) -> PeerResult:
    """Least squares for each form with lmfit, BIC choice, then emcee on the chosen form.

    Parameters
    ----------
    session : Session
        Time (s), force (N) and position (m).
    steps : int
        emcee steps per walker.
    seed : int
        Seed of emcee's walkers.
    burn : int, optional
        Steps discarded at the start; ``steps // 4`` by default.
    thin : int
        Keep every ``thin``-th step.
    nwalkers : int
        emcee walkers (lmfit's default, 100).
    window_s : float
        Savitzky-Golay window (``scipy.signal.savgol_filter``), in s.

    Returns
    -------
    PeerResult
        ``name="lmfit-emcee"``; ``note`` gives the BIC of each form, the
        acceptance fraction and emcee's autocorrelation warning, if any.
    """
    import lmfit

    burn = steps // 4 if burn is None else burn
    t0 = time.perf_counter()
    part, dt, window, note = _kinematics_input(session, window_s)
    h = window // 2
    x, v, a = (
        savgol_filter(part.position, window, POLYORDER, deriv=d, delta=dt)[h:-h] for d in (0, 1, 2)
    )
    f = part.force[h:-h]
    rms_f = float(np.sqrt(np.mean(f * f)))

    fits, starts = {}, {}
    for model in paper_laws():
        params = lmfit.Parameters()
        for name, column in zip("KSM", model.regressors(x, v, a).T, strict=True):
            scale = float(np.sqrt(np.mean(column * column)))
            params.add(name, value=rms_f / (3.0 * scale) if scale > 0 else 1.0, min=0.0)
        starts[model.name] = {name: params[name].value for name in "KSM"}
        minimizer = lmfit.Minimizer(_residual, params, fcn_args=(model, x, v, a, f))
        fits[model.name] = (minimizer, minimizer.minimize(method="leastsq"))
    best = min(fits, key=lambda name: fits[name][1].bic)
    minimizer, ls = fits[best]

    start = ls.params.copy()
    for name in "KSM":  # walkers start at value * (1 + 1e-4 N(0, 1)): none may sit at 0
        if start[name].value <= 0:
            start[name].set(value=1e-6 * starts[best][name])
    sd = max(float(np.std(ls.residual)), 1e-12)
    start.add("__lnsigma", value=np.log(sd), min=np.log(sd / 10), max=np.log(sd * 10))
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):  # lmfit prints emcee's autocorrelation warning
        sampled = minimizer.emcee(
            params=start,
            steps=steps,
            nwalkers=nwalkers,
            burn=burn,
            thin=thin,
            is_weighted=False,
            seed=seed,
            progress=False,
        )
    seconds = time.perf_counter() - t0

    bics = ", ".join(f"{name} {fit.bic:.1f}" for name, (_, fit) in fits.items())
    notes = [
        f"BIC {bics}",
        f"emcee on {best} only: {nwalkers} walkers x {steps} steps, burn {burn}, thin {thin}, "
        f"acceptance {float(np.mean(sampled.acceptance_fraction)):.2f}",
    ]
    if "shorter than 50" in printed.getvalue():
        notes.append("chain shorter than 50 autocorrelation times")
    if note:
        notes.append(note)
    return PeerResult(
        name="lmfit-emcee",
        model=best,
        params=np.array([sampled.params[name].value for name in "KSM"], dtype=float),
        seconds=seconds,
        note="; ".join(notes),
    )


def cramer_rao(truth_tissue: Tissue, model: ForcepsModel, duration_s: float) -> Array:
    """Cramér-Rao lower bound on the SD of (K, S, M) for known exact kinematics.

    Parameters
    ----------
    truth_tissue : Tissue
        The true law; its forms build the regressors.
    model : ForcepsModel
        Operator (exact x, xdot, xddot at the sample times), rate and sensors
        (force noise SD and ADC step).
    duration_s : float
        Session length; ``n = round(duration_s * rate_hz)`` samples.

    Returns
    -------
    ndarray, shape (3,)
        ``sqrt(diag(inv(A^T A / sigma^2)))`` in the units of K, S and M, with
        ``sigma^2 = force_noise_n^2 + step^2 / 12``.

    Notes
    -----
    Position noise and quantisation are ignored (the kinematics are taken as
    known), so no estimator working from measured positions can beat this
    bound, though none is guaranteed to reach it either.
    """
    n = int(round(duration_s * model.rate_hz))
    x, v, a, _ = model.truth(np.arange(n))
    A = truth_tissue.law.regressors(x, v, a)
    step = model.sensors.calibration.force.gain
    sigma2 = model.sensors.force_noise_n**2 + step**2 / 12.0
    d = np.linalg.norm(A, axis=0)  # unit-norm columns: x^3 in SI is 1e6 smaller than x
    d[d == 0] = 1.0
    cov = np.linalg.inv((A / d).T @ (A / d)) * sigma2
    return np.sqrt(np.diag(cov)) / d


def _bayes(session: Session) -> PeerResult:
    """tissuecli's own BayesianFit in the peers' format, for the comparison table."""
    t0 = time.perf_counter()
    fit = BayesianFit("paper").fit(session)
    assert fit.best_.posterior is not None
    return PeerResult(
        name="tissuecli-bayes",
        model=fit.best_.name,
        params=np.asarray(fit.best_.posterior.mean, dtype=float),
        seconds=time.perf_counter() - t0,
        note=f"probability {fit.best_.probability:.3f}",
    )


def main() -> None:
    """Print each peer's form, relative errors and time next to BayesianFit."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bits", default="8,12")
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--steps", type=int, default=2000)
    args = ap.parse_args()
    header = (
        f"{'bits':>4} {'estimator':<16} {'form':<11} {'dK %':>8} {'dS %':>8} {'dM %':>8} {'s':>7}"
    )
    for bits in (int(b) for b in args.bits.split(",")):
        model = ForcepsModel(seed=args.seed, sensors=Sensors(bits=bits))
        truth = model.tissue
        session, _ = synthesize(model, args.duration)
        crb = cramer_rao(truth, model, args.duration)
        print(header)
        results = [
            _bayes(session),
            pysindy_fit(session, seed=args.seed),
            lmfit_emcee_fit(session, steps=args.steps, seed=args.seed),
        ]
        for r in results:
            if r.model == truth.law.name:
                err = " ".join(f"{e:+8.3f}" for e in 100 * (r.params / truth.coef - 1))
            else:
                err = f"{'-':>8} {'-':>8} {'-':>8}"
            print(f"{bits:>4} {r.name:<16} {r.model:<11} {err} {r.seconds:7.2f}  {r.note}")
        print(
            f"{bits:>4} {'CRB (SD)':<16} {truth.law.name:<11} "
            + " ".join(f"{e:8.3f}" for e in 100 * crb / truth.coef)
        )
        print()


if __name__ == "__main__":
    main()
