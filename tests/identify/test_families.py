"""The structure search over families of laws: it finds the true structure where the
families are clearly apart, samples shapes of more than two parameters with emcee, and
never samples a structure decisively behind."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tissuecli.core.terms import Law
from tissuecli.core.tissue import Tissue
from tissuecli.formats.params import document, tissue_from_dict
from tissuecli.identify import BayesianFit, fit_session
from tissuecli.sim.families import FAMILIES as ALL
from tissuecli.sim.synth import random_session

FAMILIES = {
    name: ALL[name]
    for name in (
        "one branch",
        "Hunt-Crossley",
        "friction+offset",
        "hardening x+x^3",
        "two branches",
    )
}

THREE = Tissue(
    Law.of(["x", "maxwell", "maxwell", "maxwell", "xdot", "xddot"]).bind(
        {"tau1": 0.05, "tau2": 0.4, "tau3": 2.0}
    ),
    300.0,
    150.0,
    150.0,
    100.0,
    2.0,
    0.05,
)


def _session(tissue: Tissue, rate_hz: float = 500.0, duration_s: float = 8.0, seed: int = 2):
    return random_session(tissue, rate_hz=rate_hz, duration_s=duration_s, seed=seed, bits=12)[0]


@pytest.mark.parametrize("family", list(FAMILIES))
def test_the_search_finds_the_true_structure(family: str) -> None:
    tissue = FAMILIES[family]
    est = BayesianFit().fit(_session(tissue))
    assert est.best_.name == tissue.law.name
    # each of these families stands decisively (100:1) ahead of the next structure
    assert est.results_[0].ln_evidence - est.results_[1].ln_evidence > np.log(100.0)


def test_three_branches_are_sampled_by_emcee_with_diagnostics() -> None:
    law = Law.of(["x", "maxwell", "maxwell", "maxwell", "xdot", "xddot"])
    outcome = fit_session(_session(THREE, rate_hz=250.0, duration_s=10.0), forms=law.name)
    best = outcome.bayes.best_
    diag = best.shape_sampler
    assert diag is not None and diag["status"] == "sampled"
    assert len(diag["tau"]) == 3 and all(t > 0 for t in diag["tau"])
    assert 0.1 < diag["acceptance"] < 0.9  # a sampler that moves and is not lost
    assert diag["samples"] > 0 and diag["steps"] >= 400
    assert diag["converged"] == (diag["steps"] >= diag["times"] * max(diag["tau"]))
    assert best.posterior.diagnostics["shape_emcee"] is diag  # what the parameter file keeps
    for name, true in THREE.law.shape.items():
        sp = best.shape_posterior[name]
        assert sp["method"] == "emcee" and sp["tau_steps"] > 0
        # the truth within 4.5 posterior SDs: a two-sided 1e-5 event for a Gaussian,
        # with room for the chain's Monte Carlo error in the SD
        assert abs(sp["mean"] - true) < 4.5 * sp["sd"], name
    assert "shape sampled by emcee" in best.reason
    # the parameter file keeps the diagnostics and reads back
    doc = json.loads(json.dumps(document(outcome)))
    assert doc["laws"][law.name]["sampler"]["shape_emcee"]["steps"] == diag["steps"]
    assert [e["method"] for e in doc["law"]["shape"]] == ["emcee"] * 3
    assert tissue_from_dict(doc).law.shape == pytest.approx(
        {n: sp["mean"] for n, sp in best.shape_posterior.items()}, rel=1e-12
    )


def test_structures_decisively_behind_are_not_sampled() -> None:
    tissue = FAMILIES["Hunt-Crossley"]
    three = Law.of(["x", "maxwell", "maxwell", "maxwell", "xdot", "xddot"])
    est = BayesianFit(forms=[tissue.law.name, three]).fit(_session(tissue))
    behind = next(r for r in est.results_ if r.name == three.name)
    assert est.best_.ln_evidence - behind.ln_evidence > est.decisive
    assert behind.shape_sampler is not None and behind.shape_sampler["status"] == "skipped"
    assert "steps" not in behind.shape_sampler  # no chain ran
    assert "method" not in next(iter(behind.shape_posterior.values()))
    assert "shape not sampled" in behind.reason


def test_time_constants_the_session_cannot_resolve_are_not_searched() -> None:
    # 1.5 s at 250 Hz resolves time constants between about 0.03 s (the filter) and
    # 0.43 s (a third of the fitted stretch): room for one branch, not for two
    sls = Tissue(
        Law.of(["x", "maxwell", "xdot", "xddot"]).bind({"tau1": 0.15}), 300.0, 200.0, 2.0, 0.05
    )
    est = BayesianFit().fit(_session(sls, rate_hz=250.0, duration_s=1.5))
    assert est.best_.name == sls.law.name
    lo, hi = est.best_.shape_ranges["tau1"]
    assert hi < 16 * lo
    assert not any(r.name.count("maxwell") > 1 for r in est.results_)
    assert any("relaxation branch 2 not searched" in w for w in est.warnings_)
