"""Bayesian identification of ``K f0(x) + S f1(xdot) + M xddot = F`` over every form:
exact posteriors and evidences where they exist, emcee where the positivity bounds
cut the posterior, posterior probabilities of the forms, and diagnostics.

:class:`BayesianFit` puts the parts together: the candidate laws
(:mod:`~tissuecli.identify.forms`), their priors (:mod:`~tissuecli.identify.priors`),
each law scored by exact evidence (:mod:`~tissuecli.identify.scoring`, and
:mod:`~tissuecli.identify.shaped` for laws with shape parameters), the structure
search (:mod:`~tissuecli.identify.search`), the chains where no closed form applies
(:mod:`~tissuecli.identify.sampling`) and what the fit says about its choice
(:mod:`~tissuecli.identify.diagnostics`). Here: the data weight and the choice.

The estimator has the scikit-learn shape (keyword hyperparameters, ``fit(session)``
returning self, fitted attributes ending in ``_``, :meth:`BayesianFit.predict`).
It works on arrays; reading and writing files is the caller's business.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from ..core.errors import FitError
from ..core.progress import SILENT, Progress, as_progress
from ..core.session import Session
from ..core.terms import Law, term
from .blas import one_blas_thread
from .decimate import fit_stride
from .derivatives import Differentiator
from .design import design, lstsq_scaled_cond, position_noise_sd
from .diagnostics import (
    blocked_cv_rms,
    cv_scores,
    expected_residual_sd,
    identifiability,
    outlier_warnings,
    predictive_guard,
    unidentified,
)
from .estimator import Estimator
from .forms import linear_laws, parse_forms
from .identifiable import PREFERENCE, examine
from .noise import data_weight, filter_tau, residual_tau
from .prepare import Prepared
from .priors import law_prior, prior_conflict, scales_from, session_scales
from .sampling import DECISIVE, sample_posteriors, sample_shape_posteriors
from .scoring import (
    CUT_THRESHOLD,
    NOT_EVALUATED,
    Context,
    FirstPass,
    ModelResult,
    exact_result,
    first_pass,
    kept_correction,
    prepared,
    weigh,
)
from .search import Scope, Search, search_strategy
from .shaped import exact_shaped
from .shapes import shape_grid
from .whiten import ARFilter, Likelihood, Prewhitened, likelihood_strategy, precision_ratio

Array = NDArray[np.float64]

# the names other modules import from here, wherever they are defined now
__all__ = [
    "CUT_THRESHOLD",
    "DECISIVE",
    "NOT_EVALUATED",
    "BayesianFit",
    "ModelResult",
    "blocked_cv_rms",
    "law_prior",
    "linear_laws",
    "parse_forms",
    "scales_from",
    "session_scales",
]


#: a residual SD below this fraction of the force range is rounding, not sensor noise
NOISE_FREE = 1e-6


#: the data weight the best law's residuals support may fall this far below the
#: filter's before the laws are scored again at it
WEIGHT_SLACK = 2.0


class BayesianFit(Estimator):
    """Bayesian identification over candidate laws with model choice.

    Parameters
    ----------
    forms : str, Law or list of them
        ``"all"`` (the 24 linear laws of :func:`linear_laws`, then the structure search,
        by default greedy, adding contact and up to three relaxation branches),
        ``"linear"`` (the 24 alone), ``"paper"`` (the paper's four), or laws such as
        ``"x,xdot"`` or ``"x+x^3+xdot+offset+xddot"``.
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
        five times the largest force of the session
        (:func:`~tissuecli.identify.priors.session_scales`).
    decisive : float
        ln Bayes factor behind the best beyond which a form is not sampled.
    seed : int
    grasps : {"all", "none"} or list of int
        Where the session alternates grasps with free motion: fit every grasp, every
        sample, or the grasps numbered (from 1).
    progress : Progress or callable, optional
        Told the stages (filtering, the structure search law by law, sampling); a bare
        callable is called ``progress(form, steps, tau)`` while sampling.
    search : {"greedy", "exhaustive"} or Search
        The structure search of ``forms="all"`` (:mod:`~tissuecli.identify.search`): by
        name (a registered :class:`~tissuecli.identify.search.Search`) or an instance.
    likelihood : {"tempered", "prewhitened"} or Likelihood, optional
        How the evidence counts correlated residuals (:mod:`~tissuecli.identify.whiten`):
        a likelihood tempered by the data weight, or the exact likelihood of
        autoregressive residuals (force and design through its whitening filter). By
        default :data:`~tissuecli.identify.whiten.DEFAULT_LIKELIHOOD`.
    closure : {"rebuilt", "read"}
        ``"rebuilt"``: where a coarse ADC reads the closure as a staircase, the columns
        are formed from the closure rebuilt through its level crossings, with the filter
        chosen on the closure as read (:func:`~tissuecli.identify.prepare.prepare`);
        ``"read"``: from the closure as read.

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
    grasp_rules_ : GraspRules or None
        How the grasps were fitted (:func:`~tissuecli.identify.prepare.grasp_rules`),
        for a long session's other stretches; None where every sample was fitted.
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
        search: str | Search = "greedy",
        likelihood: str | Likelihood | None = None,
        closure: str = "rebuilt",
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
        self.search = search
        self.likelihood = likelihood
        self.closure = closure

    def fit(self, session: Session) -> BayesianFit:
        """Fit every candidate law to ``session``; returns self with the fitted
        attributes set.

        Raises
        ------
        FitError
            If the session cannot identify anything (too short, constant, not finite);
            no fitted attribute is set then.
        """
        with one_blas_thread():
            return self._fit(session)

    def _fit(self, session: Session) -> BayesianFit:
        """:meth:`fit`, with BLAS on one thread."""
        if self.sampler not in ("auto", "emcee"):
            raise FitError(f"unknown sampler {self.sampler!r}; choose auto or emcee")
        self._strategy = search_strategy(self.search)
        likelihood = likelihood_strategy(self.likelihood)
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
        sigma_x = self._position_noise(ready) if self.eiv else 0.0
        rng = np.random.default_rng(self.seed)
        scales = session_scales(kin, self.force_scale)
        # a long session's laws are scored on every stride-th filtered sample, the
        # same statistics at a fraction of the cost (see identify.decimate)
        stride = fit_stride(kin)
        full_kin, kin = kin, kin.every(stride)
        y = kin.force

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
        design_ = examine(kin, ready.closure, sigma_x, columns, names, scales=scales)
        self.design_ = design_
        if design_.summary:
            warnings.append(design_.summary)
        if whole_search:
            models = design_.reduce(models)
        paths: dict[str, tuple[Array, Array]] = {}  # and their noise paths
        linear = [m for m in models if not m.shape_names]
        shaped = [m for m in models if m.shape_names]
        x_full = ready.closure
        firsts = {m.name: first_pass(m, kin, x_full, y, sigma_x, columns, paths) for m in linear}
        if not firsts:  # shaped laws only: their middle node stands in for the residuals
            m0 = shaped[0]
            nodes = shape_grid(m0, kin).nodes
            firsts = {m0.name: first_pass(m0.bind(nodes[len(nodes) // 2]), kin, x_full, y,
                                           sigma_x, columns)}  # fmt: skip
        # the least-squares fit that explains the data best (by BIC): a warning if it
        # lies far outside the priors
        n_rows = y.size
        n_samples = n_rows * stride  # what the kept rows stand for
        best_name = min(
            firsts,
            key=lambda k: (
                n_samples * np.log(max(firsts[k].rss, 1e-300) / n_rows)
                + firsts[k].beta.size * np.log(n_samples)
            ),
        )
        best_ls = next((m for m in linear if m.name == best_name), None)
        if best_ls is not None:
            warnings.extend(prior_conflict(best_ls, firsts[best_name].beta, scales))
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
        tau_filter = filter_tau(kin.kernels[0]) / stride  # in kept rows
        measured = ready.measured_fraction
        weight_filter = measured / tau_filter
        A = design(best_ls, kin, x_full, sigma_x, columns) if best_ls is not None else None
        tau, weight = tau_filter, weight_filter
        if A is not None:
            residual = y - A @ firsts[best_name].beta
            tau_ls = residual_tau(residual)
            fp = firsts[best_name]
            weight_ls = data_weight(A, residual, tau_ls, kept_correction(fp), fp.beta) * measured
            if weight_ls >= weight_filter / WEIGHT_SLACK:
                tau, weight = tau_ls, weight_ls
        del A
        collapsed = weight == weight_filter
        # the prewhitened likelihood: the best linear law's residuals set the filter, its
        # lags one smoothing-filter correlation time apart, and the rows keep the
        # filter's weight (what it says of the smoothed sensor noise, exact for it)
        whiten: ARFilter | None = None
        step = max(1, round(tau_filter))
        if isinstance(likelihood, Prewhitened) and best_ls is not None:
            whiten = likelihood.filter_for(residual, step)
            tau, weight = tau_filter, weight_filter
            firsts = {m.name: first_pass(m, kin, x_full, y, sigma_x, columns, paths, whiten)
                      for m in linear}  # fmt: skip

        fit = Context(kin, x_full, y, sigma_x, weight, scales, columns, paths, rng,
                      scored=self._tick, chain_progress=self._progress_for,
                      whiten=whiten)  # fmt: skip
        self._scored = 0
        self._known = len(linear) + len(shaped)
        self._progress.stage("structure search", self._known)
        results, found = self._candidates(linear, shaped, firsts, fit)
        # The chosen law's residuals check the weight: correlated beyond it (coloured
        # sensor noise, or no candidate fits), or coefficients more variable across
        # blocks than the tempered likelihood says (noise in the regressors), the data
        # count for less, and every law is scored again at that weight.
        if whiten is not None:
            # prewhitened: the filter is refitted to the residuals of the law with the
            # most evidence, and every law scored again through it if that law is not
            # the one that set it
            top, residual_top = self._top_residual(results, fit)
            if top != best_name:
                whiten = likelihood.filter_for(residual_top, step)
                firsts = {m.name: first_pass(m, kin, x_full, y, sigma_x, columns, paths, whiten)
                          for m in linear}  # fmt: skip
                fit = replace(fit, whiten=whiten, lead=-math.inf, shaped_passes={})
                self._progress.stage("structure search, scored again", self._known)
                self._scored = 0
                results, found = self._candidates(linear, shaped, firsts, fit)
            tau_best, weight_best = tau, weight
        else:
            tau_best, weight_best = self._residual_weight(results, fit, measured)
        if weight_best < weight / WEIGHT_SLACK or (collapsed and weight_best < weight):
            tau, weight = tau_best, weight_best
            fit = replace(fit, weight=weight, lead=-math.inf)
            self._progress.stage("structure search, scored again", self._known)
            self._scored = 0
            results, found = self._candidates(linear, shaped, firsts, fit)
        if self.forms in (None, "all"):
            self._progress.stage("smaller laws", self._known)
            self._descend(results, fit)
        warnings.extend(found)
        del columns
        self._progress.stage("sampling")
        ranked = [r for r in results if r.status != NOT_EVALUATED] or results
        sample_shape_posteriors(ranked, sampler=self.sampler, decisive=self.decisive)
        sample_posteriors(ranked, rng, sampler=self.sampler, decisive=self.decisive,
                          progress_for=self._progress_for)  # fmt: skip
        results = self._set_aside(results, warnings)
        ln_z = np.array([r.ln_evidence for r in results])
        if not np.isfinite(ln_z.max()):
            # every posterior lies wholly beyond the positivity bound: the evidence
            # cannot rank the laws, so none is preferred over another
            ln_z = np.zeros_like(ln_z)
            warnings.append(
                "no law has finite evidence: the positivity bound cuts every posterior "
                "whole, so the laws are not ranked; check the force and position columns' "
                "signs and units"
            )
        prob = np.exp(ln_z - ln_z.max())
        prob /= prob.sum()
        for r, p in zip(results, prob, strict=True):
            r.probability = float(p)
            r.flags.extend(identifiability(r))
        if self.forms in (None, "all", "linear"):
            results = self._drop_unidentified(results, fit)
            self._parsimony(results, fit)
        results.sort(key=lambda r: (-r.probability, -r.ln_evidence))
        best = results[0]
        warnings.extend(predictive_guard(results, fit))
        warnings.extend(f"{best.name}: {f}" for f in best.flags)
        span = float(np.ptp(y))
        if best.posterior.sigma_mean < NOISE_FREE * span:  # type: ignore[union-attr]
            # no sensor resolves a millionth of its range: this is rounding, not noise
            warnings.append(
                f"the force residual ({best.posterior.sigma_mean:.3g} N) is below a millionth "  # type: ignore[union-attr]
                f"of the force range ({span:.3g} N): the session looks noise-free "
                "(synthetic?), so its intervals reflect rounding, not measurement noise"
            )
        if whiten is not None:
            ratio = self._whitened_ratio(best, fit)
            weight *= ratio
            tau = measured / weight
        kin = full_kin
        fitted = design(best.model, kin, x_full, sigma_x) @ best.posterior.mean  # type: ignore[union-attr]
        warnings.extend(outlier_warnings(kin, fitted))

        self.session_ = session
        self.closure_ = x_full
        self.kinematics_ = kin
        self.sigma_x_ = sigma_x
        self.scales_ = scales
        self.contact_ = contact
        self.grasp_rules_ = ready.rules
        self.tau_ = tau * stride  # samples of the raw grid
        self.n_eff_ = y.size * weight
        self.results_ = results
        self.best_ = best
        self.expected_residual_sd_ = expected_residual_sd(best, sigma_x, y.size)
        self.warnings_ = warnings
        return self

    def _descend(self, results: list[ModelResult], fit: Context) -> None:
        """Add to ``results`` the laws one term smaller than the one the fit would choose
        (:meth:`Search.descend`), scored at ``fit``'s weight. The choice is read before
        sampling, as :meth:`_drop_unidentified` will make it: the identified law with
        the most evidence. Before that, the law each law with unidentified terms stands
        for (:func:`stand_in`): the top law's always, any other's where it has no shape
        parameters and the evidence it may gain (:func:`stand_in_gain`) brings it
        within ``decisive`` nats of the choice."""
        known = {r.name: r for r in results}

        def score(law: Law | Sequence[str]) -> ModelResult:
            law = law if isinstance(law, Law) else Law.of(list(law))
            if law.name not in known:
                known[law.name] = self._score(law, fit)
                results.append(known[law.name])
            return known[law.name]

        # the law with the most evidence, should it hold a term that is not identified,
        # stands for the law without it (scored there, as _drop_unidentified would), and
        # that law, should it hold one too, for the law without that, until every term
        # is identified: the choice may be the last of them or one of its sub-laws
        ranked = evaluated(results)
        if ranked:
            r = max(ranked, key=lambda r: r.ln_evidence)
            for _ in range(len(PREFERENCE)):  # each step leaves a term out
                names = stand_in(r, unidentified_in(r))
                if names is None:
                    break
                r = score(names)
        # so may any other law, should the evidence its unidentified terms cost it
        # reach within ``decisive`` nats of the choice: every linear law carries
        # inertia, and where the session holds too little acceleration the law with
        # the offset the data need, behind the top law by inertia's ten nats, never had
        # its law without inertia scored (a friction+offset session in contact
        # throughout: the law without the offset chosen, 3.2 times the noise floor).
        # Closed-form laws alone (milliseconds each): a law with shape parameters is
        # the search's to reach, and one met here only because a bigger law's terms
        # were not identified (contact in a spring's place on a ramp-and-hold of
        # x+maxwell) is no finding of the search
        choice = provisional_choice(results)
        lead = choice.ln_evidence
        # a term the choice identifies stays in every other law's stand-in: a law that
        # cannot tell it (a relaxation branch beside inertia) says nothing of it that
        # the choice does not say better
        vague = unidentified_in(choice)
        told = {t.name for j, t in enumerate(choice.model.terms) if j not in vague}
        for r in sorted(evaluated(results), key=lambda r: -r.ln_evidence):
            for _ in range(len(PREFERENCE)):
                bad = {j for j in unidentified_in(r)
                       if r is choice or r.model.terms[j].name not in told}  # fmt: skip
                names = stand_in(r, bad)
                if names is None or Law.of(names).shape_names:
                    break
                if r.ln_evidence + stand_in_gain(r, bad) < lead - self.decisive:
                    break
                r = score(names)
                if not unidentified_in(r):
                    lead = max(lead, r.ln_evidence)
        self._strategy.descend(lambda: [provisional_choice(results)], score)

    def _drop_unidentified(self, results: list[ModelResult], fit: Context) -> list[ModelResult]:
        """Never keep a term the fit itself reports as not identified: while the most
        probable law has such terms, its probability passes to the best (by evidence)
        of its sub-laws whose terms are all identified, the law without the unidentified
        terms among them (scored if the search had not; a sub-law may hold in a term's
        place what that term equals at one of its shapes, :attr:`Term.nests`). A term
        the data do not pin down cannot be what made its law probable. Should the best
        of them be decisively
        behind (``decisive`` nats) an identified law that is not one of its sub-laws, it
        does not stand for it: the term did work that none of them does (a contact law
        whose coefficient trades with an offset, 300 nats ahead of contact alone), and
        its probability is shared by the other laws in proportion to theirs, as though
        it had not been scored. A law none of whose sub-laws is identified stays."""
        by_name = {r.name: r for r in results}

        def names_of(r: ModelResult) -> list[str]:
            return [t.name for t in (r.family or r.model).terms]

        for _ in range(4):
            best = max(results, key=lambda r: (r.probability, r.ln_evidence))
            bad = unidentified(best)
            if not bad or best.status == NOT_EVALUATED:
                break
            terms = (best.family or best.model).terms
            # the law without the unidentified terms, and should it hold one too, the law
            # without that, until every term is identified (a law with a term not
            # identified is no sub-law to pass to)
            names, held = stand_in(best, bad), best
            for _ in range(len(PREFERENCE)):  # each step leaves a term out
                if names is None:
                    break
                law = Law.of(names)
                if law.name not in by_name:
                    new = self._score(law, fit)
                    new.probability = 0.0
                    new.flags.extend(identifiability(new))
                    results.append(new)
                    by_name[new.name] = new
                if by_name[law.name] is held:
                    break
                held = by_name[law.name]
                names = stand_in(held, unidentified(held))
            mine = Counter(names_of(best))
            mine |= Counter(n for t in terms for n in term(t.name).nests)
            subs = [
                r for r in results
                if r is not best and r.status != NOT_EVALUATED and not unidentified(r)
                and not Counter(names_of(r)) - mine
            ]  # fmt: skip
            others = [
                r for r in results
                if r is not best and r.status != NOT_EVALUATED and not unidentified(r)
            ]  # fmt: skip
            if not subs or not others:
                break
            symbols = ", ".join(terms[j].symbol for j in sorted(bad))
            rival = max(others, key=lambda r: r.ln_evidence)
            smaller = max(subs, key=lambda r: r.ln_evidence)
            if smaller.ln_evidence >= rival.ln_evidence - self.decisive:
                smaller.probability += best.probability
                best.flags.append(
                    f"not chosen: {symbols} not identified; its probability counts for "
                    f"{smaller.name}"
                )
            else:
                rest = sum(r.probability for r in results if r is not best)
                if rest > 0.0:
                    for r in results:
                        if r is not best:
                            r.probability *= (rest + best.probability) / rest
                else:
                    rival.probability += best.probability
                best.flags.append(
                    f"not chosen: {symbols} not identified, and no law without "
                    f"{'them' if len(bad) > 1 else 'it'} explains the data as well as "
                    f"{rival.name}: its probability is shared by the other laws"
                )
            best.probability = 0.0
        return results

    def _parsimony(self, results: list[ModelResult], fit: Context) -> None:
        """A law must predict as well as it explains: while the most probable law leads a
        law with fewer parameters (coefficients and shape parameters) by less than
        ``decisive`` nats and predicts held-out blocks (:func:`blocked_cv_rms`) no
        better than it, its probability passes to the best such law by evidence.

        Within ``decisive`` nats the evidence alone is no decision (odds below 100:1),
        and a term that buys them by following a misfit (grasps read as one contact, a
        sensor's drift) or by splitting one term's work between two (``xdot`` as
        ``xdot|xdot|`` plus dry friction) predicts the blocks it did not see no better:
        A term the session needs predicts better, and is kept (docs/benchmarks.md,
        "Randomised paper-form sessions")
        """
        cv_scores(results, fit)

        def size(r: ModelResult) -> int:
            law = r.family or r.model
            return len(law.terms) + len(law.shape_names)

        for _ in range(len(results)):
            best = max(results, key=lambda r: (r.probability, r.ln_evidence))
            if best.status == NOT_EVALUATED or not math.isfinite(best.cv_rms):
                return
            rivals = [
                r for r in results
                if r is not best and r.status != NOT_EVALUATED and not unidentified(r)
                and size(r) < size(best) and math.isfinite(r.cv_rms)
                and r.cv_rms <= best.cv_rms
                and best.ln_evidence - r.ln_evidence < self.decisive
            ]  # fmt: skip
            if not rivals:
                return
            rival = max(rivals, key=lambda r: r.ln_evidence)
            rival.probability += best.probability
            best.probability = 0.0
            best.flags.append(
                f"not chosen: {rival.name} has fewer parameters, is within "
                f"{best.ln_evidence - rival.ln_evidence:.2g} nats of its evidence and "
                f"predicts held-out blocks as well (blocked cross-validation RMS "
                f"{rival.cv_rms:.3g} N against {best.cv_rms:.3g} N); its probability counts "
                f"for {rival.name}"
            )

    @staticmethod
    def _top(results: list[ModelResult]) -> ModelResult:
        """The evaluated law with the most evidence (any law, should none be evaluated)."""
        ranked = [r for r in results if r.status != NOT_EVALUATED] or results
        return max(ranked, key=lambda r: r.ln_evidence)

    @staticmethod
    def _least_squares_law(result: ModelResult) -> Law:
        """The law as least squares fits it (its shape at the least-squares optimum,
        where that differs from the posterior's)."""
        return result.least_squares[0] if result.least_squares is not None else result.model

    def _residual_of(self, result: ModelResult, fit: Context) -> tuple[Array, Array]:
        """A law's design at the fitted rows and its least-squares residuals (N),
        unfiltered: the law as least squares fits it where that differs."""
        law = self._least_squares_law(result)
        A = design(law, fit.kin, fit.x_full, fit.sigma_x, fit.columns)
        return A, fit.y - A @ lstsq_scaled_cond(A, fit.y)[0]

    def _top_residual(self, results: list[ModelResult], fit: Context) -> tuple[str, Array]:
        """The name of the law with the most evidence and its least-squares residuals
        (N) at the fitted rows, unfiltered."""
        top = self._top(results)
        return top.name, self._residual_of(top, fit)[1]

    def _whitened_ratio(self, best: ModelResult, fit: Context) -> float:
        """Effective samples per sample of the prewhitened evidence for the chosen law
        (:func:`~tissuecli.identify.whiten.precision_ratio`): its coefficients' precision
        through the filter against a white likelihood's on the raw rows."""
        assert fit.whiten is not None
        A, r = self._residual_of(best, fit)
        Aw, yw = fit.whiten.transform(A), fit.target
        rw = yw - Aw @ lstsq_scaled_cond(Aw, yw)[0]
        ratio = precision_ratio(Aw.T @ Aw, float(rw @ rw) / max(yw.size, 1), A.T @ A,
                                float(r @ r) / max(fit.y.size, 1))  # fmt: skip
        return float(np.clip(ratio, 1.0 / fit.y.size, 1.0e3))

    def _residual_weight(
        self, results: list[ModelResult], fit: Context, measured: float
    ) -> tuple[float, float]:
        """The residual autocorrelation time (samples) of the law with the most evidence
        and the data weight its residuals support (:func:`data_weight`)."""
        law = self._least_squares_law(self._top(results))
        fp = first_pass(law, fit.kin, fit.x_full, fit.y, fit.sigma_x, fit.columns, fit.paths)
        A = design(law, fit.kin, fit.x_full, fit.sigma_x, fit.columns)
        residual = fit.y - A @ fp.beta
        tau = residual_tau(residual)
        # the variances of the estimator the posterior reports (errors-in-variables
        # corrected where the fit corrects it)
        return tau, data_weight(A, residual, tau, kept_correction(fp), fp.beta) * measured

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

    def _position_noise(self, ready: Prepared) -> float:
        """Position noise SD (m) of the closure the fit's columns are formed from: a
        rebuilt staircase's own (:attr:`Prepared.rebuilt_sd`), else from the spectrum's
        flat top over the trusted samples, floored by the ADC step.

        Quantisation with little dither is not white and hides from the flat top, so
        the ADC step sets a floor: step / sqrt(12). Clipped and lost samples are left
        out: flat at an end of the ADC, or interpolated, they carry no noise (free jaws
        clipped for 31 % of a grasping session read the noise 20 % low, and left M 2 %
        low, 5 posterior SDs).
        """
        if ready.rebuilt_sd is not None:
            return ready.rebuilt_sd
        session = ready.session
        fs = 1.0 / float(np.median(np.diff(session.time)))
        step = session.adc.step("position") if session.adc is not None else 0.0
        return max(position_noise_sd(session.position, fs, ready.trusted), step / np.sqrt(12))

    def _tick(self, name: str) -> None:
        """One more law scored: the progress counts it against the laws known so far
        (the search beyond the linear laws learns its length as it goes)."""
        self._scored = getattr(self, "_scored", 0) + 1
        self._known = max(getattr(self, "_known", 0), self._scored)
        getattr(self, "_progress", SILENT).advance(self._scored, self._known, name)

    def _score(self, law: Law, fit: Context) -> ModelResult:
        """One law scored at ``fit``'s weight: its shape marginalised if it has one."""
        if law.shape_names:
            return exact_shaped(law, fit)
        fp = first_pass(law, fit.kin, fit.x_full, fit.y, fit.sigma_x, fit.columns, fit.paths,
                        fit.whiten)  # fmt: skip
        return exact_result(law, fp, fit)

    def _candidates(
        self,
        linear: list[Law],
        shaped: list[Law],
        firsts: dict[str, FirstPass],
        fit: Context,
    ) -> tuple[list[ModelResult], list[str]]:
        """Every candidate law scored at ``fit``'s weight: the linear ones, the search's
        (default forms) and the laws with shape parameters asked for; and what the
        search could not do."""
        found: list[str] = []
        ready = [prepared(m, firsts[m.name], fit) for m in linear]
        # the evidences weighed best first, so that a law far behind the best needs its
        # positivity bounds' mass only roughly; the draws then in the laws' order
        for i in sorted(range(len(linear)), key=lambda i: -ready[i][4].upper_ln_evidence()):
            weigh(ready[i][4], fit)
        results = [
            exact_result(m, firsts[m.name], fit, r) for m, r in zip(linear, ready, strict=True)
        ]
        if self.forms in (None, "all"):
            scope = Scope(fit.kin, getattr(self, "design_", None), fit.y.size * fit.kin.stride)
            tried, notes = self._strategy.run(results, lambda law: self._score(law, fit), scope)
            results += tried
            found += notes
        results += [exact_shaped(m, fit) for m in shaped]
        return results, list(dict.fromkeys(found))

    def _progress_for(self, name: str) -> Callable[[int, float], None] | None:
        """The callback a chain tells its steps for the law of this name, or None."""
        if self.progress is None:
            return None
        progress = as_progress(self.progress)
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


def evaluated(results: Sequence[ModelResult]) -> list[ModelResult]:
    """The laws whose evidence was evaluated and is finite."""
    return [r for r in results
            if r.status != NOT_EVALUATED and r.posterior is not None
            and math.isfinite(r.ln_evidence)]  # fmt: skip


def stand_in(r: ModelResult, bad: set[int]) -> list[str] | None:
    """The terms of the law ``r`` stands for without its terms ``bad`` (indices): a term
    that needs one left out goes with it (contact damping, contact), and one left out
    leaves what it equals at one of its shapes (:attr:`Term.nests`; contact: a spring
    and an offset) should nothing else stiffen the law. None if ``bad`` is empty or no
    stiffness remains."""
    if not bad:
        return None
    terms = (r.family or r.model).terms
    names = [t.name for j, t in enumerate(terms) if j not in bad]
    names = [n for n in names if all(q in names for q in term(n).requires)]
    if not any(term(n).role == "stiffness" for n in names):
        nested = [n for j in sorted(bad) for n in term(terms[j].name).nests]
        names = list(dict.fromkeys([*names, *nested]))
    return names if any(term(n).role == "stiffness" for n in names) else None


def stand_in_gain(r: ModelResult, bad: set[int]) -> float:
    """At most the ln evidence the law ``r`` gains without its terms ``bad`` (indices):
    the Savage-Dickey ratio of the posterior's density at zero to the prior's, with the
    posterior's density at its peak, ``sum ln s_j - ln det(Sigma_bad) / 2`` (``s_j`` the
    prior scales, ``Sigma_bad`` the posterior covariance of those coefficients). Exact but
    for the data's pull from zero (which lowers it) for a Gaussian posterior and normal
    priors; a positivity bound halves the prior's density scale and roughly doubles the
    posterior's at zero alike. Infinite where the posterior does not tell it."""
    if not bad or r.posterior is None or r.prior is None:
        return 0.0
    j = np.array(sorted(bad))
    cov = np.asarray(r.posterior.cov, float)
    if cov.shape[0] <= int(j.max()):
        return math.inf
    sign, logdet = np.linalg.slogdet(cov[np.ix_(j, j)])
    if sign <= 0 or not math.isfinite(logdet):
        return math.inf
    return float(np.sum(np.log(np.asarray(r.prior.scales, float)[j])) - 0.5 * logdet)


def unidentified_in(r: ModelResult) -> set[int]:
    """Indices of the terms :func:`identifiability` would call not identified (before
    the flags are set)."""
    if r.posterior is None or r.prior is None:
        return set()
    flags = identifiability(r)
    return {j for j, t in enumerate(r.model.terms)
            if any(f.startswith(f"{t.symbol} not identified") for f in flags)}  # fmt: skip


def provisional_choice(results: Sequence[ModelResult]) -> ModelResult:
    """The law the fit would choose among ``results`` before sampling: the one with the
    most evidence among those evaluated whose coefficients are all identified
    (:func:`identifiability`), or with the most evidence if none is."""
    ranked = evaluated(results) or list(results)
    clean = [r for r in ranked if not unidentified_in(r)]
    return max(clean or ranked, key=lambda r: r.ln_evidence)
