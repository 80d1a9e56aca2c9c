"""A coarse ADC's staircase closure rebuilt from its level crossings."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from tissuecli.identify.derivatives.staircase import staircase
from tissuecli.identify.predict import _smoothed

FS = 8000.0  # Hz
DT = 1.0 / FS


def _motion() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A squeeze of two tones over 1.5 s at 8 kHz: closure (m), speed, acceleration."""
    t = np.arange(int(1.5 * FS)) * DT
    parts = [(1e-3, 2 * np.pi * 1.3, 0.0), (0.4e-3, 2 * np.pi * 2.9, 1.0)]
    x = 2e-3 + sum(a * np.sin(w * t + p) for a, w, p in parts)
    v = sum(a * w * np.cos(w * t + p) for a, w, p in parts)
    acc = -sum(a * w**2 * np.sin(w * t + p) for a, w, p in parts)
    return x, v, acc


def _read(x: np.ndarray, noise_steps: float, seed: int = 1) -> tuple[np.ndarray, float]:
    """``x`` through an 8-bit ADC spanning it with a 10 % margin either side, after
    white noise of ``noise_steps`` ADC steps; and the step (m)."""
    step = 1.2 * float(np.ptp(x)) / 256
    noise = np.random.default_rng(seed).normal(0.0, noise_steps * step, x.size)
    return np.round((x + noise) / step) * step, step


def _rms(u: np.ndarray, w: int) -> float:
    """RMS of ``u`` away from the end windows (``w`` samples)."""
    return float(np.sqrt(np.mean(u[w:-w] ** 2)))


@pytest.mark.parametrize("w", [101, 201, 401])
@pytest.mark.parametrize("k", [1, 2])
def test_a_clean_staircase_is_rebuilt_within_its_crossing_times(w: int, k: int) -> None:
    """Without noise each level crossing is known within a sample: the rebuilt closure
    is noise of the SD ``staircase`` states (``step / sqrt(12 s)``, ``s`` samples a
    step) to a smoother. Its speed and acceleration through a cubic Savitzky-Golay
    window are within three times that noise through the kernel plus the kernel's own
    error on the true motion (0.35-0.62 times that bound today); the reading as it is,
    a sawtooth of one step that does not average out, misses the bound by 1.3-2.8
    times at every window."""
    x, v, acc = _motion()
    q, step = _read(x, 0.0)
    rebuilt = staircase(q, DT)
    assert rebuilt is not None
    closure, sd = rebuilt
    samples_a_step = (q.size - 1) / np.count_nonzero(np.diff(q))
    assert sd == pytest.approx(step / np.sqrt(12 * samples_a_step))
    truth = (v, acc)[k - 1]
    exact, gain = _smoothed(x, w, 3, k, DT)
    bound = 3 * sd * gain + _rms(exact - truth, w)
    got, _ = _smoothed(closure, w, 3, k, DT, sd)
    assert _rms(got - truth, w) <= bound
    read, _ = _smoothed(q, w, 3, k, DT, sd)
    assert _rms(read - truth, w) > bound  # the premise: the stairs do not average out


def test_chatter_near_each_crossing_is_one_crossing() -> None:
    """With noise of a tenth of a step before the ADC the reading chatters between two
    levels near each crossing; taken together, the chatter stays one crossing and the
    rebuilt closure's speed and acceleration (201 samples) keep under half the
    reading's error (2.6 and 2.7 times under today)."""
    x, v, acc = _motion()
    q, _ = _read(x, 0.1)
    clean, _ = _read(x, 0.0)
    # the premise: chatter (1538 steps read where 728 are crossed)
    assert np.count_nonzero(np.diff(q)) > 1.5 * np.count_nonzero(np.diff(clean))
    rebuilt = staircase(q, DT)
    assert rebuilt is not None
    closure, sd = rebuilt
    for k, truth in ((1, v), (2, acc)):
        got, _ = _smoothed(closure, 201, 3, k, DT, sd)
        read, _ = _smoothed(q, 201, 3, k, DT, sd)
        assert _rms(got - truth, 201) < 0.5 * _rms(read - truth, 201)


@pytest.mark.parametrize("noise_steps", [0.5, 1.0])
def test_a_dithered_reading_is_no_staircase(noise_steps: float) -> None:
    """Noise of half a step or more moves the reading every few samples: it is left as
    read (at a quarter of a step the rebuilt acceleration was already no better)."""
    x, _, _ = _motion()
    q, _ = _read(x, noise_steps)
    assert staircase(q, DT) is None


def test_values_off_an_adcs_levels_are_no_staircase() -> None:
    """Exported floats whose repeated values are not whole steps apart are left as read."""
    x, _, _ = _motion()
    q, step = _read(x, 0.0)
    levels, index = np.unique(q, return_inverse=True)
    uneven = levels + step * 0.3 * np.random.default_rng(2).random(levels.size)
    assert staircase(uneven[index], DT) is None


def test_a_step_across_a_hole_is_read_at_its_middle() -> None:
    """Samples left out (lost or clipped, interpolated stand-ins in their place), some
    of them where the reading steps: the step is read at the hole's middle, so the
    rebuilt closure stays within a step of the true closure, as it is without holes
    (left unread, the closure was rebuilt up to two thirds of a step off until the next
    crossing). The bound: a crossing's time is known within the hole's two samples, at
    a speed of at most ``max|v| dt`` a sample, on top of the error without holes."""
    x, v, _ = _motion()
    q, step = _read(x, 0.0)
    moves = np.flatnonzero(np.diff(q)) + 1
    valid = np.ones(q.size, bool)
    valid[moves[::7]] = False  # every seventh step's first sample left out
    held = q.copy()
    held[~valid] = 0.5 * (q[np.flatnonzero(~valid) - 1] + q[np.flatnonzero(~valid) + 1])
    whole = staircase(q, DT)
    holed = staircase(held, DT, valid)
    assert whole is not None and holed is not None
    inner = slice(moves[0], moves[-1])
    off_whole = float(np.max(np.abs(whole[0] - x)[inner]))
    off_holed = float(np.max(np.abs(holed[0] - x)[inner]))
    assert off_holed <= off_whole + 2 * float(np.max(np.abs(v))) * DT


def test_a_turn_is_rebuilt_as_the_parabola_through_it() -> None:
    """Points on a parabola whose vertex is one of them (a turn between two crossings
    of one threshold, with a crossing either side): the rebuilt curve is that parabola
    on both spans about the vertex, to rounding. A monotone cubic takes the harmonic
    mean of the chords at the neighbours, three quarters of the parabola's slope here,
    and misses it by 7 % of the rise to the vertex."""
    from scipy.interpolate import PchipInterpolator

    from tissuecli.identify.derivatives.staircase import _through

    t = np.array([-2.0, -1.0, 0.0, 1.0, 2.0])
    v = 1.0 - t**2
    fine = np.linspace(-1.0, 1.0, 201)
    assert np.max(np.abs(_through(t, v)(fine) - (1.0 - fine**2))) < 1e-12
    assert np.max(np.abs(PchipInterpolator(t, v)(fine) - (1.0 - fine**2))) > 0.05


def test_a_sinusoids_turns_are_rebuilt_at_their_height() -> None:
    """Noise-free sinusoids of 3-13 steps amplitude read at 1 kHz, 2000 samples a
    half period: the rebuilt closure's extremes lie on the true ones within 0.005 of a
    step on average. A sinusoid falls from its apex more slowly than a parabola as it
    goes deeper; the parabola through two thresholds' widths put the apexes 0.023 of a
    step low on average, and the acceleration through a fit's filter short with them."""
    rate, f = 1000.0, 0.5
    t = np.arange(int(20 * rate)) / rate
    per = int(rate / f)
    errors = []
    for amp in np.linspace(3.05, 12.95, 23):
        x = amp * np.sin(2 * np.pi * f * t) + 0.37
        rebuilt = staircase(np.round(x) * 1e-4, 1 / rate)
        assert rebuilt is not None
        y = rebuilt[0] / 1e-4
        for m in range(1, 19):  # the extremes at (2m + 1) quarter periods
            at = (2 * m + 1) * per // 4
            near = y[at - per // 8 : at + per // 8]
            top = near.max() if m % 2 == 0 else -near.min()
            errors.append(top - (amp + (0.37 if m % 2 == 0 else -0.37)))
    assert abs(float(np.mean(errors))) < 0.005


@settings(max_examples=100, deadline=None)
# a reading that jumps two levels in one sample: its turn one sample from its
# neighbour, whose parabola slope swung the cubic beyond it 3.2 steps off the readings
@example(seed=38, bits=6, noise_steps=0.21875, tempo=0.2, holes=0.0)
@given(
    seed=st.integers(0, 2**32 - 1),
    bits=st.integers(6, 11),
    noise_steps=st.floats(0.0, 0.3),
    tempo=st.floats(0.2, 5.0),
    holes=st.floats(0.0, 0.05),
)
def test_a_rebuilt_closure_stays_within_its_readings(
    seed: int, bits: int, noise_steps: float, tempo: float, holes: float
) -> None:
    """Any squeeze (two tones at any tempo) read through an ADC of 6-11 bits after noise
    of up to 0.3 steps, with up to 5 % of its samples left out: the rebuilt closure,
    where the reading is a staircase, is finite and never further from the reading than
    a step and a half plus four noise SDs (it passes through the crossings, between
    the readings either side of each, and the turns' parabolas stay within the level
    they turn in). About a third of the draws read as a staircase; the worst of 300 lay
    0.94 step beyond the noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(1.5 * FS)) * DT
    x = 2e-3 + 1e-3 * np.sin(2 * np.pi * 1.3 * tempo * t + rng.uniform(0, 6.3))
    x += 0.4e-3 * np.sin(2 * np.pi * 2.9 * tempo * t + rng.uniform(0, 6.3))
    step = 1.2 * float(np.ptp(x)) / 2**bits
    q = np.round((x + rng.normal(0.0, noise_steps * step, x.size)) / step) * step
    valid = rng.random(x.size) >= holes
    valid[[0, -1]] = True
    held = np.interp(t, t[valid], q[valid])
    rebuilt = staircase(held, DT, valid)
    if rebuilt is None:
        return
    closure, sd = rebuilt
    assert np.all(np.isfinite(closure)) and sd > 0
    off = np.abs(closure - q)[valid]
    assert float(np.max(off)) <= (1.5 + 4 * noise_steps) * step
