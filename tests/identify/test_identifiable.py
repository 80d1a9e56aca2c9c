"""Identifiability before evidence: columns a recording leaves empty or shares between
terms are named, merged or left out before the structure search."""

from __future__ import annotations

import numpy as np

from tissuecli.core.session import Session
from tissuecli.core.terms import Law
from tissuecli.identify import BayesianFit
from tissuecli.identify.bayes import linear_laws, session_scales
from tissuecli.identify.identifiable import Design, examine
from tissuecli.sim.synth import ForcepsModel, Sensors, synthesize

from .lab_protocols import constant_speed, relaxation


def _design(session: Session) -> Design:
    ready = BayesianFit(grasps="none").prepare(session)
    kin = ready.kinematics
    return examine(kin, ready.session.position, scales=session_scales(kin))


def test_constant_speed_is_one_column_and_no_acceleration():
    s, _ = constant_speed(0, damping=2.0, offset=0.1)
    d = _design(s)
    assert d.unexcited == ["xddot"]
    assert sorted(d.groups[0]) == sorted(["offset", "xdot", "xdot|xdot|", "sign(xdot)"])
    assert d.summary == (
        "constant speed: S, S2, friction and the offset are one column; M not excited"
    )
    reduced = {law.name for law in d.reduce(linear_laws())}
    assert reduced == {"x+offset", "x^3+offset", "x+x^3+offset", "x", "x^3", "x+x^3"}


def test_ramp_and_hold_shares_one_column_between_the_speed_terms():
    """Ramps at one speed and holds: xdot, xdot|xdot| and sign(xdot) are one step
    function; the offset and the stiffness stay apart."""
    s, _ = relaxation(0)
    d = _design(s)
    assert sorted(d.groups[0]) == sorted(["xdot", "xdot|xdot|", "sign(xdot)"])
    assert "offset" not in {n for g in d.groups for n in g}
    assert d.summary.startswith("one speed wherever it moves:")


def test_a_rich_session_keeps_every_column():
    s, _ = synthesize(ForcepsModel(seed=4, sensors=Sensors(bits=16)), 10.0)
    d = _design(s)
    assert d.unexcited == [] and d.groups == [] and d.summary == ""
    assert len(d.reduce(linear_laws())) == len(linear_laws())


def test_a_single_sine_makes_inertia_a_spring_beside_an_offset():
    """x = x0 + a sin(w t): xddot = -w^2 (x - x0), so a law with x, xddot and an offset
    has no unique coefficients; without the offset it has."""
    t = np.arange(8000) / 1000.0
    x = 2e-3 + 1e-3 * np.sin(2 * np.pi * 2.0 * t)
    rng = np.random.default_rng(0)
    f = 300 * x + 0.05 * np.gradient(np.gradient(x, t), t) + rng.normal(0, 1e-3, t.size)
    d = _design(Session(t, f, x))
    assert d.collinear(Law.of(["x", "xddot", "offset"])) is not None
    assert d.collinear(Law.of(["x", "xdot"])) is None


def test_default_search_never_compares_what_the_design_cannot_tell_apart():
    """At constant speed no law with two of the speed terms and the offset, and no
    inertia, is scored."""
    s, _ = constant_speed(2, offset=0.05)
    est = BayesianFit(grasps="none").fit(s)
    shared = {"xdot", "xdot|xdot|", "sign(xdot)", "offset", "contact*xdot"}
    for r in [*est.results_, *est.not_evaluated_]:
        names = {t.name for t in (r.family or r.model).terms}
        assert "xddot" not in names, r.name
        assert len(names & shared) <= 1, r.name


def test_a_law_of_shaped_terms_alone_is_fitted():
    """``--forms contact``: no column of the examined kind; the design is empty and the
    law is fitted (once a traceback from stacking no columns)."""
    s, _ = constant_speed(0, duration=4.0)
    ready = BayesianFit(grasps="none").prepare(s)
    d = examine(ready.kinematics, ready.session.position, names=[])
    assert d.summary == "" and not d.unexcited
    est = BayesianFit("contact", grasps="none").fit(s)
    assert est.best_.name == "contact"


def _contact_session(kc: float, noise: float, seed: int = 1) -> Session:
    """Hunt-Crossley contact ``kc x^1.5`` (N/m^1.5) at 500 Hz for 4 s, the jaw closing
    0.5-4.5 mm at 0.5 Hz, with white force noise of SD ``noise`` (N)."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 4.0, 1 / 500.0)
    x = 0.002 * (1 - np.cos(np.pi * t)) + 0.0005
    return Session(t, kc * x**1.5 + noise * rng.standard_normal(t.size), x)


def test_a_contact_stiffness_pinned_at_its_exponent_is_identified():
    """2.4 N of contact force under 2 N of noise: the exponent is loose (n about
    1.4-2.1), so Kc, in N/m^n, spans more than a decade across exponents, but given
    the exponent it is pinned to a few per cent: it is identified, judged there."""
    est = BayesianFit("contact", grasps="none").fit(_contact_session(8000.0, 2.0))
    r = est.best_
    post = r.posterior
    assert post is not None
    lo, hi = post.ci95[0]
    assert hi / lo > 10 and post.sd[0] > 0.5 * post.mean[0]  # the marginal: loose
    at = post.diagnostics["at_shape"]
    assert at["sd"][0] < 0.1 * post.mean[0]  # given the shape: pinned
    assert not any(f.startswith("Kc ") for f in r.flags), r.flags


def test_a_contact_force_below_the_noise_is_still_not_identified():
    """6 mN of contact force under 0.5 N of noise: Kc is not identified, given its
    shape or not."""
    est = BayesianFit("contact", grasps="none").fit(_contact_session(20.0, 0.5))
    assert any(f.startswith("Kc not identified") for f in est.best_.flags)


def test_a_coefficient_whose_shape_fills_its_prior_is_not_identified():
    """Kc judged at its exponent means nothing if the data leave the exponent where the
    prior put it (the whole of [1, 2.5]); an exponent they pin leaves Kc to be judged."""
    from tissuecli.identify.diagnostics import _loose_shapes
    from tissuecli.identify.scoring import ModelResult

    law = Law.of(["contact"])
    ranges = {"n": (1.0, 2.5), "x0": (-0.5e-3, 2.5e-3)}

    def result(n_ci: list[float]) -> ModelResult:
        post = {"n": {"ci95": n_ci}, "x0": {"ci95": [0.0, 1e-3]}}
        return ModelResult(model=law, shape_posterior=post, shape_ranges=ranges)

    loose = _loose_shapes(result([1.0, 2.5]), law.terms[0])
    assert loose.startswith("n 95 % interval [1, 2.5]") and "x0" not in loose
    assert _loose_shapes(result([1.4, 2.1]), law.terms[0]) == ""
