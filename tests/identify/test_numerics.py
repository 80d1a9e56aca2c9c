"""The NumPy numerics that keep SciPy and emcee off the fit's start-up path, held to the
library routines they replace and to closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest
from emcee.autocorr import integrated_time as emcee_integrated_time
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import optimize, signal, stats

from tissuecli.identify.noise import corrected_curvature, integrated_time
from tissuecli.identify.orthant import normal_cdf, normal_ppf, orthant_probability
from tissuecli.identify.posterior import _mixture_quantile
from tissuecli.identify.spectrum import convolve_valid, power_spectrum


@pytest.mark.parametrize(
    ("n", "nperseg"), [(10_000, 4096), (10_000, 256), (777, 256), (1001, 1001)]
)
def test_power_spectrum_is_scipy_welch(n: int, nperseg: int) -> None:
    x = np.random.default_rng(n).standard_normal(n)
    f_ref, p_ref = signal.welch(x, fs=1000.0, nperseg=nperseg)
    f, p = power_spectrum(x, 1000.0, nperseg)
    np.testing.assert_array_equal(f, f_ref)
    # same sums in another order: a few ulps of the largest bin
    np.testing.assert_allclose(p, p_ref, rtol=0, atol=1e-12 * p_ref.max())


@settings(max_examples=60, deadline=None)
@given(n=st.integers(1, 30_000), m=st.integers(1, 3000), seed=st.integers(0, 2**31))
def test_convolve_valid_is_the_valid_convolution(n: int, m: int, seed: int) -> None:
    m = min(m, n)
    rng = np.random.default_rng(seed)
    u, k = rng.standard_normal(n), rng.standard_normal(m)
    ref = np.convolve(u, k, mode="valid")
    got = convolve_valid(u, k)
    assert got.shape == ref.shape
    # FFT rounding grows like eps * log2(n) * sum |u_i k_j|; 1e-12 of the scale is generous
    scale = np.sqrt(m) * max(np.abs(ref).max(), 1.0)
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12 * scale)


def test_convolve_valid_refuses_a_kernel_longer_than_the_signal() -> None:
    with pytest.raises(ValueError, match="longer"):
        convolve_valid(np.ones(3), np.ones(4))


@pytest.mark.parametrize("rho", [0.0, 0.5, 0.95, 0.999])
@pytest.mark.parametrize("n", [100, 1000, 9613])
def test_integrated_time_is_emcees(n: int, rho: float) -> None:
    rng = np.random.default_rng(int(1000 * rho) + n)
    x = np.zeros(n)
    e = rng.standard_normal(n)
    for i in range(1, n):
        x[i] = rho * x[i - 1] + e[i]
    ref = emcee_integrated_time(x, c=5, tol=0, quiet=True)[0]
    assert integrated_time(x, 5.0) == pytest.approx(ref, rel=1e-12)


def test_normal_cdf_and_ppf_against_scipy() -> None:
    z = np.linspace(-37, 8, 2001)
    # Cephes' own peak error (3.4e-14), plus rounding z / sqrt(2), which moves erfc by
    # about z^2 eps relatively (1.4e-13 at z = -37)
    ref = stats.norm.cdf(z)
    assert np.all(np.abs(normal_cdf(z) - ref) <= (5e-14 + z**2 * 3e-16) * ref)
    p = np.concatenate([np.geomspace(1e-300, 0.5, 500), 1 - np.geomspace(1e-15, 0.5, 500)])
    # inverting a CDF amplifies its rounding by 1/pdf: compare in probability
    np.testing.assert_allclose(normal_cdf(normal_ppf(p)), p, rtol=1e-12, atol=1e-16)
    np.testing.assert_allclose(normal_ppf(p), stats.norm.ppf(p), rtol=1e-9, atol=1e-12)


def _sheppard(cov: np.ndarray) -> float:
    """P(X >= 0) for a zero-mean trivariate normal, exactly."""
    sd = np.sqrt(np.diag(cov))
    r = cov / np.outer(sd, sd)
    return 1 / 8 + (math.asin(r[0, 1]) + math.asin(r[0, 2]) + math.asin(r[1, 2])) / (4 * math.pi)


def test_orthant_probability_meets_its_tolerance_on_exact_cases() -> None:
    """The algorithm stops at 3 standard errors <= 1e-5: over 40 random, often strongly
    correlated cases, none may miss the exact value by more than 3e-5 (3 such errors)."""
    rng = np.random.default_rng(7)
    for _ in range(40):
        a = rng.standard_normal((3, 3))
        cov = a @ a.T
        assert abs(orthant_probability(np.zeros(3), cov) - _sheppard(cov)) < 3e-5
    # independent coordinates: a product of one-dimensional masses, tiny ones included
    mean, cov = np.array([-8.0, 1.0, 0.3]), np.diag([1.0, 4.0, 0.25])
    exact = stats.norm.cdf(-8) * stats.norm.cdf(0.5) * stats.norm.cdf(0.6)
    assert orthant_probability(mean, cov) == pytest.approx(exact, rel=1e-3)
    assert orthant_probability(np.array([0.7]), np.array([[2.0]])) == pytest.approx(
        stats.norm.cdf(0.7 / math.sqrt(2.0)), rel=1e-14
    )


def test_orthant_probability_agrees_with_genz_in_scipy() -> None:
    rng = np.random.default_rng(11)
    for _ in range(30):
        p = int(rng.integers(2, 6))
        a = rng.standard_normal((p, p))
        cov = a @ a.T + 0.05 * np.eye(p)
        mean = rng.normal(0, 2, p) * np.sqrt(np.diag(cov))
        ref = stats.multivariate_normal(mean=-mean, cov=cov, abseps=1e-9, releps=1e-9).cdf(
            np.zeros(p)
        )
        assert abs(orthant_probability(mean, cov) - ref) < 3e-5


def test_mixture_quantile_is_brents_root() -> None:
    rng = np.random.default_rng(3)
    for _ in range(100):
        m = int(rng.integers(1, 400))
        w = rng.random(m)
        w /= w.sum()
        mu = rng.normal(rng.normal(0, 1000), rng.uniform(1e-3, 50), m)
        sd = rng.uniform(0.01, 5, m) * rng.uniform(1e-3, 1)
        for q in (0.025, 0.975):
            lo, hi = float(np.min(mu - 10 * sd)), float(np.max(mu + 10 * sd))
            ref = optimize.brentq(
                lambda x, w=w, mu=mu, sd=sd, q=q: w @ stats.norm.cdf(x, mu, sd) - q,
                lo,
                hi,
                xtol=1e-14,
            )
            assert abs(_mixture_quantile(q, w, mu, sd) - ref) < 1e-9 * sd.max()


@pytest.mark.parametrize(("ratio", "p"), [(0.5, 1), (-0.5, 1), (0.3, 3)])
def test_bounded_posterior_draws_match_the_truncated_normal(ratio: float, p: int) -> None:
    """Exact draws under the positivity bound against the truncated normal's moments.

    With a million effective samples sigma is pinned (its posterior SD is 0.07 %), so
    each coefficient's posterior is N(mu, s^2) cut at 0, independent across an
    orthogonal design: mean ``mu + s phi(a) / (1 - Phi(a))``, ``a = -mu / s``. The
    draws' mean may miss it only by Monte Carlo error: 4.5 standard errors
    (two-sided 1e-5 per coefficient); the SD within 5 % (ten times the 0.5 % Monte
    Carlo error of an SD from 20 000 draws).
    """
    from tissuecli.identify.posterior import ExactPosterior, Prior, SufficientStats

    n, sigma, g = 1e6, 1.0, 4.0  # s = sigma / sqrt(g) = 0.5
    s = sigma / math.sqrt(g)
    mu = np.full(p, ratio * s)
    G = np.eye(p) * g
    b = G @ mu
    stats_ = SufficientStats(G, b, float(mu @ G @ mu + n * sigma**2), n)
    post = ExactPosterior(stats_, Prior(scales=np.full(p, 1e3))).truncated(
        np.random.default_rng(0), draws=20000
    )
    assert post is not None and post.method == "exact-draws"
    a = -ratio
    want = mu + s * stats.norm.pdf(a) / stats.norm.sf(a)
    sd_want = s * math.sqrt(
        1 + a * stats.norm.pdf(a) / stats.norm.sf(a) - (stats.norm.pdf(a) / stats.norm.sf(a)) ** 2
    )
    se = sd_want / math.sqrt(post.samples.shape[0])
    np.testing.assert_array_less(np.abs(post.mean - want), 4.5 * se)
    assert np.all(post.samples[:, :p] >= 0)
    np.testing.assert_allclose(post.sd, sd_want, rtol=0.05)


def test_corrected_curvature_is_the_corrected_estimators_sandwich() -> None:
    """Centred on (A^T A - C)^-1 A^T y; with the force-only noise s_c^2 = rss_c / n its
    covariance s_c^2 G^-1 is s^2 (A^T A - C)^-1 A^T A (A^T A - C)^-1, s^2 = rss / n;
    the least-squares residual yy - b^T G^-1 b is rss_c. Columns a million apart in
    scale (x^3 beside x in SI) change nothing."""
    rng = np.random.default_rng(3)
    A = rng.normal(size=(500, 3)) * np.array([1.0, 1e-6, 1e3])
    y = A @ np.array([2.0, 3e6, 1e-3]) + rng.normal(size=500)
    gram, b = A.T @ A, A.T @ y
    C = 0.05 * np.diag(np.diag(gram))
    rss, rss_c = 480.0, 400.0
    G, b_c, yy = corrected_curvature(gram, b, C, rss, rss_c)
    beta_c = np.linalg.solve(gram - C, b)
    np.testing.assert_allclose(np.linalg.solve(G, b_c), beta_c, rtol=1e-9)
    inv = np.linalg.inv(gram - C)
    np.testing.assert_allclose(rss_c * np.linalg.inv(G), rss * inv @ gram @ inv, rtol=1e-8)
    assert yy - b_c @ np.linalg.solve(G, b_c) == pytest.approx(rss_c, rel=1e-6)
    # no correction: the plain statistics
    G0, b0, _ = corrected_curvature(gram, b, np.zeros((3, 3)), rss, rss)
    np.testing.assert_allclose(G0, gram, rtol=1e-9)
    np.testing.assert_allclose(b0, b, rtol=1e-9)
