"""Bayesian identification of ``K f0(x) + S f1(xdot) + M xddot = F`` over every form:
exact posteriors and evidences where they exist, emcee where the positivity bounds
cut the posterior, posterior probabilities of the forms, and diagnostics.

The estimator has the scikit-learn shape (keyword hyperparameters, ``fit(session)``
returning self, fitted attributes ending in ``_``, :meth:`BayesianFit.predict`).
It works on arrays; reading and writing files is the caller's business.
"""

from __future__ import annotations

import itertools
import math
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..core.errors import FitError
from ..core.progress import SILENT, Progress, as_progress
from ..core.session import Session
from ..core.terms import (
    MAX_BRANCHES,
    Law,
    MotionScales,
    paper_laws,
    parse_law,
    searched,
    term,
)
from .derivatives import Differentiator, Kinematics
from .design import (
    design,
    eiv_correction,
    lstsq_scaled_cond,
    noise_path,
    position_noise_sd,
    raw_speed,
    term_column,
    term_noise_path,
)
from .estimator import Estimator
from .identifiable import PREFERENCE, Design, examine
from .noise import corrected_curvature, data_weight, filter_tau, residual_tau
from .posterior import CHECK_NATS, ExactPosterior, Posterior, Prior, SufficientStats
from .shapes import (
    ShapeGrid,
    hermite_nodes,
    kept,
    laplace,
    mix,
    resolvable,
    shape_grid,
    shape_summary,
    tau_range,
)

Array = NDArray[np.float64]

#: ln Bayes factor beyond which a form is decisively behind (Jeffreys: 100:1)
DECISIVE = float(np.log(100.0))


#: a residual SD below this fraction of the force range is rounding, not sensor noise
NOISE_FREE = 1e-6

#: posterior mass beyond the positivity bounds above which the posterior is sampled
CUT_THRESHOLD = 1e-3

#: shape parameters up to which a grid (and a Laplace approximation) marginalises the
#: shape; beyond, emcee samples it
MAX_GRID_SHAPES = 2

#: each further relaxation branch needs the resolvable range of time constants to
#: span this factor more (k branches: BRANCH_SPREAD**k)
BRANCH_SPREAD = 4.0

#: the data weight the best law's residuals support may fall this far below the
#: filter's before the laws are scored again at it
WEIGHT_SLACK = 2.0

#: draws of the shape's chain whose conditional posteriors make the coefficients' one
SHAPE_MIXTURE = 8


def linear_laws() -> list[Law]:
    """Every law linear in its coefficients that the default search enumerates: stiffness
    x, x^3 or both; damping xdot or xdot|xdot|; with or without dry friction; with or
    without an offset; all with inertia (24 laws)."""
    out = []
    for stiffness in (("x",), ("x^3",), ("x", "x^3")):
        for damping in ("xdot", "xdot|xdot|"):
            for friction in ((), ("sign(xdot)",)):
                for offset in ((), ("offset",)):
                    out.append(Law.of([*stiffness, damping, *friction, "xddot", *offset]))
    return out


def parse_forms(spec: str | Sequence[str | Law] | None) -> list[Law]:
    """The candidate laws: ``"all"``/None or ``"linear"`` (the 24 of :func:`linear_laws`;
    ``all`` then searches relaxation and contact from the best of them), ``"paper"``
    (the paper's four), one law (``x,xdot`` or ``x+x^3+xdot+offset+xddot``,
    ``x+maxwell+xdot+xddot``), or a list of them."""
    if spec is None or spec in ("all", "linear"):
        return linear_laws()
    if spec == "paper":
        return paper_laws()
    specs = [spec] if isinstance(spec, (str, Law)) else list(spec)
    laws = [item if isinstance(item, Law) else parse_law(item) for item in specs]
    if not laws:
        raise FitError("no law to fit; give --forms all, paper or a law such as x,xdot")
    return list(dict.fromkeys(laws))


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

    @property
    def name(self) -> str:
        return (self.family or self.model).name


class BayesianFit(Estimator):
    """Bayesian identification over candidate laws with model choice.

    Parameters
    ----------
    forms : str, Law or list of them
        ``"all"`` (the 24 linear laws of :func:`linear_laws`, then a greedy search
        adding contact and up to three relaxation branches), ``"linear"`` (the 24
        alone), ``"paper"`` (the paper's four), or laws such as ``"x,xdot"`` or
        ``"x+x^3+xdot+offset+xddot"``.
    sampler : {"auto", "emcee"}
        ``auto`` samples only where the exact posterior does not apply (the
        positivity bound cuts it); ``emcee`` samples every form not skipped,
        and also estimates its evidence by stepping-stone as a check.
    differentiator : str or Differentiator
    eiv : bool
        Correct the errors-in-variables bias from position noise.
    force_scale : float, optional
        N. Sets the priors: each term of the law is expected to stay within this
        force at the session's typical closure, speed and acceleration. By default
        five times the largest force of the session (:func:`session_scales`).
    decisive : float
        ln Bayes factor behind the best beyond which a form is not sampled.
    seed : int
    grasps : {"all", "none"} or list of int
        Where the session alternates grasps with free motion: fit every grasp, every
        sample, or the grasps numbered (from 1).
    progress : Progress or callable, optional
        Told the stages (filtering, the structure search law by law, sampling); a bare
        callable is called ``progress(form, steps, tau)`` while sampling.

    Attributes
    ----------
    results_ : list of ModelResult
        One per form, best first.
    best_ : ModelResult
    kinematics_ : Kinematics
    session_ : Session
        What was fitted: the session on its sample grid, lost samples interpolated
        (the kinematics leave out every filtered sample that depends on them).
    tau_ : float
        Integrated autocorrelation time of the best form's residuals (samples).
    n_eff_ : float
        Effective independent samples, n / tau.
    sigma_x_ : float
        Position noise SD estimated from its spectrum (m).
    scales_ : MotionScales
        The session's typical closure, speed, acceleration and force behind the priors.
    contact_ : Contact
        The grasps found in the session.
    expected_residual_sd_ : float
        Residual SD the best form expects (N): force noise plus position noise
        carried through the law.
    warnings_ : list of str
    law_, coef_, coef_sd_, coef_ci95_, tissue_
        As every estimator (:class:`~tissuecli.identify.estimator.Estimator`): the chosen
        law, its posterior means, SDs and 95 % intervals.
    """

    def __init__(
        self,
        forms: str | Law | Sequence[str | Law] = "all",
        *,
        sampler: str = "auto",
        differentiator: str | Differentiator = "gaussian",
        eiv: bool = True,
        decisive: float = DECISIVE,
        force_scale: float | None = None,
        seed: int = 0,
        grasps: str | Sequence[int] = "all",
        progress: Progress | Callable[[str, int, float], None] | None = None,
    ) -> None:
        self.forms = forms
        self.grasps = grasps
        self.force_scale = force_scale
        self.sampler = sampler
        self.differentiator = differentiator
        self.eiv = eiv
        self.decisive = decisive
        self.seed = seed
        self.progress = progress

    def fit(self, session: Session) -> BayesianFit:
        """Fit every candidate law to ``session``; returns self with the fitted
        attributes set.

        Raises
        ------
        FitError
            If the session cannot identify anything (too short, constant, not finite);
            no fitted attribute is set then.
        """
        if self.sampler not in ("auto", "emcee"):
            raise FitError(f"unknown sampler {self.sampler!r}; choose auto or emcee")
        models = parse_forms(self.forms)
        self._progress = as_progress(self.progress)
        self._progress.stage("filtering and finding grasps")
        ready = self.prepare(session)
        session, kin, warnings, contact = (
            ready.session,
            ready.kinematics,
            ready.warnings,
            ready.contact,
        )
        sigma_x = self._position_noise(session, ready.trusted) if self.eiv else 0.0
        y = kin.force
        rng = np.random.default_rng(self.seed)
        scales = session_scales(kin, self.force_scale)

        # one pass per law keeps only its sufficient statistics; the terms' columns are
        # computed once and shared by every law that has them
        columns: dict[str, Array] = {}
        # what the recording can tell apart, before any evidence: the default search
        # never compares laws that differ only by a column the design leaves empty
        whole_search = self.forms in (None, "all", "linear")
        # laws asked for by name: only their own terms are examined (a note on columns
        # no law here has would only puzzle)
        present = {t.name for m in models for t in m.terms}
        names = PREFERENCE if whole_search else [n for n in PREFERENCE if n in present]
        design_ = examine(kin, session.position, sigma_x, columns, names, scales=scales)
        self.design_ = design_
        if design_.summary:
            warnings.append(design_.summary)
        if whole_search:
            models = design_.reduce(models)
        paths: dict[str, tuple[Array, Array]] = {}  # and their noise paths
        linear = [m for m in models if not m.shape_names]
        shaped = [m for m in models if m.shape_names]
        x_full = session.position
        firsts = {m.name: _first_pass(m, kin, x_full, y, sigma_x, columns, paths) for m in linear}
        if not firsts:  # shaped laws only: their middle node stands in for the residuals
            m0 = shaped[0]
            nodes = shape_grid(m0, kin).nodes
            firsts = {m0.name: _first_pass(m0.bind(nodes[len(nodes) // 2]), kin, x_full, y,
                                           sigma_x, columns)}  # fmt: skip
        # the least-squares fit that explains the data best (by BIC): a warning if it
        # lies far outside the priors
        n_rows = y.size
        best_name = min(
            firsts,
            key=lambda k: (
                n_rows * np.log(max(firsts[k].rss, 1e-300) / n_rows)
                + firsts[k].beta.size * np.log(n_rows)
            ),
        )
        best_ls = next((m for m in linear if m.name == best_name), None)
        if best_ls is not None:
            warnings.extend(_prior_conflict(best_ls, firsts[best_name].beta, scales))
        # How much one sample counts. The filter that smooths the force makes white
        # noise correlated over tau_g = (sum g)^2 / sum g^2 samples: a likelihood
        # tempered by 1 / tau_g is that of the prewhitened residuals to second order,
        # whatever any law's misfit. The best-fitting linear law's residuals (their
        # correlation time, and a batch-means check for noise in the regressors) refine
        # it, unless they give less than half of it: then a linear law's misfit is what
        # correlates them (relaxation it cannot follow), and taken as the weight it
        # shrank a 10,000-sample session to 13-27 samples and let every law tie; the
        # filter's weight stands, and the chosen law's residuals check it after the
        # search. Bridged stand-ins are not measurements: each counts less.
        tau_filter = filter_tau(kin.kernels[0])
        measured = ready.measured_fraction
        weight_filter = measured / tau_filter
        A = design(best_ls, kin, x_full, sigma_x, columns) if best_ls is not None else None
        tau, weight = tau_filter, weight_filter
        if A is not None:
            residual = y - A @ firsts[best_name].beta
            tau_ls = residual_tau(residual)
            weight_ls = data_weight(A, residual, tau_ls) * measured
            if weight_ls >= weight_filter / WEIGHT_SLACK:
                tau, weight = tau_ls, weight_ls
        del A
        collapsed = weight == weight_filter

        fit = _Context(kin, x_full, y, sigma_x, weight, scales, columns, paths, rng)
        self._scored = 0
        self._known = len(linear) + len(shaped)
        self._progress.stage("structure search", self._known)
        results, found = self._candidates(linear, shaped, firsts, fit)
        # The chosen law's residuals check the weight: correlated beyond it (coloured
        # sensor noise, or no candidate fits), or coefficients more variable across
        # blocks than the tempered likelihood says (noise in the regressors), the data
        # count for less, and every law is scored again at that weight.
        tau_best, weight_best = self._residual_weight(results, fit, measured)
        if weight_best < weight / WEIGHT_SLACK or (collapsed and weight_best < weight):
            tau, weight = tau_best, weight_best
            fit = replace(fit, weight=weight)
            self._progress.stage("structure search, scored again", self._known)
            self._scored = 0
            results, found = self._candidates(linear, shaped, firsts, fit)
        warnings.extend(found)
        del columns
        self._progress.stage("sampling")
        ranked = [r for r in results if r.status != NOT_EVALUATED] or results
        self._sample_shapes(ranked)
        self._sample(ranked, rng)
        results = self._set_aside(results, warnings)
        ln_z = np.array([r.ln_evidence for r in results])
        prob = np.exp(ln_z - ln_z.max())
        prob /= prob.sum()
        for r, p in zip(results, prob, strict=True):
            r.probability = float(p)
            r.flags.extend(_identifiability(r))
        if self.forms in (None, "all", "linear"):
            results = self._drop_unidentified(results, fit)
        results.sort(key=lambda r: (-r.probability, -r.ln_evidence))
        best = results[0]
        warnings.extend(_predictive_guard(results, fit))
        warnings.extend(f"{best.name}: {f}" for f in best.flags)
        span = float(np.ptp(y))
        if best.posterior.sigma_mean < NOISE_FREE * span:  # type: ignore[union-attr]
            # no sensor resolves a millionth of its range: this is rounding, not noise
            warnings.append(
                f"the force residual ({best.posterior.sigma_mean:.3g} N) is below a millionth "  # type: ignore[union-attr]
                f"of the force range ({span:.3g} N): the session looks noise-free "
                "(synthetic?), so its intervals reflect rounding, not measurement noise"
            )
        fitted = design(best.model, kin, session.position, sigma_x) @ best.posterior.mean  # type: ignore[union-attr]
        warnings.extend(_outlier_warnings(kin, fitted))

        self.session_ = session
        self.kinematics_ = kin
        self.sigma_x_ = sigma_x
        self.scales_ = scales
        self.contact_ = contact
        self.tau_ = tau
        self.n_eff_ = y.size * weight
        self.results_ = results
        self.best_ = best
        self.expected_residual_sd_ = _expected_residual_sd(best, sigma_x, y.size)
        self.warnings_ = warnings
        return self

    def _drop_unidentified(self, results: list[ModelResult], fit: _Context) -> list[ModelResult]:
        """Never keep a term the fit itself reports as not identified: while the most
        probable law has such terms, its probability passes to the best (by evidence)
        of its sub-laws whose terms are all identified, the law without the unidentified
        terms among them (scored if the search had not). A term the data do not pin
        down cannot be what made its law probable."""
        by_name = {r.name: r for r in results}

        def names_of(r: ModelResult) -> list[str]:
            return [t.name for t in (r.family or r.model).terms]

        for _ in range(4):
            best = max(results, key=lambda r: (r.probability, r.ln_evidence))
            bad = _unidentified(best)
            if not bad or best.status == NOT_EVALUATED:
                break
            terms = (best.family or best.model).terms
            names = [t.name for j, t in enumerate(terms) if j not in bad]
            if "contact*xdot" in names and "contact" not in names:
                names.remove("contact*xdot")
            if any(n in ("x", "x^3", "contact") for n in names):
                law = Law.of(names)
                if law.name not in by_name:
                    if law.shape_names:
                        new = self._exact_shaped(law, fit)
                    else:
                        fp = _first_pass(law, fit.kin, fit.x_full, fit.y, fit.sigma_x,
                                         fit.columns, fit.paths)  # fmt: skip
                        new = self._exact(law, fp, fit)
                    new.probability = 0.0
                    new.flags.extend(_identifiability(new))
                    results.append(new)
                    by_name[new.name] = new
            mine = Counter(names_of(best))
            subs = [
                r for r in results
                if r is not best and r.status != NOT_EVALUATED and not _unidentified(r)
                and not Counter(names_of(r)) - mine
            ]  # fmt: skip
            if not subs:
                break
            smaller = max(subs, key=lambda r: r.ln_evidence)
            symbols = ", ".join(terms[j].symbol for j in sorted(bad))
            smaller.probability += best.probability
            best.probability = 0.0
            best.flags.append(
                f"not chosen: {symbols} not identified; its probability counts for {smaller.name}"
            )
        return results

    def _residual_weight(
        self, results: list[ModelResult], fit: _Context, measured: float
    ) -> tuple[float, float]:
        """The residual autocorrelation time (samples) of the law with the most evidence
        and the data weight its residuals support (:func:`data_weight`)."""
        ranked = [r for r in results if r.status != NOT_EVALUATED] or results
        top = max(ranked, key=lambda r: r.ln_evidence)
        law = top.least_squares[0] if top.least_squares is not None else top.model
        A = design(law, fit.kin, fit.x_full, fit.sigma_x, fit.columns)
        beta = lstsq_scaled_cond(A, fit.y)[0]
        residual = fit.y - A @ beta
        tau = residual_tau(residual)
        return tau, data_weight(A, residual, tau) * measured

    def _set_aside(self, results: list[ModelResult], warnings: list[str]) -> list[ModelResult]:
        """The laws whose evidence was evaluated; the others go to ``not_evaluated_``
        with one warning naming them. Should none be evaluated, all are kept with their
        flag rather than none chosen."""
        aside = [r for r in results if r.status == NOT_EVALUATED]
        kept = [r for r in results if r.status != NOT_EVALUATED]
        self.not_evaluated_ = aside
        if aside and kept:
            names = "; ".join(f"{r.name} ({r.reason.removeprefix('not evaluated: ')})"
                              for r in aside[:3])  # fmt: skip
            more = f" and {len(aside) - 3} more" if len(aside) > 3 else ""
            warnings.append(f"not evaluated, so never chosen: {names}{more}")
            return kept
        for r in aside:  # nothing better: rank them by the estimate they have
            r.flags.append(r.reason)
            r.ln_evidence = r.posterior.ln_evidence if r.posterior is not None else -math.inf
            if not math.isfinite(r.ln_evidence):
                r.ln_evidence = -1e300
        return results

    def _position_noise(self, session: Session, trusted: NDArray[np.bool_]) -> float:
        """Position noise SD (m) from the spectrum's flat top over the ``trusted``
        samples, floored by the ADC step.

        Quantisation with little dither is not white and hides from the flat top, so
        the ADC step sets a floor: step / sqrt(12). Clipped and lost samples are left
        out: flat at an end of the ADC, or interpolated, they carry no noise (free jaws
        clipped for 31 % of a grasping session read the noise 20 % low, and left M 2 %
        low, 5 posterior SDs).
        """
        fs = 1.0 / float(np.median(np.diff(session.time)))
        step = session.adc.step("position") if session.adc is not None else 0.0
        return max(position_noise_sd(session.position, fs, trusted), step / np.sqrt(12))

    def _stats(
        self, model: Law, fp: _FirstPass, fit: _Context
    ) -> tuple[SufficientStats, Prior, Array | None, list[str]]:
        """The tempered statistics and prior of one law, and the flags of its noise
        correction."""
        corr = fp.correction
        uncorrected = corr is not None and not _correctable(fp, corr)
        if uncorrected:
            corr = None  # noise dominates a column: the correction would be meaningless
        G, b, yy, rss = fp.gram, fp.b, fp.yy, fp.rss
        if corr is not None:  # centred on the corrected fit, with its sampling covariance
            rss = max(_corrected_rss(fp, corr), 0.0)
            G, b, yy = corrected_curvature(fp.gram, fp.b, corr, fp.rss, rss)
        w, n = fit.weight, fit.y.size
        st = SufficientStats(w * G, w * b, w * yy, w * n, w * rss)
        prior = law_prior(model, fit.scales)
        flags = []
        if uncorrected:
            flags.append(
                "position noise dominates a column: left uncorrected, so M (and "
                "perhaps S) are biased towards zero"
            )
        return st, prior, corr, flags

    def _exact(self, model: Law, fp: _FirstPass, fit: _Context) -> ModelResult:
        """The closed-form posterior and evidence of one law."""
        st, prior, corr, flags = self._stats(model, fp, fit)
        exact = ExactPosterior(st, prior)
        why = exact.untrusted()
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
        self._tick(model.name)
        res = _result(model, post, fp, fit, st, prior, corr, flags)
        if why:
            _not_evaluated(res, why)
        return res

    def _tick(self, name: str) -> None:
        """One more law scored: the progress counts it against the laws known so far
        (the search beyond the linear laws learns its length as it goes)."""
        self._scored = getattr(self, "_scored", 0) + 1
        self._known = max(getattr(self, "_known", 0), self._scored)
        getattr(self, "_progress", SILENT).advance(self._scored, self._known, name)

    def _exact_shaped(self, law: Law, fit: _Context) -> ModelResult:
        """A law with shape parameters: its exact evidence at every node of the shape's
        quadrature grid, weighted by the prior's masses. Where the posterior is sharper
        than the grid (most sessions: thousands of samples pin a time constant to a few
        per cent), Newton steps find its peak and a Laplace approximation gives the
        evidence, and three Gauss-Hermite nodes per parameter carry the shape's
        uncertainty into the coefficients; elsewhere the grid's heaviest nodes do.

        With more than :data:`MAX_GRID_SHAPES` shape parameters the grid is coarse and
        only seeds the peak; the evidence is still the Laplace approximation (or the
        grid's sum), and the shape's posterior is left to :meth:`_sample_shapes` (emcee),
        which runs only if the law is not decisively behind the best.
        """
        many = len(law.shape_names) > MAX_GRID_SHAPES
        grid = shape_grid(law, fit.kin, coarse=many)
        light = _ShapedPass(law, fit)
        cache: dict[tuple[float, ...], tuple[float, tuple[Any, ...]]] = {}

        def parts(node: dict[str, float], nodes: int = 401) -> tuple[float, tuple[Any, ...]]:
            """ln evidence given the shape without the positivity bounds' orthant mass
            (the costly part, and nearly constant over a peak), and the fit's parts."""
            bound = law.bind(node)
            key = (law.name, tuple(node[n] for n in grid.names))
            fp = fit.shaped_passes.get(key)
            if fp is None:
                fp = fit.shaped_passes[key] = light(node)
            st, prior, corr, flags = self._stats(bound, fp, fit)
            exact = ExactPosterior(st, prior, nodes=nodes)
            return exact.ln_z_untruncated, (fp, st, prior, corr, flags, exact)

        def evaluate(node: dict[str, float]) -> tuple[float, tuple[Any, ...]]:
            key = tuple(node[n] for n in grid.names)
            if key not in cache:
                cache[key] = parts(node)
            return cache[key]

        def truncation(node: dict[str, float]) -> float:
            """ln of what the positivity bounds keep of the closed form's evidence."""
            exact = evaluate(node)[1][5]
            return exact.ln_evidence() - exact.ln_z_untruncated

        ln_z = np.array([evaluate(node)[0] for node in grid.nodes])
        # the bounds matter only where the evidence does: the nodes near the top (more
        # join them if the bounds pull the top down)
        done = np.zeros(ln_z.size, bool)
        while True:
            near = np.flatnonzero(~done & (ln_z > ln_z[done].max(initial=ln_z.max()) - 30.0))
            if not near.size:
                break
            for i in near:
                ln_z[i] += truncation(grid.nodes[i])
            done[near] = True
        log_post = ln_z + grid.log_weight
        tops = np.argsort(-log_post)[:3]
        starts = [grid.to_u(grid.nodes[i]) for i in tops]
        peak = laplace(lambda u: evaluate(grid.from_u(u))[0], grid, starts)
        sharp = peak is not None and bool(np.all(peak.sd < grid.spacing))
        if sharp:
            assert peak is not None
            d = peak.u.size
            ln_evidence = (
                peak.log_z
                + truncation(grid.from_u(peak.u))
                + grid.log_density
                + 0.5 * d * np.log(2 * np.pi)
                + 0.5 * float(np.linalg.slogdet(peak.cov)[1])
            )
            point = grid.from_u(peak.u)
            if many:  # the chain will carry the shape's uncertainty, if it runs
                post = evaluate(point)[1][5].bounded(fit.rng, CUT_THRESHOLD)
            else:
                nodes_u, w = hermite_nodes(peak)
                inside = [i for i, u in enumerate(nodes_u) if grid.inside(u)]
                posts = [evaluate(grid.from_u(nodes_u[i]))[1][5].bounded(fit.rng, CUT_THRESHOLD)
                         for i in inside]  # fmt: skip
                post = mix(posts, w[inside], fit.rng)
            draws = fit.rng.multivariate_normal(peak.u, peak.cov, size=4000)
            shape_post = _shape_draws(grid, draws)
            how = (
                f"Laplace approximation at the peak over the shape, after a {len(grid.nodes)}-"
                f"node grid and {len(cache) - len(grid.nodes)} Newton evaluations"
            )
            start, start_cov = peak.u, peak.cov
        else:
            ln_evidence = float(_logsumexp(log_post))
            heavy = kept(log_post)
            weights = np.exp(log_post[heavy] - log_post[heavy[0]])
            posts = [evaluate(grid.nodes[i])[1][5].bounded(fit.rng, CUT_THRESHOLD) for i in heavy]
            post = mix(posts, weights, fit.rng)
            shape_post, point = shape_summary(grid, log_post)
            how = f"quadrature over {len(grid.nodes)} shape nodes"
            start, start_cov = grid.to_u(grid.nodes[heavy[0]]), np.diag((grid.spacing / 4) ** 2)
        post.ln_evidence = float(ln_evidence)
        ls_key, ls_value = min(cache.items(), key=lambda kv: kv[1][1][0].rss)
        ls_law = law.bind(dict(zip(grid.names, ls_key, strict=True)))
        ls_rms = float(np.sqrt(ls_value[1][0].rss / fit.y.size))
        ranges = ", ".join(f"{k} {lo:.3g}-{hi:.3g}" for k, (lo, hi) in grid.ranges.items())
        res = self._shaped_result(law, point, post, evaluate, fit)
        res.reason = f"{how} ({ranges})"
        # the evidence is trusted only if the node it rests on is, and if it stays
        # below the likelihood's maximum over every shape evaluated
        why = evaluate(point)[1][5].untrusted()
        top = max(entry[1][1].max_log_likelihood() for entry in cache.values())
        if not why and not ln_evidence <= top + CHECK_NATS:
            why = (
                f"its ln evidence ({ln_evidence:.4g}) exceeds the likelihood's maximum "
                f"({top:.4g}): a numerical failure"
            )
        res.shape_posterior = shape_post
        res.shape_ranges = grid.ranges
        res.least_squares = (ls_law, ls_rms)

        if many:
            res.shape_sampler = {"status": "pending", "evidence": how}

            def sample() -> None:
                """emcee over the shape, started at the peak; the evidence stays the
                estimate above (a chain gives none)."""
                from .sampling import sample_shapes  # emcee, only when a shape is sampled

                def target(u: Array) -> float:
                    # uniform prior in u inside the support; 101 nodes over ln sigma are
                    # exact to rounding for its near-Gaussian posterior, at a quarter the cost
                    return parts(grid.from_u(u), nodes=101)[0]

                try:
                    draws, diag = sample_shapes(
                        target, grid.interior(start), start_cov, grid.inside, fit.rng,
                        progress=self._progress_for(res),
                    )  # fmt: skip
                except FitError as e:  # keep the Laplace summary, and say why
                    res.shape_sampler = {"status": "failed", "reason": str(e), "evidence": how}
                    res.reason += f"; shape not sampled: {e}"
                    res.flags.append(f"shape not sampled ({e}): its intervals are Laplace's")
                    return
                summary = _shape_draws(grid, draws)
                for j, name in enumerate(grid.names):
                    summary[name]["method"] = "emcee"
                    summary[name]["tau_steps"] = diag["tau"][j]
                pick = fit.rng.choice(draws.shape[0], size=min(SHAPE_MIXTURE, draws.shape[0]),
                                      replace=False)  # fmt: skip
                posts = [
                    evaluate(grid.from_u(draws[i]))[1][5].bounded(fit.rng, CUT_THRESHOLD)
                    for i in pick
                ]
                mixed = mix(posts, np.ones(len(posts)), fit.rng)
                mixed.ln_evidence = res.ln_evidence
                median = np.median(draws, axis=0)
                centre = grid.from_u(median) if grid.inside(median) else grid.from_u(draws[0])
                new = self._shaped_result(law, centre, mixed, evaluate, fit)
                for name in ("model", "posterior", "cond", "cond_scaled", "residual_rms",
                             "gram", "correction", "stats", "prior", "flags"):  # fmt: skip
                    setattr(res, name, getattr(new, name))
                res.shape_posterior = summary
                diag.update(status="sampled", evidence=how)
                res.shape_sampler = diag
                mixed.diagnostics["shape_emcee"] = diag
                res.reason += (
                    f"; shape sampled by emcee ({diag['walkers']} walkers, {diag['steps']} "
                    f"steps, tau {max(diag['tau']):.0f}, acceptance {diag['acceptance']:.2f})"
                )
                if not diag["converged"]:
                    res.flags.append(
                        f"shape chain stopped at {diag['steps']} steps, shorter than 50 "
                        f"autocorrelation times ({50 * max(diag['tau']):.0f}): its intervals "
                        "are rough"
                    )

            res.sample_shape = sample
        if why:
            _not_evaluated(res, why)
        self._tick(law.name)
        return res

    def _shaped_result(
        self,
        law: Law,
        point: dict[str, float],
        post: Posterior,
        evaluate: Callable[[dict[str, float]], tuple[float, tuple[Any, ...]]],
        fit: _Context,
    ) -> ModelResult:
        """The result of a law with shape parameters, bound at ``point``.

        Its coefficients' means are those given the shape at ``point``: a coefficient's
        meaning can hang on the shape (a contact stiffness is in N/m^n), so an average
        over shapes would not predict the force the bound law gives. Their SDs and
        intervals stay those of ``post``, which carry the shape's uncertainty.
        """
        fp, st, prior, corr, flags, exact = evaluate(point)[1]
        if post.diagnostics.get("shape_nodes", 1) > 1:
            post.diagnostics["mean_over_shapes"] = [float(v) for v in post.mean]
            post.mean = exact.bounded(fit.rng, CUT_THRESHOLD).mean
        return _result(law.bind(point), post, fp, fit, st, prior, corr, list(flags), law)

    def _candidates(
        self,
        linear: list[Law],
        shaped: list[Law],
        firsts: dict[str, _FirstPass],
        fit: _Context,
    ) -> tuple[list[ModelResult], list[str]]:
        """Every candidate law scored at ``fit``'s weight: the linear ones, the search's
        (default forms) and the laws with shape parameters asked for; and what the
        search could not do."""
        found: list[str] = []
        results = [self._exact(m, firsts[m.name], fit) for m in linear]
        if self.forms in (None, "all"):
            results += self._search(results, fit, found)
        results += [self._exact_shaped(m, fit) for m in shaped]
        return results, list(dict.fromkeys(found))

    def _sample_shapes(self, results: list[ModelResult]) -> None:
        """Run emcee over the shape of the chosen law if it has more than
        :data:`MAX_GRID_SHAPES` shape parameters. A runner-up keeps its Laplace summary
        (its evidence, what ranks it, is the same estimate either way) unless every law
        not decisively behind is to be sampled (``sampler="emcee"``)."""
        top = max(r.ln_evidence for r in results)
        for res in results:
            if res.sample_shape is None:
                continue
            behind = top - res.ln_evidence
            reason = ""
            if behind > self.decisive:
                reason = (
                    f"ln Bayes factor {behind:.1f} behind the best "
                    f"(> {self.decisive:.1f}, decisive)"
                )
            elif behind > 0 and self.sampler == "auto":
                reason = (
                    f"a runner-up (ln Bayes factor {behind:.1f} behind the best): its Laplace "
                    "summary stands; --sampler emcee samples it"
                )
            if reason:
                res.shape_sampler = {
                    **(res.shape_sampler or {}),
                    "status": "skipped",
                    "reason": reason,
                }
                res.reason += f"; shape not sampled: {reason}"
            else:
                res.sample_shape()
            res.sample_shape = None

    def _search(
        self, linear: list[ModelResult], fit: _Context, warnings: list[str]
    ) -> list[ModelResult]:
        """Laws beyond the linear ones, built from the best of them and scored by exact
        evidence (a greedy search; docs/estimators.md): the terms that declare
        ``search = "replace"`` (Hunt-Crossley contact) in place of its stiffness and
        damping; then, to the better of the two, the ``"grow"`` terms (relaxation
        branches) one at a time (up to three, one on a contact law) while each raises
        the evidence; after each, ``"prune"`` terms the new one makes redundant are taken
        out while that raises the evidence."""
        # from the law the evidence prefers, and from the one that fits best by BIC:
        # on a misfit's correlated residuals the two part, and only the second may be
        # the stem of the law that fits
        n = fit.y.size
        stems = {r.name: r for r in (max(linear, key=lambda r: r.ln_evidence),
                                     min(linear, key=lambda r: _bic(r, n)))}  # fmt: skip
        tried: list[ModelResult] = []
        for best in stems.values():
            if not self._grow(best, fit, warnings, tried):
                break
        return tried

    def _grow(
        self, best: ModelResult, fit: _Context, warnings: list[str], tried: list[ModelResult]
    ) -> bool:
        """The search's steps from one linear law, appending what they score to ``tried``;
        False if the session resolves no relaxation (no other stem will either)."""
        done = {r.family.name for r in tried if r.family is not None}

        def score(names: list[str]) -> ModelResult:
            law = Law.of(names)
            if law.name in done:
                return next(r for r in tried if r.family is not None and r.family.name == law.name)
            res = self._exact_shaped(law, fit)
            tried.append(res)
            done.add(law.name)
            return res

        def prune(res: ModelResult) -> ModelResult:
            improved = True
            while improved:
                improved = False
                names = [t.name for t in res.family.terms]  # type: ignore[union-attr]
                for extra in searched("prune"):
                    fewer = [n for n in names if n != extra]
                    stiff = any(term(n).role == "stiffness" for n in fewer)
                    if extra not in names or not stiff:
                        continue
                    trial = score(fewer)
                    if trial.ln_evidence > res.ln_evidence:
                        res, improved = trial, True
                        break
            return res

        keep = [t.name for t in best.model.terms if t.role in ("friction", "inertia", "offset")]
        # a term of closure and speed together (contact damping, (x - x0)^n xdot) is, at
        # one speed, the closure term itself
        design_: Design | None = getattr(self, "design_", None)
        speed = design_ is None or (
            "xdot" not in design_.unexcited and design_.representative("xdot") == "xdot"
        )
        replace = [n for n in searched("replace") if speed or term(n).variable != "xv"]
        contact = prune(score([*replace, *keep]))
        base = contact if contact.ln_evidence > best.ln_evidence else best
        if not resolvable(fit.kin):
            lo, hi = tau_range(fit.kin)
            warnings.append(
                f"relaxation not searched: the session resolves time constants only between "
                f"{lo:.3g} s and {hi:.3g} s; record longer or with faster motion"
            )
            return False
        lo, hi = tau_range(fit.kin)
        # branches one at a time while each raises the evidence; a contact law takes one
        # (its exponent and contact point already make it the costliest to sample)
        most = 1 if base is contact else MAX_BRANCHES
        current = base
        for k in range(1, most + 1):
            if hi < BRANCH_SPREAD**k * lo:
                warnings.append(
                    f"relaxation branch {k} not searched: the session resolves time constants "
                    f"only between {lo:.3g} s and {hi:.3g} s, too narrow a range for {k} "
                    "distinct ones"
                )
                break
            names = [t.name for t in (current.family or current.model).terms]
            trial = max((score([*names, g]) for g in searched("grow")),
                        key=lambda r: r.ln_evidence)  # fmt: skip
            if trial.ln_evidence <= current.ln_evidence:
                break
            current = prune(trial)
        return True

    def _sample(self, results: list[ModelResult], rng: np.random.Generator) -> None:
        """Run emcee where no exact posterior is known (or on request): for the chosen
        law only, unless on request (runners-up keep the closed form, their evidence
        exact), and never for forms decisively behind; say for each form how its
        posterior was found."""
        top = max(r.ln_evidence for r in results)
        for res in results:
            assert res.posterior is not None
            behind = top - res.ln_evidence
            exact = res.posterior.diagnostics.get("exact", False)
            cut = res.posterior.outside
            if exact and self.sampler == "auto":
                how = (
                    "exact posterior (closed form); positivity bound cuts "
                    f"{res.posterior.outside:.1e} of it"
                    if res.posterior.outside <= CUT_THRESHOLD
                    else f"exact posterior with the positivity bound, which cuts "
                    f"{100 * cut:.2g} % of the closed form: independent draws by rejection"
                )
                # a law with shape parameters keeps how its shape was integrated
                res.reason = f"{res.reason}; {how}" if res.family is not None else how
                continue
            runner_up = behind > 0 and self.sampler == "auto"
            if (behind > self.decisive or runner_up) and len(results) > 1:
                res.status = "skipped"
                text = (
                    f"not sampled: ln Bayes factor {behind:.1f} behind the best "
                    f"(> {self.decisive:.1f}, decisive)"
                    if behind > self.decisive
                    else f"not sampled: a runner-up (ln Bayes factor {behind:.1f} behind the "
                    "best), so its intervals are the closed form's, which the positivity "
                    f"bound cuts by {100 * cut:.2g} %; its evidence is exact; --sampler emcee "
                    "samples it"
                )
                res.reason = f"{res.reason}; {text}" if res.family is not None else text
                continue
            from .sampling import run_emcee, stepping_stone  # scipy.stats and emcee, if needed

            res.posterior = run_emcee(res.stats, res.prior, rng, progress=self._progress_for(res))  # type: ignore[arg-type]
            res.status = "emcee"
            res.reason = (
                f"sampled: the positivity bound cuts {100 * cut:.2g} % of the closed-form posterior"
                if self.sampler == "auto"
                else "sampled on request (--sampler emcee)"
            )
            if self.sampler == "emcee":
                res.ln_evidence_sampler = stepping_stone(res.stats, res.prior, rng)  # type: ignore[arg-type]
                gap = res.ln_evidence_sampler - res.ln_evidence
                if not abs(gap) <= CHECK_NATS:  # two estimates of one evidence
                    res.flags.append(
                        f"the sampler's ln evidence (stepping-stone) differs from the closed "
                        f"form's by {gap:+.1f} nats (more than {CHECK_NATS:g}): one of them "
                        "is wrong; compare the law with its neighbours before trusting it"
                    )
            if not res.posterior.diagnostics.get("converged", True):
                res.flags.append("chain shorter than 50 autocorrelation times")

    def _progress_for(self, res: ModelResult) -> Callable[[int, float], None] | None:
        if self.progress is None:
            return None
        progress, name = as_progress(self.progress), res.name
        return lambda steps, tau: progress(name, steps, tau)

    def _coefficients(self) -> tuple[Law, Array]:
        post = self.best_.posterior
        assert post is not None
        return self.best_.model, post.mean

    def _uncertainty(self) -> tuple[Array, Array]:
        """The chosen law's posterior SDs and 95 % intervals."""
        post = self.best_.posterior
        assert post is not None
        return np.asarray(post.sd, dtype=float), np.asarray(post.ci95, dtype=float)

    def contributions(self) -> Array:
        """Each term's share of the fitted force at the fitted samples, shape (m, p), N
        (the best law's columns times its posterior means)."""
        law, coef = self._coefficients()
        return design(law, self.kinematics_, self.session_.position, self.sigma_x_) * coef

    def predictive_sd(self) -> Array:
        """SD of the filtered force the posterior predicts at the fitted samples, shape
        (m,), N: the coefficients' covariance carried through the law, and the noise."""
        post = self.best_.posterior
        assert post is not None
        A = design(self.best_.model, self.kinematics_, self.session_.position, self.sigma_x_)
        var = np.einsum("ij,jk,ik->i", A, post.cov, A) + post.sigma_mean**2
        return np.sqrt(np.clip(var, 0.0, None))

    def _position_noise_sd(self) -> float:
        return self.sigma_x_


def session_scales(kin: Kinematics, force_scale: float | None = None) -> MotionScales:
    """A session's typical closure, speed and acceleration (RMS of the filtered ones) and
    force scale (five times its largest force, or ``force_scale``): the priors' yardsticks.

    Priors in these physical units let a law of any size be fitted, a 100 kg stage as
    readily as a liver, while each coefficient stays weakly informed: its term may
    reach five times the session's largest force at the session's typical motion.
    """

    def ms(u: Array) -> float:
        return float(np.mean(np.square(u))) if u.size else 0.0

    peak = float(np.max(np.abs(kin.force))) if kin.force.size else 0.0
    return scales_from(ms(kin.x), ms(kin.v), ms(kin.a), peak, force_scale)


def scales_from(
    ms_x: float, ms_v: float, ms_a: float, peak_force: float, force_scale: float | None = None
) -> MotionScales:
    """:class:`MotionScales` from the mean squares of the filtered closure (m^2), speed
    (m^2/s^2) and acceleration (m^2/s^4) and the largest filtered force (N): what
    :func:`session_scales` computes from a whole session, and the online fit from its
    running sums."""

    def root(u: float) -> float:
        value = float(np.sqrt(u)) if u > 0 else 0.0
        return value if value > 0 and np.isfinite(value) else 1.0

    force = force_scale if force_scale else 5.0 * peak_force
    return MotionScales(x=root(ms_x), v=root(ms_v), a=root(ms_a), force=force or 1.0)


def law_prior(law: Law, scales: MotionScales) -> Prior:
    """The prior of a law's coefficients for a session of these scales (each term may
    reach the force scale at the typical motion; passive coefficients non-negative)."""
    return Prior(scales=law.prior_scales(scales), passive=law.passive)


def _prior_conflict(law: Law, beta: Array, scales: MotionScales) -> list[str]:
    """A warning when the best least-squares fit lies far outside the priors: a law that
    explains the data only with terms beyond five times the largest force is suspect."""
    if not np.all(np.isfinite(beta)):
        raise FitError("the least-squares fit is not finite; check the session for extreme values")
    ratio = np.abs(beta) / law.prior_scales(scales)
    j = int(np.argmax(ratio))
    if ratio[j] <= 10:
        return []
    t = law.terms[j]
    return [
        f"the data put {t.symbol} ({t.name}) at {beta[j]:.3g} {t.unit}, {ratio[j]:.0f} prior "
        f"scales: its term alone would reach {ratio[j] * scales.force:.3g} N; the law "
        f"{law.name} may not suit this session"
    ]


def _outlier_warnings(kin: Kinematics, fitted: Array, z: float = 8.0) -> list[str]:
    """Raw force samples beyond ``z`` noise SDs of the fit: glitches (ADC spikes, a knock)
    the Gaussian noise model does not explain, and which pull every parameter.

    Raw, not filtered, residuals: filtering smears a spike over the kernel, and at
    high rates with a coarse position ADC the filtered residual carries the
    quantisation of position (plateaus of K q / 2 at every turn of the jaw), which is
    not a glitch but stood at 50 filtered-noise SDs.
    """
    r = kin.force_raw - fitted
    scale = 1.4826 * float(np.median(np.abs(r - np.median(r))))  # robust SD
    if not scale > 0:
        return []
    bad = np.flatnonzero(np.abs(r) > z * scale)
    if bad.size == 0:
        return []
    t = kin.time[bad]
    return [
        f"{bad.size} force sample(s) lie beyond {z:g} noise SDs of the fit, first at "
        f"t = {t[0]:.3f} s: a glitching sensor or a knock; the parameters absorb it, so "
        "inspect the residuals in the report and fit a clean stretch"
    ]


def _expected_residual_sd(best: ModelResult, sigma_x: float, n: int) -> float:
    """Residual SD the best form expects (N): force noise plus position noise through the law.

    With the errors-in-variables correction the posterior noise SD is the force noise
    alone; noise on position reaches the residuals through the design columns too, adding
    ``beta^T C beta / n`` to their variance (C: the correction subtracted from A^T A).
    """
    post = best.posterior
    assert post is not None
    sigma = float(post.sigma_mean)
    if sigma_x <= 0 or best.correction is None:
        return sigma  # no correction, or the fit left this form uncorrected
    extra = float(post.mean @ best.correction @ post.mean) / max(n, 1)
    return float(np.sqrt(sigma**2 + max(extra, 0.0)))


class _ShapedPass:
    """:func:`_first_pass` of one law at many values of its shape parameters.

    The columns without shape parameters, their products with each other and with the
    force, and their noise paths do not change from one shape to the next: they are
    formed once, so that each shape costs only its own columns and their products
    (what makes sampling the shape affordable).
    """

    def __init__(self, law: Law, fit: _Context) -> None:
        self.law, self.fit = law, fit
        terms = law.terms
        self.fixed = [j for j, t in enumerate(terms) if not t.shapes]
        self.moving = [j for j, t in enumerate(terms) if t.shapes]
        kin, x, sx = fit.kin, fit.x_full, fit.sigma_x
        cols = [term_column(terms[j], kin, x, sx, fit.columns) for j in self.fixed]
        self.F = np.column_stack(cols) if cols else np.zeros((fit.y.size, 0))
        self.G_ff = self.F.T @ self.F
        self.b_f = self.F.T @ fit.y
        self.yy = float(fit.y @ fit.y)
        self.speed = raw_speed(kin, x)
        if sx > 0:
            paths = [term_noise_path(terms[j], kin, x, fit.paths) for j in self.fixed]
            width = kin.kernels[0].size
            self.K_f = np.array([k for k, _ in paths]).reshape(len(paths), width)
            self.D_f = np.column_stack([d for _, d in paths]) if paths else self.F[:, :0]
            self.DtD_f = self.D_f.T @ self.D_f

    def __call__(self, node: dict[str, float]) -> _FirstPass:
        fit, bound = self.fit, self.law.bind(node)
        p, fixed, moving = len(bound.terms), self.fixed, self.moving
        S = np.column_stack(
            [term_column(bound.terms[j], fit.kin, fit.x_full, fit.sigma_x,
                         raw_speed=self.speed) for j in moving]
        )  # fmt: skip
        gram = self._assemble(self.G_ff, S.T @ self.F, S.T @ S)
        b = np.empty(p)
        b[fixed] = self.b_f
        b[moving] = S.T @ fit.y
        d = np.sqrt(np.clip(np.diag(gram), 1e-300, None))
        lam_s = np.linalg.eigvalsh(gram / np.outer(d, d))
        cond_scaled = float(np.sqrt(lam_s[-1] / lam_s[0])) if lam_s[0] > 0 else float("inf")
        if cond_scaled >= 1e5:  # too ill-conditioned for the normal equations
            return _first_pass(
                bound, fit.kin, fit.x_full, fit.y, fit.sigma_x, fit.columns, fit.paths
            )
        beta = np.linalg.solve(gram / np.outer(d, d), b / d) / d
        # from the residuals themselves: yy - 2 beta.b + beta.G.beta cancels to zero (or
        # below) when the law explains all but a millionth of yy, and a zero residual
        # lets the evidence grow without bound as the noise level goes to zero
        r = fit.y - self.F @ beta[fixed] - S @ beta[moving]
        rss = float(r @ r)
        lam = np.linalg.eigvalsh(gram)
        cond = float(np.sqrt(lam[-1] / lam[0])) if lam[0] > 0 else float("inf")
        correction = None
        if fit.sigma_x > 0:
            paths = [noise_path(bound.terms[j], fit.kin, fit.x_full) for j in moving]
            K = np.empty((p, fit.kin.kernels[0].size))
            K[fixed] = self.K_f
            K[moving] = [k for k, _ in paths]
            D = np.column_stack([dd for _, dd in paths])
            DtD = self._assemble(self.DtD_f, D.T @ self.D_f, D.T @ D)
            correction = fit.sigma_x**2 * (K @ K.T) * DtD
        return _FirstPass(gram, b, self.yy, beta, rss, cond, cond_scaled, correction)

    def _assemble(self, ff: Array, mf: Array, mm: Array) -> Array:
        """A (p, p) matrix of products from its blocks: fixed with fixed, moving with
        fixed, moving with moving."""
        fixed, moving = self.fixed, self.moving
        p = len(fixed) + len(moving)
        out = np.empty((p, p))
        out[np.ix_(fixed, fixed)] = ff
        out[np.ix_(moving, fixed)] = mf
        out[np.ix_(fixed, moving)] = mf.T
        out[np.ix_(moving, moving)] = mm
        return out


@dataclass
class _FirstPass:
    """What the fit keeps of one form's design matrix: its sufficient statistics."""

    gram: Array
    b: Array
    yy: float
    beta: Array
    rss: float
    cond: float
    cond_scaled: float
    correction: Array | None


@dataclass
class _Context:
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
    shaped_passes: dict[tuple[str, tuple[float, ...]], _FirstPass] = field(default_factory=dict)


def _result(
    model: Law,
    post: Posterior,
    fp: _FirstPass,
    fit: _Context,
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
        residual_rms=float(np.sqrt(fp.rss / fit.y.size)),
        gram=fp.gram,
        correction=corr,
        stats=st,
        prior=prior,
        flags=flags,
        family=family,
    )


#: the status of a law whose evidence could not be trusted (never chosen)
NOT_EVALUATED = "not evaluated"


def _not_evaluated(res: ModelResult, why: str) -> None:
    """Mark a law's evidence as untrusted: it ranks below every evaluated law and is
    never chosen; its estimate stays in the posterior for the record."""
    res.status = NOT_EVALUATED
    res.reason = f"not evaluated: {why}"
    res.ln_evidence = -math.inf


def _bic(res: ModelResult, n: int) -> float:
    """Schwarz's criterion of a law's least-squares fit over ``n`` samples; its shape
    parameters count as parameters."""
    k = len(res.model.terms) + len(res.model.shape_names)
    rms = res.least_squares[1] if res.least_squares is not None else res.residual_rms
    return n * math.log(max(rms**2, 1e-300)) + k * math.log(n)


def _shape_draws(grid: ShapeGrid, draws: Array) -> dict[str, dict[str, Any]]:
    """Mean, SD and central 95 % interval (SI) of each shape parameter from draws in
    ``u`` (parameters of log-uniform prior, such as time constants, drawn in their
    logarithm)."""
    out: dict[str, dict[str, Any]] = {}
    for j, name in enumerate(grid.names):
        v = np.exp(draws[:, j]) if grid.log(name) else draws[:, j]
        out[name] = {
            "mean": float(np.mean(v)),
            "sd": float(np.std(v, ddof=1)),
            "ci95": [float(q) for q in np.percentile(v, [2.5, 97.5])],
        }
    return out


def _logsumexp(a: Array) -> float:
    top = float(np.max(a))
    return top + float(np.log(np.sum(np.exp(a - top)))) if np.isfinite(top) else top


def _correctable(fp: _FirstPass, corr: Array) -> bool:
    """Whether the errors-in-variables correction leaves a proper regression: ``A^T A - C``
    positive definite, and a corrected residual of at least a tenth of the raw one (the
    correction takes off what position noise adds to the residual; taking off nearly
    all of it, or more, says the noise is as large as the motion)."""
    G = fp.gram - corr
    if np.any(np.linalg.eigvalsh(G) <= 0):
        return False
    return _corrected_rss(fp, corr) > 0.1 * fp.rss


def _corrected_rss(fp: _FirstPass, corr: Array) -> float:
    """The residual sum of squares of the errors-in-variables corrected fit, N^2:
    ``rss - beta_c^T C beta`` (``yy - beta_c^T b`` cancels to rounding when the law
    explains all but a millionth of ``yy``)."""
    beta_c = np.linalg.lstsq(fp.gram - corr, fp.b, rcond=None)[0]
    return fp.rss - float(beta_c @ corr @ fp.beta)


def _first_pass(
    model: Law,
    kin: Kinematics,
    x_full: Array,
    y: Array,
    sigma_x: float,
    columns: dict[str, Array] | None = None,
    paths: dict[str, tuple[Array, Array]] | None = None,
) -> _FirstPass:
    A = design(model, kin, x_full, sigma_x, columns)
    gram = A.T @ A
    b = A.T @ y
    # least squares on unit-norm columns through the Gram matrix (one O(n p^2) product
    # instead of a second factorisation of A), unless it is too ill-conditioned for that
    d = np.sqrt(np.clip(np.diag(gram), 1e-300, None))
    lam_s = np.linalg.eigvalsh(gram / np.outer(d, d))
    cond_scaled = float(np.sqrt(lam_s[-1] / lam_s[0])) if lam_s[0] > 0 else float("inf")
    if cond_scaled < 1e5:
        beta = np.linalg.solve(gram / np.outer(d, d), b / d) / d
    else:
        beta, cond_scaled = lstsq_scaled_cond(A, y)
    r = y - A @ beta
    # the raw condition number from the Gram matrix's eigenvalues: a report figure,
    # exact to rounding up to about 1e7, and "large" beyond
    lam = np.linalg.eigvalsh(gram)
    cond = float(np.sqrt(lam[-1] / lam[0])) if lam[0] > 0 else float("inf")
    return _FirstPass(
        gram=gram,
        b=b,
        yy=float(y @ y),
        beta=beta,
        rss=float(r @ r),
        cond=cond,
        cond_scaled=cond_scaled,
        correction=eiv_correction(model, kin, x_full, sigma_x, paths) if sigma_x > 0 else None,
    )


#: contiguous blocks of the blocked cross-validation reported beside the evidence
CV_BLOCKS = 5
#: a law predicting held-out blocks this much better than the chosen one is reported
CV_MARGIN = 1.1


def blocked_cv_rms(A: Array, y: Array, blocks: int = CV_BLOCKS) -> float:
    """RMS of what each of ``blocks`` contiguous blocks leaves to the least-squares fit
    of the others (N): a prediction score of a law on data its coefficients never saw,
    from the Gram matrix of each block, formed once.

    Parameters
    ----------
    A : ndarray, shape (m, p)
        The law's design matrix at the fitted samples.
    y : ndarray, shape (m,)
        The filtered force, N.
    """
    m = y.size
    if m < 2 * blocks * max(A.shape[1], 1):
        return float("nan")
    edges = np.linspace(0, m, blocks + 1).astype(int)
    d = np.linalg.norm(A, axis=0)
    d[d == 0] = 1.0
    As = A / d
    parts = [(As[a:b].T @ As[a:b], As[a:b].T @ y[a:b]) for a, b in itertools.pairwise(edges)]
    G = sum(g for g, _ in parts)
    c = sum(v for _, v in parts)
    ss = 0.0
    for (a, b), (g, v) in zip(itertools.pairwise(edges), parts, strict=True):
        beta = np.linalg.lstsq(G - g, c - v, rcond=1e-12)[0]
        r = y[a:b] - As[a:b] @ beta
        ss += float(r @ r)
    return math.sqrt(ss / m)


def _predictive_guard(results: list[ModelResult], fit: _Context) -> list[str]:
    """Score each evaluated law by blocked cross-validation (``cv_rms``) and say when a
    law predicts the held-out blocks clearly better than the chosen one: evidence and
    prediction then disagree, and the choice rests on the priors."""
    for r in results:
        if r.status == NOT_EVALUATED:
            continue
        A = design(r.model, fit.kin, fit.x_full, fit.sigma_x, fit.columns)
        r.cv_rms = blocked_cv_rms(A, fit.y)
    best = results[0]
    scored = [r for r in results if math.isfinite(r.cv_rms)]
    if not scored or not math.isfinite(best.cv_rms):
        return []
    top = min(scored, key=lambda r: r.cv_rms)
    if top is best or best.cv_rms <= CV_MARGIN * top.cv_rms:
        return []
    return [
        f"{top.name} predicts held-out blocks better than the chosen {best.name} "
        f"(blocked cross-validation RMS {top.cv_rms:.3g} N against {best.cv_rms:.3g} N): "
        "evidence and prediction disagree"
    ]


def _unidentified(r: ModelResult) -> set[int]:
    """Indices of the terms whose coefficient :func:`_identifiability` calls not
    identified."""
    out = set()
    for j, t in enumerate(r.model.terms):
        if any(f.startswith(f"{t.symbol} not identified") for f in r.flags):
            out.add(j)
    return out


def _identifiability(r: ModelResult) -> list[str]:
    """Flags for coefficients the data do not pin down."""
    flags = []
    post = r.posterior
    assert post is not None and r.prior is not None
    scales = r.prior.scales
    for j, t in enumerate(r.model.terms):
        lo, hi = post.ci95[j]
        vague = post.sd[j] > 0.3 * scales[j]
        if vague or (
            t.passive and (lo <= 0.02 * max(hi, 1e-300) or post.sd[j] > 0.5 * abs(post.mean[j]))
        ):
            what = (
                "too little acceleration content"
                if t.role == "inertia"
                else "too little excitation"
            )
            flags.append(
                f"{t.symbol} not identified ({what}): 95 % interval [{lo:.3g}, {hi:.3g}] {t.unit}"
            )
        elif t.passive and post.sd[j] > 0.25 * abs(post.mean[j]):
            flags.append(
                f"{t.symbol} poorly identified: SD is {100 * post.sd[j] / post.mean[j]:.0f} % "
                "of its value"
            )
    return flags
