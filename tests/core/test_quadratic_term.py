"""Quadratic damping's regressor averaged over a normal spread of speeds: exact, where
a second-order expansion steps at every turn."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import integrate, special

from tissuecli.core.terms import Law, _erf_pair, _erfc


def _quadratic():
    return Law.of(["xdot|xdot|"]).terms[0]


def _mean_by_quadrature(u: float, sd: float) -> float:
    """E[(u + e)|u + e|], e ~ N(0, sd^2), by adaptive quadrature (split at the kink)."""
    pdf = lambda v: math.exp(-0.5 * ((v - u) / sd) ** 2) / (sd * math.sqrt(2 * math.pi))  # noqa: E731
    lo, hi = u - 12 * sd, u + 12 * sd
    parts = [(lo, min(0.0, hi)), (max(0.0, lo), hi)]
    return sum(integrate.quad(lambda v: v * abs(v) * pdf(v), a, b, epsabs=0, epsrel=1e-11)[0]
               for a, b in parts if b > a)  # fmt: skip


@settings(max_examples=60, deadline=None)
@given(z=st.floats(-8.0, 8.0), sd=st.floats(1e-6, 1e2))
def test_the_mean_over_a_normal_spread_is_exact(z: float, sd: float) -> None:
    u = z * sd
    got = float(_quadratic().expected(np.array([u]), np.array([sd**2]))[0])
    want = _mean_by_quadrature(u, sd)
    # the error function to a fractional 1.2e-7 of its tail, times (u^2 + sd^2)
    assert abs(got - want) <= 2e-7 * (u**2 + sd**2) + 1e-12 * abs(want)


@settings(max_examples=60, deadline=None)
@given(z=st.floats(-8.0, 8.0), sd=st.floats(1e-6, 1e2))
def test_taking_a_spread_off_is_the_same_bias_with_the_other_sign(z: float, sd: float) -> None:
    term, u = _quadratic(), np.array([z * sd])
    up = term.expected(u, np.array([sd**2])) - term(u)
    down = term.expected(u, np.array([-(sd**2)])) - term(u)
    np.testing.assert_allclose(down, -up, rtol=1e-12, atol=0)


def test_no_spread_is_the_regressor_and_a_turn_has_no_bias() -> None:
    term = _quadratic()
    u = np.linspace(-5e-3, 5e-3, 11)
    np.testing.assert_array_equal(term.expected(u, 0.0), term(u))
    # a spread about a turn averages to nothing, either way; the odd mean is continuous
    assert term.expected(np.array([0.0]), np.array([1e-4]))[0] == 0.0
    eps = np.array([-1e-12, 1e-12])
    assert np.max(np.abs(term.expected(eps, np.array([1e-4, 1e-4])))) < 1e-13
    # the second-order expansion steps by twice the variance there
    step = term(eps) + 0.5 * term.curvature(eps) * 1e-4
    assert np.ptp(step) > 1.9e-4


def test_far_from_a_turn_it_is_the_second_order_mean() -> None:
    term, var = _quadratic(), 1e-6
    u = np.array([-0.02, -0.01, 0.01, 0.02])  # 10-20 SDs of the spread from a turn
    np.testing.assert_allclose(term.expected(u, var), term(u) + np.sign(u) * var, rtol=1e-12)


def test_the_complementary_error_function_is_within_its_stated_error() -> None:
    z = np.concatenate([np.linspace(0.0, 25.0, 20001), [np.inf]])
    want = special.erfc(z)
    np.testing.assert_allclose(_erfc(z[:-1]), want[:-1], rtol=1.2e-7, atol=0)
    assert _erfc(z[-1:])[0] == 0.0


def test_the_error_function_near_zero_keeps_its_fractional_precision() -> None:
    z = np.geomspace(1e-12, 3.0, 2001)
    erf, tail = _erf_pair(z)
    np.testing.assert_allclose(erf, special.erf(z), rtol=1.2e-7, atol=0)
    np.testing.assert_allclose(tail, special.erfc(z), rtol=1.2e-7, atol=0)
