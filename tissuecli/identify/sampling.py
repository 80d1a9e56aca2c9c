"""Sampling a posterior with emcee where no closed form exists, and a sampler-based
evidence (generalised stepping-stone) to check the exact one against; and which laws of
a fit are sampled (:func:`sample_posteriors`, :func:`sample_shape_posteriors`).

emcee and ``scipy.stats`` are imported only when a chain is actually run.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..core.errors import FitError
from .posterior import (
    CHECK_NATS,
    LN_2PI,
    REJECTION_ACCEPTANCE,
    ExactPosterior,
    Posterior,
    Prior,
    SufficientStats,
    logsumexp,
)
from .scoring import CUT_THRESHOLD, ModelResult

Array = NDArray[np.float64]

#: ln Bayes factor beyond which a form is decisively behind (Jeffreys: 100:1)
DECISIVE = float(np.log(100.0))

#: autocorrelation times a shape's chain runs (emcee's rule is 50). Its walkers (8 for
#: three parameters) then give about 8 (30 - 2) = 224 independent draws after the
#: burn-in: the mean's Monte Carlo error is 1 / sqrt(224) = 0.07 posterior SD, a 95 %
#: bound's 2.7 / sqrt(224) = 0.18 SD (under 5 % of the interval's width), well inside
#: the Laplace and grid approximations the chain refines; the chain is the cost of
#: a fit whose best law has three shape parameters, each step one exact evidence
SHAPE_TIMES = 30.0


class PowerPosterior:
    """``ln p(y | theta) + ln p(theta)`` over theta = (gamma, ln sigma).

    gamma are the coefficients of unit-norm columns, so all walkers move on
    comparable scales; vectorised over walkers for emcee.
    """

    def __init__(self, stats: SufficientStats, prior: Prior) -> None:
        self.s, self.d = stats.scaled()
        self.ws = prior.scales * self.d
        self.prior = prior
        self.lo, self.hi = np.log(prior.sigma_lo), np.log(prior.sigma_hi)
        self._ln_prior_const = float(
            np.sum(np.log(2) * prior.bounded - np.log(self.ws) - 0.5 * LN_2PI)
            - np.log(prior.ln_sigma_range)
        )

    def log_likelihood(self, theta: Array) -> Array:
        return self.s.log_likelihood(theta[:, :-1], np.exp(theta[:, -1]))

    def log_prior(self, theta: Array) -> Array:
        g, u = theta[:, :-1], theta[:, -1]
        ok = np.all(g[:, self.prior.bounded] >= 0, axis=1) & (u >= self.lo) & (u <= self.hi)
        lp = self._ln_prior_const - 0.5 * np.sum((g / self.ws) ** 2, axis=1)
        return np.where(ok, lp, -np.inf)

    def __call__(self, theta: Array) -> Array:
        lp = self.log_prior(theta)
        good = np.isfinite(lp)
        out = np.full(theta.shape[0], -np.inf)
        if np.any(good):
            # a walker at a noise level far below the residual has a likelihood that
            # underflows: -inf is the right value, not a warning
            with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
                ll = self.log_likelihood(theta[good])
            out[good] = lp[good] + np.where(np.isnan(ll), -np.inf, ll)
        return out

    def to_si(self, theta: Array) -> Array:
        """(k, p + 1) array of SI coefficients and sigma."""
        return np.column_stack([theta[:, :-1] / self.d, np.exp(theta[:, -1])])


def _start(
    exact: ExactPosterior, target: PowerPosterior, walkers: int, rng: np.random.Generator
) -> Array:
    """Walkers around the least-squares solution, the bounded coefficients reflected
    into >= 0."""
    mu, cov = exact.conditional(float(np.exp(exact.u[int(np.argmax(exact.weights))])))
    gamma = _spread(mu * target.d, cov * np.outer(target.d, target.d), walkers, rng)
    gamma[:, exact.prior.bounded] = np.abs(gamma[:, exact.prior.bounded])
    u = exact.u[int(np.argmax(exact.weights))] + 1e-3 * rng.standard_normal(walkers)
    # a noise level piled against the prior's end must not start walkers beyond it
    # (they would start at -inf, and emcee's moves subtract -inf from -inf)
    u = np.clip(u, target.lo + 1e-9, target.hi - 1e-9)
    walkers_at = np.column_stack([gamma, u])
    # a walker whose likelihood underflows (far out along a direction the data pin
    # down to rounding) is pulled back towards the centre until it is finite
    centre = np.median(walkers_at, axis=0)
    for _ in range(60):
        lost = ~np.isfinite(target(walkers_at))
        if not np.any(lost):
            break
        walkers_at[lost] = centre + 0.5 * (walkers_at[lost] - centre)
    return walkers_at


def _spread(mean: Array, cov: Array, walkers: int, rng: np.random.Generator) -> Array:
    """Gaussian draws (walkers, p) around ``mean`` with ``cov`` (unit-norm coefficients),
    its eigenvalues floored so that a near-singular covariance still spreads the walkers
    in every direction (an ensemble on a line cannot leave it)."""
    lam, vec = np.linalg.eigh(0.5 * (cov + cov.T))
    # 1e-7 of the widest direction keeps the ensemble's covariance within emcee's
    # condition limit (1e8) without moving the walkers noticeably
    floor = 1e-7 * max(float(np.max(lam)), 1e-300)
    z = rng.standard_normal((walkers, mean.size))
    return mean + (z * np.sqrt(np.clip(lam, floor, None))) @ vec.T


# emcee refuses an initial ensemble whose covariance has a condition number above 1e8;
# ours is full rank by construction (:func:`_spread`), but a posterior that is itself
# that ill-conditioned (a session that barely moves a term) must still be sampled, so
# every run_mcmc call skips that check.


def _ensemble(
    log_prob: Callable[[Array], Array], walkers: int, ndim: int, rng: np.random.Generator
) -> Any:
    """A vectorised emcee sampler seeded from ``rng``, so runs are reproducible."""
    import emcee  # only when sampling is needed

    sampler = emcee.EnsembleSampler(walkers, ndim, log_prob, vectorize=True)
    sampler.random_state = np.random.RandomState(int(rng.integers(2**31))).get_state()
    return sampler


def _run_chain(
    sampler: Any,
    p0: Array,
    chunk: int,
    min_steps: int,
    max_steps: int,
    progress: Callable[[int, float], None] | None,
    give_up_early: bool = False,
    times: float = 50.0,
) -> tuple[Array, bool, Array]:
    """Run an emcee sampler from ``p0`` until the chain is longer than ``times``
    integrated autocorrelation times (50: emcee's rule) and ``min_steps``, or
    ``max_steps``.

    Returns the autocorrelation time per parameter (steps), whether the rule was met,
    and the flat chain after a burn-in of 2 tau, thinned by tau / 2.
    """
    tau = np.full(p0.shape[1], np.inf)
    state: Any = p0
    while sampler.iteration < max_steps:
        # runs grow with the chain, so the autocorrelation time (O(n log n) over the
        # whole chain) is estimated O(log n) times, not once per chunk; a run that
        # would overshoot the length the last estimate asks for stops there (a tenth
        # beyond it), since every further step is a costly evaluation
        steps = min(max(chunk, sampler.iteration // 4), max_steps - sampler.iteration)
        need = max(min_steps, times * float(np.max(tau)))
        if np.isfinite(need) and need > sampler.iteration:
            steps = min(steps, max(chunk // 4, int(np.ceil(1.1 * need)) - sampler.iteration))
        state = sampler.run_mcmc(state, steps, progress=False, skip_initial_state_check=True)
        tau = sampler.get_autocorr_time(tol=0)
        if progress is not None:
            progress(sampler.iteration, float(np.max(tau)))
        if sampler.iteration >= max(min_steps, times * np.max(tau)):
            break
        if give_up_early and sampler.iteration >= max_steps // 4:
            if times * np.max(tau) > 2 * max_steps:
                break  # would need more than twice the budget: say so now, not at the budget
    top = float(np.max(tau))
    converged = bool(sampler.iteration >= times * top)
    burn = int(min(2 * top, sampler.iteration // 2))
    thin = max(1, int(top / 2))
    return tau, converged, sampler.get_chain(discard=burn, thin=thin, flat=True)


def run_emcee(
    stats: SufficientStats,
    prior: Prior,
    rng: np.random.Generator,
    *,
    walkers: int = 32,
    chunk: int = 500,
    min_steps: int = 1000,
    max_steps: int = 40_000,
    progress: Callable[[int, float], None] | None = None,
) -> Posterior:
    """Sample the truncated posterior with emcee until the chain exceeds 50 tau.

    The evidence is the exact one (closed form times the orthant mass); run
    :func:`stepping_stone` for a sampler-based estimate.
    """
    exact = ExactPosterior(stats, prior)
    target = PowerPosterior(stats, prior)
    p0 = _start(exact, target, walkers, rng)
    sampler = _ensemble(target, walkers, p0.shape[1], rng)
    tau, converged, chain = _run_chain(
        sampler, p0, chunk, min_steps, max_steps, progress, give_up_early=True
    )
    chain = target.to_si(chain)
    beta = chain[:, :-1]
    inside = exact.orthant_mass()
    ln_z = exact.ln_evidence()
    return Posterior(
        mean=beta.mean(axis=0),
        sd=beta.std(axis=0, ddof=1),
        ci95=np.percentile(beta, [2.5, 97.5], axis=0).T,
        cov=np.cov(beta.T),
        sigma_mean=float(chain[:, -1].mean()),
        sigma_ci95=tuple(float(v) for v in np.percentile(chain[:, -1], [2.5, 97.5])),  # type: ignore[arg-type]
        ln_evidence=float(ln_z),
        outside=1.0 - inside,
        method="emcee",
        samples=chain,
        diagnostics={
            "steps": int(sampler.iteration),
            "walkers": walkers,
            "tau": [float(t) for t in tau],
            "acceptance": float(np.mean(sampler.acceptance_fraction)),
            "converged": bool(converged),
            "independent_samples": int(
                beta.shape[0] * max(1, int(np.max(tau) / 2)) / max(np.max(tau), 1)
            ),
        },
        below_zero=exact.below_zero(),
    )


class ReferencePath:
    """Log density ``t (ln L + ln prior) + (1 - t) ln q`` on the path from a reference ``q``
    (a Gaussian fitted to posterior draws, widened) to the posterior."""

    def __init__(self, target: PowerPosterior, mean: Array, cov: Array) -> None:
        self.target = target
        from scipy import stats  # only when a chain runs

        self.q = stats.multivariate_normal(mean=mean, cov=cov, allow_singular=True)
        self.t = 1.0

    def log_ratio(self, theta: Array) -> Array:
        """ln L + ln prior - ln q: the quantity whose powers the ladder averages."""
        lp = self.target.log_prior(theta)
        out = np.full(theta.shape[0], -np.inf)
        good = np.isfinite(lp)
        if np.any(good):
            out[good] = lp[good] + self.target.log_likelihood(theta[good])
        return out - self.q.logpdf(theta)

    def __call__(self, theta: Array) -> Array:
        lq = self.q.logpdf(theta)
        if self.t == 0.0:
            return lq
        with np.errstate(invalid="ignore"):
            return np.where(np.isfinite(lr := self.log_ratio(theta)), lq + self.t * lr, -np.inf)


def stepping_stone(
    stats_: SufficientStats,
    prior: Prior,
    rng: np.random.Generator,
    *,
    temperatures: int = 8,
    power: float = 3.0,
    walkers: int = 32,
    steps: int = 500,
    burn: int = 200,
    widen: float = 1.5,
) -> float:
    """Sampler-based ln evidence: generalised stepping-stone over emcee (Fan et al. 2011).

    The ladder ``t_k = (k / K)^power`` runs from a reference ``q`` (a Gaussian
    fitted to emcee posterior draws, its SD widened by ``widen``), drawn
    directly, to the posterior; ``ln Z = sum_k ln E_{t_k}[(L p / q)^(t_{k+1} - t_k)]``.
    Starting from a reference near the posterior instead of the prior cuts the
    variance of each rung; it needs only the unnormalised posterior, so it
    applies to models without a closed form.
    """
    exact = ExactPosterior(stats_, prior)
    target = PowerPosterior(stats_, prior)
    state = _start(exact, target, walkers, rng)
    sampler = _ensemble(target, walkers, state.shape[1], rng)
    state = sampler.run_mcmc(
        state, burn + 2 * steps, progress=False, skip_initial_state_check=True
    ).coords
    draws = sampler.get_chain(discard=burn, flat=True)
    path = ReferencePath(target, draws.mean(axis=0), np.cov(draws.T) * widen**2)
    ladder = (np.arange(temperatures + 1) / temperatures) ** power
    ln_z = 0.0
    for k in range(temperatures - 1, -1, -1):
        t, dt = ladder[k], ladder[k + 1] - ladder[k]
        if t == 0.0:
            theta = path.q.rvs(size=walkers * steps, random_state=rng)
        else:
            path.t = t
            sampler = _ensemble(path, walkers, state.shape[1], rng)
            state = sampler.run_mcmc(
                state, burn + steps, progress=False, skip_initial_state_check=True
            ).coords
            theta = sampler.get_chain(discard=burn, flat=True)
        lr = path.log_ratio(theta)
        ln_z += float(logsumexp(dt * lr) - np.log(lr.size))
    return ln_z


def sample_shapes(
    log_post: Callable[[Array], float],
    start: Array,
    cov: Array,
    inside: Callable[[Array], bool],
    rng: np.random.Generator,
    *,
    walkers: int | None = None,
    chunk: int = 200,
    min_steps: int = 400,
    max_steps: int = 3000,
    times: float = SHAPE_TIMES,
    progress: Callable[[int, float], None] | None = None,
    log_post_many: Callable[[Array], Any] | None = None,
) -> tuple[Array, dict[str, Any]]:
    """Sample a law's shape parameters with emcee, the coefficients and noise level
    marginalised exactly (``log_post`` is the log evidence given the shape plus the log
    prior of the shape, up to a constant).

    Parameters
    ----------
    log_post : callable
        ``log_post(u)`` for one point ``u``, shape (d,), in the shape's coordinates
        (ln tau for a time constant, n and x0 as they are).
    start, cov : ndarray, shapes (d,) and (d, d)
        Where to start the walkers: the peak found from the grid and a covariance
        (the Laplace approximation's, or the grid's spacing).
    inside : callable
        Whether a point lies in the prior's support.
    walkers : int, optional
        Default ``max(8, 2 d + 2)`` (emcee needs at least 2 d).
    chunk, min_steps, max_steps : int
        Steps per run between checks of the autocorrelation time, and the bounds on
        the chain's length: it stops at ``times`` integrated autocorrelation times
        (:data:`SHAPE_TIMES`), or at ``max_steps`` with ``converged`` false.
    times : float
        Autocorrelation times the chain must span.
    log_post_many : callable, optional
        ``log_post`` at many points ``u``, shape (k, d), returning k values: the same
        numbers, cheaper together. emcee then hands it each move's proposals at once.

    Returns
    -------
    draws : ndarray, shape (k, d)
        Posterior draws in ``u`` after a burn-in of 2 tau, thinned by tau / 2.
    diagnostics : dict
        ``steps``, ``walkers``, ``tau`` (per parameter, steps), ``acceptance``,
        ``converged``, ``times`` (the autocorrelation times asked for), ``samples``
        (draws kept) and ``independent_samples``.
    """
    import emcee  # only when a shape is sampled

    d = start.size
    walkers = walkers or max(8, 2 * d + 2)

    def target(u: Array) -> float:
        if not inside(u):
            return -np.inf
        value = log_post(u)
        return value if np.isfinite(value) else -np.inf

    # walkers around the start, within the support (pulled in towards the start if not)
    if not np.isfinite(target(start)):
        raise FitError("its peak lies outside the prior's support or has no finite evidence")
    p0 = _spread(start, cov, walkers, rng)
    for k in range(walkers):
        for _ in range(40):
            if np.isfinite(target(p0[k])):
                break
            p0[k] = start + 0.5 * (p0[k] - start)
        else:  # a walker starting at -inf would poison emcee's acceptance ratios
            p0[k] = start
    # differential evolution moves suit a compact posterior in a few dimensions: they
    # mix faster than the stretch move there (emcee's documentation)
    moves = [(emcee.moves.DEMove(), 0.8), (emcee.moves.DESnookerMove(), 0.2)]

    def target_many(us: Array) -> Array:
        out = np.full(us.shape[0], -np.inf)
        ok = [k for k in range(us.shape[0]) if inside(us[k])]
        if ok:
            assert log_post_many is not None
            values = np.asarray(log_post_many(us[ok]), dtype=float)
            out[ok] = np.where(np.isfinite(values), values, -np.inf)
        return out

    vectorize = log_post_many is not None
    sampler = emcee.EnsembleSampler(walkers, d, target_many if vectorize else target,
                                    moves=moves, vectorize=vectorize)  # fmt: skip
    sampler.random_state = np.random.RandomState(int(rng.integers(2**31))).get_state()
    tau, converged, draws = _run_chain(
        sampler, p0, chunk, min_steps, max_steps, progress, times=times
    )
    top = float(np.max(tau))
    thin = max(1, int(top / 2))
    return draws, {
        "steps": int(sampler.iteration),
        "walkers": int(walkers),
        "tau": [float(t) for t in tau],
        "acceptance": float(np.mean(sampler.acceptance_fraction)),
        "converged": converged,
        "times": float(times),
        "samples": int(draws.shape[0]),
        "independent_samples": int(draws.shape[0] * thin / max(top, 1.0)),
    }


def sample_shape_posteriors(
    results: list[ModelResult], *, sampler: str = "auto", decisive: float = DECISIVE
) -> None:
    """Run emcee over the shape of the chosen law if it has more than
    :data:`~tissuecli.identify.shaped.MAX_GRID_SHAPES` shape parameters. A runner-up
    keeps its Laplace summary (its evidence, what ranks it, is the same estimate
    either way) unless every law not decisively behind is to be sampled
    (``sampler="emcee"``)."""
    top = max(r.ln_evidence for r in results)
    for res in results:
        if res.sample_shape is None:
            continue
        behind = top - res.ln_evidence
        reason = ""
        if behind > decisive:
            reason = f"ln Bayes factor {behind:.1f} behind the best (> {decisive:.1f}, decisive)"
        elif behind > 0 and sampler == "auto":
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


def sample_posteriors(
    results: list[ModelResult],
    rng: np.random.Generator,
    *,
    sampler: str = "auto",
    decisive: float = DECISIVE,
    progress_for: Callable[[str], Callable[[int, float], None] | None] | None = None,
) -> None:
    """Run emcee where no exact posterior is known (or on request): for the chosen
    law only, unless on request (runners-up keep the closed form, their evidence
    exact), and never for forms decisively behind; say for each form how its
    posterior was found."""
    top = max(r.ln_evidence for r in results)
    for res in results:
        assert res.posterior is not None
        behind = top - res.ln_evidence
        if res.refine is not None and behind <= 0:
            res.refine(rng)  # a shape posterior piled on the prior's edge, made finer
        exact = res.posterior.diagnostics.get("exact", False)
        cut = res.posterior.outside
        if exact and sampler == "auto":
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
        runner_up = behind > 0 and sampler == "auto"
        if (behind > decisive or runner_up) and len(results) > 1:
            res.status = "skipped"
            text = (
                f"not sampled: ln Bayes factor {behind:.1f} behind the best "
                f"(> {decisive:.1f}, decisive)"
                if behind > decisive
                else f"not sampled: a runner-up (ln Bayes factor {behind:.1f} behind the "
                "best), so its intervals are the closed form's, which the positivity "
                f"bound cuts by {100 * cut:.2g} %; its evidence is exact; --sampler emcee "
                "samples it"
            )
            res.reason = f"{res.reason}; {text}" if res.family is not None else text
            continue
        if sampler == "auto" and res.stats is not None and res.prior is not None:
            # exact draws where the bound keeps enough for rejection to beat a chain
            # a law whose shape is marginalised keeps it so: drawn at its point alone,
            # a contact stiffness lost the shape's part of its spread (z of 80)
            drawn = (
                res.redraw(rng, REJECTION_ACCEPTANCE)
                if res.redraw is not None
                else ExactPosterior(res.stats, res.prior).truncated(
                    rng, min_acceptance=REJECTION_ACCEPTANCE
                )
            )
            if drawn is not None:
                drawn.diagnostics["exact"] = True
                res.posterior = drawn
                how = (
                    f"exact posterior with the positivity bound, which cuts {100 * cut:.4g} % "
                    "of the closed form: independent draws by rejection"
                )
                res.reason = f"{res.reason}; {how}" if res.family is not None else how
                continue
        progress = progress_for(res.name) if progress_for is not None else None
        res.posterior = run_emcee(res.stats, res.prior, rng, progress=progress)  # type: ignore[arg-type]
        res.status = "emcee"
        res.reason = (
            f"sampled: the positivity bound cuts {100 * cut:.2g} % of the closed-form posterior"
            if sampler == "auto"
            else "sampled on request (--sampler emcee)"
        )
        if sampler == "emcee":
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
