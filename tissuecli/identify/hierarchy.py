"""Tissues compared across specimens: a normal hierarchical model over many sessions'
posteriors of one scalar quantity (a coefficient, or the force at a given closure and
speed), numerics only.

The model (docs/estimators.md), for session ``s`` of specimen ``k`` of group ``g``::

    y_s      ~ N(theta_s, v_s)        the session's posterior mean and variance
    theta_s  ~ N(eta_k, omega^2)      sessions scatter about their specimen
    eta_k    ~ N(mu_g, tau^2)         specimens scatter about their group (tissue)
    mu_g     ~ N(m0, s0^2)            a proper prior, so that Bayes factors exist

``omega`` and ``tau`` are uniform on ``[0, upper]`` (BDA ch. 5: uniform on the SD)
and integrated on a grid; given them, every specimen and group mean is normal and
the marginal likelihood is closed form (the eight-schools computation with a level
more), so nothing is sampled. Groups share ``omega`` and ``tau``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..core.errors import FitError
from ..core.terms import Law
from .orthant import normal_cdf
from .posterior import _mixture_quantile

Array = NDArray[np.float64]
LN_2PI = math.log(2 * math.pi)


@dataclass(frozen=True)
class Estimates:
    """One scalar quantity's posterior from each session, with the session's labels.

    Attributes
    ----------
    value, var : ndarray, shape (n,)
        Posterior mean and variance of the quantity in each session (its unit, squared).
    group, specimen : ndarray of int, shape (n,)
        Index of each session's group in ``groups`` and specimen in ``specimens``.
    groups, specimens : tuple of str
        Names; a specimen belongs to one group.
    """

    value: Array
    var: Array
    group: NDArray[np.int64]
    specimen: NDArray[np.int64]
    groups: tuple[str, ...]
    specimens: tuple[str, ...]

    @classmethod
    def of(
        cls,
        value: ArrayLike,
        var: ArrayLike,
        group: Sequence[str],
        specimen: Sequence[str],
    ) -> Estimates:
        """From per-session values and names; a specimen name is read within its group
        (specimen ``1`` of liver and of kidney are two specimens)."""
        value = np.asarray(value, dtype=float)
        var = np.asarray(var, dtype=float)
        if value.ndim != 1 or var.shape != value.shape or len(group) != value.size:
            raise FitError("give one value, variance, group and specimen per session")
        if len(specimen) != value.size:
            raise FitError("give one value, variance, group and specimen per session")
        if not (np.all(np.isfinite(value)) and np.all(np.isfinite(var)) and np.all(var >= 0)):
            raise FitError("session estimates must be finite, with variances >= 0")
        groups = tuple(dict.fromkeys(group))
        keys = [(g, s) for g, s in zip(group, specimen, strict=True)]
        spec_keys = tuple(dict.fromkeys(keys))
        gi = np.array([groups.index(g) for g in group], dtype=np.int64)
        where = {k: i for i, k in enumerate(spec_keys)}
        si = np.array([where[k] for k in keys], dtype=np.int64)
        names = tuple(f"{g}/{s}" for g, s in spec_keys)
        return cls(value, var, gi, si, groups, names)

    @property
    def specimen_group(self) -> NDArray[np.int64]:
        """Group index of each specimen, shape (k,)."""
        out = np.zeros(len(self.specimens), dtype=np.int64)
        out[self.specimen] = self.group
        return out


def _logsumexp(a: Array, axis: int | None = None) -> Array:
    m = np.max(a, axis=axis, keepdims=True)
    m = np.where(np.isfinite(m), m, 0.0)
    out = np.log(np.sum(np.exp(a - m), axis=axis, keepdims=True)) + m
    return np.squeeze(out, axis=axis) if axis is not None else out.reshape(())


class Hierarchy:
    """The hierarchical normal model of sessions within specimens within groups.

    Parameters
    ----------
    prior_mean, prior_sd : float, optional
        ``m0`` and ``s0`` of the group means' normal prior, in the quantity's unit;
        by default the mean of the session values and twice their SD plus the largest
        session SD (broad: the Bayes factors depend on ``s0``, see docs/estimators.md).
    upper : float, optional
        Upper end of the uniform priors of ``omega`` and ``tau``; by default the
        range of the session values plus three of the largest session SD.
    grid : int
        Points of each log-spaced grid over ``omega`` and ``tau`` (from ``1e-4 upper``
        to ``upper``, weighted for a prior uniform on the SD).

    Attributes
    ----------
    weights_ : ndarray, shape (grid, grid)
        Posterior of (omega, tau) on the grid, summing to 1.
    omega_, tau_ : ndarray, shape (grid,)
        The grid.
    group_mean_, group_sd_ : ndarray, shape (g,)
        Posterior mean and SD of each group mean ``mu_g``.
    specimen_mean_, specimen_sd_ : ndarray, shape (k,)
        Posterior mean and SD of each specimen mean ``eta_k``.
    ln_evidence_ : float
        ln p(y) under the model (the grid's prior normalised).
    """

    def __init__(
        self,
        *,
        prior_mean: float | None = None,
        prior_sd: float | None = None,
        upper: float | None = None,
        grid: int = 72,
    ) -> None:
        self.prior_mean = prior_mean
        self.prior_sd = prior_sd
        self.upper = upper
        self.grid = grid

    # -- the closed form given (omega, tau) -------------------------------------------

    def _specimens(self, omega: Array) -> tuple[Array, Array, Array]:
        """Per specimen and omega: precision-weighted mean ``ybar`` and its variance ``V``
        (k, O), and ``ln C`` (k, O) with ``prod_s N(y_s | eta, v_s + omega^2) =
        C N(ybar | eta, V)``."""
        e = self.data_
        k = len(e.specimens)
        var = e.var[:, None] + omega[None, :] ** 2  # (n, O)
        var = np.maximum(var, 1e-300)
        w = 1.0 / var
        sw = np.zeros((k, omega.size))
        np.add.at(sw, e.specimen, w)
        swy = np.zeros((k, omega.size))
        np.add.at(swy, e.specimen, w * e.value[:, None])
        ybar = swy / sw
        dev = e.value[:, None] - ybar[e.specimen]
        q = np.zeros((k, omega.size))
        np.add.at(q, e.specimen, w * dev**2 + np.log(var) + LN_2PI)
        V = 1.0 / sw
        ln_c = -0.5 * q + 0.5 * (LN_2PI + np.log(V))
        return ybar, V, ln_c

    def _groups(
        self, ybar: Array, V: Array, tau: Array, spec_group: NDArray[np.int64], n_groups: int
    ) -> tuple[Array, Array, Array]:
        """For one omega: group posterior mean and precision (g, T) and ln p(ybar | tau)
        (T,) with the group means integrated against their prior."""
        m0, s0 = self.m0_, self.s0_
        U = V[:, None] + tau[None, :] ** 2  # (k, T)
        prec = np.full((n_groups, tau.size), 1.0 / s0**2)
        np.add.at(prec, spec_group, 1.0 / U)
        num = np.full((n_groups, tau.size), m0 / s0**2)
        np.add.at(num, spec_group, ybar[:, None] / U)
        mhat = num / prec
        # ln p(ybar) = ln p(ybar | mhat) + ln p(mhat) - ln p(mhat | ybar), per group, summed
        r = ybar[:, None] - mhat[spec_group]
        ll = -0.5 * np.sum(r**2 / U + np.log(U) + LN_2PI, axis=0)
        ll += np.sum(-0.5 * ((mhat - m0) ** 2 / s0**2 + math.log(s0**2) + LN_2PI), axis=0)
        ll += np.sum(0.5 * (LN_2PI - np.log(prec)), axis=0)
        return mhat, prec, ll

    def _grid_loglik(
        self, spec_group: NDArray[np.int64], n_groups: int
    ) -> tuple[Array, Array, Array, Array, Array]:
        """ln p(y | omega, tau) (O, T), and the group means' posterior mean and precision
        (O, g, T), the specimens' ybar and V (k, O)."""
        ybar, V, ln_c = self._specimens(self.omega_)
        n_om, n_tau = self.omega_.size, self.tau_.size
        ll = np.empty((n_om, n_tau))
        mhat = np.empty((n_om, n_groups, n_tau))
        prec = np.empty((n_om, n_groups, n_tau))
        for i in range(n_om):
            mhat[i], prec[i], ll[i] = self._groups(
                ybar[:, i], V[:, i], self.tau_, spec_group, n_groups
            )
            ll[i] += ln_c[:, i].sum()
        return ll, mhat, prec, ybar, V

    # -- fitting ------------------------------------------------------------------------

    def fit(self, estimates: Estimates) -> Hierarchy:
        """Compute the posterior over the grid and the group and specimen means."""
        e = estimates
        if e.value.size < 2:
            raise FitError("the comparison needs at least two sessions")
        self.data_ = e
        sd_max = float(np.sqrt(np.max(e.var)))
        spread = float(np.ptp(e.value))
        self.m0_ = float(np.mean(e.value)) if self.prior_mean is None else float(self.prior_mean)
        s0 = self.prior_sd if self.prior_sd is not None else 2 * float(np.std(e.value)) + sd_max
        self.s0_ = float(s0) if s0 > 0 else 1.0
        upper = self.upper if self.upper is not None else spread + 3 * sd_max
        upper = float(upper) if upper > 0 else 1.0
        self.omega_ = upper * np.logspace(-4, 0, self.grid)
        self.tau_ = upper * np.logspace(-4, 0, self.grid)
        # uniform on the SD over a log grid: weight d(sd) = sd d(ln sd)
        self._ln_prior = (
            np.log(self.omega_)[:, None]
            + np.log(self.tau_)[None, :]
            - 2 * math.log(upper)
            + 2 * math.log(math.log(1e4) / (self.grid - 1))
        )
        spec_group = e.specimen_group
        ll, mhat, prec, ybar, V = self._grid_loglik(spec_group, len(e.groups))
        lp = ll + self._ln_prior
        self.ln_evidence_ = float(_logsumexp(lp))
        self.weights_ = np.exp(lp - self.ln_evidence_)
        self._mhat, self._prec = mhat, prec  # (O, g, T)
        w = self.weights_[:, None, :]
        m1 = np.sum(w * mhat, axis=(0, 2))
        m2 = np.sum(w * (1.0 / prec + mhat**2), axis=(0, 2))
        self.group_mean_ = m1
        self.group_sd_ = np.sqrt(np.maximum(m2 - m1**2, 0.0))
        # specimens: eta_k | omega, tau ~ N(B mhat + (1 - B) ybar, V tau^2/(V + tau^2) + B^2/prec)
        tau2 = self.tau_[None, None, :] ** 2  # (1, 1, T)
        Vk = V.T[:, :, None]  # (O, k, 1)
        B = Vk / (Vk + tau2)
        mg = mhat[:, spec_group, :]
        pg = prec[:, spec_group, :]
        mean = B * mg + (1 - B) * ybar.T[:, :, None]
        var = Vk * tau2 / (Vk + tau2) + B**2 / pg
        s1 = np.sum(w * mean, axis=(0, 2))
        s2 = np.sum(w * (var + mean**2), axis=(0, 2))
        self.specimen_mean_ = s1
        self.specimen_sd_ = np.sqrt(np.maximum(s2 - s1**2, 0.0))
        self.omega_mean_ = float(np.sum(self.weights_.sum(axis=1) * self.omega_))
        self.tau_mean_ = float(np.sum(self.weights_.sum(axis=0) * self.tau_))
        return self

    def _index(self, group: str | int) -> int:
        if isinstance(group, str):
            try:
                return self.data_.groups.index(group)
            except ValueError:
                raise FitError(
                    f"no group {group!r}; groups: {', '.join(self.data_.groups)}"
                ) from None
        return int(group)

    def _difference(self, a: str | int, b: str | int) -> tuple[Array, Array, Array]:
        """Mixture of ``mu_a - mu_b``: weights, means, SDs (flattened over the grid)."""
        i, j = self._index(a), self._index(b)
        d = self._mhat[:, i, :] - self._mhat[:, j, :]
        sd = np.sqrt(1.0 / self._prec[:, i, :] + 1.0 / self._prec[:, j, :])
        return self.weights_.ravel(), d.ravel(), sd.ravel()

    def prob_greater(self, a: str | int, b: str | int) -> float:
        """``P(mu_a > mu_b | y)``: group ``a``'s mean above group ``b``'s."""
        w, d, sd = self._difference(a, b)
        return float(w @ normal_cdf(d / sd))

    def difference_interval(
        self, a: str | int, b: str | int, level: float = 0.95
    ) -> tuple[float, float, float]:
        """Posterior mean and central ``level`` interval of ``mu_a - mu_b``."""
        w, d, sd = self._difference(a, b)
        keep = w > 1e-12 * w.max()
        w, d, sd = w[keep] / w[keep].sum(), d[keep], sd[keep]
        lo = _mixture_quantile((1 - level) / 2, w, d, sd)
        hi = _mixture_quantile((1 + level) / 2, w, d, sd)
        return float(w @ d), lo, hi

    def group_interval(self, g: str | int, level: float = 0.95) -> tuple[float, float]:
        """Central ``level`` interval of the group mean ``mu_g``."""
        i = self._index(g)
        w = self.weights_.ravel()
        m = self._mhat[:, i, :].ravel()
        sd = np.sqrt(1.0 / self._prec[:, i, :]).ravel()
        keep = w > 1e-12 * w.max()
        w, m, sd = w[keep] / w[keep].sum(), m[keep], sd[keep]
        return (
            _mixture_quantile((1 - level) / 2, w, m, sd),
            _mixture_quantile((1 + level) / 2, w, m, sd),
        )

    def ln_bayes_same(self, a: str | int, b: str | int) -> float:
        """ln of the Bayes factor for "a and b are one tissue" (one group mean for both)
        against two group means, the other groups unchanged; > 0 favours the same tissue."""
        i, j = self._index(a), self._index(b)
        if i == j:
            return 0.0
        e = self.data_
        spec_group = e.specimen_group.copy()
        spec_group[spec_group == j] = i
        # renumber so the merged model has g - 1 groups
        _, spec_group = np.unique(spec_group, return_inverse=True)
        ll, *_ = self._grid_loglik(spec_group, len(e.groups) - 1)
        return float(_logsumexp(ll + self._ln_prior)) - self.ln_evidence_

    def ln_predictive(self, value: ArrayLike, var: ArrayLike) -> Array:
        """ln p(y_new | group g, data) for a session of a new specimen, shape (m, g) for
        ``m`` values: ``N(mu_g, 1/prec + v + omega^2 + tau^2)`` mixed over the grid."""
        y = np.atleast_1d(np.asarray(value, dtype=float))
        v = np.atleast_1d(np.asarray(var, dtype=float))
        spread = (
            1.0 / self._prec  # (O, g, T)
            + self.omega_[:, None, None] ** 2
            + self.tau_[None, None, :] ** 2
        )
        out = np.empty((y.size, len(self.data_.groups)))
        ln_w = np.log(np.maximum(self.weights_, 1e-300))[:, None, :]
        for m in range(y.size):
            s2 = spread + v[m]
            lp = -0.5 * ((y[m] - self._mhat) ** 2 / s2 + np.log(s2) + LN_2PI) + ln_w
            out[m] = _logsumexp(lp.transpose(1, 0, 2).reshape(lp.shape[1], -1), axis=1)
        return out

    def predict(self, value: ArrayLike, var: ArrayLike) -> Array:
        """Posterior probability of each group for sessions of new specimens (equal prior
        odds), shape (m, g)."""
        return classify_probabilities([self.ln_predictive(value, var)])


def classify_probabilities(ln_predictives: Sequence[Array]) -> Array:
    """Group probabilities from the ln predictive densities of several quantities, each
    (m, g), taken as independent given the group; equal prior odds; shape (m, g)."""
    total = np.sum(np.stack(ln_predictives), axis=0)
    return np.exp(total - _logsumexp(total, axis=1)[:, None])


def steady_force(
    law: Law, mean: ArrayLike, cov: ArrayLike, closure_m: float, speed_m_s: float
) -> tuple[float, float]:
    """The tissue's force at closure ``closure_m`` while closing at constant speed
    ``speed_m_s`` (no acceleration; relaxation branches at their steady state
    ``tau * speed``; the sensor offset left out), with its posterior variance, N and
    N^2: a quantity every law predicts, so sessions fitted with different laws compare.

    Parameters
    ----------
    law : Law
        The fitted law, its shape parameters bound.
    mean, cov : array_like, shapes (p,) and (p, p)
        The coefficients' posterior mean and covariance, SI.
    """
    x = np.array([closure_m])
    v = np.array([speed_m_s])
    a = np.zeros(1)
    row = np.zeros(len(law.terms))
    for j, t in enumerate(law.terms):
        if not t.rendered:
            continue  # a sensor offset is not tissue
        # a term with memory in steady motion (a branch: its spring stretched tau v)
        row[j] = t.steady(closure_m, speed_m_s) if t.memory else float(t.regressor(x, v, a)[0])
    m = np.asarray(mean, dtype=float)
    c = np.asarray(cov, dtype=float)
    return float(row @ m), float(row @ c @ row)
