"""Laws of long sessions scored on every stride-th filtered sample: the columns are the
full-rate filter's own outputs, the stride keeps the kernels' band, sessions up to the
threshold are scored on every sample, and a decimated fit agrees with the full one to a
small fraction of the posterior SDs."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.signal import lfilter

from tissuecli.core.terms import Law, Maxwell
from tissuecli.identify import BayesianFit, decimate
from tissuecli.identify.decimate import fit_stride
from tissuecli.identify.derivatives import Gaussian
from tissuecli.identify.derivatives.base import first_order, level_basis, padded_levels
from tissuecli.identify.design import design, noise_path
from tissuecli.identify.noise import filter_tau
from tissuecli.identify.spectrum import convolve_valid, convolve_valid_every
from tissuecli.sim.families import FAMILIES
from tissuecli.sim.synth import ForcepsModel, random_session, synthesize


@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(1, 400),
    m=st.integers(1, 60),
    step=st.integers(1, 70),
    seed=st.integers(0, 2**31),
)
def test_every_stride_th_output_of_the_full_convolution(
    n: int, m: int, step: int, seed: int
) -> None:
    if m > n:
        with pytest.raises(ValueError):
            convolve_valid_every(np.ones(n), np.ones(m), step)
        return
    rng = np.random.default_rng(seed)
    u, k = rng.standard_normal(n), rng.standard_normal(m)
    ref = convolve_valid(u, k)[::step]
    got = convolve_valid_every(u, k, step)
    assert got.shape == ref.shape
    # the same sums in another order: rounding of the largest partial sums
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12 * np.abs(u).max() * np.abs(k).sum())


def _kinematics(rate_hz: float, seconds: float):  # type: ignore[no-untyped-def]
    s = synthesize(ForcepsModel(seed=1, rate_hz=rate_hz), seconds)[0]
    return s, Gaussian()(s.time, s.position, s.force)


def test_sessions_up_to_the_threshold_are_scored_on_every_sample() -> None:
    # a 10 s session at 1 kHz and the longest measured recordings (36,000 samples)
    for rate, seconds in ((1000.0, 10.0), (1000.0, 36.0), (10000.0, 3.6)):
        _, kin = _kinematics(rate, seconds)
        assert kin.force.size <= decimate.DECIMATE_ABOVE
        assert fit_stride(kin) == 1
        assert kin.every(1) is kin


def test_stride_keeps_the_kernels_band_and_rows_per_correlation_time() -> None:
    s, kin = _kinematics(10000.0, 6.0)
    stride = fit_stride(kin)
    tau = filter_tau(kin.kernels[0])
    assert 2 <= stride <= tau / decimate.ROWS_PER_TAU
    nfft = 1 << 16
    above = np.fft.rfftfreq(nfft) > 0.5 / stride
    for k in kin.kernels:
        e = np.abs(np.fft.rfft(k, nfft)) ** 2
        assert e[above].sum() <= decimate.ALIAS_TOLERANCE * e.sum()
    # a kernel that is not band-limited (a moving average's sidelobes) is never decimated
    flat = type(kin)(**{**kin.__dict__, "kernels": (np.ones(801) / 801,) * 3})
    assert fit_stride(flat) == 1


def test_columns_on_the_coarse_grid_are_the_full_columns_kept_rows() -> None:
    s, kin = _kinematics(10000.0, 6.0)
    coarse = kin.every(40)
    law = Law.of(["x^3", "x", "maxwell", "xdot", "xddot", "offset"]).bind({"tau1": 0.3})
    full = design(law, kin, s.position, 1e-6)
    kept = design(law, coarse, s.position, 1e-6)
    rows = np.arange(kin.force.size) % 40 == 0
    np.testing.assert_allclose(kept, full[rows], rtol=1e-9, atol=1e-12 * np.abs(full).max())
    np.testing.assert_array_equal(coarse.time, kin.time[rows])
    assert coarse.dt == pytest.approx(kin.dt)
    # with samples left out (a hole, as lost frames or a grasp's edges make): the kept
    # rows are those of the full grid's multiples of the stride that remain
    valid = np.ones(len(s), bool)
    valid[20_000:20_500] = False
    holed = Gaussian()(s.time, s.position, s.force, valid)
    assert holed.rows is not None
    coarse = holed.every(40)
    assert coarse.rows is not None
    assert np.all(coarse.rows % 40 == 0)
    kept = np.isin(holed.rows, coarse.rows)
    np.testing.assert_allclose(
        design(law, coarse, s.position, 1e-6),
        design(law, holed, s.position, 1e-6)[kept],
        rtol=1e-9,
        atol=1e-12 * np.abs(full).max(),
    )
    np.testing.assert_array_equal(coarse.keep, np.asarray(holed.keep)[kept])


@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(0, 300),
    a=st.one_of(st.sampled_from([0.0, 1e-300, 1.0]), st.floats(0.0, 1.0)),
    seed=st.integers(0, 2**31),
)
def test_the_doubled_recursion_is_the_recursion(n: int, a: float, seed: int) -> None:
    u = np.random.default_rng(seed).standard_normal(n)
    ref, y = np.zeros(n), 0.0
    for k in range(n):
        y = a * y + u[k]
        ref[k] = y
    # pairwise sums: rounding of at most log2(n) additions of partial sums
    np.testing.assert_allclose(first_order(u, a), ref, rtol=0, atol=1e-13 * max(n, 1))


@pytest.mark.parametrize("stride", [1, 7, 40])
@pytest.mark.parametrize("tau", [1e-5, 3e-3, 0.3, 30.0, 1e4])
def test_a_relaxation_column_from_the_filtered_increments(stride: int, tau: float) -> None:
    # the recursion and the filter are linear from rest and commute: the same column as
    # the branch's series filtered, at the kept rows, with and without a hole; from a
    # branch faster than a sample to one that never relaxes within the record
    s, kin = _kinematics(10000.0, 3.0)
    valid = np.ones(len(s), bool)
    valid[12_000:12_300] = False
    branch = Maxwell(1, {"tau1": tau})
    a, b = branch.recursion(kin.dt)  # type: ignore[misc]
    assert branch.series(kin.dt, s.position, s.position, s.position) == pytest.approx(
        lfilter([b], [1.0, -a], np.diff(s.position, prepend=s.position[0])), rel=1e-9, abs=1e-15
    )
    for k in (kin, Gaussian()(s.time, s.position, s.force, valid)):
        coarse = k.every(stride)
        ref = coarse.smooth(branch.series(kin.dt, s.position, s.position, s.position))
        got = coarse.smooth_recursion(a, b, s.position)
        assert got.shape == ref.shape
        # rounding: the reference's own blocked recursion is within 2e-12 of its largest
        # value (for tau = 1e4 s, against a long-double recursion), the new one 2e-13
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-11 * np.abs(ref).max())


def test_contact_and_speed_columns_on_the_coarse_grid() -> None:
    # on the coarse grid, a closure on few ADC levels: each level's filtered indicator
    # (times the speed) once, each shape's columns their sum weighted by its values
    s, kin = _kinematics(10000.0, 6.0)
    x0 = float(np.median(s.position))
    law = Law.of(["contact", "contact*xdot", "xdot", "xddot", "offset"]).bind({"n": 1.7, "x0": x0})
    full = design(law, kin, s.position, 1e-6)
    coarse = kin.every(40)
    assert level_basis(coarse, s.position) is not None
    assert level_basis(coarse, s.position, speed=True) is not None
    rows = np.arange(kin.force.size) % 40 == 0
    np.testing.assert_allclose(
        design(law, coarse, s.position, 1e-6),
        full[rows],
        rtol=1e-9,
        atol=1e-12 * np.abs(full).max(),
    )
    contact = law.terms[0]
    slope = noise_path(contact, kin, s.position, 1e-6)[1]
    np.testing.assert_allclose(
        noise_path(contact, coarse, s.position, 1e-6)[1],
        slope[rows],
        rtol=1e-9,
        atol=1e-12 * np.abs(slope).max(),
    )
    # speed terms: the half window's speeds formed once, their mean filtered at the
    # kept rows alone
    speed = Law.of(["x", "xdot", "xdot|xdot|", "sign(xdot)", "xddot"])
    by_speed = design(speed, kin, s.position, 1e-6)
    np.testing.assert_allclose(
        design(speed, coarse, s.position, 1e-6),
        by_speed[rows],
        rtol=1e-9,
        atol=1e-12 * np.abs(by_speed).max(),
    )
    friction = speed.terms[3]
    slope = noise_path(friction, kin, s.position, 1e-6)[1]
    np.testing.assert_allclose(
        noise_path(friction, coarse, s.position, 1e-6)[1],
        slope[rows],
        rtol=1e-9,
        atol=1e-12 * np.abs(slope).max(),
    )
    # a closure on as many levels as samples has no basis: the columns are filtered
    smooth = s.position + 1e-9 * np.random.default_rng(0).standard_normal(len(s))
    assert level_basis(coarse, smooth) is None
    np.testing.assert_allclose(
        design(law, coarse, smooth, 1e-6),
        design(law, kin, smooth, 1e-6)[rows],
        rtol=1e-9,
        atol=1e-12 * np.abs(full).max(),
    )


@pytest.mark.parametrize("stride", [2, 7, 40, 41])
def test_closure_columns_read_into_the_padded_input_are_the_filtered_ones(stride: int) -> None:
    # a closure on many ADC levels, each flickering within a stride (no level basis
    # pays): the function's values at the levels are read straight into the strided
    # filter's padded input, bit for bit the sums of filtering them at every sample
    rng = np.random.default_rng(3)
    n = 20_000
    x = np.round((np.sin(np.linspace(0, 9, n)) + 0.05 * rng.standard_normal(n)) * 600) / 6e5
    force = rng.standard_normal(n)
    kin = Gaussian()(np.arange(n) * 1e-4, x, force).every(stride)
    assert padded_levels(x, kin.window, stride) is not None
    assert level_basis(kin, x) is None and level_basis(kin, x, speed=True) is None
    speed = np.gradient(x, kin.dt)
    for fn in (lambda z: np.abs(z) ** 1.7, lambda z: np.where(z > 0, z, 0.0)):
        assert np.array_equal(kin.smooth_pointwise(fn, x), kin.smooth(kin.pointwise(fn, x)))
        assert np.array_equal(
            kin.smooth_pointwise(fn, x, speed), kin.smooth(kin.pointwise(fn, x) * speed)
        )
    # a closure on as many levels as samples is filtered as before
    smooth = x + 1e-12 * rng.standard_normal(n)
    assert padded_levels(smooth, kin.window, stride) is None


def _both(session, monkeypatch, above: int):  # type: ignore[no-untyped-def]
    monkeypatch.setattr(decimate, "DECIMATE_ABOVE", 10**12)
    full = BayesianFit().fit(session)
    monkeypatch.setattr(decimate, "DECIMATE_ABOVE", above)
    coarse = BayesianFit().fit(session)
    return full, coarse


@pytest.mark.parametrize(
    "session",
    [
        pytest.param(lambda: synthesize(ForcepsModel(seed=1, rate_hz=10000.0), 3.0)[0], id="paper"),
        pytest.param(
            lambda: random_session(
                FAMILIES["one branch"], rate_hz=10000.0, seed=300, duration_s=3.0, bits=12
            )[0],
            id="branch",
        ),
    ],
)
def test_a_decimated_fit_agrees_with_the_full_one(session, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    # 30,000 samples, decimated below the usual threshold to keep the test short
    s = session()
    full, coarse = _both(s, monkeypatch, 10_000)
    assert coarse.kinematics_.force.size == full.kinematics_.force.size  # reported in full
    assert coarse.best_.name == full.best_.name
    pf, pc = full.best_.posterior, coarse.best_.posterior
    # the kept rows carry the same information: estimates within a small fraction of
    # the posterior SD (measured 0.00003-0.015 SD). The data weight's batch-means check
    # reads blocks of 5 tau on either grid, whose edges differ: its own sampling error
    # with about 100 blocks, sqrt(2/100) = 14 %, bounds the weights' difference (7 %
    # measured), and half of it the SDs' (4 %)
    assert np.all(np.abs(pc.mean - pf.mean) <= 0.1 * pf.sd)
    np.testing.assert_allclose(pc.sd, pf.sd, rtol=0.08)
    assert coarse.n_eff_ == pytest.approx(full.n_eff_, rel=0.15)
    assert coarse.best_.probability == pytest.approx(full.best_.probability, abs=0.05)


@pytest.mark.slow
def test_a_long_session_decimated_at_the_threshold(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    s = synthesize(ForcepsModel(seed=1, rate_hz=10000.0), 20.0)[0]
    full, coarse = _both(s, monkeypatch, decimate.DECIMATE_ABOVE)
    assert coarse.best_.name == full.best_.name
    pf, pc = full.best_.posterior, coarse.best_.posterior
    assert np.all(np.abs(pc.mean - pf.mean) <= 0.1 * pf.sd)


def test_functions_of_the_closure_on_its_adc_levels_are_those_of_every_sample() -> None:
    """On every sample too, a closure an ADC has put on few levels (the simulated
    forceps' 8 bits: 96 levels in 10,000 samples) has a term, its slope and curvature
    evaluated on the levels and read back: the same numbers, to the last bit."""
    from tissuecli.core.terms import term
    from tissuecli.sim.synth import Sensors

    s = synthesize(ForcepsModel(seed=1, sensors=Sensors(bits=8)), 10.0)[0]
    kin = Gaussian()(s.time, s.position, s.force)
    assert kin.stride == 1 and np.unique(s.position).size <= s.position.size // 8
    x = np.asarray(s.position)
    contact = Law.of(["contact"]).bind({"n": 1.7, "x0": float(np.quantile(x, 0.2))}).terms[0]
    for t in (term("x^3"), contact):
        for fn in (t, t.derivative, t.curvature):
            np.testing.assert_array_equal(kin.pointwise(fn, x), fn(x))
