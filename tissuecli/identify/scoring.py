"""One law scored by exact evidence: its sufficient statistics (one pass over its
design matrix), its tempered likelihood and prior, the closed-form posterior and
evidence, and the :class:`ModelResult` that reports them. What every law of one
session shares is a :class:`Context`."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..core.terms import Law, MotionScales
from .derivatives import Kinematics
from .design import design, eiv_correction, lstsq_scaled_cond
from .noise import corrected_curvature
from .posterior import ExactPosterior, Posterior, Prior, SufficientStats, gram_lstsq
from .priors import law_prior
from .whiten import ARFilter

Array = NDArray[np.float64]

#: posterior mass beyond the positivity bounds above which the posterior is sampled
CUT_THRESHOLD = 1e-3


#: the status of a law whose evidence could not be trusted (never chosen)
NOT_EVALUATED = "not evaluated"


@dataclass
class ModelResult:
    """The fit of one law."""

    model: Law
    ln_evidence: float = float("nan")
    probability: float = float("nan")
    posterior: Posterior | None = None
    ln_evidence_sampler: float | None = None
    status: str = "exact"  # exact | emcee | skipped | not evaluated
    reason: str = ""
    cond: float = float("nan")
    cond_scaled: float = float("nan")
    residual_rms: float = float("nan")
    #: blocked cross-validation: RMS of the force each of CV_BLOCKS contiguous blocks
    #: leaves to the law fitted (least squares) to the others, N
    cv_rms: float = float("nan")
    flags: list[str] = field(default_factory=list)
    gram: Array = field(default_factory=lambda: np.zeros((0, 0)), repr=False)  # A^T A
    correction: Array | None = field(default=None, repr=False)  # errors-in-variables, if applied
    stats: SufficientStats | None = field(default=None, repr=False)
    prior: Prior | None = field(default=None, repr=False)
    #: for a law with shape parameters: their posterior (mean, sd, ci95 by name, SI),
    #: the range searched, and the law as fitted before binding
    shape_posterior: dict[str, dict[str, Any]] | None = None
    shape_ranges: dict[str, tuple[float, float]] | None = None
    family: Law | None = field(default=None, repr=False)
    #: the law bound at its least-squares shape and that fit's residual RMS (N):
    #: what BIC compares (the posterior's point may sit elsewhere on a flat shape)
    least_squares: tuple[Law, float] | None = field(default=None, repr=False)
    #: with more than MAX_GRID_SHAPES shape parameters: the shape sampler's diagnostics
    #: (``status`` pending, sampled or skipped, and emcee's figures once sampled)
    shape_sampler: dict[str, Any] | None = None
    sample_shape: Callable[[], None] | None = field(default=None, repr=False, compare=False)
    #: for a law whose sharp shape is marginalised over nodes: its posterior drawn again,
    #: every node exact under the positivity bounds down to an acceptance (None if one
    #: keeps less), the shape still marginalised (the chosen law's, where the search's
    #: draws were not exact)
    redraw: Callable[[np.random.Generator, float], Posterior | None] | None = field(
        default=None, repr=False, compare=False
    )
    #: for a law whose shape posterior piled against the prior's edge on the grid: its
    #: shape and coefficients' posterior made finer, in place (the chosen law's)
    refine: Callable[[np.random.Generator], None] | None = field(
        default=None, repr=False, compare=False
    )

    @property
    def name(self) -> str:
        return (self.family or self.model).name


@dataclass
class FirstPass:
    """What the fit keeps of one form's design matrix: its sufficient statistics."""

    gram: Array
    b: Array
    yy: float
    beta: Array
    rss: float
    cond: float
    cond_scaled: float
    correction: Array | None
    #: what :func:`law_stats` takes from these statistics before any weight (the
    #: corrected curvature and the flag), formed once: a law is scored again at each
    #: data weight the fit tries, and each node of its shape's grid more than once
    untempered: tuple[Array, Array, float, float, Array | None, bool] | None = field(
        default=None, init=False, repr=False, compare=False
    )


def _nothing(name: str) -> None:
    """No progress to tell."""


def _no_progress(name: str) -> None:
    """No chain progress to tell."""


@dataclass
class Context:
    """What every law's fit of one session shares."""

    kin: Kinematics
    x_full: Array
    y: Array
    sigma_x: float
    weight: float
    scales: MotionScales
    columns: dict[str, Array]
    paths: dict[str, tuple[Array, Array]]
    rng: np.random.Generator
    #: first passes of laws with shape parameters, by law and shape: they do not depend
    #: on the data weight, so a fit scored again at another weight reuses them
    shaped_passes: dict[tuple[str, tuple[float, ...]], FirstPass] = field(default_factory=dict)
    #: the spans of closure functions a long session's shaped laws share
    #: (:mod:`~tissuecli.identify.reduced`), and their products, by kind
    spans: dict[Any, Any] = field(default_factory=dict)
    #: told the name of each law scored (the fit's progress)
    scored: Callable[[str], None] = field(default=_nothing, repr=False)
    #: a chain's progress callback for the law of this name, or None
    chain_progress: Callable[[str], Callable[[int, float], None] | None] = field(
        default=_no_progress, repr=False
    )
    #: the best evidence of a trusted law scored at this weight so far (a law that
    #: cannot come near it needs its bounds' mass only roughly: ExactPosterior.rough)
    lead: float = -math.inf
    #: the prewhitened likelihood's filter (:mod:`~tissuecli.identify.whiten`): force
    #: and columns pass through it before their statistics are taken; None: tempered
    whiten: ARFilter | None = None

    @property
    def target(self) -> Array:
        """The force the statistics are taken of: ``y``, through the filter if any."""
        if self.whiten is None:
            return self.y
        cached = getattr(self, "_target", None)
        if cached is None or cached[0] is not self.whiten:
            cached = (self.whiten, self.whiten.transform(self.y))
            self._target = cached
        return cached[1]

    @property
    def rows(self) -> int:
        """Rows of the statistics: ``y``'s, less the filter's order."""
        return self.y.size - (self.whiten.span if self.whiten is not None else 0)


def first_pass(
    model: Law,
    kin: Kinematics,
    x_full: Array,
    y: Array,
    sigma_x: float,
    columns: dict[str, Array] | None = None,
    paths: dict[str, tuple[Array, Array]] | None = None,
    whiten: ARFilter | None = None,
) -> FirstPass:
    """One pass over ``model``'s design matrix at the fitted samples (shape (m, p)):
    its Gram matrix and products with the force ``y`` (N), the least-squares fit and its
    residual, the condition numbers, and the errors-in-variables correction for position
    noise of SD ``sigma_x`` (m). ``columns`` and ``paths`` share the terms' columns and
    noise paths between laws. ``whiten``: the statistics of force and columns passed
    through that filter (the prewhitened likelihood)."""
    A = design(model, kin, x_full, sigma_x, columns)
    if whiten is not None:
        A, y = whiten.transform(A), whiten.transform(y)
    gram = A.T @ A
    b = A.T @ y
    # least squares on unit-norm columns through the Gram matrix (one O(n p^2) product
    # instead of a second factorisation of A), unless it is too ill-conditioned for that
    d = np.sqrt(np.maximum(gram.diagonal(), 1e-300))
    scaled = gram / (d[:, None] * d)  # np.outer's numbers, formed once
    lam_s = np.linalg.eigvalsh(scaled)
    cond_scaled = float(np.sqrt(lam_s[-1] / lam_s[0])) if lam_s[0] > 0 else float("inf")
    if cond_scaled < 1e5:
        beta = np.linalg.solve(scaled, b / d) / d
    else:
        beta, cond_scaled = lstsq_scaled_cond(A, y)
    r = y - A @ beta
    # the raw condition number from the Gram matrix's eigenvalues: a report figure,
    # exact to rounding up to about 1e7, and "large" beyond
    lam = np.linalg.eigvalsh(gram)
    cond = float(np.sqrt(lam[-1] / lam[0])) if lam[0] > 0 else float("inf")
    return FirstPass(
        gram=gram,
        b=b,
        yy=float(y @ y),
        beta=beta,
        rss=float(r @ r),
        cond=cond,
        cond_scaled=cond_scaled,
        correction=(
            eiv_correction(model, kin, x_full, sigma_x, paths, whiten) if sigma_x > 0 else None
        ),
    )


def law_stats(
    model: Law, fp: FirstPass, fit: Context
) -> tuple[SufficientStats, Prior, Array | None, list[str]]:
    """The tempered statistics and prior of one law, and the flags of its noise
    correction."""
    if fp.untempered is None:
        fp.untempered = _untempered(fp)
    G, b, yy, rss, corr, uncorrected = fp.untempered
    w, n = fit.weight, fit.rows
    st = SufficientStats(w * G, w * b, w * yy, w * n, w * rss)
    prior = law_prior(model, fit.scales)
    flags = []
    if uncorrected:
        flags.append(
            "position noise dominates a column: left uncorrected, so M (and "
            "perhaps S) are biased towards zero"
        )
    return st, prior, corr, flags


def kept_correction(fp: FirstPass) -> Array | None:
    """The errors-in-variables correction (p, p) the law's posterior is centred and
    curved by, or None: none applied, or left out as noise dominates a column."""
    if fp.untempered is None:
        fp.untempered = _untempered(fp)
    return fp.untempered[4]


def _untempered(fp: FirstPass) -> tuple[Array, Array, float, float, Array | None, bool]:
    """:func:`law_stats`' statistics before the data weight: the Gram matrix, moment
    vector, ``yy`` and residual sum of squares (corrected for position noise where the
    correction leaves a proper regression), the correction kept, and whether it was
    left out."""
    corr = fp.correction
    corrected = fp.gram - corr if corr is not None else None  # A^T A - C, formed once
    rss_c = _correctable(fp, corr, corrected) if corr is not None else None
    uncorrected = corr is not None and rss_c is None
    if uncorrected:
        corr = None  # noise dominates a column: the correction would be meaningless
    G, b, yy, rss = fp.gram, fp.b, fp.yy, fp.rss
    if corr is not None and rss_c is not None:
        # centred on the corrected fit, with the raw residual: position noise reaches
        # the force through the law's columns, so the residuals about the corrected fit
        # scatter by the force noise and that path together (variance
        # s_f^2 + beta^T Sigma_u beta per row, whose best value given the data is the
        # raw rss / n). Scored on the force noise alone (rss_c), a law gained what its
        # own columns' noise took off: the more noise a law's columns carry, the more
        # it gained, and where that noise was nearly all of the residual rss_c was a
        # difference of two like numbers, near zero or below it (the law then left
        # uncorrected, hundreds of nats behind laws that were not)
        G, b, yy = corrected_curvature(fp.gram, fp.b, corr, fp.rss, fp.rss, corrected)
    return G, b, yy, rss, corr, uncorrected


def prepared(
    model: Law, fp: FirstPass, fit: Context
) -> tuple[SufficientStats, Prior, Array | None, list[str], ExactPosterior]:
    """:func:`law_stats` of one law, and its closed-form posterior (no orthant mass yet)."""
    st, prior, corr, flags = law_stats(model, fp, fit)
    return st, prior, corr, flags, ExactPosterior(st, prior)


def weigh(exact: ExactPosterior, fit: Context) -> str:
    """Why the law's evidence cannot be trusted, or "" (:meth:`ExactPosterior.untrusted`),
    its orthant mass taken roughly if it is far behind ``fit.lead``, which a trusted
    evidence raises."""
    exact.rough(fit.lead)
    why = exact.untrusted()
    if not why:
        fit.lead = max(fit.lead, exact.ln_evidence())
    return why


def exact_result(
    model: Law,
    fp: FirstPass,
    fit: Context,
    ready: tuple[SufficientStats, Prior, Array | None, list[str], ExactPosterior] | None = None,
) -> ModelResult:
    """The closed-form posterior and evidence of one law (``ready``: its
    :func:`prepared`, if at hand)."""
    st, prior, corr, flags, exact = ready if ready is not None else prepared(model, fp, fit)
    why = weigh(exact, fit)
    post = exact.bounded(fit.rng, CUT_THRESHOLD)
    if corr is not None:
        # the correction rests on an estimated noise level: say when it matters
        shift = post.mean - fp.beta
        for j in np.flatnonzero(np.abs(shift) > post.sd):
            flags.append(
                f"{model.symbols[j]} moved {100 * shift[j] / post.mean[j]:+.1f} % by the "
                f"position-noise correction (noise {fit.sigma_x * 1e6:.3g} um); its "
                "interval does not include that correction's own uncertainty"
            )
    fit.scored(model.name)
    res = result_of(model, post, fp, fit, st, prior, corr, flags)
    if why:
        not_evaluated(res, why)
    return res


def result_of(
    model: Law,
    post: Posterior,
    fp: FirstPass,
    fit: Context,
    st: SufficientStats,
    prior: Prior,
    corr: Array | None,
    flags: list[str],
    family: Law | None = None,
) -> ModelResult:
    """A law's result from its posterior and its least-squares pass over ``fit``."""
    return ModelResult(
        model=model,
        ln_evidence=post.ln_evidence,
        posterior=post,
        cond=fp.cond,
        cond_scaled=fp.cond_scaled,
        residual_rms=float(np.sqrt(fp.rss / fit.rows)),
        gram=fp.gram,
        correction=corr,
        stats=st,
        prior=prior,
        flags=flags,
        family=family,
    )


def not_evaluated(res: ModelResult, why: str) -> None:
    """Mark a law's evidence as untrusted: it ranks below every evaluated law and is
    never chosen; its estimate stays in the posterior for the record."""
    res.status = NOT_EVALUATED
    res.reason = f"not evaluated: {why}"
    res.ln_evidence = -math.inf


#: smallest eigenvalue of the corrected Gram matrix on unit-norm columns that counts
#: as positive definite (rounding leaves about 1e-16 there)
DEFINITE = 1e-12


def _correctable(fp: FirstPass, corr: Array, corrected: Array | None = None) -> float | None:
    """The corrected fit's residual sum of squares (:func:`_corrected_rss`, N^2) if the
    errors-in-variables correction leaves a proper regression, else None: ``A^T A - C``
    positive definite, and a corrected residual of at least a tenth of the raw one (the
    correction takes off what position noise adds to the residual; taking off nearly
    all of it, or more, says the noise is as large as the motion). ``corrected``:
    ``A^T A - C``, if at hand.

    Definiteness is judged on unit-norm columns (``A^T A - C`` over the outer product
    of the columns' norms), to :data:`DEFINITE` of the unit diagonal: columns whose
    norms differ by 1e8 (a contact stiffness in N/m^n beside an inertia) leave the
    raw matrix's smallest eigenvalue at 1e-16 of its largest, where rounding alone
    decides its sign, and a shape that moved by a millionth of its SD then switched
    the correction on or off (the law's evidence jumping by hundredths of a nat,
    which finite differences of the evidence over the shape read as curvature)."""
    G = fp.gram - corr if corrected is None else corrected
    d = np.sqrt(np.maximum(fp.gram.diagonal(), 1e-300))
    if np.any(np.linalg.eigvalsh(G / (d[:, None] * d)) <= DEFINITE):
        return None
    rss = _corrected_rss(fp, corr, G)
    return rss if rss > 0.1 * fp.rss else None


def _corrected_rss(fp: FirstPass, corr: Array, corrected: Array | None = None) -> float:
    """The residual sum of squares of the errors-in-variables corrected fit, N^2:
    ``rss - beta_c^T C beta`` (``yy - beta_c^T b`` cancels to rounding when the law
    explains all but a millionth of ``yy``). Solved on unit-norm columns: unscaled, an
    ``x^3`` column beside an offset's fell below the solver's cut-off, and the corrected
    fit without it took a third of the residual away. ``corrected``: ``A^T A - C``, if
    at hand."""
    beta_c = gram_lstsq(fp.gram - corr if corrected is None else corrected, fp.b)
    return fp.rss - float(beta_c @ corr @ fp.beta)
