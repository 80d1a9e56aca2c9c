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
