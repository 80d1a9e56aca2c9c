"""Evidence that cannot break: finite, possible ln Z on the protocols laboratories run
(constant-speed pulls, ramp-and-hold relaxation), truncation corrections in logarithms,
untrusted evidence set aside and never chosen."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from tissuecli.identify import BayesianFit
from tissuecli.identify.orthant import orthant_log_probability, tail_log_probability
from tissuecli.identify.posterior import ExactPosterior, Prior, SufficientStats

from .lab_protocols import constant_speed, relaxation

#: no evidence of Gaussian data may exceed this many nats per sample in magnitude (a
#: sample's log density is -ln(sigma sqrt(2 pi e)): 20 nats is a residual of 1e-9 of
#: the noise, or a noise of e^20 of the signal)
PER_SAMPLE = 20.0


def _sane(est: BayesianFit) -> None:
    """Every evaluated ln Z finite, within PER_SAMPLE nats per sample, and below the
    likelihood's maximum; every probability finite and summing to one."""
    n = est.kinematics_.force.size
    for r in est.results_:
        assert math.isfinite(r.ln_evidence), r.name
        assert abs(r.ln_evidence) <= PER_SAMPLE * n, (r.name, r.ln_evidence)
        if r.stats is not None:
            assert r.ln_evidence <= r.stats.max_log_likelihood() + 3.0, r.name
    prob = np.array([r.probability for r in est.results_])
    assert np.all(np.isfinite(prob)) and prob.sum() == pytest.approx(1.0)


def _terms(est: BayesianFit) -> set[str]:
    return {t.name for t in (est.best_.family or est.best_.model).terms}


@pytest.mark.parametrize(
    ("damping", "offset", "position_noise"),
    [(0.0, 0.0, 2e-6), (2.0, 0.1, 0.0)],
)
def test_constant_speed_pull_keeps_the_evidence_sane(damping, offset, position_noise):
    """A linear specimen pulled at constant speed (350 N/m, 10 mN noise, 1 kHz, 10 s,
    1 -> 3 mm): once chosen with ln Z 1e21, a 2 N friction and 30 kg of inertia. Now
    every ln Z is possible, the design is named in one line, and the law uses the
    stiffness and the one column speed terms and offset share (within 2 %)."""
    s, truth = constant_speed(3, damping=damping, offset=offset, position_noise=position_noise)
    est = BayesianFit(grasps="none").fit(s)
    _sane(est)
    line = next(w for w in est.warnings_ if w.startswith("constant speed:"))
    assert "are one column" in line and "M not excited" in line
    shared = {"xdot", "xdot|xdot|", "sign(xdot)", "offset"}
    assert _terms(est) <= {"x"} | shared
    assert len(_terms(est) & shared) <= 1
    k = est.best_.posterior.mean[0]
    assert k == pytest.approx(truth["K"], rel=0.02)


def test_ramp_and_hold_recovers_the_standard_linear_solid():
    """A spring beside one Maxwell branch (tau 1.5 s), ramped 1 s and held 19 s at
    500 Hz: once a contact law with 9-35 kg of inertia at ln Z -7 for 10,000 samples;
    the data weight no longer collapses, and the law is the truth's."""
    s, truth = relaxation(1)
    est = BayesianFit(grasps="none").fit(s)
    _sane(est)
    assert est.n_eff_ > 0.05 * s.time.size
    assert est.best_.name == "x+maxwell"
    post = est.best_.posterior
    assert post.mean[0] == pytest.approx(truth["K"], rel=0.02)
    assert post.mean[1] == pytest.approx(truth["K1"], rel=0.05)


def test_evidence_survives_cancellation_in_the_residual():
    """Columns of condition 1e8 that explain all but 1e-9 of y: ``yy - b G^-1 b``
    cancels to rounding; the evidence must stay below the likelihood's maximum."""
    rng = np.random.default_rng(0)
    t = np.linspace(0.0, 1.0, 5000)
    A = np.column_stack([1.0 + t, 1.0 + t + 1e-8 * t**2, np.ones_like(t)]) * 1e3
    y = A @ np.array([1.0, 2.0, 3.0]) + 1e-6 * rng.standard_normal(t.size)
    st = SufficientStats.from_data(A, y)
    exact = ExactPosterior(st, Prior(np.array([1e9, 1e9, 1e9]), np.zeros(3, bool)))
    assert exact.ln_z_untruncated <= st.max_log_likelihood()
    assert st.least_squares_rss() == pytest.approx(t.size * 1e-12, rel=0.1)


@pytest.mark.parametrize("m", [-5.0, -30.0, -300.0])
def test_orthant_mass_in_logarithms(m):
    """Masses far below 1e-300 keep their logarithm; Laplace's tail estimate agrees in
    the deep tail (exact as the mass goes to zero)."""
    ln_p, err = orthant_log_probability(np.array([m]), np.array([[1.0]]))
    assert ln_p == pytest.approx(float(stats.norm.logcdf(m)), rel=1e-12)
    mean = np.array([m, m / 2, 1.0])
    cov = np.eye(3)
    ln_p, err = orthant_log_probability(mean, cov)
    exact = float(np.sum(stats.norm.logcdf(mean)))
    assert ln_p == pytest.approx(exact, abs=1e-3 * abs(exact) + 1e-3)
    if m <= -30:
        assert tail_log_probability(mean, cov) == pytest.approx(exact, abs=0.05)


def test_a_posterior_far_beyond_its_bound_is_not_evaluated():
    """Data that want a passive coefficient 40 SDs below zero: the closed form times its
    orthant mass is no longer the evidence, and the law says so."""
    rng = np.random.default_rng(1)
    x = rng.standard_normal(400)
    A = np.column_stack([x, np.ones_like(x)])
    y = -2.0 * x + 0.05 * rng.standard_normal(x.size)
    st = SufficientStats.from_data(A, y)
    prior = Prior(np.array([10.0, 10.0]), np.array([True, False]))
    assert "positivity bounds keep" in ExactPosterior(st, prior).untrusted()
    ok = SufficientStats.from_data(A, -y)
    assert ExactPosterior(ok, prior).untrusted() == ""
