"""The rounding error of a quantised closure through the derivative filters."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tissuecli.identify.quantisation import (
    FOURTH,
    PositionNoise,
    Staircase,
    analog_sd,
    dither_share,
    staircase_analog_sd,
    staircase_correction,
)


def _kernels(width: int = 41, sd: float = 6.0) -> list[np.ndarray]:
    """A Gaussian smoother and its second difference, the shapes of the position and
    acceleration kernels (per sample)."""
    t = np.arange(width) - width // 2
    g = np.exp(-0.5 * (t / sd) ** 2)
    g /= g.sum()
    return [np.convolve(g, [0.0, 1.0, 0.0]), np.convolve(g, [1.0, -2.0, 1.0])]


def _speed(c: float, n: int, lag: int = 0) -> np.ndarray:
    """Steps a sample at each of ``n`` samples from sample ``lag`` on."""
    return c * np.exp(0.2 * np.sin(2 * np.pi * (np.arange(n) + lag) / 333.0))


def _rounded_ramp(c: float, sigma: float, n: int, rng: np.random.Generator) -> np.ndarray:
    """The rounding error (steps) of a closure moving at about ``c`` steps a sample
    (the speed wanders by a fifth either way every 333 samples), with analog noise
    ``sigma`` steps."""
    speed = _speed(c, n)
    s = np.cumsum(speed) + rng.uniform()
    return np.round(s + rng.normal(0.0, sigma, n)) - s


@pytest.mark.parametrize("sigma", [0.0, 0.05, 0.3])
@pytest.mark.parametrize("c", [0.003, 0.03, 0.1, 0.5, 0.9])
def test_covariances_match_the_rounding_of_a_moving_closure(c: float, sigma: float) -> None:
    """The covariances at each sample's speed, averaged, are the mean energy and
    cross-product of the rounding error a moving closure leaves through the position
    and acceleration kernels, from sparse crossings to several a sample (where a speed
    of a whole step, or half a step, a sample repeats the error). 200,000 samples hold
    600 crossings at the slowest speed: with each crossing's energy spread by about
    its own size (its phase between samples), the mean is within 2 SEs, 6 %, of its
    expectation (the white model of the step's variance is off by up to 8 times)."""
    rng = np.random.default_rng(7)
    kx, ka = _kernels()
    e = _rounded_ramp(c, sigma, 200_000, rng)
    ex, ea = np.convolve(e, kx, mode="valid"), np.convolve(e, ka, mode="valid")
    cov = Staircase.of([kx, ka], PositionNoise(sigma, 1.0)).at(_speed(c, ea.size, kx.size // 2))
    assert float(np.mean(ea**2)) == pytest.approx(float(np.mean(cov[:, 1, 1])), rel=0.06)
    scale = np.sqrt(np.mean(ea**2) * np.mean(ex**2))
    assert abs(float(np.mean(ex * ea)) - float(np.mean(cov[:, 0, 1]))) <= 0.06 * scale


def test_limits_are_white_noise_and_a_held_closure() -> None:
    """Analog noise that dithers the steps leaves white noise of ``sigma^2 + q^2/12``;
    a closure at rest without analog noise has a constant error, which a derivative
    kernel (summing to zero) does not pass, but for the sawtooth's harmonics beyond
    the 4096 summed (1.5e-4 of its variance, taken as white)."""
    kx, ka = _kernels()
    q = 2e-6
    dithered = Staircase.of([kx, ka], PositionNoise(q, q))
    white = (q**2 + q**2 / 12) * np.array([[kx @ kx, kx @ ka], [ka @ kx, ka @ ka]])
    for c in (0.0, 0.01, 0.5):
        assert np.allclose(dithered.at(np.array([c]))[0], white, rtol=1e-6, atol=0)
    rest = Staircase.of([kx, ka], PositionNoise(0.0, q)).at(np.zeros(1))[0]
    assert rest[1, 1] == pytest.approx(0.0, abs=2e-4 * q**2 / 12 * (ka @ ka))
    assert rest[0, 0] == pytest.approx(q**2 / 12 * kx.sum() ** 2, rel=1e-3)


def test_a_staircase_is_not_white() -> None:
    """At a fiftieth of a step a sample, each crossing leaves a spike through the
    acceleration kernel: several times the energy white noise of the step's variance
    has (the benchmark's 8-9-bit sessions had 4.6-13.5 times)."""
    kx, ka = _kernels()
    table = Staircase.of([kx, ka], PositionNoise(0.0, 1.0))
    assert table.at(np.array([0.02]))[0, 1, 1] > 3 * (ka @ ka) / 12


def test_correction_sums_each_samples_covariance() -> None:
    """The correction is ``sum_n d_i d_j cov_ij(n)``; a column without a kernel (an
    offset) carries none."""
    kx, ka = _kernels()
    m = 500
    rng = np.random.default_rng(3)
    slopes = np.column_stack([rng.uniform(1, 2, m), np.ones(m), np.ones(m)])
    speed = rng.uniform(0, 0.1, m)  # m/s at dt = 1 s and q = 1 m: steps a sample
    noise = PositionNoise(0.01, 1.0)
    C = staircase_correction([kx, ka, np.zeros_like(kx)], slopes, speed, 1.0, noise)
    cov = Staircase.of([kx, ka], noise).at(speed)
    assert C[0, 1] == pytest.approx(float(np.sum(slopes[:, 0] * cov[:, 0, 1])), rel=1e-9)
    assert C[1, 1] == pytest.approx(float(np.sum(cov[:, 1, 1])), rel=1e-9)
    assert np.all(C[2] == 0) and np.all(C[:, 2] == 0)
    assert np.all(np.linalg.eigvalsh(C[:2, :2]) >= -1e-12 * C[1, 1])


@pytest.mark.parametrize("sigma", [0.03, 0.1, 0.3])
def test_analog_noise_from_fourth_differences(sigma: float) -> None:
    """A squeeze read through a coarse ADC: the analog noise beneath the staircase is
    recovered from the fourth differences within a fifth of itself or a hundredth of a
    step (the flat top of the spectrum reads about a tenth of a step for any of these)."""
    rng = np.random.default_rng(11)
    n = 20_000
    t = np.arange(n) / 1000.0
    s = 40.0 * (1 - np.cos(2 * np.pi * 0.7 * t))  # steps
    x = np.round(s + rng.normal(0.0, sigma, n))
    d4 = np.convolve(x, FOURTH, mode="valid")
    speed = np.abs(np.gradient(s))[2:-2]
    got = staircase_analog_sd(d4, speed, 1.0)
    assert abs(got - sigma) <= max(0.2 * sigma, 0.01)


@settings(max_examples=30, deadline=None)
@given(st.floats(0.0, 3.0), st.floats(1e-7, 1e-3))
def test_flat_top_inversion_is_monotone_and_bounded(ratio: float, step: float) -> None:
    """The analog SD behind a flat-top reading is no more than the reading, and the
    reading it predicts is the reading given."""
    sd = ratio * step
    measured = np.sqrt(sd**2 + step**2 / 12 * (1 - dither_share(ratio)))
    got = analog_sd(float(measured), step)
    assert 0.0 <= got <= measured * (1 + 1e-9)
    assert got == pytest.approx(sd, abs=2e-3 * step)


def test_noise_is_a_float_that_survives_pickling() -> None:
    noise = PositionNoise(1e-6, 4e-6)
    assert float(noise) == pytest.approx(np.sqrt(1e-12 + 16e-12 / 12))
    again = pickle.loads(pickle.dumps(noise))
    assert (again.analog, again.step) == (noise.analog, noise.step)
    assert noise.staircase and not PositionNoise(4e-6, 4e-6).staircase


@pytest.mark.parametrize("seed", [9028, 9029, 9034, 9040, 9051])
def test_correction_holds_the_rounding_the_column_carries(seed: int) -> None:
    """8-bit grasp sessions sampled at 1.4-2.4 kHz, where the jaws cross a step every
    30-300 samples: the fit's correction of the acceleration column is the energy the
    rounding actually put there (the simulation knows the true closure) within a factor
    1.6, and nearer to it than white noise of the same variance, which puts 2.7-6.8
    times less. (A session's crossings fall at one phase each: the realised energy of
    a few hundred crossings spreads about its expectation; the rest is the speed as the
    filter reads it near the turns.)"""
    from tissuecli.identify import BayesianFit
    from tissuecli.identify.derivatives.base import convolve_valid
    from tissuecli.identify.design import eiv_correction
    from tissuecli.sim.scenes import FAMILIES, random_scene

    families = [name for name in FAMILIES if name.startswith("paper")]
    scene = random_scene(seed, families=families, max_samples=20_000, contact="grasps")
    est = BayesianFit(forms=scene.tissue.law.name, seed=0).fit(scene.session)
    kin, noise, x = est.kinematics_, est.sigma_x_, est.session_.position
    assert isinstance(noise, PositionNoise) and noise.staircase
    ea = kin._rows(convolve_valid(x - scene.x, kin.kernels[2]))  # the column's own noise
    realised = float(ea @ ea)
    staircase = eiv_correction(est.best_.model, kin, x, noise)[2, 2]
    white = float(noise) ** 2 * float(kin.kernels[2] @ kin.kernels[2]) * ea.size
    assert 1 / 1.6 <= realised / staircase <= 1.6
    assert abs(np.log(realised / staircase)) < abs(np.log(realised / white))
