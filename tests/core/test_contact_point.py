"""The contact point's prior reaches as far below the fitted closures as the force
across them allows a contact law of the steepest exponent in the prior."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from tissuecli.core.terms import CONTACT_POINT, EXPONENT, SessionSpan


def _span(x: np.ndarray, f: np.ndarray) -> SessionSpan:
    a, b = np.percentile(x, [5.0, 95.0])
    low, high = x <= a, x >= b
    return SessionSpan(
        dt=1e-3, cutoff_hz=10.0, duration_s=10.0,
        x_low=float(np.percentile(x, 2)), x_span=float(np.ptp(x)),
        f_ratio=float(np.median(f[low]) / np.median(f[high])),
        x_ends=(float(np.median(x[low])), float(np.median(x[high]))),
    )  # fmt: skip


@given(
    x0=st.floats(-5e-3, 5e-3),
    depth=st.floats(0.05, 20.0),
    n=st.floats(EXPONENT.prior[0], EXPONENT.prior[1]),
)
def test_the_prior_holds_the_touch_of_any_law_in_the_exponents_prior(
    x0: float, depth: float, n: float
) -> None:
    """A tissue held throughout, its closures from ``depth`` times their own span above
    the touch: the contact point lies inside the prior for every exponent in the
    exponent's prior (the steepest one sets the reach; a power law's force ratio across
    the closures gives it), down to three spans below the closures."""
    width = 2e-3
    x = x0 + depth * width + np.linspace(0.0, width, 2001)
    f = 100.0 * (x - x0) ** n
    span = _span(x, f)
    lo, hi = CONTACT_POINT.prior_range(span)
    floor = span.x_low - 3.0 * span.x_span  # the reach is capped at three spans below
    if x0 >= floor:
        assert lo <= x0 < hi
    else:
        assert math.isclose(lo, floor, rel_tol=1e-12, abs_tol=1e-15)


@given(n=st.floats(EXPONENT.prior[0], EXPONENT.prior[1]))
def test_a_grasp_read_from_the_touch_keeps_the_prior_near_it(n: float) -> None:
    """A grasp read from the touch (its force zero at the lowest closure): the prior
    reaches at most 0.6 of the closures' span below them (a quarter before), the
    steepest exponent's reading of a linear law's low end putting it 0.53 below."""
    x = np.linspace(0.0, 2e-3, 2001)
    f = 100.0 * x**n
    span = _span(x, f)
    lo, _ = CONTACT_POINT.prior_range(span)
    assert span.x_low - 0.6 * span.x_span <= lo <= span.x_low - 0.25 * span.x_span
