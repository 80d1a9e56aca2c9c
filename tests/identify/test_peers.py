"""Peer estimators (PySINDy, lmfit + emcee) and the Cramér-Rao bound in benchmarks/peers.py.

PySINDy and lmfit are an optional extra (``pip install -e ".[bench]"``): the
tests that need them are skipped without them; the bound's tests always run.
"""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.peers import PeerResult, cramer_rao, lmfit_emcee_fit, pysindy_fit
from tissuecli.core.session import Session
from tissuecli.core.tissue import DEFAULT_TISSUE
from tissuecli.identify import BayesianFit
from tissuecli.sim.synth import ForcepsModel, Sensors, synthesize

#: 16-bit ADC and no analogue noise: only a fine quantisation remains.
CLEAN = Sensors(bits=16, force_noise_n=0.0, position_noise_m=0.0)


@pytest.fixture(scope="module")
def clean_session() -> Session:
    """A 10 s, 1 kHz session of the default x,xdot tissue through a clean 16-bit ADC."""
    session, _ = synthesize(ForcepsModel(seed=3, sensors=CLEAN), 10.0)
    return session


def test_cramer_rao_is_not_beaten_by_bayesian_fit() -> None:
    """Over 10 seeds of a 12-bit session, the SD of BayesianFit's K is at least 0.8 CRB.

    The sample SD of 10 estimates has a relative standard error of about
    1 / sqrt(2 (10 - 1)) = 24 %, so an estimator that attained the bound could
    show a sample SD near 0.8 CRB by chance; a sample SD well below that would
    mean beating the bound, which no unbiased estimator can. (BayesianFit also
    differentiates noisy positions, which the bound leaves out, so it is not
    expected to reach the bound either.) The seeds are fixed: the test is
    deterministic.
    """
    truth = DEFAULT_TISSUE
    estimates = []
    for seed in range(10):
        model = ForcepsModel(tissue=truth, seed=seed, sensors=Sensors(bits=12))
        session, _ = synthesize(model, 10.0)
        fit = BayesianFit().fit(session)
        (result,) = [r for r in fit.results_ if r.name == truth.law.name]
        assert result.posterior is not None
        estimates.append(result.posterior.mean[0])
    crb = cramer_rao(truth, ForcepsModel(tissue=truth, sensors=Sensors(bits=12)), 10.0)
    assert np.all(np.isfinite(crb)) and np.all(crb > 0)
    assert np.std(estimates, ddof=1) >= 0.8 * crb[0]


def test_cramer_rao_shrinks_as_one_over_root_duration() -> None:
    model = ForcepsModel(sensors=Sensors(bits=12))
    ratio = cramer_rao(DEFAULT_TISSUE, model, 10.0) / cramer_rao(DEFAULT_TISSUE, model, 40.0)
    assert ratio.shape == (3,)
    np.testing.assert_allclose(ratio, 2.0, rtol=0.1)


def test_cramer_rao_follows_the_force_noise() -> None:
    """Halving the force noise (with a fine ADC) halves the bound: it is linear in sigma."""
    fine = ForcepsModel(sensors=Sensors(bits=16, force_noise_n=0.01))
    finer = ForcepsModel(sensors=Sensors(bits=16, force_noise_n=0.005))
    ratio = cramer_rao(DEFAULT_TISSUE, fine, 10.0) / cramer_rao(DEFAULT_TISSUE, finer, 10.0)
    np.testing.assert_allclose(ratio, 2.0, rtol=0.01)


def check(result: PeerResult, name: str) -> None:
    """The common contract of a peer on the clean x,xdot session."""
    assert result.name == name
    assert result.params.shape == (3,)
    assert np.all(np.isfinite(result.params))
    assert result.seconds > 0
    assert result.model == DEFAULT_TISSUE.law.name
    assert result.params[0] == pytest.approx(DEFAULT_TISSUE.K, rel=0.01)


def test_pysindy_finds_the_form_and_stiffness(clean_session: Session) -> None:
    pytest.importorskip("pysindy")
    check(pysindy_fit(clean_session, seed=0), "pysindy-stlsq")


def test_lmfit_emcee_finds_the_form_and_stiffness(clean_session: Session) -> None:
    pytest.importorskip("lmfit")
    # a short chain keeps the test quick; the benchmark runs the default 2000 steps
    result = lmfit_emcee_fit(clean_session, steps=300, seed=0)
    check(result, "lmfit-emcee")
    assert "BIC" in result.note
