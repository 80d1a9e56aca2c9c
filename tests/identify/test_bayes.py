"""The choice among scored laws: a term the fit reports as not identified is never kept,
its law's probability passing to the law without it."""

from __future__ import annotations

from tissuecli.core.terms import Law
from tissuecli.identify import BayesianFit
from tissuecli.identify.scoring import ModelResult


def _result(names: list[str], ln_z: float, p: float, flags: list[str] | None = None) -> ModelResult:
    law = Law.of(names)
    return ModelResult(model=law, ln_evidence=ln_z, probability=p, flags=list(flags or []))


def test_the_probability_of_a_law_with_an_unidentified_term_passes_to_the_law_without_it():
    branch = _result(["x", "maxwell", "xdot", "xddot"], 10.0, 0.9, ["Km1 not identified (...)"])
    plain = _result(["x", "xdot", "xddot"], 8.0, 0.1)
    other = _result(["x^3", "xdot", "xddot"], 9.0, 0.0)
    out = BayesianFit()._drop_unidentified([branch, plain, other], fit=None)  # type: ignore[arg-type]
    assert len(out) == 3
    assert branch.probability == 0.0 and plain.probability == 1.0
    assert (
        branch.flags[-1]
        == "not chosen: Km1 not identified; its probability counts for x+xdot+xddot"
    )


def test_a_term_goes_with_the_term_it_requires():
    # without contact, contact damping has no meaning: the law left is x+xddot
    both = _result(["x", "contact", "contact*xdot", "xddot"], 10.0, 1.0, ["Kc not identified"])
    spring = _result(["x", "xddot"], 5.0, 0.0)
    out = BayesianFit()._drop_unidentified([both, spring], fit=None)  # type: ignore[arg-type]
    assert [r.name for r in out] == [both.name, "x+xddot"]
    assert spring.probability == 1.0


def test_no_sub_law_far_behind_an_identified_law_takes_the_probability():
    # a contact law whose coefficient trades with the offset: far ahead of contact alone,
    # its only identified sub-law, and of which a cubic law is not a sub-law
    both = _result(["contact", "offset"], -618.2, 0.99, ["Kc not identified (...)"])
    alone = _result(["contact"], -925.1, 0.0)
    cubic = _result(["x^3", "offset"], -619.2, 0.008)
    slow = _result(["x", "maxwell"], -623.9, 0.002)
    # what contact is at n = 1, a spring and an offset, no better identified here
    spring = _result(["x", "offset"], -700.0, 0.0, ["K not identified (...)"])
    laws = [both, alone, cubic, slow, spring]
    out = BayesianFit()._drop_unidentified(laws, fit=None)  # type: ignore[arg-type]
    assert both.probability == 0.0 and alone.probability == 0.0
    # shared as though it had not been scored
    assert abs(cubic.probability - 0.8) < 1e-12 and abs(slow.probability - 0.2) < 1e-12
    assert both.flags[-1] == (
        "not chosen: Kc not identified, and no law without it explains the data as well "
        "as x^3+offset: its probability is shared by the other laws"
    )
    assert abs(sum(r.probability for r in out) - 1.0) < 1e-12


def test_a_contact_law_nests_a_spring_and_an_offset():
    # contact at n = 1 is Kc (x - x0): the spring with an offset is one of its sub-laws,
    # and it is what a contact law whose coefficient is not identified stands for
    both = _result(["contact", "offset"], -618.2, 0.99, ["Kc not identified (...)"])
    alone = _result(["contact"], -925.1, 0.0)
    spring = _result(["x", "offset"], -619.2, 0.01)
    BayesianFit()._drop_unidentified([both, alone, spring], fit=None)  # type: ignore[arg-type]
    assert both.probability == 0.0 and spring.probability == 1.0
    assert both.flags[-1] == "not chosen: Kc not identified; its probability counts for x+offset"


def test_a_relaxation_branch_nests_a_spring_and_an_offset():
    # a branch that never relaxes is, from rest, Km (x - x(0)): a spring and an offset
    import numpy as np

    x = 2e-3 + 1e-3 * np.sin(np.arange(2000) * 0.01)
    never = Law.of(["x", "maxwell"]).bind({"tau1": 1e12}).terms[1]
    column = never.series(1e-3, x, np.gradient(x, 1e-3), np.zeros_like(x))
    np.testing.assert_allclose(column, x - x[0], rtol=0, atol=1e-12)
    # so the spring with an offset is one of its law's sub-laws: a continuous session
    # whose branch and inertia are not identified, where the offset is what the data need
    both = _result(["x", "maxwell", "xdot", "xddot"], 10.0, 0.9, ["Km1 not identified (...)"])
    plain = _result(["x", "xdot", "xddot"], 8.0, 0.1)
    offset = _result(["x", "xdot", "xddot", "offset"], 9.0, 0.0)
    BayesianFit()._drop_unidentified([both, plain, offset], fit=None)  # type: ignore[arg-type]
    assert both.probability == 0.0 and offset.probability == 0.9 and plain.probability == 0.1
    assert both.flags[-1] == (
        "not chosen: Km1 not identified; its probability counts for x+xdot+xddot+offset"
    )


def _cv(names: list[str], ln_z: float, p: float, cv: float) -> ModelResult:
    r = _result(names, ln_z, p)
    r.cv_rms = cv
    return r


def test_a_law_that_predicts_no_better_than_a_smaller_one_within_decisive_evidence_loses():
    # a grasp session of x^3+xdot+xddot whose damping the evidence split between
    # xdot|xdot| and dry friction, 1.7 nats ahead, predicting held-out blocks no better
    split = _cv(["x^3", "xdot|xdot|", "sign(xdot)", "xddot"], 1990.13, 0.760, 0.014451)
    truth = _cv(["x^3", "xdot", "xddot"], 1988.40, 0.135, 0.014434)
    friction = _cv(["x^3", "xdot", "sign(xdot)", "xddot"], 1988.14, 0.105, 0.014448)
    BayesianFit()._parsimony([split, truth, friction], fit=None)  # type: ignore[arg-type]
    assert split.probability == 0.0
    assert abs(truth.probability - 0.895) < 1e-12 and friction.probability == 0.105
    assert split.flags[-1].startswith("not chosen: x^3+xdot+xddot has fewer parameters")


def test_a_law_that_predicts_better_or_is_decisively_ahead_is_kept():
    better = _cv(["x", "maxwell", "xdot", "xddot"], 10.0, 0.9, 0.010)
    plain = _cv(["x", "xdot", "xddot"], 8.0, 0.1, 0.011)
    BayesianFit()._parsimony([better, plain], fit=None)  # type: ignore[arg-type]
    assert better.probability == 0.9 and plain.probability == 0.1
    # odds of 100:1 or more are a decision, whatever five blocks say
    ahead = _cv(["x", "maxwell", "xdot", "xddot"], 20.0, 1.0, 0.012)
    plain = _cv(["x", "xdot", "xddot"], 8.0, 0.0, 0.011)
    BayesianFit()._parsimony([ahead, plain], fit=None)  # type: ignore[arg-type]
    assert ahead.probability == 1.0


def test_laws_whose_posteriors_all_lie_beyond_the_positivity_bound_get_finite_probabilities():
    # the force climbs 300 N while the jaw closes and opens again: every posterior of a
    # passive law lies below zero, so no evidence is finite and none may turn into NaN
    import warnings

    import numpy as np

    from tissuecli.core.session import Session

    t = np.arange(300) * 1e-3
    position = 2e-3 * (1 - np.cos(6 * np.pi * t)) + np.random.default_rng(0).normal(0, 2e-6, 300)
    session = Session(t, np.arange(300.0), position)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        fit = BayesianFit(forms="x,xdot").fit(session)
    probabilities = [r.probability for r in fit.results_]
    assert all(np.isfinite(probabilities)) and abs(sum(probabilities) - 1.0) < 1e-12
    assert any(w.startswith("no law has finite evidence") for w in fit.warnings_)
