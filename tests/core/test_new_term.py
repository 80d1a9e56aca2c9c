"""A new term is one class: registered here (and only here), it fits, reports, goes
through a parameter file and back, is simulated, and is rendered or refused by name.

The term is a logarithmic spring ``K log(1 + x / xl)``, stiff at first contact and
softening with depth, with its length scale ``xl`` a shape parameter whose prior it
declares (log-uniform from 0.2 to 20 mm).
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from numpy.typing import ArrayLike, NDArray

from tissuecli.app.fit import write_report
from tissuecli.core.errors import InputError, RenderError
from tissuecli.core.terms import (
    TERMS,
    Law,
    MotionScales,
    ShapeParameter,
    Term,
    register,
    unregister,
)
from tissuecli.core.tissue import Tissue
from tissuecli.formats.params import document, tissue_from_dict, tissue_to_dict
from tissuecli.identify import BayesianFit, WindowedPinv, fit_session
from tissuecli.render import PAPER_DISPLAY, Controller, check
from tissuecli.render.law import split_law
from tissuecli.sim.synth import ForcepsModel, Sensors, synthesize

Array = NDArray[np.float64]


class LogSpring(Term):
    """K log(1 + x / xl): a spring that softens with depth; K in N, xl in m."""

    name, symbol, unit, label, role, variable = (
        "logspring", "Kl", "N", "log(1+x/xl)", "stiffness", "x",
    )  # fmt: skip
    order = 15.0  # between x and x^3
    shapes = ("xl",)
    parameters = (ShapeParameter("xl", "m", "log-spring length scale", (1e-6, 1.0),
                                 prior=(2e-4, 2e-2), log=True, nodes=9, coarse=5),)  # fmt: skip

    def __init__(self, shape: dict[str, float] | None = None) -> None:
        self.shape = dict(shape or {})

    def _xl(self) -> float:
        return self.shape.get("xl", 2e-3)

    def __call__(self, u: ArrayLike) -> Array:
        return np.log1p(np.maximum(np.asarray(u, dtype=float), 0.0) / self._xl())

    def derivative(self, u: ArrayLike) -> Array:
        u = np.asarray(u, dtype=float)
        return np.where(u > 0, 1.0 / (self._xl() + np.maximum(u, 0.0)), 0.0)

    def scalar(self, u: float) -> float:
        return math.log1p(u / self._xl()) if u > 0 else 0.0

    def typical(self, scales: MotionScales) -> float:
        return float(self(np.array([scales.x]))[0]) or 1.0


@pytest.fixture(scope="module")
def logspring() -> Iterator[type[LogSpring]]:
    register(LogSpring)
    yield LogSpring
    unregister("logspring")


TRUTH = {"Kl": 1.2, "S": 3.0, "M": 0.05, "xl": 1.5e-3}


def _truth() -> Tissue:
    law = Law.of(["logspring", "xdot", "xddot"]).bind({"xl": TRUTH["xl"]})
    return Tissue(law, TRUTH["Kl"], TRUTH["S"], TRUTH["M"])


@pytest.fixture(scope="module")
def outcome(logspring):
    model = ForcepsModel(tissue=_truth(), seed=4, sensors=Sensors(bits=12))
    session, _ = synthesize(model, 6.0)
    session.name = "logspring"
    return fit_session(session, forms=["logspring+xdot+xddot", "x+xdot+xddot"], seed=1)


def test_the_registry_places_the_term_and_refuses_unknown_names(logspring):
    law = Law.of(["xddot", "x^3", "logspring", "x", "xdot"])
    assert law.name == "x+logspring+x^3+xdot+xddot"
    assert law.shape_names == ("xl",)
    assert law.shape_parameter("xl").unit == "m"
    with pytest.raises(InputError, match="unknown term 'logspirng'.*logspring"):
        Law.of(["logspirng", "xdot"])


def test_the_term_fits_and_the_evidence_prefers_it(outcome):
    est = outcome.bayes
    assert est.best_.name == "logspring+xdot+xddot"
    assert est.best_.probability > 0.99
    post = est.best_.shape_posterior["xl"]
    lo, hi = post["ci95"]
    assert lo < TRUTH["xl"] < hi
    # the shared vocabulary: law_, coef_, coef_sd_, tissue_
    assert est.law_.name == "logspring+xdot+xddot"
    j = est.law_.symbols.index("Kl")
    assert abs(est.coef_[j] - TRUTH["Kl"]) < 4 * est.coef_sd_[j] + 0.02 * TRUTH["Kl"]
    assert est.tissue_.law == est.law_
    assert est.predict().shape == est.kinematics_.force.shape
    assert est.score() > 0.99


def test_the_html_report_shows_the_term_and_its_shape(outcome, tmp_path: Path):
    path = tmp_path / "report.html"
    write_report(path, outcome)
    text = path.read_text(encoding="utf-8")
    assert "Kl" in text and "log(1+x/xl)" in text
    assert "log-spring length scale" in text


def test_the_parameter_file_round_trips(outcome, logspring, tmp_path: Path):
    doc = json.loads(json.dumps(document(outcome)))
    back = tissue_from_dict(doc)
    fitted = outcome.bayes.law_
    assert back.law.name == fitted.name == doc["law"]["name"]
    # the file gives the shape's posterior mean; the law was bound at its peak
    assert back.law.shape["xl"] == pytest.approx(fitted.shape["xl"], rel=1e-3)
    np.testing.assert_allclose(back.coef, outcome.bayes.coef_, rtol=1e-12)
    assert tissue_from_dict(tissue_to_dict(_truth())) == _truth()
    # out of the range the term declares: refused in one line that names it
    bad = tissue_to_dict(_truth())
    bad["law"]["shape"][0]["mean"] = 5.0
    with pytest.raises(InputError, match=r"shape\[0\]\.mean = 5 m must be <= 1 m"):
        tissue_from_dict(bad)


def test_an_unregistered_term_in_a_file_is_refused_not_dropped(logspring):
    doc = tissue_to_dict(_truth())
    unregister("logspring")
    try:
        with pytest.raises(InputError, match="'logspring' is not a term"):
            tissue_from_dict(doc)
    finally:
        register(LogSpring)


def test_the_display_checks_it_as_a_position_term(logspring):
    soft = _truth()  # 3.4 N, a liver grasp, lies 24 mm deep: past the stroke
    parts = split_law(soft)
    assert [t.name for t, _ in parts.position] == ["logspring"] and not parts.refusals
    assert soft.static_force(np.array([1.5e-3]))[0] == pytest.approx(1.2 * math.log(2.0))
    assert check(soft).reasons == ["at 3.4 N the tissue is deeper than the 15 mm stroke"]
    law = Law.of(["logspring", "xdot", "xddot"]).bind({"xl": 5e-3})
    firm = Tissue(law, 3.5, 3.0, 0.05)  # 3.4 N at 8 mm
    res = check(firm)
    assert res.renderable, res.reasons


def test_a_term_that_declares_itself_unrenderable_is_refused_by_name(logspring):
    class Refused(LogSpring):
        display = "refused"

    law = Law((Refused({"xl": 1e-3}), Law.of(["xdot"]).terms[0]))
    tissue = Tissue(law, 1.0, 3.0)
    assert "logspring (Kl)" in split_law(tissue).refusals[0]
    res = check(tissue)
    assert not res.renderable and any("logspring (Kl)" in r for r in res.reasons)
    with pytest.raises(RenderError, match="logspring"):
        Controller(tissue, PAPER_DISPLAY, 1000.0, res.gains)


def test_estimators_read_and_set_their_hyperparameters():
    est = BayesianFit("paper", seed=3)
    params = est.get_params()
    assert params["forms"] == "paper" and params["seed"] == 3
    assert est.set_params(seed=5, sampler="emcee") is est and est.seed == 5
    assert BayesianFit(**est.get_params()).get_params() == est.get_params()
    pinv = WindowedPinv("x,xdot")
    assert pinv.set_params(window_s=0.5).get_params()["window_s"] == 0.5
    with pytest.raises(Exception, match="no parameter 'windows'.*window_s"):
        pinv.set_params(windows=2)
    with pytest.raises(Exception, match="not fitted"):
        pinv.predict()


def test_a_registered_name_is_not_taken_twice(logspring):
    class Other(LogSpring):
        pass

    with pytest.raises(InputError, match="already registered"):
        register(Other)
    assert type(TERMS["logspring"]) is LogSpring


class _Fading(Term):
    """A relaxation branch written only as its series (no recursion of its own, no
    rendering declared): what the simulator, the report's step response and the
    display make of a term with memory from the class alone."""

    name, symbol, unit, label, role, variable = "fading", "Kf", "N/m", "fade", "relaxation", "h"
    memory = True
    shapes = ("tf",)
    parameters = (ShapeParameter("tf", "s", "fading time", (1e-4, 1e4), prior=(0.01, 10.0),
                                 log=True),)  # fmt: skip

    def __init__(self, shape: dict[str, float] | None = None) -> None:
        self.shape = dict(shape or {})

    def __call__(self, u: ArrayLike) -> Array:
        raise TypeError("needs the history")

    def derivative(self, u: ArrayLike) -> Array:
        return np.ones_like(np.asarray(u, dtype=float))

    def series(self, dt: float, x: Array, v: Array, a: Array) -> Array:
        # r_k = sum_j exp(-(k - j) dt / tf) (x_j - x_{j-1}): the branch as a convolution
        steps = np.diff(np.asarray(x, dtype=float), prepend=x[0])
        kernel = np.exp(-np.arange(steps.size) * dt / self.shape["tf"])
        return np.convolve(steps, kernel)[: steps.size]


def test_a_term_with_memory_is_simulated_and_stepped_from_its_series_alone():
    fading = _Fading({"tf": 0.2})
    tissue = Tissue(Law((Law.of(["x"]).terms[0], fading)), 300.0, 100.0)
    branch = Law.of(["x", "maxwell"]).bind({"tau1": 0.2})
    model = ForcepsModel(tissue=tissue, seed=1)
    reference = ForcepsModel(tissue=Tissue(branch, 300.0, 100.0), seed=1)
    # streamed in two blocks, as the simulated forceps does
    first, second = model.truth(np.arange(300))[3], model.truth(np.arange(300, 600))[3]
    expected = reference.truth(np.arange(600))[3]
    # the convolution of the discrete steps against the exact recursion: within the
    # closure's change over a fine step, a part in a thousand of the branch force
    np.testing.assert_allclose(np.concatenate([first, second]), expected, rtol=2e-3, atol=1e-3)
    t = np.array([0.05, 0.2, 1.0])
    np.testing.assert_allclose(fading.step_response(t, 1e-3), 1e-3 * np.exp(-t / 0.2), rtol=1e-3)
    assert fading.steady(3e-3, 0.01) == pytest.approx(0.2 * 0.01, rel=0.02)
    assert "fading (Kf) has a memory" in split_law(tissue).refusals[0]
