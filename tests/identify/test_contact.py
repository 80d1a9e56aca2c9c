"""Grasp detection scored sample by sample against scenes of known contact.

The scenes are :func:`tissuecli.sim.scenes.random_scene` grasp sessions of every family;
their true contact is the closure above 0. The seeds are fixed; each set was read wrong
by the detector before the change its test holds (in brackets).
"""

from __future__ import annotations

import numpy as np
import pytest

from tissuecli.core.session import Session
from tissuecli.identify.contact import _flat, _min_free, _noise_sd, find_contact
from tissuecli.sim.scenes import FAMILIES, random_scene

PAPER = [f for f in FAMILIES if f.startswith("paper")]


def _read(seed: int) -> tuple[bool, float, float]:
    """(read as one contact, share of free samples read in contact, share of contact
    samples read free)."""
    scene = random_scene(seed, max_samples=20_000, contact="grasps")
    found = find_contact(scene.session)
    true = scene.x > 0
    return (
        found.all_contact,
        float(np.mean(found.mask[~true])),
        float(np.mean(~found.mask[true])),
    )


@pytest.mark.parametrize(
    "seed", [5033, 5178, 5196, 5227, 5253, 5269, 5292, 5156, 5096, 5155, 5166, 1127934]
)
def test_short_free_stretches_of_fast_sessions_are_found(seed: int) -> None:
    """Sessions of 5.5-9.8 kHz cut at 20,000 samples, whose jaws rest open for only
    0.04-0.1 s between grasps, and one at 406 Hz whose quantised closure's moving mean
    spans one step exactly (all read as one contact when a free stretch had to
    last 0.1 s and stay strictly within the step): their grasps are found and their
    free jaws read free."""
    whole, free_as_contact, _ = _read(seed)
    assert not whole
    assert free_as_contact < 0.01


@pytest.mark.parametrize("seed", [5109, 5123, 5152, 5181, 5209])
def test_weak_grasps_of_noisy_sessions_are_found(seed: int) -> None:
    """Noisy sessions (5.6-9.3 % of the force range) whose smoothed grasp force stays
    under 6 SDs of the raw force's noise (no grasp found at all, every contact sample
    read free): thresholds in the smoothed force's own noise find grasps, and no more
    than a tenth of a percent of the free samples are read in contact."""
    whole, free_as_contact, contact_as_free = _read(seed)
    assert not whole
    assert free_as_contact < 1e-3
    assert contact_as_free < 0.7


def _read_fitted(seed: int) -> tuple[bool, float, float]:
    """:func:`_read` on the first 70 % of a paper-form scene of at most 10,000 samples,
    the part the generalisation benchmark fits."""
    scene = random_scene(seed, families=PAPER, max_samples=10_000)
    i = int(np.searchsorted(scene.session.time, scene.session.time[0] + 0.7 * np.ptp(
        scene.session.time)))  # fmt: skip
    found = find_contact(scene.session.replace(scene.session.time[:i],
                                               scene.session.force[:i],
                                               scene.session.position[:i]))  # fmt: skip
    true = scene.x[:i] > 0
    return (
        found.all_contact,
        float(np.mean(found.mask[~true])),
        float(np.mean(~found.mask[true])),
    )


@pytest.mark.parametrize("seed", [11768711, 11768714])
def test_rests_shorter_than_two_smoothing_widths_are_found(seed: int) -> None:
    """1 s sessions at 9-10 kHz whose jaws rest open for 20-40 ms between grasps (one
    to two smoothing widths of 20 ms), read as one contact when a rest had to last two
    widths; and where the damped tissue's pull on release kept the smoothed force off
    the free level for most of the break, the break was closed as shorter than
    MIN_GAP_S, merging the grasps (44 % of the free samples read in contact). A rest
    seen on the closure now ends a grasp."""
    whole, free_as_contact, _ = _read_fitted(seed)
    assert not whole
    assert free_as_contact < 0.05


def test_grasp_edges_are_placed_within_the_smoothing() -> None:
    """Over 40 grasp scenes of every family: none read as one contact (1 before), at
    most 2 % of the free samples read in contact in any (4.1 % before: the moving mean
    spreads each edge by half its width), and the median share of contact samples read
    free under 5 % (16 % before)."""
    readings = [_read(seed) for seed in range(100, 140)]
    assert not any(whole for whole, _, _ in readings)
    assert max(fc for _, fc, _ in readings) < 0.02
    assert float(np.median([cf for _, _, cf in readings])) < 0.05


def test_a_free_stretch_is_a_few_smoothing_widths_and_samples() -> None:
    """One smoothing width at a fast rate, never fewer than 32 samples, never more
    than 0.1 s."""
    assert _min_free(1 / 8000, 160) == 160
    assert _min_free(1 / 1000, 20) == 32
    assert _min_free(1 / 400, 8) == 32
    assert _min_free(1 / 250, 5) == 25
    assert _min_free(1 / 100, 2) == 10


def test_flatness_of_a_short_stretch() -> None:
    """A stretch shorter than four smoothing widths is still told flat or sloping: a
    level holds, a slope of many noise SDs does not."""
    rng = np.random.default_rng(0)
    width, noise = 160, 0.01
    raw = noise * rng.standard_normal(600)
    level = np.convolve(raw, np.ones(width) / width, mode="same")[100:500]
    assert _flat(level, noise, width)
    assert not _flat(level + np.linspace(0, 20 * noise, level.size), noise, width)


def test_a_coarsely_quantised_force_keeps_the_raw_thresholds() -> None:
    """A force whose noise is about one quantisation step (a moving mean of it is a
    staircase): the thresholds stay in the raw force's noise, so a grasp of 4 noise SDs
    is not read, while a dithered force of the same grasp is."""
    rng = np.random.default_rng(1)
    rate, n = 2000.0, 8000
    t = np.arange(n) / rate
    grasp = ((t % 1.0) > 0.5).astype(float)
    noise = 0.01
    position = 1e-3 * grasp + 1e-6 * rng.standard_normal(n)
    for step, read in ((noise, False), (noise / 20, True)):
        force = 4 * noise * grasp + noise * rng.standard_normal(n)
        force = np.round(force / step) * step
        session = Session(t, force, position)
        found = find_contact(session)
        assert (not found.all_contact and found.mask[grasp > 0].mean() > 0.9) == read


@pytest.mark.parametrize("rate_hz", [250.0, 1000.0, 10000.0])
def test_the_force_noise_is_not_read_from_the_signal_slope(rate_hz: float) -> None:
    """White noise on a squeeze sampled slowly: the estimate is the noise's SD (the MAD
    of n >= 1250 second differences has a relative SE near 1.1 / sqrt(n) < 4 %, so 10 %
    is over 2.5 SE), not the slope's steps (up to 0.15 N a sample at 250 Hz); a
    quantised noiseless force gives its quantisation's order, not the slope's."""
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 5.0, 1.0 / rate_hz)
    signal = 2.0 * (1.0 - np.cos(2.0 * np.pi * 1.5 * t))  # N, up to 4 N at 1.5 Hz
    sd = _noise_sd(signal + rng.normal(0.0, 0.01, t.size))
    assert 0.9 * 0.01 < sd < 1.1 * 0.01
    step = 4.0 / 255
    assert step / np.sqrt(12) <= _noise_sd(np.round(signal / step) * step) <= 0.75 * step
