"""Bayesian linear regression for ``y = A beta + noise`` with physical priors.

The model for one choice of forms: ``y ~ N(A beta, sigma^2 I)`` with

- ``beta_j >= 0`` with a half-normal prior of scale ``w_j`` (SI units), so
  stiffness, damping and mass are non-negative and of plausible size;
- ``sigma`` log-uniform on ``[sigma_lo, sigma_hi]`` (N): proper, scale-free.

Given sigma the posterior of beta is Gaussian and the evidence closed form
(Bishop, PRML 3.3); sigma is one dimension, integrated by quadrature on
``ln sigma``. The positivity bound multiplies the evidence by
``P(beta >= 0 | y) / P_prior(beta >= 0)`` (the latter is 1/8 for three
zero-centred half-normals); when that posterior mass outside the bound is not
negligible the posterior is sampled with emcee instead
(:mod:`tissuecli.identify.sampling`). Everything works on sufficient statistics
(A^T A, A^T y, y^T y, n), so cost does not grow with n. The data weight
``n_eff / n`` tempers the likelihood for correlated residuals.

NumPy alone: a fit that needs no sampler loads neither SciPy nor emcee.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..core.errors import FitError
from .orthant import (
    ROUGH_ABS_TOL,
    ROUGH_REL_TOL,
    normal_cdf,
    normal_ppf,
    orthant_log_probability,
    orthant_log_upper_bound,
    tail_log_probability,
)

Array = NDArray[np.float64]

LN_2PI = float(np.log(2 * np.pi))


def gram_scales(G: Array) -> Array:
    """The column norms behind a Gram matrix ``A^T A``, shape (p,): ``sqrt(diag G)``,
    1 for an empty column."""
    d = np.sqrt(np.maximum(G.diagonal(), 0.0))
    d[d == 0] = 1.0
    return d


def gram_lstsq(G: Array, b: Array) -> Array:
    """Least squares ``G beta = b`` for a Gram-like matrix ``G`` (p, p), solved on unit-norm
    columns, shape (p,).

    Columns in SI units span many decades (``x^3`` in m^3 is 1e-8 where an offset's
    column is 1), so the Gram matrix's eigenvalues span their squares: a pseudo-inverse
    with a relative cut-off (``lstsq``'s ``rcond``) then drops the small column's
    direction as if it were rank-deficient, though the scaled matrix is well
    conditioned. Scaled first, only a truly collinear direction is dropped.
    """
    d = gram_scales(G)
    return np.asarray(np.linalg.lstsq(G / (d[:, None] * d), b / d, rcond=None)[0] / d)


def gram_pinv(G: Array) -> Array:
    """The pseudo-inverse of a Gram-like matrix (p, p), taken on unit-norm columns (see
    :func:`gram_lstsq`)."""
    d = gram_scales(G)
    return np.asarray(np.linalg.pinv(G / np.outer(d, d), hermitian=True) / np.outer(d, d))


@dataclass(frozen=True)
class Prior:
    """Scales of the coefficients' priors (SI) and the range of the noise SD (N).

    A passive coefficient (``passive[j]``) is half-normal on ``[0, inf)``, any other
    normal, both of scale ``scales[j]``.
    """

    scales: Array
    passive: NDArray[np.bool_] | None = None  # None: every coefficient is passive
    # wide on purpose: the range only adds a constant to every form's ln evidence,
    # and sessions in any physical scale (nN to MN) must fit inside it
    sigma_lo: float = 1e-12
    sigma_hi: float = 1e9

    @property
    def ln_sigma_range(self) -> float:
        return float(np.log(self.sigma_hi / self.sigma_lo))

    @property
    def bounded(self) -> NDArray[np.bool_]:
        """Which coefficients are bounded below by 0, shape (p,)."""
        if self.passive is None:
            return np.ones(self.scales.size, bool)
        return np.asarray(self.passive, bool)


@dataclass(frozen=True)
class SufficientStats:
    """Sufficient statistics of a linear-Gaussian regression, possibly tempered.

    Attributes
    ----------
    G : ndarray, shape (p, p)
        ``w A^T A`` (minus any errors-in-variables correction).
    b : ndarray, shape (p,)
        ``w A^T y``.
    yy : float
        ``w y^T y``.
    n : float
        ``w n``: the effective number of independent observations.
    rss : float, optional
        ``w`` times the least-squares residual sum of squares, computed from the
        residuals themselves. ``yy - b^T G^-1 b`` loses it to cancellation when the
        fit explains all but a millionth of ``yy`` on ill-conditioned columns (a ramp
        at constant speed); without it the evidence would grow without bound as the
        noise level goes to zero.
    """

    G: Array
    b: Array
    yy: float
    n: float
    rss: float | None = None

    @classmethod
    def from_data(
        cls, A: Array, y: Array, weight: float = 1.0, correction: Array | None = None
    ) -> SufficientStats:
        G = A.T @ A
        if correction is not None:
            G = G - correction
        d = np.linalg.norm(A, axis=0)
        d[d == 0] = 1.0
        beta = np.linalg.lstsq(A / d, y, rcond=None)[0] / d
        r = y - A @ beta
        rss = float(r @ r)
        if correction is not None:  # the corrected fit's residual, without cancellation
            beta_c = gram_lstsq(G, A.T @ y)
            rss = max(rss - float(beta_c @ correction @ beta), 0.0)
        return cls(
            weight * G,
            weight * (A.T @ y),
            float(weight * (y @ y)),
            weight * y.size,
            weight * rss,
        )

    def scaled(self) -> tuple[SufficientStats, Array]:
        """Statistics of unit-norm columns, and the column norms ``d`` (beta = gamma / d)."""
        # np.maximum and a column times a row: np.clip's and np.outer's numbers, without
        # their wrappers (a shaped law's climb forms thousands of these)
        d = np.sqrt(np.maximum(self.G.diagonal(), 1e-300))
        return SufficientStats(self.G / (d[:, None] * d), self.b / d, self.yy, self.n, self.rss), d

    def least_squares_rss(self) -> float:
        """The least-squares residual sum of squares (``w`` times), >= 0: the given one,
        else ``yy - b^T G^+ b`` floored at zero."""
        if self.rss is not None:
            return max(float(self.rss), 0.0)
        d = np.sqrt(np.clip(np.diag(self.G), 1e-300, None))
        gamma = np.linalg.lstsq(self.G / np.outer(d, d), self.b / d, rcond=None)[0]
        return max(self.yy - float(gamma @ (self.b / d)), 0.0)

    def max_log_likelihood(self) -> float:
        """ln of the likelihood's maximum over (beta, sigma): an upper bound on any
        evidence of these data (a proper prior averages the likelihood)."""
        rss = self.least_squares_rss()
        if not self.n > 0:
            return 0.0
        var = max(rss / self.n, 1e-300)
        return float(-0.5 * self.n * (np.log(2 * np.pi * var) + 1.0))

    def log_likelihood(self, beta: Array, sigma: Array) -> Array:
        """ln p(y | beta, sigma) for beta of shape (k, p) and sigma (k,)."""
        quad = self.yy - 2 * beta @ self.b + np.einsum("ki,ij,kj->k", beta, self.G, beta)
        # a sum of squares: rounding in a near-exact fit must not make it negative (the
        # likelihood would grow without bound as sigma -> 0)
        quad = np.maximum(quad, 0.0)
        return -self.n * (np.log(sigma) + 0.5 * LN_2PI) - 0.5 * quad / sigma**2


@dataclass
class Posterior:
    """Summary of a posterior over (beta, sigma), all in SI.

    ``samples`` has shape (k, p + 1): coefficient draws, then sigma.
    """

    mean: Array
    sd: Array
    ci95: Array
    cov: Array
    sigma_mean: float
    sigma_ci95: tuple[float, float]
    ln_evidence: float
    outside: float
    method: str
    samples: Array
    diagnostics: dict[str, Any] = field(default_factory=dict)
    #: each coefficient's posterior mass below zero without the positivity bounds (p,),
    #: where the closed form gives it: a passive coefficient with more than 2.5 % there
    #: has an unbounded 95 % interval reaching zero (not identified)
    below_zero: Array | None = None


class ExactPosterior:
    """Closed-form posterior and evidence, integrated over ln sigma by quadrature.

    Parameters
    ----------
    stats : SufficientStats
    prior : Prior
    nodes : int
        Quadrature nodes over +-12 posterior SDs of ln sigma.
    """

    def __init__(self, stats: SufficientStats, prior: Prior, nodes: int = 401) -> None:
        self.stats, self.prior = stats, prior
        self._inside: float | None = None
        self._inside_error = 0.0
        self._tail: float | None = None
        #: the mass is known only to lie below ``_inside`` (:data:`FAR_NATS`)
        self.bound_only = False
        #: the lattice's target is the looser one of a law far behind (:meth:`rough`)
        self._rough = False
        self._mixture: tuple[Array, Array, Array, NDArray[np.intp]] | None = None
        self._modal_at: tuple[Array, Array] | None = None
        self._below: Array | None = None
        s, self.d = stats.scaled()
        self.ws = prior.scales * self.d  # prior scales of the unit-norm coefficients
        # whiten by the prior: gamma = ws * delta, delta ~ N(0, I); then diagonalise
        Gw = s.G * (self.ws[:, None] * self.ws)
        lam, self.Q = np.linalg.eigh(Gw)
        self.lam = np.maximum(lam, 0.0)
        # rounding can leave a null direction of G with a sliver of b: the data say
        # nothing there, and c^2 / lam would blow the evidence up as sigma -> 0
        null = self.lam <= 1e-13 * max(float(self.lam.max()), 1e-300)
        self.c = np.where(null, 0.0, self.Q.T @ (self.ws * s.b))
        self.s = s
        # the least-squares residual, never from yy - sum c^2 / lam (cancellation: a
        # fit that explains all but 1e-7 of yy on columns of condition 1e8 left it
        # negative, and the evidence grew as 1 / sigma^2 to 1e21)
        self._lam_safe = np.where(null, 1.0, self.lam)
        if s.rss is not None:
            self.rss0 = max(float(s.rss), 0.0)
        else:
            self.rss0 = max(s.yy - float(np.sum(self.c**2 / self._lam_safe)), 0.0)
        lo, hi = np.log(prior.sigma_lo), np.log(prior.sigma_hi)
        # the least-squares noise level may lie outside the prior's range (a noise-free
        # session, where rounding leaves a residual of 1e-150 N, or none at all): the
        # posterior then piles up at that end, so start there. Unclamped, the grid ran
        # from lo down to below lo, its node spacing was negative and every weight NaN.
        u_hat = 0.5 * np.log(max(self._rss_ls() / max(s.n, 1.0), 1e-300))
        u_hat = min(max(u_hat, lo), hi)
        half = max(12.0 / np.sqrt(2 * max(s.n, 1.0)), 0.05)
        for _ in range(8):  # widen until the integrand is negligible at both ends
            self.u = np.linspace(max(lo, u_hat - half), min(hi, u_hat + half), nodes)
            self.f = self._ln_z_given_sigma(np.exp(self.u))
            peak = self.f.max()
            ok_lo = self.u[0] <= lo or self.f[0] < peak - 40
            ok_hi = self.u[-1] >= hi or self.f[-1] < peak - 40
            if ok_lo and ok_hi:
                break
            u_hat = self.u[int(np.argmax(self.f))]
            half *= 2
        w = np.full(nodes, self.u[1] - self.u[0])
        w[[0, -1]] *= 0.5
        lw = self.f + np.log(w)
        total = logsumexp(lw)
        self.ln_z_untruncated = float(total - np.log(prior.ln_sigma_range))
        self.weights = np.exp(lw - total)
        if not (np.all(np.isfinite(self.weights)) and math.isfinite(self.ln_z_untruncated)):
            raise FitError(
                "the posterior of the noise level is not finite (the session's forces or "
                "positions reach values floating point cannot square); check its units"
            )

    def _rss_ls(self) -> float:
        return float(max(self.rss0, 1e-300 * self.s.yy + 1e-300))

    def _ln_z_given_sigma(self, sigma: Array) -> Array:
        s2 = sigma[:, None] ** 2
        lam = self._lam_safe
        # yy - c^T (lam + s2)^-1 c = rss0 + sum c^2 s2 / (lam (lam + s2)): every term >= 0
        quad = self.rss0 + (self.c**2 / (lam * (lam + s2))).sum(axis=1) * s2[:, 0]
        return (
            -self.s.n * (np.log(sigma) + 0.5 * LN_2PI)
            - 0.5 * quad / sigma**2
            - 0.5 * np.log1p(self.lam / s2).sum(axis=1)
        )

    def conditional(self, sigma: float) -> tuple[Array, Array]:
        """Mean (p,) and covariance (p, p) of beta given sigma, untruncated, SI."""
        s2 = sigma**2
        scale = self.ws / self.d
        mu = scale * (self.Q @ (self.c / (self.lam + s2)))
        cov = (self.Q * (s2 / (self.lam + s2))) @ self.Q.T * np.outer(scale, scale)
        return mu, cov

    def conditionals(self, sigma: Array) -> tuple[Array, Array]:
        """:meth:`conditional` at each of several noise levels: means (m, p) and
        covariances (m, p, p), SI, in one product each."""
        s2 = np.asarray(sigma, dtype=float)[:, None] ** 2
        scale = self.ws / self.d
        mus = scale * ((self.c / (self.lam + s2)) @ self.Q.T)
        covs = np.matmul(self.Q * (s2 / (self.lam + s2))[:, None, :], self.Q.T)
        return mus, covs * np.outer(scale, scale)

    def mixture(self) -> tuple[Array, Array, Array, NDArray[np.intp]]:
        """Weights (m,), means (m, p), covariances (m, p, p) and node indices (m,) of the
        significant quadrature nodes (computed once: the summary and the exact draws
        both need them)."""
        if self._mixture is None:
            self._mixture = self._mix()
        return self._mixture

    def _mix(self) -> tuple[Array, Array, Array, NDArray[np.intp]]:
        idx = np.flatnonzero(self.weights > 1e-12 * self.weights.max())
        w = self.weights[idx]
        if idx.size > MIXTURE_NODES:
            # the conditional posteriors change smoothly with sigma: neighbouring nodes
            # pooled into one (at their weighted centre) change no moment or quantile
            # beyond rounding, and each summary costs a tenth
            # the bins of np.array_split(np.arange(idx.size), MIXTURE_NODES): the first
            # idx.size % MIXTURE_NODES one longer
            size, longer = divmod(idx.size, MIXTURE_NODES)
            starts = np.arange(MIXTURE_NODES) * size + np.minimum(np.arange(MIXTURE_NODES), longer)
            ww = w + 1e-300
            at = np.arange(idx.size, dtype=float)
            centre = np.rint(np.add.reduceat(at * ww, starts) / np.add.reduceat(ww, starts))
            w = np.add.reduceat(w, starts)
            idx = idx[centre.astype(np.intp)]
        mus, covs = self.conditionals(np.exp(self.u[idx]))
        w = w / w.sum()
        return w, mus, covs, idx

    def below_zero(self) -> Array:
        """Each coefficient's mass below zero under the posterior without the positivity
        bounds (p,): exact, from the Gaussian mixture over sigma's nodes (computed once;
        each caller gets its own copy)."""
        if self._below is None:
            w, mus, covs, _ = self.mixture()
            sds = np.sqrt(np.clip(np.einsum("mii->mi", covs), 0.0, None))
            with np.errstate(divide="ignore", invalid="ignore"):
                z = np.nan_to_num(-mus / sds, nan=-np.inf)  # SD 0: a point mass, at its mean
            self._below = np.asarray(w @ normal_cdf(z), dtype=float)
        return self._below.copy()

    def orthant_mass(self) -> float:
        """Posterior mass of the bounded coefficients >= 0 at the modal sigma (sigma's
        posterior is narrow). Computed once: the evidence, the summary and the exact
        draws all need it, and the lattice is the costly part of a posterior."""
        return math.exp(self.ln_orthant_mass())

    def ln_orthant_mass(self) -> float:
        """ln of :meth:`orthant_mass`, computed in logarithms (a mass of 1e-400 is not 0).

        Where even its closed-form upper bound (:func:`orthant_log_upper_bound`) is below
        ``-FAR_NATS``, that bound (:attr:`bound_only`): the law is not evaluated
        whatever the mass, and the lattice, which spends its largest size on such
        tails, is not run; :meth:`refine` runs it where the figure is wanted."""
        if self._inside is None:
            self._inside, self._inside_error, self._tail = self._orthant_mass()
        return self._inside

    def refine(self) -> float:
        """:meth:`ln_orthant_mass` from the lattice, even where the bound decides."""
        if self._inside is None or self.bound_only:
            self._inside, self._inside_error, self._tail = self._orthant_mass(lattice=True)
            self.bound_only = False
        return self._inside

    def tighten(self) -> None:
        """:meth:`ln_orthant_mass` again at the lattice's full target where it was taken
        to the looser one (:meth:`loosen`, :meth:`rough`)."""
        if self._rough and self._inside is not None and not self.bound_only:
            self._rough = False
            self._inside, self._inside_error, self._tail = self._orthant_mass()

    def upper_ln_evidence(self) -> float:
        """An upper bound on :meth:`ln_evidence` that needs no orthant mass (it is at
        most 1)."""
        return float(self.ln_z_untruncated + int(np.sum(self.prior.bounded)) * np.log(2))

    def rough(self, lead: float) -> None:
        """Take the orthant mass to the lattice's looser target
        (:data:`~tissuecli.identify.orthant.ROUGH_ABS_TOL`, about 0.01 in its logarithm)
        if this law's evidence cannot come within :data:`FAR_BEHIND` nats of ``lead``
        (the best evidence known): no choice then turns on its last hundredth of a nat,
        and the full target took a 3-dimensional lattice of 16 times the points. Before
        the mass is first computed only."""
        if self._inside is None and self.upper_ln_evidence() < lead - FAR_BEHIND:
            self._rough = True

    def loosen(self) -> None:
        """Take the orthant mass to the lattice's looser target, as :meth:`rough` does,
        whatever the evidence: for a closed form whose share of a sum is known to be
        small (a node of a shape grid far below its top). Before the mass is first
        computed only."""
        if self._inside is None:
            self._rough = True

    def _modal(self) -> tuple[Array, Array]:
        """Mean and covariance of the bounded coefficients at the modal sigma (computed
        once: the orthant mass and the exact draws both read them; not to be written)."""
        if self._modal_at is None:
            mu, cov = self.conditional(float(np.exp(self.u[int(np.argmax(self.weights))])))
            on = self.prior.bounded
            self._modal_at = mu[on], cov[np.ix_(on, on)]
        return self._modal_at

    def _orthant_mass(self, lattice: bool = False) -> tuple[float, float, float | None]:
        on = self.prior.bounded
        if not np.any(on):
            return 0.0, 0.0, None
        mu, cov = self._modal()
        sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        if np.all(mu > 6 * sd):
            return 0.0, 0.0, None
        if not lattice:
            top = orthant_log_upper_bound(mu, cov)
            if top < -FAR_NATS:
                self.bound_only = True
                return top, 0.0, None
        if self._rough:
            ln_p, error = orthant_log_probability(mu, cov, ROUGH_ABS_TOL, ROUGH_REL_TOL)
        else:
            ln_p, error = orthant_log_probability(mu, cov)
        # where the bound keeps little, Laplace's tail estimate checks the lattice
        tail = tail_log_probability(mu, cov) if ln_p < math.log(MIN_ACCEPTANCE) else None
        return ln_p, error, tail

    def untrusted(self) -> str:
        """Why this law's evidence cannot be trusted, or "" if it can.

        The closed form times the orthant mass is exact only while the bounds cut a
        modest share of the posterior: where they keep less than ``exp(-TAIL_NATS)``
        the data put a passive coefficient many SDs below zero, the noise level's
        posterior moves with the cut, and the mass at the modal noise level no longer
        corrects the evidence (that is how a law came to an ln evidence of 1e21).
        """
        ln_p = self.ln_orthant_mass()
        if not math.isfinite(ln_p):
            return "the positivity bounds keep none of the closed-form posterior"
        if ln_p < -TAIL_NATS:
            at_most = "at most " if self.bound_only else ""
            return (
                f"the positivity bounds keep {at_most}e^{ln_p:.0f} of the closed-form "
                "posterior: the data put a passive coefficient far below zero"
            )
        if self._inside_error > 0.5:
            return (
                f"the mass inside the positivity bounds (e^{ln_p:.1f}) is known only to "
                f"{100 * self._inside_error:.0f} %"
            )
        if self._tail is not None and abs(self._tail - ln_p) > CHECK_NATS:
            return (
                f"the truncation correction (ln {ln_p:.1f} by lattice, ln {self._tail:.1f} by "
                f"Laplace's tail estimate) disagrees by more than {CHECK_NATS:g} nats"
            )
        ln_z = self.ln_evidence()
        top = self.stats.max_log_likelihood()
        if not math.isfinite(ln_z) or ln_z > top + CHECK_NATS:
            return (
                f"its ln evidence ({ln_z:.4g}) exceeds the likelihood's maximum ({top:.4g}): "
                "a numerical failure"
            )
        return ""

    def ln_evidence(self) -> float:
        """ln p(y): the closed form over the whole space times the prior's normalisation
        and the posterior mass inside the positivity bounds."""
        return float(
            self.ln_z_untruncated
            + self.ln_orthant_mass()
            + int(np.sum(self.prior.bounded)) * np.log(2)
        )

    def summary(self, rng: np.random.Generator, draws: int = 4000) -> Posterior:
        """The posterior; exact when the positivity bound cuts off no more than 1e-3."""
        return self._summary(*self._summary_draws(rng, draws))

    def _summary_draws(self, rng: np.random.Generator, draws: int = 4000) -> tuple[Array, Array]:
        """The random numbers :meth:`summary` draws, in its order: a uniform for each
        draw's node (draws,) and standard normals (draws, p). ``rng.choice(m, draws,
        p=w)`` draws those uniforms and looks each up in ``w``'s CDF; the lookup, most of
        its cost, is left to :meth:`_summary`, for the draws that are used."""
        return rng.random(draws), rng.standard_normal((draws, self.d.size))

    def _summary(self, uniform: Array, z: Array, intervals: bool = True) -> Posterior:
        """:meth:`summary` from its random numbers (:meth:`_summary_draws`); without
        ``intervals`` the 95 % intervals are left NaN (a mixture's component needs none)."""
        w, mus, covs, idx = self.mixture()
        cdf = w.cumsum()  # the nodes rng.choice(w.size, p=w) picks with these uniforms
        cdf /= cdf[-1]
        pick = cdf.searchsorted(uniform, side="right")
        inside = self.orthant_mass()
        ln_z = self.ln_evidence()
        mean = w @ mus
        second = np.einsum("m,mij->ij", w, covs + np.einsum("mi,mj->mij", mus, mus))
        cov = second - np.outer(mean, mean)
        sds = np.sqrt(np.clip(np.einsum("mii->mi", covs), 0.0, None))
        # every coefficient's two quantiles at once: (0.025, 0.975) for each
        p = mean.size
        q = np.tile([0.025, 0.975], p)
        if intervals:
            ci = _mixture_quantiles(q, w, np.repeat(mus, 2, axis=1), np.repeat(sds, 2, axis=1))
            ci = ci.reshape(p, 2)
        else:
            ci = np.full((p, 2), np.nan)
        sig = np.exp(self.u[idx])
        cdf = np.cumsum(w)
        sigma_ci = (float(np.interp(0.025, cdf, sig)), float(np.interp(0.975, cdf, sig)))
        # draws for plots: pick a node, then a Gaussian draw; the bound is applied by rejection
        chol = _matrix_roots(covs)
        beta = mus[pick] + np.einsum("kij,kj->ki", chol[pick], z)
        samples = np.column_stack([beta, sig[pick]])
        samples = samples[np.all(beta[:, self.prior.bounded] >= 0, axis=1)]
        return Posterior(
            mean=mean,
            sd=np.sqrt(np.clip(np.diag(cov), 0.0, None)),
            ci95=ci,
            cov=cov,
            sigma_mean=float(w @ sig),
            sigma_ci95=sigma_ci,
            ln_evidence=float(ln_z),
            outside=1.0 - inside,
            method="exact",
            samples=samples,
            below_zero=self.below_zero(),
        )

    def bounded(
        self,
        rng: np.random.Generator,
        cut: float = 1e-3,
        intervals: bool = True,
        draws: int = 4000,
    ) -> Posterior:
        """The posterior as exact as it is known: the closed form where the positivity
        bound cuts no more than ``cut`` of it, else exact draws under the bound
        (:meth:`truncated`). ``diagnostics["exact"]`` says whether either applied; if
        not (the bound keeps too little for rejection), a sampler is needed.

        ``draws`` posterior draws are kept in ``samples`` (fewer where the closed form's
        draws fall outside the bound); the closed form's moments and intervals do not
        depend on them, the draws' do. Without ``intervals`` the 95 % intervals are left
        NaN, the rest as with them: a component of a mixture over shapes, or a posterior
        read for its mean, needs none."""
        if 1.0 - self.orthant_mass() > cut:
            exact = self.truncated(rng, draws=draws, intervals=intervals)
            if exact is None:
                post = self._summary(*self._summary_draws(rng, draws), intervals=intervals)
                post.diagnostics["exact"] = False
                return post
            post = exact
        else:
            post = self._summary(*self._summary_draws(rng, draws), intervals=intervals)
        post.diagnostics["exact"] = True
        return post

    def truncated(
        self,
        rng: np.random.Generator,
        draws: int = 4000,
        intervals: bool = True,
        min_acceptance: float = 0.0,
    ) -> Posterior | None:
        """The posterior with the positivity bound applied, from independent exact draws.

        The untruncated posterior is a known mixture of Gaussians over sigma's nodes, so
        draws from it kept where the bounded coefficients are non-negative are exact
        draws from the bounded posterior (rejection sampling): no Markov chain, no
        burn-in, no autocorrelation. Moments and intervals then carry only Monte Carlo
        error (an SD over ``sqrt(draws)``). None when the bound keeps less than
        :data:`MIN_ACCEPTANCE` of the mass (``min_acceptance`` instead, if given):
        rejection would take too many draws.
        """
        inside = self.orthant_mass()
        if inside < (min_acceptance or MIN_ACCEPTANCE):
            return None
        w, mus, covs, idx = self.mixture()
        p = mus.shape[1]
        bounded = self.prior.bounded
        # the bounds a draw may plausibly cross are checked on every draw; the whole
        # coefficient vector (and every bound) only on the draws that pass them
        mu_m, cov_m = self._modal()
        z_m = mu_m / np.sqrt(np.clip(np.diag(cov_m), 1e-300, None))
        on_at = np.flatnonzero(bounded)
        close = z_m < NEAR_SDS
        if not close.any():
            close[int(np.argmin(z_m))] = True
        # the near coefficients first, the one the bound cuts most leading: a Cholesky
        # root's first rows then take only a draw's first normals. The leading one is
        # drawn under its bound by inverse CDF (its node in proportion to the mass its
        # bound keeps there), the other near ones checked by rejection, and a draw's
        # remaining normals drawn only if it passes them
        near = on_at[close][np.argsort(z_m[close], kind="stable")]
        rest = np.ones(p, bool)
        rest[near] = False
        order = np.concatenate([near, np.flatnonzero(rest)])
        back = np.argsort(order)
        q = near.size
        try:
            roots = np.linalg.cholesky(covs[:, order][:, :, order])
            width = q
        except np.linalg.LinAlgError:  # a singular direction: plain rejection
            roots = _matrix_roots(covs[:, order][:, :, order])
            width = p
        mus, on = mus[:, order], bounded[order]
        if width < p:
            keep = normal_cdf(mus[:, 0] / roots[:, 0, 0])  # each node's mass the lead keeps
            lead = w * keep
            share = float(lead.sum())  # of the whole posterior, the lead's bound keeps
            lead /= share
        else:
            keep, lead, share = None, w, 1.0
        node_sigma = np.exp(self.u[idx])
        kept: list[Array] = []
        have, total = 0, 0
        rate = min(1.0, inside / share)  # the share of draws the other bounds keep
        batch = int(min(2_000_000, max(draws, math.ceil(1.3 * draws / rate))))
        while have < draws and total < 20 * batch:
            counts = rng.multinomial(batch, lead)
            node = np.repeat(np.arange(w.size), counts)
            if keep is None:
                z = rng.standard_normal((batch, width))
            else:  # the lead's normal under its bound: -Phi^-1(u Phi(mu / sd))
                z = -normal_ppf(rng.random(batch) * keep[node])[:, None]
                if q > 1:
                    z = np.hstack([z, rng.standard_normal((batch, q - 1))])
            # every draw against the other near bounds, node by node (one small product
            # each); the lead's holds by construction (but for rounding, which the check
            # of every bound below catches)
            lead_only = keep is not None and q == 1
            if lead_only:
                pick = node
            else:
                first = _by_node(counts, z, mus[:, :q], roots[:, :q, :width])
                ok = first[:, q - 1] >= 0
                for j in range(0 if keep is None else 1, q - 1):
                    ok &= first[:, j] >= 0
                # np.compress: what boolean indexing gives, at a third of its cost
                pick = np.compress(ok, node)
                z = np.compress(ok, z, axis=0)
            if width < p:
                z = np.hstack([z, rng.standard_normal((pick.size, p - width))])
            beta = _by_node(counts if lead_only else np.bincount(pick, minlength=w.size), z,
                            mus, roots)  # fmt: skip
            ok = (beta[:, on] >= 0).all(axis=1)
            good = np.empty((int(np.count_nonzero(ok)), p + 1))
            good[:, :p] = np.compress(ok, beta, axis=0)[:, back]
            good[:, p] = node_sigma[np.compress(ok, pick)]
            kept.append(good)
            have += good.shape[0]
            total += batch
        if have < 100:
            return None
        # in random order: the draws come grouped by noise node, and a first ``draws``
        # of them would leave out the largest noise levels (and a mixture takes a
        # component's first draws)
        samples = np.concatenate(kept)
        samples = samples[rng.permutation(samples.shape[0])[:draws]]
        beta, sig = samples[:, :-1], samples[:, -1]
        mean = beta.mean(axis=0)
        centred = beta - mean
        cov = centred.T @ centred / (beta.shape[0] - 1)
        ci = (  # the coefficients', then sigma's
            central95(samples) if intervals else np.full((samples.shape[1], 2), np.nan)
        )
        return Posterior(
            mean=mean,
            sd=np.sqrt(np.diag(cov)),
            ci95=ci[:-1],
            cov=cov,
            sigma_mean=float(sig.mean()),
            sigma_ci95=(float(ci[-1, 0]), float(ci[-1, 1])),
            ln_evidence=self.ln_evidence(),
            outside=1.0 - inside,
            method="exact-draws",
            samples=samples,
            # the share of plain Gaussian draws that would pass: what the bounds keep
            diagnostics={"draws": int(samples.shape[0]), "acceptance": share * have / total},
            below_zero=self.below_zero(),
        )


#: bounds whose coefficient's modal mean lies fewer posterior SDs inside them are
#: checked on every rejection draw, the others only on the draws that pass those
NEAR_SDS = 8.0

#: most nodes of sigma's quadrature a posterior's summary mixes
MIXTURE_NODES = 32

#: the least share of the posterior the positivity bound may keep for exact rejection
#: draws (below it a Markov chain is cheaper)
MIN_ACCEPTANCE = 0.02

#: where a law would otherwise be sampled by a Markov chain, exact rejection draws
#: are taken down to this share of the posterior kept by the bound: 4000 draws then
#: take 8 million Gaussian proposals, a few seconds, where the chain took 9,500 steps
#: of 32 walkers (6-7 s) for a quarter of the independent draws
REJECTION_ACCEPTANCE = 5e-4

#: the positivity bounds may cut all but exp(-TAIL_NATS) of a closed-form posterior
#: before its evidence is "not evaluated"
TAIL_NATS = 20.0
#: where the closed-form upper bound on the mass the positivity bounds keep is below
#: exp(-FAR_NATS) (far beyond exp(-TAIL_NATS), so the law is not evaluated either way),
#: the bound stands for the mass and the lattice is not run: such a tail cost it its
#: largest size (0.2-0.3 s) and said only how far beyond
FAR_NATS = 500.0
#: a law whose evidence is at most this many nats below the best known has its orthant
#: mass to the lattice's full target (:meth:`ExactPosterior.rough`): far beyond any
#: ln Bayes factor a choice is made on (DECISIVE, 4.6)
FAR_BEHIND = 50.0
#: two estimates of one evidence (or of its truncation) that disagree by more than this
#: many nats are flagged
CHECK_NATS = 3.0


def logsumexp(a: Array) -> float:
    """``ln sum exp(a)`` without overflow."""
    top = float(np.max(a))
    if not math.isfinite(top):
        return top
    return top + math.log(float(np.sum(np.exp(a - top))))


_SQRT2PI = math.sqrt(2.0 * math.pi)


def _mixture_quantile(q: float, w: Array, mu: Array, sd: Array) -> float:
    """The ``q`` quantile of the Gaussian mixture ``sum_i w_i N(mu_i, sd_i^2)``
    (:func:`_mixture_quantiles` for one)."""
    mu, sd = np.asarray(mu, dtype=float), np.asarray(sd, dtype=float)
    return float(_mixture_quantiles(np.array([q]), w, mu[:, None], sd[:, None])[0])


def _mixture_quantiles(q: Array, w: Array, mu: Array, sd: Array) -> Array:
    """The ``q[j]`` quantile of each Gaussian mixture ``sum_i w_i N(mu_ij, sd_ij^2)``.

    Newton's method on the CDF (its slope is the mixture's density), kept inside a
    bracket that shrinks with every step and bisected when Newton leaves it; stops
    when a step is below ``1e-14 + 4 eps |x|``, Brent's default tolerance. All
    mixtures at once, each stopping at its own step.

    Parameters
    ----------
    q : ndarray, shape (k,)
    w : ndarray, shape (m,)
        The components' weights (sum 1).
    mu, sd : ndarray, shape (m, k)
        Each mixture's component means and SDs.

    Returns
    -------
    ndarray, shape (k,)
    """
    lo = np.min(mu - 10 * sd, axis=0)
    hi = np.max(mu + 10 * sd, axis=0)
    out = np.array(mu[0], dtype=float)
    active = hi > lo
    x = np.minimum(np.maximum(w @ mu, lo), hi)
    tol = 4 * np.finfo(float).eps
    for _ in range(200):
        if not active.any():
            return out
        z = (x - mu) / sd
        excess = w @ normal_cdf(z) - q
        above = excess > 0
        hi = np.where(above, x, hi)
        lo = np.where(above, lo, x)
        density = w @ (np.exp(-0.5 * z * z) / (sd * _SQRT2PI))
        with np.errstate(divide="ignore"):
            step = np.where(density > 0, excess / np.where(density > 0, density, 1.0), math.inf)
        newton = x - step
        # a Newton step below the tolerance is convergence, even one that rounding puts
        # on the bracket's edge (bisecting then went back 40 steps to where it was)
        still = np.abs(newton - x) <= 1e-14 + tol * np.abs(newton)
        new = np.where((lo < newton) & (newton < hi), newton, 0.5 * (lo + hi))
        new = np.where(still, newton, new)
        done = active & (still | (np.abs(new - x) <= 1e-14 + tol * np.abs(new)))
        out[done] = new[done]
        active &= ~done
        x = np.where(active, new, x)
    out[active] = x[active]
    return out


def central95(samples: Array) -> Array:
    """Each column's 2.5 and 97.5 percentiles, shape (k, 2), for ``samples`` (n, k):
    ``np.percentile(samples, [2.5, 97.5], axis=0).T`` (linear interpolation between the
    order statistics), from each column's sort."""
    n = samples.shape[0]
    at = np.array([0.025, 0.975]) * (n - 1)
    lo = np.floor(at).astype(np.intp)
    hi = np.minimum(lo + 1, n - 1)
    # the order statistics of each column sorted as a contiguous row: the same values as
    # a partition at the four of them, which costs several times a sort at 4000 draws
    ordered = np.sort(np.ascontiguousarray(samples.T), axis=1)
    a, b, t = ordered[:, lo], ordered[:, hi], at - lo
    # numpy's interpolation: from the nearer order statistic
    return np.where(t >= 0.5, b - (b - a) * (1 - t), a + (b - a) * t)


def _by_node(counts: NDArray[np.intp], z: Array, mus: Array, roots: Array) -> Array:
    """``mus[i] + roots[i] z`` for each row of ``z`` (k, p), its rows grouped by node:
    the first ``counts[0]`` of node 0, and so on; shape (k, q) for ``mus`` (m, q) and
    ``roots`` (m, q, p)."""
    out = np.empty((z.shape[0], mus.shape[1]))
    start = 0
    for i in np.flatnonzero(counts):
        stop = start + int(counts[i])
        out[start:stop] = mus[i] + z[start:stop] @ roots[i].T
        start = stop
    return out


def _matrix_roots(covs: Array) -> Array:
    """``L`` with ``L L^T = C`` for each covariance (m, p, p): Cholesky where it works,
    else the symmetric root with negative eigenvalues (rounding in a singular
    direction: a term whose column the session leaves empty) set to zero."""
    try:
        return np.linalg.cholesky(covs)
    except np.linalg.LinAlgError:
        lam, vec = np.linalg.eigh(0.5 * (covs + np.swapaxes(covs, -1, -2)))
        return vec * np.sqrt(np.clip(lam, 0.0, None))[:, None, :]
