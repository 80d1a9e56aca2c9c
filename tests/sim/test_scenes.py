"""Random scenes and lab protocols carry a truth consistent with what they measured."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tissuecli.core.terms import Law
from tissuecli.core.tissue import Tissue
from tissuecli.sim import scenes
from tissuecli.sim.protocols import PROTOCOLS, Creep, Knots, Sweep, random_protocol
from tissuecli.sim.scenes import FAMILIES, Scene, random_scene, true_force
from tissuecli.sim.synth import ForcepsModel, Operator, Sensors


def _noise_ratio(scene: Scene) -> float:
    """SD of measured minus true force over what noise and quantisation predict."""
    resid = scene.session.force - scene.force
    step = scene.session.adc.step("force") if scene.session.adc is not None else 0.0
    expected = np.hypot(scene.noise_n * scene.units[0], step / np.sqrt(12.0))
    return float(np.std(resid) / expected)


@pytest.mark.parametrize("family", list(FAMILIES))
def test_each_family_measures_its_true_force_plus_noise(family):
    """The measured force is the truth plus noise of the stated SD and the ADC's rounding:
    over thousands of samples the SD of the difference is within 10 % of that (the
    sample SD's own spread is 1/sqrt(2n), under 2 %); nothing is clipped."""
    scene = random_scene(11, families=[family], max_samples=8000)
    assert scene.family == family
    assert scene.tissue.law.name == Law.of(FAMILIES[family][0]).name
    n = len(scene.session)
    assert scene.force.shape == scene.x.shape == (n,)
    assert np.all(np.isfinite(scene.force))
    assert 0.9 < _noise_ratio(scene) < 1.1
    adc = scene.session.adc
    lo, hi = adc.ends("force")
    assert lo < scene.session.force.min() and scene.session.force.max() < hi


@pytest.mark.parametrize("family", [f for f in FAMILIES if "branch" not in f])
def test_the_true_force_is_the_law_at_the_true_kinematics(family):
    scene = random_scene(5, families=[family], max_samples=5000, contact="continuous")
    law, coef = scene.tissue.law, scene.tissue.coef
    expected = law.force(coef, scene.x, scene.v, scene.a)
    expected = np.where(scene.x > 0, expected - _offset(scene.tissue), 0.0)
    np.testing.assert_allclose(scene.force, expected + _offset(scene.tissue), rtol=1e-12,
                               atol=1e-12 * np.ptp(scene.force))  # fmt: skip


def _offset(tissue: Tissue) -> float:
    law = tissue.law
    return float(tissue.coef[law.symbols.index("F0")]) if "F0" in law.symbols else 0.0


def test_relaxation_truth_agrees_with_the_forceps_simulator():
    """In continuous contact the scene's branches are the simulated forceps' own."""
    tissue = Tissue(
        Law.of(["x", "maxwell", "maxwell", "xdot", "xddot"]).bind({"tau1": 0.1, "tau2": 1.0}),
        300.0, 150.0, 100.0, 2.0, 0.05,
    )  # fmt: skip
    op = Operator()
    model = ForcepsModel(tissue=tissue, operator=op, sensors=Sensors(bits=16))
    k = np.arange(3000)
    _, _, _, f_model = model.truth(k)
    _, _, _, f_scene = true_force(tissue, op, k / 1000.0)
    np.testing.assert_allclose(f_scene, f_model, rtol=1e-9, atol=1e-9)


def test_grasps_have_free_jaws_with_no_tissue_force():
    scene = random_scene(3, contact="grasps", families=["one branch"], max_samples=20000)
    free = scene.x <= 0
    assert 0.05 < free.mean() < 0.6
    assert np.all(scene.force[free] == 0.0)


def test_a_seed_gives_one_scene():
    a, b = random_scene(42, max_samples=3000), random_scene(42, max_samples=3000)
    assert a.describe() == b.describe() and a.tissue == b.tissue
    np.testing.assert_array_equal(a.session.force, b.session.force)
    assert random_scene(43, max_samples=3000).describe() != a.describe()


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**31),
    rate=st.floats(250.0, 10_000.0),
    bits=st.integers(8, 16),
    noise=st.floats(0.005, 0.10),
    contact=st.sampled_from(["continuous", "grasps"]),
    tempo=st.floats(0.25, 4.0),
    family=st.sampled_from(list(FAMILIES)),
)
def test_any_setting_gives_a_consistent_scene(seed, rate, bits, noise, contact, tempo, family):
    """Over the whole space: settings kept, sample count bounded, the truth finite, the
    noise as stated (with the ADC's rounding) to within the sample SD's spread, the ADC
    never saturated."""
    scene = random_scene(seed, families=[family], max_samples=4000, rate_hz=rate, bits=bits,
                         noise_frac=noise, contact=contact, tempo=tempo)  # fmt: skip
    s = scene.settings
    assert (s["rate_hz"], s["bits"], s["noise_frac"], s["contact"]) == (rate, bits, noise, contact)
    n = len(scene.session)
    assert n <= 4000 + 1
    assert np.all(np.isfinite(scene.force)) and np.all(np.isfinite(scene.session.position))
    assert np.all(np.diff(scene.session.time) > 0)
    # the sample SD of n draws lies within 5/sqrt(2n) of the truth but for 6e-7 of runs
    assert abs(_noise_ratio(scene) - 1.0) < 5.0 / np.sqrt(2 * n) + 0.02
    lo, hi = scene.session.adc.ends("force")
    assert lo < scene.session.force.min() and scene.session.force.max() < hi
    assert set(scene.unexcited) <= {t.name for t in scene.tissue.law.terms}


@pytest.mark.parametrize("name", list(PROTOCOLS))
def test_each_protocol_scales_its_truth_with_its_units(name):
    """The session is in scaled units; the law at the scaled coefficients and scaled
    closure gives the scaled true force (the truth in any units is one truth)."""
    scene = random_protocol(1, name, rate_hz=500.0, max_samples=6000, force_unit=1e3,
                            length_unit=1e6, quantisation="float64")  # fmt: skip
    cf, cx = scene.units
    law = scene.tissue.law
    if law.shape_names:
        law = Law(tuple(t for t in law.terms)).bind(scene.shapes)
    dt = 1.0 / 500.0
    f = law.force(scene.coefficients, cx * scene.x, cx * scene.v, cx * scene.a, dt)
    # a branch integrated at the samples (closure linear between them) rather than on the
    # scene's grid eight times finer differs by the rule's O(dt^2) at the ramp's corners
    rtol = 1e-4 if law.memory else 1e-9
    np.testing.assert_allclose(f, scene.force, rtol=rtol, atol=1e-9 * np.ptp(scene.force))
    assert 0.9 < _noise_ratio(scene) < 1.1


def test_protocol_motions_are_exact_integrals():
    """Closure, speed and acceleration of each motion agree with each other: the
    trapezoid integral of the speed (of the acceleration) on a fine grid gives the
    closure (the speed) to the rule's O(h^2)."""
    t = np.linspace(0.0, 4.0, 400_001)
    motions = [
        Knots(1e-3, (0.0, 1.0, 2.0, 3.0), (1e-3, -1e-3, 0.0, 2e-3), blend_s=0.1),
        Sweep(2e-3, 1e-3, 0.5, 5.0, 4.0),
        Creep(300.0, 200.0, 0.5, 1e-3, 0.3, 0.2),
    ]
    for m in motions:
        x, v, a = m.kinematics(t)
        h = t[1] - t[0]
        xi = x[0] + np.concatenate([[0.0], np.cumsum((v[1:] + v[:-1]) * h / 2)])
        vi = v[0] + np.concatenate([[0.0], np.cumsum((a[1:] + a[:-1]) * h / 2)])
        assert np.max(np.abs(xi - x)) < 1e-6 * np.ptp(x), type(m).__name__
        assert np.max(np.abs(vi - v)) < 1e-4 * np.ptp(v), type(m).__name__


def test_creep_holds_its_force():
    scene = random_protocol(2, "creep SLS", rate_hz=1000.0, noise_frac=0.01,
                            force_unit=1.0, length_unit=1.0)  # fmt: skip
    f, n = scene.force, len(scene.force)
    hold = int(0.06 * n)  # the load is on by 5 %
    assert np.ptp(f[hold:]) < 1e-4 * np.ptp(f)
    assert np.ptp(scene.x[hold:]) > 0.1 * np.ptp(scene.x)  # and it creeps meanwhile


def test_the_design_tells_which_laws_are_the_truths():
    ramp = random_protocol(0, "ramp offset", max_samples=2000)
    assert ramp.within_truth(Law.of(["x", "xdot", "xddot"]))  # xdot is the offset here
    assert ramp.right(Law.of(["x", "sign(xdot)"]))
    assert not ramp.within_truth(Law.of(["x", "maxwell", "xdot"]))
    assert not ramp.within_truth(Law.of(["contact", "offset"]))
    sls = random_protocol(0, "ramp-hold SLS", max_samples=2000)
    assert sls.right(Law.of(["x", "maxwell", "xddot"]))
    assert not sls.right(Law.of(["x", "maxwell", "maxwell"]))
    assert not sls.within_truth(Law.of(["x", "maxwell", "offset"]))
    sweep = random_protocol(0, "sine sweep", max_samples=2000)
    assert not sweep.right(Law.of(["x", "xdot"]))


@pytest.mark.parametrize(
    ("tau", "coef", "visible"), [(1e-4, 1e5, False), (0.2, 300.0, True), (1e3, 300.0, False)]
)
def test_a_branch_the_other_terms_carry_is_not_seen(tau, coef, visible):
    # a 1 Hz squeeze: a branch far quicker than it is a damper (tau xdot), one far
    # slower than the session a spring; the law's own xdot and x carry either
    rate, t = 1000.0, np.arange(10_000) / 1000.0
    x = 1e-3 * (1.0 - np.cos(2 * np.pi * t))  # from rest at the first sample
    v = 2e-3 * np.pi * np.sin(2 * np.pi * t)
    a = 4e-3 * np.pi**2 * np.cos(2 * np.pi * t)
    law = Law.of(["x", "maxwell", "xdot"]).bind({"tau1": tau})
    tissue = Tissue(law, 300.0, coef, 5.0)
    noise = 0.01 * 300.0 * 2e-3  # 1 % of the spring's force range
    raw = scenes.detectability(tissue, x, v, a, rate, noise)["maxwell"]
    (seen,) = scenes.branch_detectability(tissue, x, v, a, rate, noise)
    assert raw > 10 * scenes.DETECTABLE  # its own force stands far above the noise
    assert (seen >= scenes.DETECTABLE) == visible


def test_a_law_without_a_branch_no_design_can_see_is_right():
    # two branches (tau 0.033 s and 0.46 s) on a 5.4 s squeeze: the slower one's force
    # is the law's other columns' to within the noise
    scene = scenes.random_scene(119, families=["one branch", "two branches"], max_samples=20_000)
    assert scene.visible_branches == 1
    assert scene.right(Law.of(["x", "maxwell", "xdot", "xddot"]))
    assert scene.right(scene.tissue.law)
    assert not scene.right(Law.of(["x", "xdot", "xddot"]))
    assert not scene.right(Law.of(["x", "maxwell", "maxwell", "maxwell", "xdot", "xddot"]))


def test_a_scene_is_judged_on_the_part_a_fit_sees():
    # quadratic damping that stands above the noise over the whole session only because
    # of its last 30 %: a fit of the first 70 % cannot be asked for it
    scene = scenes.random_scene(777027, max_samples=10_000)
    assert scene.tissue.law.name.startswith("x+xdot|xdot|")
    t = scene.session.time
    head = int(np.searchsorted(t, t[0] + 0.7 * (t[-1] - t[0])))
    judged = scene.judged_on(head)
    assert "xdot|xdot|" not in scene.unexcited and "xdot|xdot|" in judged.unexcited
    without = Law.of([t.name for t in scene.tissue.law.terms if t.name != "xdot|xdot|"])
    assert judged.right(without) and not scene.right(without)
    assert judged.right(scene.tissue.law)  # an unexcited term may be in or out
    # the whole session judged again is the scene as drawn
    again = scene.judged_on(len(scene.session))
    assert (again.unexcited, again.visible_branches) == (scene.unexcited, scene.visible_branches)
