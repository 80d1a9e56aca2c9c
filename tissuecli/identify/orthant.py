"""Probabilities of Gaussians in an orthant, ``P(X >= 0)`` for ``X ~ N(mu, Sigma)``: how
much of a closed-form posterior the positivity bounds cut off.

Genz's separation-of-variables algorithm (Genz 1992, J. Comput. Graph. Stat. 1:141;
Genz & Bretz 2009, ch. 4) with Genz's variable prioritisation and randomised
Richtmyer lattices, refined until the spread over the random shifts says the
estimate is good to 1e-3 relative, and to 1e-5 absolute for a mass within 0.01 of 1. The shifts come
from a fixed seed, so the answer is the same every time. Each lattice estimate is
a product of conditional probabilities, so a tiny mass keeps its relative accuracy
where an absolute tolerance would return 0.

NumPy and ``scipy.special`` (26 ms to import): ``scipy.stats.multivariate_normal.cdf``
would cost a fit 0.36 s of start-up whenever a law's posterior comes near its bound,
most sessions.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

#: random shifts per lattice size; their spread is the error estimate
SHIFTS = 8
#: the absolute target binds only on a mass within this of 1 (where the sampling rule
#: asks whether the bound cuts more than 1e-3 of a posterior); below, ln P to REL_TOL
ABS_BAND = 0.01
#: first and largest lattice sizes (points per shift)
FIRST_POINTS, MAX_POINTS = 1 << 10, 1 << 16
#: target: 3 standard errors below this absolute error and this fraction of the mass
#: (the evidence needs ln P to 1e-3; the sampling rule, P near 1, needs 1e-5 absolute)
ABS_TOL, REL_TOL = 1e-5, 1e-3
#: the looser target of a mass whose law's evidence lies far behind the best
#: (:data:`~tissuecli.identify.posterior.FAR_BEHIND`): ln P to about 0.01
ROUGH_ABS_TOL, ROUGH_REL_TOL = 1e-3, 1e-2
#: standardised limits beyond which the lattice works in logarithms
LINEAR_LIMIT = 8.0
#: ln of the smallest mass the direct products are trusted to carry
LINEAR_FLOOR = 600.0
_PRIMES = (2, 3, 5, 7, 11, 13, 17, 19, 23, 29, 31, 37, 41, 43, 47, 53, 59, 61, 67, 71)


def normal_cdf(z: Array) -> Array:
    """Standard normal CDF to double precision, the lower tail included (SciPy's
    ``ndtr``, compiled: the lattice evaluates it millions of times; imported when first
    needed, so that importing the fit loads no SciPy)."""
    from scipy.special import ndtr

    return ndtr(np.asarray(z, dtype=float))


def normal_ppf(p: Array) -> Array:
    """Inverse standard normal CDF (SciPy's ``ndtri``); ``p`` is clipped to
    ``[1e-300, 1 - 1e-16]`` so that the lattice never meets an infinite quantile."""
    from scipy.special import ndtri

    return ndtri(np.clip(np.asarray(p, dtype=float), 1e-300, 1.0 - 1e-16))


def log_normal_cdf(z: Array) -> Array:
    """``ln Phi(z)`` to double precision far into the lower tail (SciPy's ``log_ndtr``)."""
    from scipy.special import log_ndtr

    return log_ndtr(np.asarray(z, dtype=float))


def normal_ppf_log(log_p: Array) -> Array:
    """``Phi^-1(exp(log_p))`` for ``log_p`` down to -1e300 (SciPy's ``ndtri_exp``): the
    quantile of a probability too small for a double."""
    from scipy.special import ndtri_exp

    return ndtri_exp(np.minimum(np.asarray(log_p, dtype=float), -1e-16))


def orthant_probability(mean: Array, cov: Array) -> float:
    """``P(X >= 0)`` for ``X ~ N(mean, cov)``, shapes (p,) and (p, p).

    A singular ``cov`` (a parameter the data fix exactly) is regularised by 1e-12 of
    its diagonal. Below 1e-300 the answer is 0; :func:`orthant_log_probability` gives
    its logarithm.
    """
    return math.exp(orthant_log_probability(mean, cov)[0])


def orthant_log_probability(
    mean: Array, cov: Array, abs_tol: float = ABS_TOL, rel_tol: float = REL_TOL
) -> tuple[float, float]:
    """``ln P(X >= 0)`` for ``X ~ N(mean, cov)`` and its relative error (3 standard
    errors over the random shifts, as a fraction of P), refined until that error is
    below ``rel_tol`` of P, and below ``abs_tol`` absolute where P lies within
    :data:`ABS_BAND` of 1.

    Computed in logarithms throughout (each factor by ``ln Phi``, each quantile from
    a log probability), so a mass of 1e-400 keeps its relative accuracy instead of
    becoming 0. The error says whether the estimate can be trusted: far in the tail
    the product of factors varies over the lattice by orders of magnitude and the
    mean over its points is carried by a few of them.

    Where every coefficient but one lies so far inside its bound that together they
    change the answer by less than :data:`ONE_BOUND_TOL` of it, the answer is that
    one's normal CDF, in closed form (the lattice's factors for the others are 1 to
    the last bit there, and it returns the same).
    """
    mean = np.asarray(mean, dtype=float)
    cov = np.asarray(cov, dtype=float)
    sd = np.sqrt(np.diag(cov))
    # P(X >= 0) = P(Z <= h) with Z = (mean - X) / sd standard, correlation R
    h = mean / sd
    corr = cov / np.outer(sd, sd) + 1e-12 * np.eye(mean.size)
    if mean.size == 1:
        return float(log_normal_cdf(h)[0]), 0.0
    one = _one_bound(h)
    if one is not None:
        return one, 0.0
    chol, h = _prioritised_cholesky(corr, h)
    dims = h.size - 1  # the shifts are drawn for every variable, whichever are kept
    chol, h = _without_sure_tail(chol, h)
    if h.size == 1:
        return float(log_normal_cdf(np.array([h[0] / chol[0, 0]]))[0]), 0.0
    # the direct products while every factor stays far from underflow (half the cost);
    # in logarithms beyond
    log_space = bool(np.min(h) < -LINEAR_LIMIT)
    sov = _sov_log if log_space else _sov_linear
    rng = np.random.default_rng(20261123)  # fixed shifts: the same answer every time
    root = np.sqrt(np.array(_PRIMES[: h.size - 1], dtype=float))
    points = FIRST_POINTS
    while True:
        k = np.arange(1, points + 1)[:, None]
        lattice = k * root
        lattice -= np.floor(lattice)  # exact, as % 1.0 is, and cheaper
        # every shift's estimate in one pass (the shifts drawn in the order one call
        # per shift would draw them)
        estimates = sov(chol, h, lattice, rng.random((SHIFTS, dims))[:, : h.size - 1])
        top = float(np.max(estimates))
        if not log_space and not (np.all(np.isfinite(estimates)) and top > -LINEAR_FLOOR):
            log_space, sov = True, _sov_log  # a product underflowed: again in logarithms
            continue
        if not math.isfinite(top):
            return top, math.inf
        ratio = np.exp(estimates - top)
        value = top + math.log(float(np.mean(ratio)))
        rel = 3 * float(np.std(ratio, ddof=1)) / math.sqrt(SHIFTS) / float(np.mean(ratio))
        # 3 SEs below REL_TOL of the mass, and below ABS_TOL absolute for a mass near 1
        # (compared in logarithms: a mass of 1e-400 has no absolute error a double can
        # hold); elsewhere the absolute target asked 50 times REL_TOL's points of a mass
        # of one half, for the evidence's fourth decimal
        small = (rel == 0 or value + math.log(rel) <= math.log(abs_tol)
                 or math.exp(value) < 1.0 - ABS_BAND)  # fmt: skip
        if (small and rel <= rel_tol) or points >= MAX_POINTS:
            return value, rel
        points *= 4


def orthant_log_upper_bound(mean: Array, cov: Array) -> float:
    """An upper bound on ``ln P(X >= 0)`` for ``X ~ N(mean, cov)``, in closed form.

    The orthant lies inside every half-space ``g . x >= 0`` with ``g >= 0``, whose mass
    is ``Phi(g . mean / sqrt(g^T cov g))``. Two such ``g`` are tried: each axis (the
    bound that keeps least) and the normal of the orthant's face nearest to ``mean`` in
    the metric of ``cov`` (the active set of :func:`tail_log_probability`), whose
    half-space's mass is ``Phi(-d)`` for the Mahalanobis distance ``d`` to the orthant,
    within a few nats of the mass itself far in the tail. Any ``g >= 0`` gives a bound,
    so a rough active set costs tightness, never validity. NaN where a variance is
    zero or not finite.
    """
    mean = np.asarray(mean, dtype=float)
    cov = np.asarray(cov, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        h = mean / np.sqrt(np.diag(cov))
    if h.size == 0 or not (np.all(np.isfinite(h)) and np.all(np.isfinite(cov))):
        return math.nan
    best = float(log_normal_cdf(np.array([np.min(h)]))[0])
    try:
        a = np.flatnonzero(_held(mean, cov))
        if a.size > 1:
            g = np.zeros(mean.size)
            g[a] = np.maximum(-np.linalg.solve(cov[np.ix_(a, a)], mean[a]), 0.0)
            spread = float(g @ cov @ g)
            if spread > 0.0 and math.isfinite(spread):
                z = float(g @ mean) / math.sqrt(spread)
                best = min(best, float(log_normal_cdf(np.array([z]))[0]))
    except np.linalg.LinAlgError:
        pass  # the axis bound stands
    return best


def _held(mean: Array, cov: Array) -> NDArray[np.bool_]:
    """The bounds held at zero at the point of the orthant nearest to ``mean`` in the
    metric of ``cov`` (an active set: each held bound's slope points into the orthant,
    each free coordinate, given the held ones at zero, has its mean inside)."""
    p = mean.size
    active = mean < 0
    for _ in range(p + 1):  # active set: bounds held at zero, the rest conditioned
        a, f = np.flatnonzero(active), np.flatnonzero(~active)
        if a.size == 0:
            return active
        saa = cov[np.ix_(a, a)]
        g = -np.linalg.solve(saa, mean[a])  # slope of -ln density into the orthant
        cond = mean[f] - cov[np.ix_(f, a)] @ np.linalg.solve(saa, mean[a])
        drop = a[g <= 0]
        add = f[cond < 0]
        if drop.size == 0 and add.size == 0:
            break
        active[drop] = False
        active[add] = True
    return active


#: the other bounds may change a one-bound answer by at most this fraction of it
ONE_BOUND_TOL = 1e-12


def _one_bound(h: Array) -> float | None:
    """``ln P(Z_j <= h_j)`` for the one standardised limit ``h_j`` that matters, if the
    others are so far out that they change ``P(Z <= h)`` by less than
    :data:`ONE_BOUND_TOL` of it, else None.

    ``P(Z_j <= h_j) - sum_i P(Z_i > h_i) <= P(Z <= h) <= P(Z_j <= h_j)`` (a union
    bound), so the relative error is at most ``sum_i Phi(-h_i) / Phi(h_j)``. ``h_j``
    is scaled as the lattice's regularised correlation scales it.
    """
    j = int(np.argmin(h))
    others = np.delete(h, j)
    ln_keep = float(log_normal_cdf(np.array([h[j] / math.sqrt(1.0 + 1e-12)]))[0])
    ln_out = log_normal_cdf(-others)
    top = float(np.max(ln_out))
    if math.isfinite(top):
        ln_sum = top + math.log(float(np.sum(np.exp(ln_out - top))))
        if ln_sum > math.log(ONE_BOUND_TOL) + ln_keep:
            return None
    return ln_keep


#: a standardised limit beyond which the normal CDF is 1 to the last bit
SURE = 9.0
#: the largest |quantile| a lattice point can be drawn at: ``Phi^-1`` of the smallest
#: probability a point of :data:`MAX_POINTS` per shift reaches is about -4.4; far
#: more is allowed, so that no point of any shift can come near
QUANTILE_BOUND = 40.0


def _without_sure_tail(chol: Array, h: Array) -> tuple[Array, Array]:
    """The prioritised factor and limits without the trailing variables whose
    conditional factor is 1 to the last bit at any draw of the earlier ones: limits
    beyond :data:`SURE` even with every earlier draw at :data:`QUANTILE_BOUND` against
    them. The lattice's estimate is the same to the last bit without them (each factor
    multiplies it by 1.0) at less cost; at least one variable is kept."""
    keep = h.size
    while keep > 1:
        i = keep - 1
        worst = h[i] - QUANTILE_BOUND * float(np.sum(np.abs(chol[i, :i])))
        if not worst / chol[i, i] > SURE:
            break
        keep -= 1
    return chol[:keep, :keep], h[:keep]


def _shifted(lattice: Array, shifts: Array) -> Array:
    """The baker's-transformed points of every shift, shape (shifts * points, d): the
    first shift's points first."""
    u = lattice[None, :, :] + shifts[:, None, :]
    # (lattice + shift) mod 1 for both in [0, 1): u - 1 is exact where u >= 1 (Sterbenz),
    # as fmod is, and takes a fraction of its time
    u -= u >= 1.0
    u *= 2.0
    u -= 1.0
    return np.abs(u, out=u).reshape(-1, lattice.shape[1])  # the baker's transform periodises


def _sov_linear(chol: Array, h: Array, lattice: Array, shifts: Array) -> Array:
    """:func:`_sov_log` by direct products, for limits no factor can underflow at."""
    w = _shifted(lattice, shifts)
    e = np.full(w.shape[0], normal_cdf(np.array([h[0] / chol[0, 0]]))[0])
    f = e.copy()
    y = np.zeros((w.shape[0], h.size - 1))
    for i in range(1, h.size):
        y[:, i - 1] = normal_ppf(w[:, i - 1] * e)
        e = normal_cdf((h[i] - y[:, :i] @ chol[i, :i]) / chol[i, i])
        f *= e
    mean = np.mean(f.reshape(shifts.shape[0], -1), axis=1)
    with np.errstate(divide="ignore"):
        return np.where(mean > 0, np.log(np.where(mean > 0, mean, 1.0)), -math.inf)


def _sov_log(chol: Array, h: Array, lattice: Array, shifts: Array) -> Array:
    """Randomised-lattice estimates of ``ln P(L Z <= h)``, Z standard normal, one per
    row of ``shifts`` (shifts, d)."""
    w = _shifted(lattice, shifts)
    with np.errstate(divide="ignore"):
        log_w = np.log(w)
    log_e = np.full(w.shape[0], log_normal_cdf(np.array([h[0] / chol[0, 0]]))[0])
    log_f = log_e.copy()
    y = np.zeros((w.shape[0], h.size - 1))
    for i in range(1, h.size):
        # draw variable i-1 below its limit, then the limit of variable i given the draws
        y[:, i - 1] = normal_ppf_log(log_w[:, i - 1] + log_e)
        log_e = log_normal_cdf((h[i] - y[:, :i] @ chol[i, :i]) / chol[i, i])
        log_f += log_e
    log_f = log_f.reshape(shifts.shape[0], -1)
    top = np.max(log_f, axis=1)
    out = top.copy()
    ok = np.isfinite(top)
    if np.any(ok):
        tail = np.mean(np.exp(log_f[ok] - top[ok, None]), axis=1)
        out[ok] = top[ok] + np.log(tail)
    return out


def tail_log_probability(mean: Array, cov: Array) -> float:
    """Laplace's estimate of ``ln P(X >= 0)`` for a mass deep in the tail: the Gaussian's
    log density at the nearest point of the orthant (in the metric of ``cov``) plus the
    exponential tail beyond each bound that holds there (the multivariate Mills ratio).
    Independent of the lattice, it checks :func:`orthant_log_probability` where that is
    carried by a few points; exact in one dimension as the mass goes to zero.
    """
    mean = np.asarray(mean, dtype=float)
    cov = np.asarray(cov, dtype=float)
    active = _held(mean, cov)
    a, f = np.flatnonzero(active), np.flatnonzero(~active)
    if a.size == 0:
        return 0.0
    saa = cov[np.ix_(a, a)]
    g = np.maximum(-np.linalg.solve(saa, mean[a]), 1e-300)
    sign, logdet = np.linalg.slogdet(saa)
    # the free coordinates, given the held ones at zero: their own chance of >= 0
    gain = np.linalg.solve(saa, cov[np.ix_(a, f)])
    cond_mean = mean[f] - gain.T @ mean[a]
    cond_var = np.diag(cov[np.ix_(f, f)] - cov[np.ix_(f, a)] @ gain)
    free = float(np.sum(log_normal_cdf(cond_mean / np.sqrt(np.maximum(cond_var, 1e-300)))))
    return float(
        -0.5 * mean[a] @ np.linalg.solve(saa, mean[a])
        - 0.5 * a.size * math.log(2 * math.pi)
        - 0.5 * logdet
        - np.sum(np.log(g))
        + free
    )


def _prioritised_cholesky(corr: Array, h: Array) -> tuple[Array, Array]:
    """Cholesky factor and limits reordered so that at each step the variable least
    likely to stay below its limit, given the earlier ones at their expected values,
    comes next (Genz & Bretz 2009, section 4.1.3): the later factors vary less."""
    sigma, h = corr.copy(), h.copy()
    p = h.size
    chol = np.zeros((p, p))
    y = np.zeros(p)
    for i in range(p):
        rest = np.arange(i, p)
        var = np.maximum(np.diag(sigma)[rest] - np.sum(chol[rest, :i] ** 2, axis=1), 1e-300)
        limits = (h[rest] - chol[rest, :i] @ y[:i]) / np.sqrt(var)
        j = i + int(np.argmin(normal_cdf(limits)))
        for arr in (h,):
            arr[[i, j]] = arr[[j, i]]
        sigma[[i, j]] = sigma[[j, i]]
        sigma[:, [i, j]] = sigma[:, [j, i]]
        chol[[i, j]] = chol[[j, i]]
        chol[i, i] = math.sqrt(max(sigma[i, i] - float(chol[i, :i] @ chol[i, :i]), 1e-300))
        below = np.arange(i + 1, p)
        chol[below, i] = (sigma[below, i] - chol[below, :i] @ chol[i, :i]) / chol[i, i]
        limit = (h[i] - float(chol[i, :i] @ y[:i])) / chol[i, i]
        mass = max(float(normal_cdf(np.array([limit]))[0]), 1e-300)
        y[i] = -math.exp(-0.5 * limit * limit) / (math.sqrt(2 * math.pi) * mass)
    return chol, h
