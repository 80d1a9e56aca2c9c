"""Identifiability before evidence: columns a recording leaves empty or shares between
terms are named, merged or left out before the structure search."""

from __future__ import annotations

import itertools

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tissuecli.core.session import Session
from tissuecli.core.terms import Law
from tissuecli.identify import BayesianFit
from tissuecli.identify.bayes import linear_laws, session_scales
from tissuecli.identify.identifiable import Design, examine
from tissuecli.sim.protocols import random_protocol
from tissuecli.sim.scenes import FAMILIES, Scene, random_scene
from tissuecli.sim.synth import ForcepsModel, Sensors, synthesize

from .lab_protocols import constant_speed, relaxation

PAPER = [f for f in FAMILIES if f.startswith("paper")]


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


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(force_unit=st.sampled_from([1e-3, 1.0, 1e3]), length_unit=st.sampled_from([1.0, 1e3, 1e6]))
def test_what_is_excited_does_not_hang_on_the_units(force_unit: float, length_unit: float):
    """A sine sweep (x+xdot+xddot) excites speed and acceleration whatever units its
    file is in. Speed was judged rounding against the RMS of the last column whose
    variable is the closure (x^3, which in um^3 dwarfs the closure itself): in mN and
    um the sweep's damping was left out of every law, and the fit chose
    x+maxwell+xdot|xdot|+xddot with M 66 % off."""
    scene = random_protocol(7000096, "sine sweep", max_samples=20_000)
    s = scene.session
    si = s.replace(s.time, s.force / scene.units[0], s.position / scene.units[1])
    scaled = si.replace(si.time, si.force * force_unit, si.position * length_unit)
    assert _design(scaled).unexcited == []


def test_ramp_and_hold_makes_friction_the_other_speed_terms_together():
    """A ramp at one speed and a hold: friction's smoothed step lies in the span of
    xdot and xdot|xdot| (its own part is below what the prior could make visible), so
    no law holds all three; xdot and xdot|xdot| differ at the ramp's ends by more than
    that, and both stay, as do the offset and the stiffness."""
    s, _ = relaxation(0)
    d = _design(s)
    assert d.groups == []
    assert d.combined == {"sign(xdot)": ["xdot", "xdot|xdot|"]}
    assert d.summary == "on this recording: friction is S and S2 together"
    assert d.collinear(Law.of(["x", "xdot", "xdot|xdot|", "sign(xdot)"])) is not None
    reduced = {law.name for law in d.reduce(linear_laws())}
    assert {"x+xdot+xddot", "x+xdot|xdot|+xddot"} <= reduced


def _scene_design(scene: Scene, closure: str = "rebuilt") -> Design:
    """The design the default fit examines on a scene's session (with its position noise)."""
    est = BayesianFit(closure=closure)
    ready = est.prepare(scene.session)
    kin = ready.kinematics
    sigma_x = est._position_noise(ready)
    return examine(kin, ready.closure, sigma_x, scales=session_scales(kin))


def test_a_slow_8_bit_squeeze_keeps_both_dampings_apart():
    """An 8-bit slow squeeze in contact throughout (4.4 kHz, truth x+xdot|xdot|):
    friction's column, smoothed at speeds about its smoothing speed, is xdot and
    xdot|xdot| together. Once that made the two one column, so the default search never
    scored a law with xdot|xdot| and chose x+maxwell or a contact law, 160-180 times the
    noise floor on held-out data; each of the two is its own column here. Formed from
    the staircase rebuilt through its level crossings, whose speed resolves the turns,
    friction is a column of its own too."""
    scene = random_scene(2520607, families=PAPER, max_samples=10_000)
    assert scene.tissue.law.name == "x+xdot|xdot|+xddot" and scene.settings["bits"] == 8
    rebuilt = _scene_design(scene)
    assert rebuilt.combined == {}
    assert {rebuilt.representative(n) for n in ("xdot", "xdot|xdot|", "sign(xdot)")} == {
        "xdot", "xdot|xdot|", "sign(xdot)"}  # fmt: skip
    d = _scene_design(scene, "read")
    assert d.representative("xdot|xdot|") == "xdot|xdot|"
    assert d.representative("xdot") == "xdot"
    assert d.combined == {"sign(xdot)": ["xdot", "xdot|xdot|"]}
    reduced = {law.name for law in d.reduce(linear_laws())}
    assert {"x+xdot|xdot|+xddot", "x+xdot+xddot", "x+xdot|xdot|+sign(xdot)+xddot"} <= reduced
    assert not any({"xdot", "xdot|xdot|", "sign(xdot)"} <= {t.name for t in law.terms}
                   for law in d.reduce(linear_laws()))  # fmt: skip


@settings(max_examples=16, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**31 - 1), protocol=st.booleans())
def test_a_merged_term_is_one_column_with_the_term_that_stands_for_it(seed: int, protocol: bool):
    """On any scene or lab protocol: a term replaced by another is one column with that
    term alone (not with a combination of others, which would merge terms plainly
    apart), the terms that stand for groups are apart from each other, and a term only
    a combination carries is one with that combination and with none of it alone."""
    draw = random_protocol if protocol else random_scene
    d = _scene_design(draw(seed, max_samples=3000))
    index = {n: i for i, n in enumerate(d.names)}
    heads = [g[0] for g in d.groups]
    for group in d.groups:
        for name in group[1:]:
            assert d.merged(index[name], [index[group[0]]]), (group, name)
    for a, b in itertools.combinations(heads, 2):
        later, earlier = sorted((a, b), key=index.__getitem__, reverse=True)
        assert not d.merged(index[later], [index[earlier]]), (a, b)
    for name, partners in d.combined.items():
        assert len(partners) >= 2
        assert d.merged(index[name], [index[p] for p in partners]), (name, partners)
        assert not any(d.merged(index[name], [index[p]]) for p in partners), (name, partners)


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
    # M lies in the span of K and the offset; K and the offset stay apart, and M beside
    # K alone is scored (the three were once made one column: every law lost M, and
    # the offset became K)
    assert d.groups == [] and d.combined == {"xddot": ["x", "offset"]}
    reduced = {law.name for law in d.reduce(linear_laws())}
    assert "x+xdot+xddot" in reduced and "x+xdot+xddot+offset" not in reduced


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
