"""The hierarchical model of sessions within specimens within groups: its closed form
against the dense multivariate normal, its calibration on studies drawn from itself,
its Bayes factor for one tissue, and classification."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from tissuecli.core.errors import FitError
from tissuecli.core.terms import Law
from tissuecli.core.tissue import Tissue
from tissuecli.identify.hierarchy import Estimates, Hierarchy, steady_force


def draw_study(
    rng: np.random.Generator,
    groups: int,
    specimens: int,
    sessions: int,
    mu: np.ndarray,
    omega: float,
    tau: float,
) -> Estimates:
    """Session posteriors drawn from the model itself: each session's posterior SD drawn
    between 0.01 and 0.1, its mean from N(theta, v)."""
    vals, var, gs, ss = [], [], [], []
    for g in range(groups):
        for k in range(specimens):
            eta = rng.normal(mu[g], tau)
            for _ in range(sessions):
                v = rng.uniform(0.01, 0.1) ** 2
                vals.append(rng.normal(rng.normal(eta, omega), math.sqrt(v)))
                var.append(v)
                gs.append(f"g{g}")
                ss.append(f"s{k}")
    return Estimates.of(vals, var, gs, ss)


def test_closed_form_is_the_dense_normal() -> None:
    rng = np.random.default_rng(3)
    e = draw_study(rng, 3, 3, 4, np.array([0.0, 0.2, -0.1]), 0.05, 0.1)
    h = Hierarchy(prior_mean=0.05, prior_sd=0.4, upper=0.5, grid=9).fit(e)
    ll, *_ = h._grid_loglik(e.specimen_group, len(e.groups))
    for i, j in ((0, 0), (4, 6), (8, 3)):
        om, tau = h.omega_[i], h.tau_[j]
        z_spec = np.eye(len(e.specimens))[e.specimen]
        z_group = np.eye(len(e.groups))[e.group]
        cov = np.diag(e.var + om**2) + tau**2 * z_spec @ z_spec.T
        cov += 0.4**2 * z_group @ z_group.T
        dense = stats.multivariate_normal(np.full(e.value.size, 0.05), cov).logpdf(e.value)
        assert ll[i, j] == pytest.approx(dense, rel=1e-10, abs=1e-8)


def test_prob_greater_is_calibrated() -> None:
    """Across studies drawn from the prior, events given probability p happen at rate p:
    in each fifth of [0, 1] the observed rate is within 3.5 binomial SDs of the mean
    predicted probability (all five bins: a false alarm under 0.5 % of the time)."""
    rng = np.random.default_rng(20261125)
    upper, s0 = 0.3, 0.15
    ps, hits = [], []
    for _ in range(150):
        omega, tau = rng.uniform(0, upper, 2)
        mu = rng.normal(0.0, s0, 4)
        e = draw_study(rng, 4, 5, 4, mu, omega, tau)
        h = Hierarchy(prior_mean=0.0, prior_sd=s0, upper=upper, grid=40).fit(e)
        for a in range(4):
            for b in range(a + 1, 4):
                ps.append(h.prob_greater(a, b))
                hits.append(mu[a] > mu[b])
    p, hit = np.array(ps), np.array(hits)
    bins = np.minimum((p * 5).astype(int), 4)
    for i in range(5):
        m = bins == i
        assert m.sum() >= 30
        pred, seen = p[m].mean(), hit[m].mean()
        se = math.sqrt(max(np.mean(p[m] * (1 - p[m])), 1e-4) / m.sum())
        assert abs(seen - pred) < 3.5 * se, (i, m.sum(), pred, seen, se)


def test_same_tissue_is_judged_same() -> None:
    """Two groups with one mean, among others that differ: the Bayes factor favours one
    tissue in at least 90 % of 100 studies; groups a prior SD apart are told apart."""
    rng = np.random.default_rng(7)
    same = differ = 0
    for _ in range(100):
        mu = rng.normal(0.0, 0.5, 4)
        mu[1] = mu[0]
        e = draw_study(rng, 4, 8, 3, mu, 0.05, 0.1)
        h = Hierarchy(prior_mean=0.0, prior_sd=0.5, upper=0.5, grid=32).fit(e)
        same += h.ln_bayes_same(0, 1) > 0
        mu[1] = mu[0] + 0.5
        e = draw_study(rng, 4, 8, 3, mu, 0.05, 0.1)
        h = Hierarchy(prior_mean=0.0, prior_sd=0.5, upper=0.5, grid=32).fit(e)
        differ += h.ln_bayes_same(0, 1) < 0
    assert same >= 90
    assert differ >= 90


def test_intervals_and_specimens() -> None:
    rng = np.random.default_rng(11)
    mu = np.array([1.0, 1.3])
    e = draw_study(rng, 2, 6, 5, mu, 0.02, 0.05)
    h = Hierarchy().fit(e)
    mean, lo, hi = h.difference_interval(1, 0)
    assert lo < mean < hi and lo < 0.3 < hi
    assert h.prob_greater("g1", "g0") > 0.99
    for g in range(2):
        lo, hi = h.group_interval(g)
        assert lo < h.group_mean_[g] < hi
    assert h.specimen_mean_.shape == (12,) and np.all(h.specimen_sd_ > 0)
    with pytest.raises(FitError, match="no group"):
        h.prob_greater("liver", "g0")


def test_classify_picks_the_group_of_its_mean() -> None:
    rng = np.random.default_rng(5)
    e = draw_study(rng, 3, 6, 4, np.array([0.0, 0.5, 1.0]), 0.03, 0.05)
    h = Hierarchy().fit(e)
    p = h.predict([0.0, 0.5, 1.0, 0.25], [1e-4] * 4)
    assert p.shape == (4, 3)
    np.testing.assert_allclose(p.sum(axis=1), 1.0)
    assert list(np.argmax(p[:3], axis=1)) == [0, 1, 2]
    assert 0.2 < p[3, 0] < 0.8 and 0.2 < p[3, 1] < 0.8


def test_steady_force_is_the_law_at_constant_speed() -> None:
    tissue = Tissue(Law.of(["x", "x^3", "xdot", "xddot", "offset"]), 300.0, 5e6, 3.0, 0.05, 0.2)
    cov = np.diag([4.0, 1e10, 0.01, 1e-4, 1e-4])
    f, var = steady_force(tissue.law, tissue.coef, cov, 3e-3, 0.02)
    assert f == pytest.approx(300 * 3e-3 + 5e6 * 27e-9 + 3 * 0.02)  # no offset, no mass
    assert var == pytest.approx(4 * 9e-6 + 1e10 * (27e-9) ** 2 + 0.01 * 4e-4)
    relax = Law.of(["x", "maxwell", "xdot", "xddot"]).bind({"tau1": 0.5})
    f, _ = steady_force(relax, [300.0, 200.0, 2.0, 0.05], np.eye(4), 3e-3, 0.02)
    assert f == pytest.approx(300 * 3e-3 + 200 * 0.5 * 0.02 + 2 * 0.02)
