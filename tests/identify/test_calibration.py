"""Calibration fits: a sensor channel against references, the display's constants from
a sweep and ring-downs, and the slow load cell warning."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tissuecli.core.errors import InputError
from tissuecli.identify.calibration import (
    MIN_FORCE_RATE_HZ,
    ChannelFit,
    G,
    fit_display,
    fit_ringdown,
    held_rate,
    off_stops,
    slow_force_warning,
)
from tissuecli.render.plant import piston_step
from tissuecli.render.profile import PAPER_DISPLAY

GAIN, OFFSET = 0.0235294, -2.0117647  # N per count, N
LOADS = np.repeat([0.0, 0.5, 1.0, 2.0, 3.0, 5.0], 2)  # N


def readings(rng: np.random.Generator, noise: float = 1.5, quad: float = 0.0) -> np.ndarray:
    """Raw counts of a load cell at LOADS: linear, plus ``quad`` counts per N^2."""
    return (LOADS - OFFSET) / GAIN + quad * LOADS**2 + rng.normal(0, noise, LOADS.size)


def test_gain_and_offset_fall_within_their_intervals_at_the_stated_rate():
    """95 % intervals from a straight line with Student t: over 400 seeds the truth is
    inside 380 +- 4.4 times; 360 is 4.5 SD below (delta-method intervals lose a little
    coverage, at most 1 % for a gain known to 0.5 %)."""
    inside_gain = inside_offset = 0
    for seed in range(400):
        fit = ChannelFit().fit(LOADS, readings(np.random.default_rng(seed)))
        inside_gain += fit.gain_ci_[0] <= GAIN <= fit.gain_ci_[1]
        inside_offset += fit.offset_ci_[0] <= OFFSET <= fit.offset_ci_[1]
    assert inside_gain >= 360 and inside_offset >= 360
    assert inside_gain <= 396 and inside_offset <= 396  # not uselessly wide either


def test_a_quadratic_sensor_is_reported_and_a_linear_one_is_not():
    rng = np.random.default_rng(3)
    linear = ChannelFit().fit(LOADS, readings(rng))
    assert linear.quadratic_p_ is not None and not linear.nonlinear
    bent = ChannelFit().fit(LOADS, readings(rng, quad=4.0))  # 100 counts at 5 N
    assert bent.nonlinear and bent.quadratic_p_ < 1e-6
    # the departure of 4 L^2 counts from their own least-squares line, in N by the fit
    line = np.polyfit(LOADS, 4.0 * LOADS**2, 1)
    grid = np.linspace(0, 5, 101)
    departure = np.max(np.abs(4.0 * grid**2 - np.polyval(line, grid))) * bent.gain_
    assert bent.nonlinearity_ == pytest.approx(departure, rel=0.1)


def test_too_few_or_flat_points_are_one_line_errors():
    with pytest.raises(InputError, match="at least 3 points"):
        ChannelFit().fit([0, 1], [10, 20])
    with pytest.raises(InputError, match="at least 3 points"):
        ChannelFit().fit([1, 1, 1], [10, 11, 12])
    with pytest.raises(InputError, match="do not change"):
        ChannelFit().fit([0, 1, 2], [5, 5, 5])
    with pytest.raises(InputError, match="finite"):
        ChannelFit().fit([0, 1, np.nan], [5, 6, 7])


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.lists(
        st.tuples(
            st.floats(allow_nan=True, allow_infinity=True, width=64),
            st.floats(allow_nan=True, allow_infinity=True, width=64),
        ),
        max_size=12,
    )
)
def test_any_points_give_a_fit_or_one_input_error(points):
    ref = [p[0] for p in points]
    raw = [p[1] for p in points]
    try:
        with np.errstate(all="ignore"):
            fit = ChannelFit().fit(ref, raw)
    except InputError as exc:
        assert "\n" not in str(exc)
        return
    assert fit.n_ == len(points)


def test_the_slow_load_cell_warning_names_its_rate():
    assert slow_force_warning(MIN_FORCE_RATE_HZ) is None
    text = slow_force_warning(80.0)
    assert text is not None and "80 Hz" in text and "M" in text


def test_a_ring_down_gives_its_frequency_and_decay():
    t = np.arange(1500) * 1e-3
    x = 0.004 + np.exp(-1.3 * t) * (0.002 * np.cos(31.0 * t) - 0.001 * np.sin(31.0 * t))
    ring = fit_ringdown(t, np.round(x / 1e-6) * 1e-6)  # a 1 um encoder
    assert ring.sigma == pytest.approx(1.3, rel=1e-3)
    assert ring.omega == pytest.approx(31.0, rel=1e-4)
    assert ring.c == pytest.approx(0.004, abs=1e-7)
    with pytest.raises(InputError, match="no damped oscillation"):
        fit_ringdown(t, 0.004 + 0.001 * np.exp(-t / 0.1))


def bench_frames(profile, mass: float, seed: int, cut_share: float = 0.02):
    """What the display reports over a short calibration, simulated in this process:
    positions (m, a 1 um encoder), the voltage applied after each frame and stretch labels;
    a share of frames with the solenoid cut (the watchdog on a busy machine)."""
    rng = np.random.default_rng(seed)
    plant = replace(profile, Mp=profile.Mp + mass)
    weight = mass * G
    plan = [0.0] + [profile.v_max * math.sqrt(i / 5) for i in range(6)] + [0.9, 0.0, 0.9, 0.0]
    x = v = 0.0
    xs, vs = [], []
    for volts in plan:
        for _ in range(800):
            applied = 0.0 if rng.random() < cut_share else volts
            xs.append(round(x / profile.resolution) * profile.resolution)
            vs.append(applied)
            x, v, _ = piston_step(plant, x, v, applied, lambda t: weight, 0.0, 1e-3)
    xs, vs = np.array(xs), np.array(vs)
    inside = off_stops(xs, 0.0, profile.stroke, 2e-6)
    starts = inside & ~np.roll(inside, 1)
    starts[0] = inside[0]
    return xs[inside], vs[inside], np.cumsum(starts)[inside]


@pytest.mark.parametrize(
    "factors",
    [
        {"Kp": 0.7, "alpha": 1.3, "Mp": 1.35, "b": 1.4},
        {"Kp": 1.3, "alpha": 0.75, "Mp": 0.65, "b": 0.75},
    ],
)
def test_the_display_fit_recovers_constants_it_was_not_told(factors):
    truth = replace(PAPER_DISPLAY, **{k: getattr(PAPER_DISPLAY, k) * f for k, f in factors.items()})
    x, volts, seg = bench_frames(truth, 0.2, seed=1)
    fit = fit_display(x, volts, seg, 1e-3, 0.2)
    for key in ("Kp", "alpha", "Mp"):
        est = getattr(fit, key)
        assert est.value == pytest.approx(getattr(truth, key), rel=0.01), key
        assert est.lo < est.hi
    assert fit.b.value == pytest.approx(truth.b, rel=0.05)


def test_a_display_fit_without_a_sweep_is_refused():
    x, volts, seg = bench_frames(PAPER_DISPLAY, 0.2, seed=2, cut_share=0.0)
    with pytest.raises(InputError, match="never changed"):
        fit_display(x[:700], np.zeros(700), seg[:700], 1e-3, 0.2)
    with pytest.raises(InputError, match="frames off the end stops"):
        fit_display(x[:100], volts[:100], seg[:100], 1e-3, 0.2)


def test_a_reading_repeated_on_a_faster_line_gives_its_own_rate():
    rng = np.random.default_rng(0)
    hx711 = np.repeat(rng.normal(0, 5, 20).round(), 12)  # 80 Hz held on a 1 kHz line
    assert held_rate(hx711, 1000.0) == pytest.approx(1000.0 / 12)
    quiet = rng.normal(0, 0.6, 240).round()  # an ADC at rest: changes at random
    assert held_rate(quiet, 1000.0) is None
    assert held_rate(np.zeros(240), 1000.0) is None
