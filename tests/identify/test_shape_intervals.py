"""A law with shape parameters: its coefficients' intervals carry the shape's uncertainty
as the continuous posterior over the shape does, not as three points per parameter."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from tissuecli.core.terms import EXPONENT
from tissuecli.identify import BayesianFit, posterior
from tissuecli.identify.posterior import Posterior
from tissuecli.identify.shapes import (
    Peak,
    ShapeGrid,
    continuous_mixture,
    hermite_interpolant,
    hermite_nodes,
    mix,
)
from tissuecli.sim.scenes import random_scene

HUNT_CROSSLEY = "contact+contact*xdot+xddot"


def _fitted_part(seed: int):  # type: ignore[no-untyped-def]
    """The first 70 % of a Hunt-Crossley scene (as the generalisation benchmark fits)."""
    session = random_scene(seed, families=["Hunt-Crossley"], max_samples=10_000).session
    t = session.time
    i = int(np.searchsorted(t, t[0] + 0.7 * (t[-1] - t[0])))
    return session.replace(t[:i], session.force[:i], session.position[:i])


@pytest.mark.parametrize("d", [1, 2])
def test_the_interpolant_passes_through_the_nodes_with_their_moments(d: int) -> None:
    rng = np.random.default_rng(0)
    peak = Peak(u=np.zeros(d), log_z=0.0, cov=np.eye(d))
    nodes, w = hermite_nodes(peak)
    values = rng.normal(size=(len(nodes), 2))
    z = np.array(list(itertools.product((-math.sqrt(3.0), 0.0, math.sqrt(3.0)), repeat=d)))
    assert np.allclose(hermite_interpolant(values, z), values)
    # its mean and variance over N(0, I) are the nodes' weighted ones (three-point
    # Gauss-Hermite integrates polynomials of degree 5 in each direction exactly)
    draws = hermite_interpolant(values, rng.standard_normal((400_000, d)))
    mean = w @ values
    var = w @ (values - mean) ** 2
    assert np.allclose(draws.mean(axis=0), mean, atol=5 * np.sqrt(var / 400_000))
    assert np.allclose(draws.var(axis=0), var, rtol=0.02)


def _point(mean: float, sd: float, rng: np.random.Generator) -> Posterior:
    beta = rng.normal(mean, sd, (2000, 1))
    samples = np.column_stack([beta, np.ones(2000)])
    return Posterior(mean=np.array([mean]), sd=np.array([sd]), ci95=np.full((1, 2), np.nan),
                     cov=np.array([[sd**2]]), sigma_mean=1.0, sigma_ci95=(1.0, 1.0),
                     ln_evidence=0.0, outside=0.0, method="test", samples=samples)  # fmt: skip


def test_a_coefficient_that_follows_the_shape_gets_a_gaussian_interval() -> None:
    """A coefficient linear in a Gaussian shape parameter, nearly exact given it: its 95 %
    interval spans 1.96 SDs either side. Three narrow components at the nodes put its
    quantiles at sqrt(3) = 1.73 SDs."""
    rng = np.random.default_rng(1)
    peak = Peak(u=np.array([0.5]), log_z=0.0, cov=np.array([[0.01]]))
    nodes, w = hermite_nodes(peak)
    slope = 10.0  # the coefficient per unit of shape
    parts = [_point(slope * (float(u[0]) - 0.5), 1e-3, rng) for u in nodes]
    mixed = mix(parts, w, rng)
    sd = slope * 0.1
    assert mixed.ci95[0, 1] < 1.8 * sd  # the nodes' quantile
    grid = ShapeGrid(nodes=[{"n": 0.0}], log_weight=np.zeros(1), ranges={"n": (-10.0, 10.0)},
                     spacing=np.array([1.0]), params={"n": EXPONENT})  # fmt: skip
    out = continuous_mixture(mixed, parts, peak, grid, np.array([False]), rng)
    # 4000 draws put each 2.5 % quantile within 0.042 SDs (1 SD of its Monte Carlo error)
    lo, hi = out.ci95[0]
    assert hi / sd == pytest.approx(1.96, abs=4 * 0.042)
    assert -lo / sd == pytest.approx(1.96, abs=4 * 0.042)


def test_the_contact_stiffness_interval_spans_its_shape_spread() -> None:
    """On a Hunt-Crossley session the contact stiffness (N/m^n) moves with the exponent:
    nearly all of its SD is the shape's (95 times its SD given the shape). Its interval
    spans 1.96 SDs either side up to Monte Carlo error (0.03 SDs in the width) and the
    marginal's slight skew; over three nodes per parameter it spanned 1.74."""
    best = BayesianFit(HUNT_CROSSLEY, seed=7028).fit(_fitted_part(7028)).best_
    post = best.posterior
    assert post is not None
    at_shape = np.array(post.diagnostics["at_shape"]["sd"])
    assert post.sd[0] > 20 * at_shape[0]
    width = (post.ci95[:, 1] - post.ci95[:, 0]) / (2 * post.sd)
    assert width[0] > 1.88


def test_exact_draws_under_a_deep_cut_keep_the_shape_marginalised(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Where the positivity bound cuts a node's posterior deeper than the search draws
    exactly (the inertia's, by 97 % at some shape nodes of this session; the search's
    limit is raised here so that it does so on any prior over the contact point), the
    chosen law's posterior is drawn again exactly and keeps the shape's spread (the
    contact stiffness's SD about 58 times its SD given the shape) instead of falling
    back to draws at the point shape alone (an interval 0.6 % wide that missed the
    truth by 80 of its SDs)."""
    monkeypatch.setattr(posterior, "MIN_ACCEPTANCE", 0.5)
    best = BayesianFit(HUNT_CROSSLEY, seed=7024).fit(_fitted_part(7024)).best_
    post = best.posterior
    assert post is not None and post.diagnostics["exact"]
    assert "at_shape" in post.diagnostics, "drawn at the point shape alone"
    at_shape = np.array(post.diagnostics["at_shape"]["sd"])
    assert post.sd[0] > 10 * at_shape[0]
    assert post.outside > 0.5  # the cut this is about


def test_a_shape_posterior_cut_by_the_prior_gives_a_cut_interval() -> None:
    """A peak on the prior's edge: half its Gaussian lies outside. The coefficient, linear
    in the shape, then follows a half-normal: its 95 % interval runs from the 2.5 % to the
    97.5 % quantile of |N(0, 1)| (0.031 and 2.241 SDs), its mean sqrt(2 / pi)."""
    rng = np.random.default_rng(2)
    peak = Peak(u=np.array([1.5]), log_z=0.0, cov=np.array([[0.01]]))
    nodes, w = hermite_nodes(peak)
    slope, sd = 10.0, 0.1
    parts = [_point(slope * (float(u[0]) - 1.5), 1e-4, rng) for u in nodes]
    inside = [i for i, u in enumerate(nodes) if u[0] >= 1.5]
    mixed = mix([parts[i] for i in inside], w[inside], rng)
    grid = ShapeGrid(nodes=[{"n": 1.5}], log_weight=np.zeros(1), ranges={"n": (1.5, 2.5)},
                     spacing=np.array([0.25]), params={"n": EXPONENT})  # fmt: skip
    out = continuous_mixture(mixed, parts, peak, grid, np.array([False]), rng, truncated=True)
    scale = slope * sd
    lo, hi = out.ci95[0] / scale
    # Monte Carlo: about 2000 of 4000 draws kept; the 97.5 % quantile of a half-normal within
    # 0.06 (1 SD of its error), the 2.5 % within 0.002
    assert hi == pytest.approx(2.241, abs=4 * 0.06)
    assert lo == pytest.approx(0.031, abs=4 * 0.002)
    assert out.mean[0] / scale == pytest.approx(math.sqrt(2 / math.pi), abs=0.05)
