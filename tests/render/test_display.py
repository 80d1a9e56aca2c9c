"""Display numerics: profile, piston physics, operator, control law, check, offline loop."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tissuecli.core.errors import InputError
from tissuecli.core.flags import NONFINITE, SATURATED, UNRENDERABLE
from tissuecli.core.terms import Law
from tissuecli.core.tissue import Tissue
from tissuecli.render import (
    PAPER_DISPLAY,
    Controller,
    DisplayProfile,
    Gains,
    RenderLaw,
    check,
    choose_gains,
    control_voltage,
    piston_step,
    profile_from_dict,
    simulate_offline,
    tracking_bound,
)
from tissuecli.sim.finger import OperatorForce

LINEAR = Law.paper("x", "xdot")
INSIDE = Tissue(LINEAR, K=600.0, S=3.0, M=0.05)
STIFF = Tissue(LINEAR, K=5000.0, S=3.0, M=0.05)


# --------------------------------------------------------------------------- profile


def test_paper_constants_in_si():
    p = PAPER_DISPLAY
    assert (p.Mp, p.Kp, p.alpha, p.v_max, p.stroke) == (0.08335, 264.78, 1.1768, 1.5, 0.015)
    assert p.max_pull == pytest.approx(2.648, abs=1e-3)
    # natural frequency of the bare piston, field notes: 8.97 Hz
    assert math.sqrt(p.Kp / p.Mp) / (2 * math.pi) == pytest.approx(8.97, abs=0.01)


def test_profile_from_dict_numbers_units_and_round_trip():
    p = profile_from_dict({"Mp": 0.1, "Kp": {"value": 300, "unit": "N/m"}, "name": "bench"})
    assert (p.Mp, p.Kp, p.alpha) == (0.1, 300.0, PAPER_DISPLAY.alpha)
    assert profile_from_dict(p.as_dict()) == p


@pytest.mark.parametrize(
    ("data", "needle"),
    [
        ({"Kp": {"value": 27, "unit": "gf/mm"}}, "'N/m'"),
        ({"stiffnes": 1.0}, "unknown key"),
        ({"Mp": -1.0}, "Mp"),
        ({"alpha": float("nan")}, "alpha"),
        ({"v_max": "1.5"}, "number"),
    ],
)
def test_profile_from_dict_refuses_bad_input(data, needle):
    with pytest.raises(InputError, match=needle):
        profile_from_dict(data)


# --------------------------------------------------------------------------- physics


def _settle(force: float, volts: float, seconds: float = 3.0) -> tuple[float, float, bool]:
    p = DisplayProfile(b=5.0)  # well damped, so it settles fast
    x = v = 0.0
    limit = False
    for k in range(int(seconds * 1000)):
        x, v, limit = piston_step(p, x, v, volts, lambda t: force, k * 1e-3, 1e-3)
    return x, v, limit


def test_piston_settles_where_eq6_says():
    x, v, limit = _settle(1.0, 0.5)
    p = PAPER_DISPLAY
    assert x == pytest.approx((1.0 - p.alpha * 0.25) / p.Kp, rel=1e-6)
    assert abs(v) < 1e-9 and not limit


def test_end_stops_hold_and_flag():
    x, _, limit = _settle(0.0, 1.5)  # the solenoid pulls the piston up onto the top stop
    assert x == 0.0 and limit
    x, _, limit = _settle(10.0, 0.0)  # pressed beyond the stroke
    assert x == PAPER_DISPLAY.stroke and limit


def test_piston_clamps_voltage_it_is_given():
    for bad in (float("nan"), -3.0, 99.0):
        x, v, _ = piston_step(PAPER_DISPLAY, 0.005, 0.0, bad, lambda t: 1.3, 0.0, 1e-3)
        assert math.isfinite(x) and math.isfinite(v)


# --------------------------------------------------------------------------- operator


def test_operator_presses_are_smooth_bounded_and_reproducible():
    op = OperatorForce(seed=4)
    t = np.arange(0.0, 10.0, 1e-3)
    f = np.array([op(s) for s in t])
    assert f.min() == 0.0 and 1.0 <= f.max() <= 2.5
    assert np.max(np.abs(np.diff(f))) / 1e-3 < 2.5 * math.pi / (2 * 0.25) * 1.01  # N/s
    starts = np.sum((f[1:] > 0) & (f[:-1] == 0))
    assert 3 <= starts <= 4  # a few presses per 10 s
    assert np.array_equal(f, [OperatorForce(seed=4)(s) for s in t])
    # a 2.5 s run holds one whole press
    assert f[100:2500].max() >= 1.0 and f[2500] == 0.0


# --------------------------------------------------------------------------- control law


def _law(K: float = 600.0, S: float = 3.0, **kw: float) -> RenderLaw:
    base = dict(Kp=264.78, b=0.0, alpha=1.1768, v_max=1.5, Cp=100.0, Cv=5.0)
    base.update(kw)
    return RenderLaw(static=lambda u: K * u, speed=lambda u: S * u, **base)


def test_linear_law_is_paper_eq9():
    law = _law()
    xp, vp, xm, vm = 3e-3, 0.01, 2.9e-3, 0.008
    volts, flags = control_voltage(law, xp, vp, xm, vm)
    e, edot = xp - xm, vp - vm
    expected = math.sqrt((3.0 * vp + (600 - 264.78) * xp + 5.0 * edot + 100.0 * e) / 1.1768)
    assert volts == pytest.approx(expected, rel=1e-12) and flags == 0


def test_law_flags_saturation_unrenderable_and_nonfinite():
    law = _law()
    assert control_voltage(law, 0.014, 0.0, 0.014, 0.0) == (1.5, SATURATED)
    assert control_voltage(law, 1e-3, -0.2, 1e-3, -0.2) == (0.0, UNRENDERABLE)
    assert control_voltage(law, 0.0, 0.0, 0.0, 0.0) == (0.0, 0)  # at rest: nothing to do
    assert control_voltage(law, float("nan"), 0.0, 0.0, 0.0) == (0.0, NONFINITE)
    assert control_voltage(_law(alpha=0.0), 3e-3, 0, 0, 0) == (0.0, NONFINITE)


anything = st.floats(allow_nan=True, allow_infinity=True)
state = st.one_of(st.floats(-1.0, 1.0), anything)
gain = st.one_of(st.floats(0.0, 1e5), anything)


@settings(max_examples=400, deadline=None)
@given(
    xp=state,
    vp=state,
    xm=state,
    vm=state,
    K=gain,
    S=gain,
    Cp=gain,
    Cv=gain,
    b=gain,
    Kp=st.one_of(st.floats(1.0, 1e4), anything),
    alpha=st.one_of(st.floats(1e-6, 1e3), anything),
    v_max=st.one_of(st.floats(1e-3, 100.0), anything),
    forms=st.sampled_from([(f0, f1) for f0 in ("x", "x^3") for f1 in ("xdot", "xdot^2")]),
)
def test_voltage_never_leaves_0_vmax(xp, vp, xm, vm, K, S, Cp, Cv, b, Kp, alpha, v_max, forms):
    tissue = Tissue(Law.paper(*forms), K, S, 0.05)
    law = RenderLaw.build(tissue, PAPER_DISPLAY, Gains(Cp, Cv, 20.0, 0.05))
    law = RenderLaw(
        static=law.static, speed=law.speed, Kp=Kp, b=b, alpha=alpha, v_max=v_max, Cp=Cp, Cv=Cv
    )
    volts, flags = control_voltage(law, xp, vp, xm, vm)
    assert isinstance(volts, float) and math.isfinite(volts)
    if 0 < v_max < math.inf:
        assert 0.0 <= volts <= v_max
    else:
        assert volts == 0.0 and flags == NONFINITE
    if not all(math.isfinite(z) for z in (xp, vp, xm, vm)):
        assert volts == 0.0 and flags & NONFINITE


# --------------------------------------------------------------------------- controller


def test_filter_has_no_lag_on_constant_acceleration():
    tissue = INSIDE
    gains, _ = choose_gains(tissue, PAPER_DISPLAY, 1000.0, 5e-3)
    ctrl = Controller(tissue, PAPER_DISPLAY, 1000.0, gains)
    for k in range(400):
        t = k * 1e-3
        step = ctrl.update(1e-3 + 0.02 * t + 0.5 * 0.3 * t * t, 0.0)
    t = 399e-3
    assert step.xp == pytest.approx(1e-3 + 0.02 * t + 0.15 * t * t, abs=1e-12)
    assert step.vp == pytest.approx(0.02 + 0.3 * t, abs=1e-9)
    assert step.ap == pytest.approx(0.3, abs=1e-6)


def test_observer_sees_the_static_force_and_the_model_settles_under_it():
    p = PAPER_DISPLAY
    gains, _ = choose_gains(INSIDE, p, 1000.0, 5e-3)
    ctrl = Controller(INSIDE, p, 1000.0, gains)
    x, volts = 4e-3, 0.9
    for _ in range(3000):
        step = ctrl.update(x, volts)
    force = p.Kp * x + p.alpha * volts**2
    assert step.force == pytest.approx(force, rel=1e-9)
    assert step.xm == pytest.approx(force / INSIDE.K, rel=1e-6)


def test_controller_survives_nonfinite_readings():
    gains, _ = choose_gains(INSIDE, PAPER_DISPLAY, 1000.0, 5e-3)
    ctrl = Controller(INSIDE, PAPER_DISPLAY, 1000.0, gains)
    ctrl.update(2e-3, 0.5)
    step = ctrl.update(float("nan"), float("inf"))
    assert step.volts == 0.0
    step = ctrl.update(2e-3, 0.5)
    assert math.isfinite(step.volts) and 0.0 <= step.volts <= PAPER_DISPLAY.v_max


# --------------------------------------------------------------------------- gains, check


def test_gains_make_error_dynamics_at_least_critically_damped():
    for tissue in (INSIDE, Tissue(LINEAR, 350.0, 3.0, 0.05), Tissue(LINEAR, 900.0, 0.5, 0.2)):
        g, radius = choose_gains(tissue, PAPER_DISPLAY, 1000.0, 5e-3)
        assert (tissue.S + g.Cv) ** 2 >= 4 * g.M * (tissue.K + g.Cp) * (1 - 1e-9)
        assert g.bandwidth_hz <= 1000.0 / 50 + 1e-9  # well below the loop rate
        assert radius < 1.0


def test_band_edges_are_the_field_notes_figures():
    res = check(INSIDE)
    p = PAPER_DISPLAY
    np.testing.assert_allclose(res.k_max, p.Kp + p.max_pull / res.depth)
    np.testing.assert_allclose(res.k_min, p.Kp)
    for depth, k in ((2e-3, 1589.0), (10e-3, 530.0)):
        assert p.Kp + p.max_pull / depth == pytest.approx(k, abs=1.0)


def test_tissue_inside_the_band_is_accepted():
    res = check(INSIDE, PAPER_DISPLAY, 1000.0)
    assert res.renderable and not res.reasons
    assert res.verdict.startswith("renderable")
    assert res.force_limit == pytest.approx(p_limit(INSIDE), rel=1e-6)
    assert res.spectral_radius < 1.0
    assert res.as_dict()["renderable"] is True


def p_limit(t: Tissue) -> float:
    """Largest force a linear tissue is rendered to: where (K - Kp) x = alpha Vmax^2."""
    p = PAPER_DISPLAY
    return t.K * p.max_pull / (t.K - p.Kp)


def test_stiff_tissue_is_refused_with_the_reason():
    res = check(STIFF, PAPER_DISPLAY, 1000.0)
    assert not res.renderable and res.verdict == "not renderable"
    assert any("too stiff" in r and "saturates at 0.56 mm" in r for r in res.reasons), res.reasons
    assert res.force_limit == pytest.approx(p_limit(STIFF), rel=1e-6)
    assert any("refused: too stiff" in line for line in res.lines())


def test_soft_tissue_is_refused_because_the_solenoid_cannot_push():
    res = check(Tissue(LINEAR, 200.0, 3.0, 0.05))
    assert not res.renderable
    assert any("softer than the display's spring" in r for r in res.reasons)


def test_passivity_margin_is_colgates():
    res = check(INSIDE, PAPER_DISPLAY, 1000.0)
    g, p = res.gains, PAPER_DISPLAY
    k_d = INSIDE.K - p.Kp + g.Cp
    b_d = INSIDE.S + g.Cv - p.b
    assert res.passivity_required == pytest.approx(k_d * 1e-3 / 2 + abs(b_d))
    assert res.passivity_margin == pytest.approx(p.b - res.passivity_required)


# --------------------------------------------------------------------------- offline loop


def _rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(e**2)))


def test_offline_tracking_is_within_the_error_equation_bound():
    out = simulate_offline(INSIDE, OperatorForce(), duration_s=4.0)
    g, _ = choose_gains(INSIDE, PAPER_DISPLAY, 1000.0, 5.67e-3)
    bound = tracking_bound(
        g.M, PAPER_DISPLAY.Mp, np.abs(out["ap"]).max(), INSIDE.K + g.Cp, PAPER_DISPLAY.resolution
    )
    assert _rms(out["e"]) < bound
    assert np.all((out["volts"] >= 0) & (out["volts"] <= PAPER_DISPLAY.v_max))
    assert not np.any(out["flags"] & SATURATED)


def _tissue_response(tissue: Tissue, force: OperatorForce, seconds: float) -> np.ndarray:
    """The tissue itself under the operator's force, at 100 kHz, sampled at 1 kHz; like the
    piston it cannot rise above its rest position (the jaws leave it)."""
    x = v = 0.0
    h = 1e-5
    out = []
    for i in range(int(round(seconds / h))):
        if i % 100 == 0:
            out.append(x)
        v += h * (force(i * h) - tissue.S * v - tissue.K * x) / tissue.M
        x += h * v
        if x < 0.0:
            x, v = 0.0, max(v, 0.0)
    return np.array(out)


def test_matched_mass_tracks_to_the_encoder_resolution():
    matched = Tissue(LINEAR, 600.0, 3.0, PAPER_DISPLAY.Mp)
    out = simulate_offline(matched, OperatorForce(), duration_s=4.0)
    assert _rms(out["e"]) < PAPER_DISPLAY.resolution
    # end to end: the piston moves as the tissue itself would under the same finger
    truth = _tissue_response(matched, OperatorForce(), 4.0)
    assert _rms(out["x"] - truth) < 2 * PAPER_DISPLAY.resolution
    assert np.max(np.abs(out["x"] - truth)) < 10 * PAPER_DISPLAY.resolution
