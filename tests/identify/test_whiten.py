"""The prewhitened likelihood: the autoregressive filter, its effective samples and the
calibration of the intervals it gives."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from tissuecli.core.errors import FitError
from tissuecli.core.terms import Law
from tissuecli.identify import BayesianFit
from tissuecli.identify.scoring import Context, first_pass
from tissuecli.identify.shaped import ShapedPass
from tissuecli.identify.whiten import (
    ARFilter,
    Prewhitened,
    Tempered,
    likelihood_strategy,
    precision_ratio,
)
from tissuecli.sim.families import FAMILIES
from tissuecli.sim.synth import random_session


def _ar1(rng: np.random.Generator, n: int, phi: float) -> np.ndarray:
    """A stationary AR(1) series of unit innovations."""
    e = rng.standard_normal(n)
    r = np.empty(n)
    r[0] = e[0] / np.sqrt(1.0 - phi**2)
    for t in range(1, n):
        r[t] = phi * r[t - 1] + e[t]
    return r


def test_ar1_noise_gives_the_theoretical_effective_samples():
    """AR(1) residuals of coefficient 0.8 over 20,000 samples: BIC picks order 1, and the
    evidence's effective samples for a constant and a slow sine are n (1 - phi) / (1 + phi)
    = n / 9. The coefficient's SE is sqrt((1 - phi^2) / n) = 0.0042; the ratio's
    logarithm moves 2 / (1 - phi^2) = 5.6 times as much, 2.4 %: 10 % is 4 SE."""
    n, phi = 20_000, 0.8
    r = _ar1(np.random.default_rng(7), n, phi)
    f = ARFilter().fit(r)
    assert f.order_ == 1
    assert f.coef_[0] == pytest.approx(phi, abs=4 * np.sqrt((1 - phi**2) / n))
    t = np.arange(n) / n
    A = np.column_stack([np.ones(n), np.sin(2 * np.pi * t)])
    Aw = f.transform(A)
    ratio = precision_ratio(Aw.T @ Aw, f.innovation_var_, A.T @ A, f.variance_)
    assert ratio * n == pytest.approx(n * (1 - phi) / (1 + phi), rel=0.10)
    assert 1.0 / f.tau == pytest.approx((1 - phi) / (1 + phi), rel=0.10)


def test_prewhitened_intervals_cover_at_their_nominal_rate():
    """A line fitted through AR(1) noise (phi 0.9), 400 sessions of 2,000 samples: the
    95 % intervals of the prewhitened regression hold the slope in 93-97 % of them
    (the binomial range of 400 draws at 95 % is 92.8-97.0 %); the white likelihood's,
    too narrow by sqrt(19), hold it far less often."""
    rng = np.random.default_rng(11)
    n, phi, slope = 2000, 0.9, 2.0
    t = np.linspace(0.0, 1.0, n)
    A = np.column_stack([np.ones(n), t])
    held = white_held = 0
    sessions = 400
    z = stats.norm.ppf(0.975)
    for _ in range(sessions):
        y = A @ np.array([1.0, slope]) + 0.1 * _ar1(rng, n, phi)
        r = y - A @ np.linalg.lstsq(A, y, rcond=None)[0]
        f = ARFilter().fit(r)
        Aw, yw = f.transform(A), f.transform(y)
        beta, *_ = np.linalg.lstsq(Aw, yw, rcond=None)
        rw = yw - Aw @ beta
        sd = np.sqrt(rw @ rw / (yw.size - 2) * np.linalg.inv(Aw.T @ Aw)[1, 1])
        held += abs(beta[1] - slope) < z * sd
        b0 = np.linalg.lstsq(A, y, rcond=None)[0]
        sd0 = np.sqrt(r @ r / (n - 2) * np.linalg.inv(A.T @ A)[1, 1])
        white_held += abs(b0[1] - slope) < z * sd0
    assert 0.928 <= held / sessions <= 0.970
    assert white_held / sessions < 0.6


def test_the_filter_keeps_rows_and_kernels_consistent():
    """The filter leaves out the first q rows, and a kernel through it is the kernel
    convolved with its taps spread ``stride`` samples apart."""
    f = ARFilter(max_order=3).fit(_ar1(np.random.default_rng(3), 5000, 0.5))
    X = np.arange(20.0).reshape(10, 2)
    out = f.transform(X)
    assert out.shape == (10 - f.order_, 2)
    k = np.array([[0.25, 0.5, 0.25]])
    spread = f.kernels(k, stride=2)
    assert spread.shape == (1, 3 + 2 * f.order_)
    assert spread.sum() == pytest.approx(k.sum() * f.phi.sum())


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(min_value=-1e6, max_value=1e6, allow_nan=False), min_size=0, max_size=60))
def test_any_residuals_give_a_stable_filter(values):
    """Short, constant or wild residuals: a filter of order at most n / 20, finite, whose
    innovation variance does not exceed the residuals' own."""
    r = np.asarray(values, dtype=float)
    f = ARFilter().fit(r)
    assert 0 <= f.order_ <= max(r.size // 20, 0)
    assert np.all(np.isfinite(f.coef_))
    assert f.innovation_var_ <= f.variance_ * (1 + 1e-9) + 1e-300
    assert f.transform(r).shape == (max(r.size - f.order_, 0),)


def test_strategies_by_name():
    assert isinstance(likelihood_strategy("prewhitened"), Prewhitened)
    assert isinstance(likelihood_strategy("tempered"), Tempered)
    with pytest.raises(FitError, match="unknown likelihood"):
        likelihood_strategy("robust")


def _misfit_fit(duration_s: float, likelihood: str) -> BayesianFit:
    """A two-branch relaxing tissue fitted with a law that has no relaxation."""
    s, _ = random_session(FAMILIES["two branches"], rate_hz=1000.0, duration_s=duration_s, seed=3)
    return BayesianFit("x+xdot+xddot", grasps="none", likelihood=likelihood).fit(s)


@pytest.mark.slow
def test_a_misfitting_law_keeps_its_effective_samples_as_the_session_grows():
    """The law's misfit correlates the residuals over seconds: the batch-means weight
    counts 0.4 % of the samples; the prewhitened likelihood models that misfit and
    counts at least 2 % of them, growing at least half as fast as the session (4 times
    longer: at least twice as many; a stationary residual gives 4 times)."""
    short, long = _misfit_fit(5.0, "prewhitened"), _misfit_fit(20.0, "prewhitened")
    for est in (short, long):
        assert est.n_eff_ >= 0.02 * est.kinematics_.time.size
    assert long.n_eff_ >= 2.0 * short.n_eff_


def test_the_prewhitened_likelihood_agrees_with_the_tempered_one_on_a_law_that_fits():
    """A paper-form session fitted with its own law: residuals are the smoothed sensor
    noise alone, which the filter's weight already counts exactly, so the two
    likelihoods choose alike and give SDs within 25 % of each other."""
    s, _ = random_session(FAMILIES["paper x+xdot"], rate_hz=1000.0, duration_s=5.0, seed=4)
    fits = [BayesianFit("paper", likelihood=lk).fit(s) for lk in ("tempered", "prewhitened")]
    assert fits[0].best_.name == fits[1].best_.name == "x+xdot+xddot"
    ratio = fits[1].best_.posterior.sd / fits[0].best_.posterior.sd
    assert np.all((ratio > 0.75) & (ratio < 1.25))


def test_a_law_with_shape_parameters_is_scored_through_the_filter():
    """Laws whose columns hang on a shape (a relaxation time, a contact exponent) take
    the filter in the shape's batched first passes too, and have a finite evidence."""
    s, _ = random_session(FAMILIES["one branch"], rate_hz=500.0, duration_s=4.0, seed=5)
    est = BayesianFit(["x+maxwell+xdot+xddot", "contact+xddot"], grasps="none",
                      likelihood="prewhitened").fit(s)  # fmt: skip
    assert np.isfinite(est.best_.ln_evidence)
    assert est.best_.name == "x+maxwell+xdot+xddot"
    assert 0 < est.n_eff_ < 10 * s.time.size


def test_the_shapes_first_passes_equal_a_pass_over_the_filtered_design():
    """:class:`ShapedPass` (one node, and nodes in a batch) forms the filtered Gram
    matrix, products and position-noise correction as :func:`first_pass` does over
    the filtered design: equal to rounding."""
    s, _ = random_session(FAMILIES["one branch"], rate_hz=500.0, duration_s=4.0, seed=5)
    est = BayesianFit("x+xdot+xddot", grasps="none").fit(s)
    kin, x, sx = est.kinematics_, est.session_.position, max(est.sigma_x_, 1e-6)
    y = kin.force
    w = ARFilter(step=3).fit(y - np.convolve(y, np.ones(50) / 50, "same"))
    assert w.order_ >= 1
    fit = Context(kin, x, y, sx, 0.5, est.scales_, {}, {}, np.random.default_rng(0), whiten=w)
    law = Law.of(["x", "maxwell", "xdot", "xddot"])
    bound = law.bind({law.shape_names[0]: 0.7})
    want = first_pass(bound, kin, x, y, sx, None, None, w)
    light = ShapedPass(law, fit)
    for got in (light({law.shape_names[0]: 0.7}), light.many([bound])[0]):
        for name in ("gram", "b", "yy", "rss", "correction"):
            a, b = np.asarray(getattr(got, name)), np.asarray(getattr(want, name))
            assert np.max(np.abs(a - b)) <= 1e-12 * np.max(np.abs(b)), name
