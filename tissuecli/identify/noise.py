"""How much one sample counts: residual autocorrelation and the data weight that keeps
intervals honest when filtered residuals are correlated."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .posterior import gram_pinv

Array = NDArray[np.float64]


def residual_tau(r: Array) -> float:
    """Integrated autocorrelation time of residuals (samples), >= 1."""
    return max(1.0, integrated_time(r, c=5.0))


def filter_tau(kernel: Array) -> float:
    """Integrated autocorrelation time (samples) of white noise through an FIR filter:
    ``(sum g)^2 / sum g^2``, the sum of its autocorrelation over every lag."""
    g = np.asarray(kernel, dtype=float)
    energy = float(g @ g)
    return max(1.0, float(g.sum()) ** 2 / energy) if energy > 0 else 1.0


def integrated_time(x: Array, c: float = 5.0) -> float:
    """Integrated autocorrelation time of a series (samples), with Sokal's automatic window.

    ``tau(M) = 1 + 2 sum_{t=1}^{M} rho(t)`` at the smallest ``M >= c tau(M)``: the
    estimator of ``emcee.autocorr.integrated_time`` for one series (the tests hold
    the two together), here so that a fit needs no sampler library.
    """
    x = np.asarray(x, dtype=float)
    n = x.size
    size = 2 << int(np.ceil(np.log2(max(n, 1))))  # zero-padded: a linear, not circular, ACF
    f = np.fft.rfft(x - x.mean(), size)
    acf = np.fft.irfft(f.real**2 + f.imag**2, size)[:n]
    if not acf[0] > 0:
        return 1.0  # a constant series has no correlation to measure
    taus = 2.0 * np.cumsum(acf / acf[0]) - 1.0
    short = np.arange(n) < c * taus
    window = int(np.argmin(short)) if np.any(short) and not np.all(short) else n - 1
    return float(taus[window])


def data_weight(
    A: Array,
    r: Array,
    tau: float,
    correction: Array | None = None,
    beta: Array | None = None,
) -> float:
    """How much one sample counts, ``n_eff / n``, for honest intervals.

    Starts from ``1 / tau`` (residuals correlated over tau samples) and lowers it
    further if a batch-means estimate of the coefficients' sampling variance
    (robust to any residual correlation and to noise in the regressors) exceeds
    what the tempered Gaussian likelihood implies: the curvature adjustment of
    a misspecified likelihood (Ribatet et al. 2012), kept O(n).

    With the errors-in-variables ``correction`` ``C`` (shape (p, p), position noise's
    expected share of ``A^T A``) and the least-squares coefficients ``beta`` (shape
    (p,)) that ``r`` is the residual of, both variances are those of the estimator the
    posterior reports, ``beta_c = (A^T A - C)^-1 A^T y``: the likelihood's is the
    sandwich ``s^2 (A^T A - C)^-1 A^T A (A^T A - C)^-1`` of
    :func:`corrected_curvature`, the batch means' are of its estimating equation
    ``A_b^T (y_b - A_b beta_c) + C_b beta_c``. Compared with the least-squares
    variance instead, an inertia whose column is mostly noise read its own
    attenuation-inflated scatter as correlation and, through the one weight every
    coefficient shares, widened a stiffness's interval by 1.5-2x.
    """
    n = r.size
    block = max(int(np.ceil(5 * tau)), 1)
    if n // block < 30:
        block = max(n // 30, 1)
    nb = n // block
    gram = A.T @ A
    corrected = _corrected_inverse(gram, correction) if correction is not None else None
    if corrected is not None and beta is not None:
        gc_inv = corrected
        beta_c = gc_inv @ (gram @ beta)  # A^T y = A^T A beta: r is beta's residual
        r_c = r - A @ (beta_c - beta)
        share = (correction @ beta_c) * (block / n)  # each block's share of C beta_c
        scores = (A[: nb * block] * r_c[: nb * block, None]).reshape(nb, block, -1).sum(axis=1)
        scores = scores + share
        v_robust = np.diag(gc_inv @ (scores.T @ scores) @ gc_inv)
        v_model = (r @ r / n) * np.diag(gc_inv @ gram @ gc_inv)
    else:
        scores = (A[: nb * block] * r[: nb * block, None]).reshape(nb, block, -1).sum(axis=1)
        G_inv = gram_pinv(gram)  # on unit-norm columns: x^3 beside an offset is 1e-8 of it
        v_robust = np.diag(G_inv @ (scores.T @ scores) @ G_inv)
        v_model = (r @ r / n) * np.diag(G_inv)
    ratio = float(np.min(v_model / np.where(v_robust > 0, v_robust, np.inf)))
    return min(1.0 / tau, ratio) if ratio > 0 else 1.0 / tau


def _corrected_inverse(gram: Array, correction: Array) -> Array | None:
    """``(A^T A - C)^-1`` (p, p), taken on unit-norm columns, or None where ``A^T A - C``
    is not positive definite (the correction is then left out, as a fit leaves it)."""
    d = np.sqrt(np.maximum(gram.diagonal(), 1e-300))
    dd = d[:, None] * d
    gc_s = (gram - correction) / dd
    gc_s = 0.5 * (gc_s + gc_s.T)
    lam = np.linalg.eigvalsh(gc_s)
    if not lam[0] > 1e-12 * lam[-1]:
        return None
    return np.asarray(np.linalg.inv(gc_s) / dd)


def corrected_curvature(
    gram: Array,
    b: Array,
    correction: Array,
    rss: float,
    rss_corrected: float,
    corrected: Array | None = None,
) -> tuple[Array, Array, float]:
    """Gaussian statistics ``(G, b, yy)`` whose posterior is centred on the
    errors-in-variables corrected coefficients with their sampling covariance.

    The corrected estimator ``beta_c = (A^T A - C)^-1 A^T y`` takes the bias off, but
    not the noise: position noise still reaches the residuals through the columns, so
    its covariance is the sandwich ``s^2 (A^T A - C)^-1 A^T A (A^T A - C)^-1`` with
    ``s^2`` the raw residual variance (force noise and position noise through the law),
    not ``s_c^2 (A^T A - C)^-1`` with the corrected, force-only residual: that was too
    narrow for a stiffness fitted through noisy position (a cubic term's intervals held
    the truth in 59 % of sessions at 20 um of position noise) and too wide for an
    inertia whose column is mostly noise. The returned curvature
    ``H = (s_c^2 / s^2) (A^T A - C) (A^T A)^-1 (A^T A - C)`` gives that covariance with
    the noise SD still the force noise alone, and ``yy = rss_c + beta_c^T H beta_c``
    keeps the least-squares residual ``yy - b^T H^-1 b`` at ``rss_c``.

    Parameters
    ----------
    gram : ndarray, shape (p, p)
        ``A^T A``.
    b : ndarray, shape (p,)
        ``A^T y``.
    correction : ndarray, shape (p, p)
        ``C``, the noise's expected share of ``A^T A``; ``A^T A - C`` positive definite.
    rss, rss_corrected : float
        Residual sums of squares of the raw and the corrected fits, N^2.
    corrected : ndarray, shape (p, p), optional
        ``A^T A - C``, if already formed.

    Returns
    -------
    G : ndarray, shape (p, p)
    b : ndarray, shape (p,)
    yy : float
    """
    d = np.sqrt(np.maximum(gram.diagonal(), 1e-300))  # unit-norm columns: x^3 is 1e-6 of x
    dd = d[:, None] * d  # np.outer's numbers
    gram_s = gram / dd
    gc_s = (gram - correction if corrected is None else corrected) / dd
    # pseudo-inverses: a shape node can make two columns one (a branch slower than the
    # session is a spring), which leaves these singular where the posterior is not
    beta_s = np.linalg.lstsq(gc_s, b / d, rcond=None)[0]
    h_s = gc_s @ _pinv_symmetric(gram_s) @ gc_s
    # a correction that took the whole residual (never applied in a full fit) keeps the
    # curvature proper
    ratio = rss_corrected / rss if rss > 0 and rss_corrected > 0 else 1.0
    h_s = 0.5 * (h_s + h_s.T) * ratio
    G = h_s * dd
    b_c = (h_s @ beta_s) * d
    yy = rss_corrected + float(beta_s @ h_s @ beta_s)
    return G, b_c, yy


def _pinv_symmetric(a: Array) -> Array:
    """``np.linalg.pinv(a, hermitian=True)`` of a symmetric (p, p) matrix, the same
    numbers at half its cost (its steps without its generality): the eigenvalues by
    magnitude, those below 1e-15 of the largest dropped."""
    s, u = np.linalg.eigh(a)
    order = np.argsort(np.abs(s))[::-1]
    sign, s, u = np.sign(s)[order], np.abs(s)[order], u[:, order]
    large = s > 1e-15 * np.max(s)
    s = np.divide(1, s, where=large, out=s)
    s[~large] = 0
    return np.matmul(u * sign[None, :], np.multiply(s[:, None], u.T))
