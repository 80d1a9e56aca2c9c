"""Dry friction's regressor averaged over a spread of speeds: the mean of its two
directions near a turn, where a second-order expansion fails."""

from __future__ import annotations

import numpy as np
import pytest

from tissuecli.core.terms import V_SMOOTH, Law


def _coulomb():
    return Law.of(["sign(xdot)"]).terms[0]


@pytest.mark.parametrize("sd", [0.0, 0.3 * V_SMOOTH, V_SMOOTH, 3 * V_SMOOTH, 30 * V_SMOOTH])
def test_the_mean_over_a_normal_spread_is_within_its_stated_bound(sd: float) -> None:
    term = _coulomb()
    e = np.random.default_rng(0).standard_normal(100_000)
    u = np.linspace(-4, 4, 17) * max(sd, V_SMOOTH)
    exact = np.array([np.mean(term(ui + sd * e)) for ui in u])
    # the docstring's bound, 0.04, plus the Monte Carlo mean's 3 SDs (1 / sqrt(1e5))
    assert np.max(np.abs(term.expected(u, sd**2) - exact)) < 0.04 + 0.01


def test_no_spread_is_the_regressor_and_a_spread_cannot_be_taken_out_of_a_step() -> None:
    term = _coulomb()
    u = np.linspace(-5e-3, 5e-3, 11)
    np.testing.assert_array_equal(term.expected(u, 0.0), term(u))
    np.testing.assert_array_equal(term.expected(u, -1e-6), term(u))
    # where a second-order expansion puts tens at a turn, the mean stays within +-1
    spread = np.full_like(u, 0.01**2)  # 10 mm/s, a smoothing window across a fast turn
    assert np.all(np.abs(term.expected(u, spread)) <= 1.0)
    assert np.max(np.abs(term(u) + 0.5 * term.curvature(u) * spread)) > 10


def test_a_smooth_regressor_keeps_its_second_order_mean() -> None:
    cubic = Law.of(["x^3"]).terms[0]
    u = np.linspace(-2e-3, 2e-3, 9)
    # E[(u + e)^3] = u^3 + 3 u var, exact at second order
    np.testing.assert_allclose(cubic.expected(u, 1e-8), u**3 + 3 * u * 1e-8, rtol=1e-5, atol=1e-15)


@pytest.mark.parametrize("sd", [0.0, V_SMOOTH, 10 * V_SMOOTH])
def test_the_mean_s_slope_is_the_derivative_of_the_mean(sd: float) -> None:
    """What the errors-in-variables correction takes for dry friction is the slope of the
    very mean the fit's column is, bounded by one over the widened smoothing speed."""
    term = _coulomb()
    u = np.linspace(-4, 4, 33) * max(sd, V_SMOOTH)
    h = 1e-4 * V_SMOOTH
    numeric = (term.expected(u + h, sd**2) - term.expected(u - h, sd**2)) / (2 * h)
    slope = term.expected_slope(u, sd**2)
    np.testing.assert_allclose(slope, numeric, rtol=1e-6, atol=1e-9 / V_SMOOTH)
    assert np.max(slope) <= 1.0 / np.sqrt(V_SMOOTH**2 + 0.5 * np.pi * sd**2) * (1 + 1e-12)


def test_a_smooth_regressor_s_slope_is_its_own() -> None:
    for name in ("xdot", "xdot|xdot|"):
        term = Law.of([name]).terms[0]
        assert not term.step
        u = np.linspace(-2e-2, 2e-2, 9)
        np.testing.assert_array_equal(term.expected_slope(u, 1e-4), term.derivative(u))
    assert _coulomb().step
