"""Grasp detection scored sample by sample against scenes of known contact.

The scenes are :func:`tissuecli.sim.scenes.random_scene` grasp sessions of every family;
their true contact is the closure above 0. The seeds are fixed; each set was read wrong
by the detector before the change its test holds (in brackets).
"""

from __future__ import annotations

import numpy as np
import pytest

from tissuecli.core.session import Session
from tissuecli.identify.contact import _extend, _flat, _min_free, _noise_sd, find_contact
from tissuecli.sim.scenes import FAMILIES, random_scene

OTHER = [f for f in FAMILIES if not f.startswith("paper")]
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


def _other(seed: int) -> tuple[float, float, float]:
    """A grasp scene of the families beyond the paper's forms, cut at 10,000 samples (as
    the generalisation benchmark draws them): (RMS over the session of the true force on
    contact samples read free, in noise SDs; share of free samples read in contact;
    share of the last grasp read in contact)."""
    scene = random_scene(seed, families=OTHER, max_samples=10_000)
    found = find_contact(scene.session)
    true = scene.x > 0
    missed = np.where(true & ~found.mask, scene.force, 0.0)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], true.astype(np.int8), [0]])))
    last = slice(int(edges[-2]), int(edges[-1]))
    return (
        float(np.sqrt(np.mean(missed**2))) / scene.noise_n,
        float(np.mean(found.mask[~true])),
        float(np.mean(found.mask[last])),
    )


@pytest.mark.parametrize("seed", [5150127, 5150018])
def test_a_grasp_cut_by_the_end_of_the_recording_is_found(seed: int) -> None:
    """The recording ends in a grasp whose force stands 7-22 noise SDs high for less
    than 0.1 s above the threshold (none of it read in contact when a grasp had to last
    0.1 s; the held-out end of a session is exactly there): read in contact, and no
    free sample read in contact."""
    missed, free_as_contact, last = _other(seed)
    assert last > 0.9
    assert free_as_contact < 1e-3
    assert missed < 0.3  # 1.7-3.8 before


@pytest.mark.parametrize("seed", [5150121, 5150115, 5150013])
def test_weak_contact_is_found_by_wider_means(seed: int) -> None:
    """Noisy two-branch grasps (8-15 bits, 8-9 % noise) and a Hunt-Crossley law near
    zero force below its contact point: stretches of contact a noise SD above the
    free-jaw level, for hundreds of samples, were read free (the true force there 0.6-1.9
    noise SDs RMS over the session); wider moving means find them, and read no free
    sample in contact."""
    missed, free_as_contact, _ = _other(seed)
    assert missed < 0.4
    assert free_as_contact < 1e-3


def test_wider_means_raise_no_false_alarm() -> None:
    """Square grasps of 50 noise SDs between free stretches of white noise, 1 s each at
    2 kHz: no sample further than a few from a true edge is read in contact (the
    thresholds are 6 SDs of each mean's noise, about 2e-9 per independent window; an
    edge pushed out takes in a noise sample beyond 3 SDs, 0.27 %)."""
    rate, n = 2000.0, 20_000
    t = np.arange(n) / rate
    grasp = (t % 2.0) > 1.0
    edges = np.flatnonzero(np.diff(grasp.astype(np.int8))) + 1
    near = np.zeros(n, bool)
    for e in edges:
        near[max(e - 8, 0) : e + 8] = True
    wrong = 0
    for seed in range(8):
        rng = np.random.default_rng(seed)
        position = np.where(grasp, 1e-3, -1e-3) + 1e-6 * rng.standard_normal(n)
        force = 0.5 * grasp + 0.01 * rng.standard_normal(n)
        found = find_contact(Session(t, force, position))
        wrong += int(np.count_nonzero(found.mask & ~grasp & ~near))
        assert found.mask[grasp].mean() > 0.99
    assert wrong == 0


def test_an_edge_is_pushed_to_the_foot_of_a_fast_release() -> None:
    """A release that falls from 50 noise SDs to the level over 30 samples, its edge read
    a third of the way down: pushed out to where the ramp comes within 3 SDs of the
    level (the 28th of its samples). Into free noise, the edge moves with the
    probability that a sample lies beyond 3 SDs (0.27 %; at most 2 % in 2000 draws,
    over 6 binomial SEs)."""
    rng = np.random.default_rng(0)
    noise = 0.01
    ramp = np.concatenate([np.full(100, 0.5), np.linspace(0.5, 0.0, 30), np.zeros(100)])
    mask = np.zeros(ramp.size, bool)
    mask[:110] = True
    out = _extend(mask, ramp + noise * rng.standard_normal(ramp.size), noise, 40)
    assert 126 <= int(out.sum()) <= 130
    moved = []
    for _ in range(2000):
        mask = np.zeros(200, bool)
        mask[:100] = True
        moved.append(int(_extend(mask, rng.standard_normal(200), 1.0, 50).sum()) - 100)
    assert np.mean(np.array(moved) > 0) < 0.02
    assert max(moved) <= 3


def _edges(mask: np.ndarray) -> np.ndarray:
    return np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(np.int8), [0]])))


@pytest.mark.parametrize(
    "seed, families, first",
    [(7301013, ["friction", "friction+offset", "offset"], 0), (6587750, OTHER, 1)],
)
def test_edges_where_the_force_steps_through_the_level(
    seed: int, families: list[str], first: int
) -> None:
    """Grasps whose force crosses the free-jaw level on its way: an offset law's damping
    pulls it 6 noise SDs below the level while the jaws open, then it steps back at the
    release (11 bits, 3.3 kHz); a massive law's force leaps at the touch and falls
    through the level (8 bits, 5.5 kHz, noise 1.2 quantisation steps: not dithered, so
    no edge was placed at all). Their edges were read 7-48 samples late (14 at the
    first's release: the half widths' means either side of the step average near the
    level), and the law's force put on free jaws there. Least squares with the grasp's
    force a parabola puts each within 2 samples (the steps stand 6 to 50 noise SDs
    high, where a change point falls within a sample or two). From grasp ``first`` on:
    the second scene's first grasp begins with 0.3 s of force 2-6 noise SDs above the
    level on a coarse ADC, contact the thresholds do not reach."""
    scene = random_scene(seed, families=families, max_samples=10_000)
    found = _edges(find_contact(scene.session).mask)
    true = _edges(scene.x > 0)
    assert found.size == true.size
    assert np.max(np.abs(found[2 * first :] - true[2 * first :])) <= 2


@pytest.mark.parametrize("seed", [100, 103, 107, 127, 129, 133, 135])
def test_a_stretch_read_with_the_sessions_levels_finds_the_sessions_grasps(seed: int) -> None:
    """A long session fitted block by block finds each block's grasps against the whole
    session's free-jaw level, thresholds, jaws resting open and coarse scales' noise:
    the middle third of a grasp scene, read with 2 s more either side, is then in
    contact exactly where the whole session is. (Read alone, six of these stretches
    differ from the session in 1 to 1,816 samples; with the session's level and
    thresholds but their own coarse scales' noise, four in 2 to 575: seeds 103, 127,
    129 and 135. Seed 100 rests its jaws open.)"""
    session = random_scene(seed, max_samples=20_000, contact="grasps").session
    whole = find_contact(session)
    assert not whole.all_contact
    n = len(session)
    margin = int(2.0 / float(np.median(np.diff(session.time))))
    a, b = n // 3, 2 * n // 3
    lo, hi = max(0, a - margin), min(n, b + margin)
    t, f, x = (u[lo:hi] for u in (session.time, session.force, session.position))
    part = find_contact(session.replace(t, f, x), whole)
    np.testing.assert_array_equal(part.mask[a - lo : b - lo], whole.mask[a:b])
