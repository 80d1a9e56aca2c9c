"""How one law is scored: the statistics its evidence and posterior are taken from."""

from __future__ import annotations

import numpy as np
import pytest

from tissuecli.core.terms import Law
from tissuecli.core.tissue import Tissue
from tissuecli.identify import BayesianFit
from tissuecli.identify.design import design
from tissuecli.sim.synth import random_session


@pytest.fixture(scope="module")
def noisy_closure_fit() -> BayesianFit:
    """A 5 kHz session whose closure is read with 40 um of noise: the acceleration
    column's noise is a large share of every law's residual."""
    tissue = Tissue(Law.paper("x", "xdot"), 350.0, 3.0, 0.05)
    session, _ = random_session(tissue, rate_hz=5000.0, seed=3, duration_s=3.0, bits=12,
                                position_noise_m=40e-6, force_noise_n=0.01)  # fmt: skip
    return BayesianFit("paper", seed=3).fit(session)


def test_a_corrected_law_is_scored_on_its_raw_residual(noisy_closure_fit):
    """The residuals about the corrected fit scatter by the force noise and the position
    noise through the columns together (variance ``s_f^2 + beta^T Sigma_u beta`` a row,
    whose best value given the data is the raw rss / n): the evidence takes that, the
    same for every law, corrected or not, so no law gains what its own columns' noise
    takes off."""
    est = noisy_closure_fit
    weight = est.n_eff_ / est.kinematics_.force.size
    corrected = [r for r in est.results_ if r.correction is not None]
    assert corrected
    for r in corrected:
        rows = est.kinematics_.force.size
        raw = r.residual_rms**2 * rows
        assert r.stats.rss == pytest.approx(weight * raw, rel=1e-9)
        # and the correction does take a share off: it is not a no-op
        assert float(r.posterior.mean @ r.correction @ r.posterior.mean) > 1e-3 * raw


def test_the_corrected_posterior_keeps_the_sandwich_spread(noisy_closure_fit):
    """Centred on the corrected coefficients with the corrected estimator's sampling
    covariance ``s^2 (A^T A - C)^-1 A^T A (A^T A - C)^-1`` (``s^2`` the raw residual
    variance at the data weight): within the 4 % a posterior mean of sigma and the
    prior's pull leave on a session of this length."""
    est = noisy_closure_fit
    r = est.best_
    assert r.correction is not None
    kin = est.kinematics_
    A = design(r.model, kin, est.session_.position, est.sigma_x_)
    G, C = A.T @ A, r.correction
    beta_c = np.linalg.solve(G - C, A.T @ kin.force)
    np.testing.assert_allclose(r.posterior.mean, beta_c, rtol=0.02)
    w = est.n_eff_ / kin.force.size
    s2 = r.residual_rms**2
    inv = np.linalg.inv(G - C)
    sd = np.sqrt(np.diag(s2 / w * inv @ G @ inv))
    np.testing.assert_allclose(r.posterior.sd, sd, rtol=0.04)
