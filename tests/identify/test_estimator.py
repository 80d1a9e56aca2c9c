"""What the estimators share: hyperparameters read and set in the scikit-learn manner,
from the signature of ``__init__``, and one vocabulary for what a fit found."""

from __future__ import annotations

import inspect

import numpy as np
import pytest

from tissuecli.core.errors import FitError
from tissuecli.core.tissue import Tissue
from tissuecli.identify import BayesianFit, WindowedPinv
from tissuecli.identify.estimator import Estimator
from tissuecli.identify.search import ExhaustiveSearch
from tissuecli.sim.families import FAMILIES
from tissuecli.sim.synth import random_session

ESTIMATORS = [BayesianFit, WindowedPinv]


@pytest.mark.parametrize("cls", ESTIMATORS)
def test_parameters_are_the_keywords_of_init_with_their_defaults(cls: type[Estimator]):
    sig = inspect.signature(cls.__init__)
    expected = {k: p.default for k, p in sig.parameters.items() if k != "self"}
    assert cls().get_params() == expected


def test_search_is_a_hyperparameter_like_the_others():
    est = BayesianFit()
    assert est.get_params()["search"] == "greedy"
    exhaustive = ExhaustiveSearch(max_branches=1)
    assert est.set_params(search=exhaustive, seed=4) is est
    assert est.search is exhaustive and est.seed == 4
    assert "search=ExhaustiveSearch(max_branches=1)" in repr(est)
    assert "search" not in repr(BayesianFit())
    # what a clone does: a new estimator from the parameters, equal in every one
    copy = type(est)(**est.get_params())
    assert copy.get_params() == est.get_params() and copy is not est


@pytest.mark.parametrize("cls", ESTIMATORS)
def test_an_unknown_parameter_is_refused_with_the_choices(cls: type[Estimator]):
    est = cls()
    with pytest.raises(FitError, match="no parameter 'windw'.*differentiator"):
        est.set_params(windw=2)
    assert est.get_params() == cls().get_params()  # nothing set on the way


def test_a_parameter_set_after_a_fit_counts_at_the_next_fit():
    s, _ = random_session(FAMILIES["paper x+xdot"], rate_hz=500.0, seed=2, duration_s=3.0)
    est = BayesianFit("x,xdot").fit(s)
    before = est.best_.name
    est.set_params(forms="x^3,xdot")
    assert est.best_.name == before  # the fit made stands
    assert est.fit(s).best_.name == "x^3+xdot+xddot"


def test_both_estimators_answer_in_one_vocabulary():
    s, _ = random_session(FAMILIES["paper x+xdot"], rate_hz=500.0, seed=3, duration_s=4.0)
    fitted = [BayesianFit("x,xdot").fit(s), WindowedPinv("x,xdot", window_s=1.0).fit(s)]
    for est in fitted:
        p = len(est.law_.terms)
        assert est.law_.name == "x+xdot+xddot"
        assert est.coef_.shape == est.coef_sd_.shape == (p,)
        assert est.coef_ci95_.shape == (p, 2)
        assert np.all(est.coef_ci95_[:, 0] <= est.coef_ci95_[:, 1])
        assert isinstance(est.tissue_, Tissue) and est.tissue_.law == est.law_
        np.testing.assert_allclose(est.tissue_.coef, est.coef_)
        assert isinstance(est.warnings_, list)
        assert est.predict().shape == est.kinematics_.time.shape
        assert est.predict(s).shape == s.time.shape
        assert 0.9 < est.score() <= 1.0
    bayes, pinv = fitted
    np.testing.assert_allclose(bayes.coef_, pinv.coef_, rtol=0.3)
