"""The NumPy numerics that keep SciPy and emcee off the fit's start-up path, held to the
library routines they replace and to closed forms."""

from __future__ import annotations

import gc
import math

import numpy as np
import pytest
from emcee.autocorr import integrated_time as emcee_integrated_time
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import optimize, signal, stats

from tissuecli.identify import spectrum
from tissuecli.identify.noise import corrected_curvature, integrated_time
from tissuecli.identify.orthant import (
    ABS_BAND,
    ABS_TOL,
    REL_TOL,
    normal_cdf,
    normal_ppf,
    orthant_probability,
)
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


@pytest.mark.parametrize(("n", "m"), [(10_000, 173), (9_828, 301), (50_000, 65)])
def test_convolve_valid_in_one_batch_is_the_batched_sums(
    n: int, m: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    # the single-batch path adds each block's spill in place: the same sums, bit for bit
    rng = np.random.default_rng(n + m)
    u, k = rng.standard_normal(n), rng.standard_normal(m)
    one = convolve_valid(u, k)
    monkeypatch.setattr(spectrum, "BATCH_SAMPLES", 1)  # a batch per block
    np.testing.assert_array_equal(one, convolve_valid(u, k))


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


def _target(p: float) -> float:
    """The lattice's stopping target for a mass ``p``: 3 standard errors below 1e-3 of
    it, and below 1e-5 absolute within 0.01 of 1."""
    return min(REL_TOL * p, ABS_TOL) if p > 1.0 - ABS_BAND else REL_TOL * p


def test_orthant_probability_meets_its_tolerance_on_exact_cases() -> None:
    """The algorithm stops at 3 standard errors within its target: over 40 random,
    often strongly correlated cases, none may miss the exact value by more than three
    times the target (3 such errors), and near 1 by more than 3e-5."""
    rng = np.random.default_rng(7)
    for _ in range(40):
        a = rng.standard_normal((3, 3))
        cov = a @ a.T
        exact = _sheppard(cov)
        assert abs(orthant_probability(np.zeros(3), cov) - exact) < 3 * _target(exact)
    # a mass within 0.01 of 1: the absolute target, 3e-5 at 3 errors
    a = rng.standard_normal((3, 3))
    cov = a @ a.T
    mean = 3.0 * np.sqrt(np.diag(cov))
    ref = stats.multivariate_normal(mean=-mean, cov=cov, abseps=1e-9, releps=1e-9).cdf(
        np.zeros(3)
    )
    assert ref > 1.0 - ABS_BAND
    assert abs(orthant_probability(mean, cov) - ref) < 3e-5
    # independent coordinates: a product of one-dimensional masses, tiny ones included
    mean, cov = np.array([-8.0, 1.0, 0.3]), np.diag([1.0, 4.0, 0.25])
    exact = stats.norm.cdf(-8) * stats.norm.cdf(0.5) * stats.norm.cdf(0.6)
    assert orthant_probability(mean, cov) == pytest.approx(exact, rel=1e-3)
    assert orthant_probability(np.array([0.7]), np.array([[2.0]])) == pytest.approx(
        stats.norm.cdf(0.7 / math.sqrt(2.0)), rel=1e-14
    )


def _random_gaussian(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A Gaussian of 2-5 dimensions, its mean 0-2 SDs from the orthant's faces: (mean,
    cov)."""
    p = int(rng.integers(2, 6))
    a = rng.standard_normal((p, p))
    cov = a @ a.T + 0.05 * np.eye(p)
    return rng.normal(0, 2, p) * np.sqrt(np.diag(cov)), cov


def _agrees_with_genz(ref_eps: float) -> None:
    """Over 30 random Gaussians, the orthant mass within three times its target (3
    standard errors of it, as on the exact cases) of SciPy's Genz integration asked for
    ``ref_eps`` (absolute: a mass far below it is checked only to it), beside the
    reference's own error: within three times the target and twice ``ref_eps`` of the
    true mass."""
    rng = np.random.default_rng(11)
    for _ in range(30):
        mean, cov = _random_gaussian(rng)
        ref = stats.multivariate_normal(mean=-mean, cov=cov, abseps=ref_eps, releps=ref_eps).cdf(
            np.zeros(mean.size)
        )
        assert abs(orthant_probability(mean, cov) - ref) < 3 * _target(ref) + ref_eps


def test_orthant_probability_agrees_with_genz_in_scipy() -> None:
    """Genz's reference to 1e-6 (0.5 s of CPU; 1e-9 takes 9 s, below): the bound it
    checks is the same, three times the target, with 1e-6 beside it for the reference."""
    _agrees_with_genz(1e-6)


@pytest.mark.slow
def test_orthant_probability_agrees_with_genz_in_scipy_to_1e_9() -> None:
    """The same 30 cases against a reference 1000 times finer."""
    _agrees_with_genz(1e-9)


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


def _cut_posterior(cut_sds: float, p: int = 4, seed: int = 0) -> tuple[object, object]:
    """Sufficient statistics and prior of a correlated regression whose second coefficient
    sits ``cut_sds`` posterior SDs above its positivity bound (the others far inside)."""
    from tissuecli.identify.posterior import Prior, SufficientStats

    rng = np.random.default_rng(seed)
    n, sigma = 2000.0, 0.1
    A = rng.standard_normal((int(n), p))
    A[:, 1] += 0.5 * A[:, 0]
    G = A.T @ A
    sd = sigma * np.sqrt(np.diag(np.linalg.inv(G)))
    beta = np.full(p, 50.0) * sd
    beta[1] = cut_sds * sd[1]
    y = A @ beta + sigma * rng.standard_normal(int(n))
    return SufficientStats.from_data(A, y), Prior(scales=np.full(p, 10.0))


@pytest.mark.parametrize("cut_sds", [8.0, 1.0, -0.5, -3.0])
def test_bounded_posterior_is_the_summary_or_the_draws(cut_sds: float) -> None:
    """:meth:`ExactPosterior.bounded` is the closed-form summary where the bound cuts no
    more than 1e-3 of it, else the draws under the bound, each on the generator as it
    is given (the summary's random numbers are drawn only when it is the answer)."""
    from tissuecli.identify.posterior import ExactPosterior

    stats_, prior = _cut_posterior(cut_sds)

    def reference(rng: np.random.Generator) -> object:
        exact = ExactPosterior(stats_, prior)
        if 1.0 - exact.orthant_mass() <= 1e-3:
            post = exact.summary(rng)
        else:
            post = exact.truncated(rng)
            if post is None:
                post = exact.summary(rng)
                post.diagnostics["exact"] = False
                return post
        post.diagnostics["exact"] = True
        return post

    rng_lazy, rng_ref = np.random.default_rng(5), np.random.default_rng(5)
    lazy = ExactPosterior(stats_, prior).bounded(rng_lazy)
    ref = reference(rng_ref)
    assert lazy.method == ref.method and lazy.diagnostics == ref.diagnostics
    for name in ("mean", "sd", "ci95", "cov", "samples"):
        np.testing.assert_array_equal(getattr(lazy, name), getattr(ref, name))
    assert (lazy.sigma_mean, lazy.sigma_ci95, lazy.ln_evidence, lazy.outside) == (
        ref.sigma_mean, ref.sigma_ci95, ref.ln_evidence, ref.outside,
    )  # fmt: skip
    assert rng_lazy.random() == rng_ref.random()  # the same stream for what follows


@pytest.mark.parametrize("cut_sds", [8.0, 1.0, -0.5, -3.0])
def test_bounded_posterior_without_intervals_is_the_same_but_them(cut_sds: float) -> None:
    """A mixture's component skips its own intervals: every other figure, the draws and
    the generator's stream after it are those of the full posterior."""
    from tissuecli.identify.posterior import ExactPosterior

    stats_, prior = _cut_posterior(cut_sds)
    rng_full, rng_bare = np.random.default_rng(5), np.random.default_rng(5)
    full = ExactPosterior(stats_, prior).bounded(rng_full)
    bare = ExactPosterior(stats_, prior).bounded(rng_bare, intervals=False)
    assert bare.method == full.method and bare.diagnostics == full.diagnostics
    for name in ("mean", "sd", "cov", "samples"):
        np.testing.assert_array_equal(getattr(bare, name), getattr(full, name))
    assert (bare.sigma_mean, bare.ln_evidence, bare.outside) == (
        full.sigma_mean, full.ln_evidence, full.outside,
    )  # fmt: skip
    assert np.all(np.isnan(bare.ci95)) and bare.ci95.shape == full.ci95.shape
    # the noise's interval costs nothing in closed form, and is kept there
    assert all(math.isnan(v) for v in bare.sigma_ci95) or bare.sigma_ci95 == full.sigma_ci95
    assert rng_bare.random() == rng_full.random()


@pytest.mark.parametrize(("cut_sds", "second"), [(1.0, None), (-0.5, None), (-1.5, 0.5)])
def test_bounded_draws_are_those_of_plain_rejection(cut_sds: float, second: float | None) -> None:
    """The draws under the bound (the most-cut coefficient drawn under its bound by
    inverse CDF, the other near bounds by rejection) have the distribution of plain
    rejection from the untruncated mixture: every coefficient's and the noise's draws
    pass a two-sample Kolmogorov-Smirnov test against 200,000 plain rejection draws (at
    1e-3: with 5 coordinates and 3 cases, a correct sampler fails it with a chance of
    1.5 % under a fixed seed, which this seed does not), their means agree within 4
    Monte Carlo SEs, and the acceptance reported is the share of plain draws kept."""
    from tissuecli.identify.posterior import ExactPosterior, _matrix_roots

    stats_, prior = _cut_posterior(cut_sds)
    if second is not None:  # a second coefficient near its bound, pulled there by the data
        rng = np.random.default_rng(1)
        A = rng.standard_normal((2000, 4))
        A[:, 1] += 0.5 * A[:, 0]
        A[:, 2] -= 0.4 * A[:, 1]
        sd = 0.1 * np.sqrt(np.diag(np.linalg.inv(A.T @ A)))
        beta = 50.0 * sd
        beta[1], beta[2] = cut_sds * sd[1], second * sd[2]
        y = A @ beta + 0.1 * rng.standard_normal(2000)
        stats_ = type(stats_).from_data(A, y)
    exact = ExactPosterior(stats_, prior)
    post = exact.truncated(np.random.default_rng(3))
    assert post is not None and post.samples.shape == (4000, 5)
    assert np.all(post.samples[:, :-1] >= 0)
    # plain rejection: every coefficient drawn, every bound checked
    rng = np.random.default_rng(11)
    w, mus, covs, idx = exact.mixture()
    chol = _matrix_roots(covs)
    want, have, total = [], 0, 0
    while have < 200_000:
        pick = np.repeat(np.arange(w.size), rng.multinomial(200_000, w))
        beta = mus[pick] + np.einsum("kij,kj->ki", chol[pick], rng.standard_normal((pick.size, 4)))
        ok = np.all(beta >= 0, axis=1)
        want.append(np.column_stack([beta[ok], np.exp(exact.u[idx])[pick[ok]]]))
        have, total = have + int(ok.sum()), total + pick.size
    plain = np.concatenate(want)
    for j in range(5):
        assert stats.ks_2samp(post.samples[:, j], plain[:, j]).pvalue > 1e-3, j
    se = plain.std(axis=0) / math.sqrt(4000)
    assert np.all(np.abs(post.samples.mean(axis=0) - plain.mean(axis=0)) < 4 * se)
    # its SD: that of a share estimated from the draws
    assert post.diagnostics["acceptance"] == pytest.approx(have / total, rel=0.05)


def test_orthant_mass_of_one_bound_is_its_normal_cdf() -> None:
    """Where one bound alone matters the mass is that coefficient's normal CDF (to the
    union bound's 1e-12): exact for independent coefficients, and within it for
    correlated ones."""
    from tissuecli.identify.orthant import orthant_log_probability

    sd = np.array([1.0, 2.0, 0.5])
    for rho in (0.0, 0.6, -0.9):
        corr = np.array([[1.0, rho, 0.0], [rho, 1.0, rho / 2], [0.0, rho / 2, 1.0]])
        cov = corr * np.outer(sd, sd)
        mean = np.array([40.0, 0.3, 60.0]) * sd
        ln_p, err = orthant_log_probability(mean, cov)
        want = math.log(stats.norm.cdf(0.3 / math.sqrt(1 + 1e-12)))
        assert err == 0.0
        assert ln_p == pytest.approx(want, rel=1e-12, abs=1e-15)


def test_orthant_lattice_without_a_sure_tail_is_the_same(monkeypatch: pytest.MonkeyPatch) -> None:
    """Leaving out trailing variables whose factor is 1 to the last bit changes the
    lattice's estimate not at all: the same value, bit for bit, as the full lattice."""
    from tissuecli.identify import orthant

    sd = np.array([1.0, 1.0, 1.0, 1.0])
    corr = np.array(
        [[1.0, 0.5, 0.2, 0.3], [0.5, 1.0, 0.4, -0.2], [0.2, 0.4, 1.0, 0.1], [0.3, -0.2, 0.1, 1.0]]
    )
    mean = np.array([0.4, -0.3, 1.2, 300.0])
    got = orthant.orthant_log_probability(mean, corr * np.outer(sd, sd))
    monkeypatch.setattr(orthant, "_without_sure_tail", lambda chol, h: (chol, h))
    monkeypatch.setattr(orthant, "_one_bound", lambda h: None)
    assert orthant.orthant_log_probability(mean, corr * np.outer(sd, sd)) == got


def test_recent_columns_answer_only_their_own_session_within_their_bound() -> None:
    """The kept shaped columns are found again only for the very kinematics and closure
    they came from, and never hold more than their byte bound."""
    from tissuecli.identify.design import RecentColumns

    class Kin:  # any object a weak reference can point to
        pass

    kin, other = Kin(), Kin()
    x = np.arange(10.0)
    cache = RecentColumns(max_bytes=3 * 80)
    col = np.ones(10)
    cache.put(("column", 0.0, "a"), kin, x, col)  # type: ignore[arg-type]
    assert cache.get(("column", 0.0, "a"), kin, x) is col  # type: ignore[arg-type]
    assert cache.get(("column", 0.0, "a"), other, x) is None  # type: ignore[arg-type]
    assert cache.get(("column", 0.0, "a"), kin, x.copy()) is None  # type: ignore[arg-type]
    for name in "bcd":  # three more of 80 bytes: the first is dropped
        cache.put(("column", 0.0, name), kin, x, np.zeros(10))  # type: ignore[arg-type]
    assert cache.get(("column", 0.0, "a"), kin, x) is None  # type: ignore[arg-type]
    assert cache.get(("column", 0.0, "d"), kin, x) is not None  # type: ignore[arg-type]
    assert cache.nbytes <= 3 * 80
    del kin
    gc.collect()  # a finished fit's columns go when the next fit keeps its first
    cache.put(("column", 0.0, "e"), other, x, np.zeros(10))  # type: ignore[arg-type]
    assert cache.nbytes == 80


def _bound_above_genz(abseps: float, releps: float, slack: float) -> None:
    """Over 40 random Gaussians, the half-space bound at least SciPy's Genz mass (asked
    for ``abseps``, ``releps``) less ``slack``, the reference's own accuracy."""
    from tissuecli.identify.orthant import orthant_log_upper_bound

    rng = np.random.default_rng(23)
    for _ in range(40):
        mean, cov = _random_gaussian(rng)
        ref = stats.multivariate_normal(mean=-mean, cov=cov, abseps=abseps, releps=releps).cdf(
            np.zeros(mean.size)
        )
        assert math.exp(orthant_log_upper_bound(mean, cov)) >= ref - slack


@pytest.mark.slow
def test_orthant_upper_bound_holds_against_scipy_to_1e_9() -> None:
    """The bound against Genz's masses to 1e-12 absolute, 1e-9 relative (40 s of CPU)."""
    _bound_above_genz(1e-12, 1e-9, 1e-9)


def test_orthant_upper_bound_holds_against_scipy_and_the_lattice() -> None:
    """The half-space bound is above every mass SciPy's Genz integration gives (to its
    accuracy: 1e-6 here, 3 s of CPU, which judges the masses above about 1e-6; the slow
    test above holds it to 1e-9 in 40 s), and, far in the tail, within a few nats of
    Laplace's tail estimate (both are ``-d^2 / 2`` to leading order in the distance
    ``d`` to the orthant)."""
    from tissuecli.identify.orthant import orthant_log_upper_bound, tail_log_probability

    _bound_above_genz(1e-6, 1e-6, 1e-6)
    # far out: tight where the axis bound is not
    corr = np.array([[1.0, 0.9], [0.9, 1.0]])
    mean = np.array([-30.0, -30.0])
    top = orthant_log_upper_bound(mean, corr)
    axis = math.log(stats.norm.cdf(-30.0))
    assert top < axis - 10.0
    assert abs(top - tail_log_probability(mean, corr)) < 5.0


def test_a_far_tail_is_not_evaluated_from_its_bound_without_the_lattice(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Where the upper bound is beyond FAR_NATS the lattice is never run and the law is
    not evaluated, the bound in its reason; refine() runs the lattice, whose figure lies
    below the bound."""
    from tissuecli.identify import posterior as post_mod
    from tissuecli.identify.posterior import FAR_NATS, ExactPosterior

    stats_, prior = _cut_posterior(-60.0)
    calls: list[int] = []
    lattice = post_mod.orthant_log_probability

    def counted(mean: np.ndarray, cov: np.ndarray) -> tuple[float, float]:
        calls.append(1)
        return lattice(mean, cov)

    monkeypatch.setattr(post_mod, "orthant_log_probability", counted)
    exact = ExactPosterior(stats_, prior)
    top = exact.ln_orthant_mass()
    assert top < -FAR_NATS and exact.bound_only and not calls
    assert exact.untrusted().startswith(f"the positivity bounds keep at most e^{top:.0f} ")
    assert exact.orthant_mass() == 0.0
    # (the lattice regularises the correlation by 1e-12, so the same figure to 1e-11)
    assert exact.refine() <= top + 1e-11 * abs(top) and calls and not exact.bound_only


def test_rejection_reaches_below_the_chains_threshold_where_asked() -> None:
    """A posterior the bound keeps 0.16 % of: too little for the default rejection (a
    chain samples it), enough at REJECTION_ACCEPTANCE, and every draw inside the bound
    with the acceptance the orthant mass predicts."""
    from tissuecli.identify.posterior import (
        MIN_ACCEPTANCE,
        REJECTION_ACCEPTANCE,
        ExactPosterior,
    )

    stats_, prior = _cut_posterior(-1.8)
    exact = ExactPosterior(stats_, prior)
    inside = exact.orthant_mass()
    assert REJECTION_ACCEPTANCE < inside < MIN_ACCEPTANCE
    assert exact.truncated(np.random.default_rng(1)) is None
    post = exact.truncated(np.random.default_rng(1), min_acceptance=REJECTION_ACCEPTANCE)
    assert post is not None and post.method == "exact-draws"
    assert np.all(post.samples[:, :-1][:, exact.prior.bounded] >= 0)  # sigma last
    # the mass is that at the modal noise level, the draws mix over it (its SD is 1.6 %
    # of it at 2000 samples, which moves a mass 3 SDs out by about 5 %): within 20 %
    assert post.diagnostics["acceptance"] == pytest.approx(inside, rel=0.2)


@pytest.mark.parametrize("unit", [1.0, 1e-8])
def test_the_corrected_residual_and_data_weight_do_not_depend_on_a_columns_unit(
    unit: float,
) -> None:
    """An ``x^3`` column in m^3 (1e-8 at a closure of a few mm) beside an offset's column
    of ones: the errors-in-variables corrected residual, the batch-means data weight and
    the streamed sums are what they are with the same column in well-scaled units. A
    change of unit rescales a coefficient and nothing else; solved unscaled, the Gram
    matrix's eigenvalues spanned 1e-17 and the solver dropped the cubic column as
    collinear, which took a third of the residual away and gave an offset 27 nats it
    had not earned."""
    from tissuecli.core.terms import Law
    from tissuecli.identify.noise import data_weight
    from tissuecli.identify.posterior import SufficientStats
    from tissuecli.identify.scoring import FirstPass, _corrected_rss
    from tissuecli.identify.stream import _Sums

    rng = np.random.default_rng(61127002)
    n = 3000
    t = np.linspace(0.0, 3.0, n)
    cubic = (0.5 + 0.5 * np.sin(2 * np.pi * 1.3 * t)) ** 3  # positive, as in a grasp
    speed = np.cos(2 * np.pi * 0.7 * t)
    y = 2.0 * cubic + 0.3 * speed + 0.01 + 0.02 * rng.standard_normal(n)
    # the columns as measured, with noise of known variance: C is its expected share
    noise = np.array([0.01, 0.02, 0.0])
    A_ref = np.column_stack([cubic, speed, np.ones(n)]) + rng.standard_normal((n, 3)) * noise
    C_ref = np.diag(n * noise**2)
    scale = np.array([unit, 1.0, 1.0])
    A = A_ref * scale
    C = C_ref * np.outer(scale, scale)

    def corrected(A: np.ndarray, C: np.ndarray) -> float:
        gram = A.T @ A
        beta = np.linalg.lstsq(A / np.linalg.norm(A, axis=0), y, rcond=None)[0]
        beta /= np.linalg.norm(A, axis=0)
        r = y - A @ beta
        fp = FirstPass(gram, A.T @ y, float(y @ y), beta, float(r @ r), 1.0, 1.0, C)
        return _corrected_rss(fp, C)

    want = corrected(A_ref, C_ref)
    assert 0.5 * float(0.02**2 * n) < want < 1.5 * float(0.02**2 * n)
    assert corrected(A, C) == pytest.approx(want, rel=1e-9)
    assert SufficientStats.from_data(A, y, correction=C).rss == pytest.approx(
        SufficientStats.from_data(A_ref, y, correction=C_ref).rss, rel=1e-9
    )
    sums = _Sums.empty(Law.of(["x^3", "xdot", "offset"]), corrected=True)
    sums.add(A, y)
    sums.correction = C
    assert sums.rss() == pytest.approx(want, rel=1e-6)
    r = y - A_ref @ np.linalg.lstsq(A_ref, y, rcond=None)[0]
    assert data_weight(A, r, 1.0) == pytest.approx(data_weight(A_ref, r, 1.0), rel=1e-9)
