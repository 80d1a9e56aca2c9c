"""A PC's epoch stamps (seconds, milliseconds or microseconds since 1970) are read as
well as a logger's own: their resolution, their clock and their lost samples."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tissuecli.core.timebase import resolution, sample_clock
from tissuecli.formats.recording import epoch_unit, read_recording

EPOCH_S = 1.7e9


def _stamps(rate_hz: float, n: int, jitter_s: float, lost: list[int], seed: int = 0):
    rng = np.random.default_rng(seed)
    k = np.delete(np.arange(n), lost)
    return k, k / rate_hz + rng.uniform(0.0, jitter_s, k.size)


@pytest.mark.parametrize("offset", [0.0, EPOCH_S])
def test_millisecond_stamps_have_millisecond_resolution_whatever_their_origin(offset):
    """At 1.7e9 s a tolerance relative to the stamps took every millisecond stamp for a
    whole second, and the clock then counted steps of up to a second as one sample."""
    _, t = _stamps(90.0, 3000, 2e-3, [])
    assert resolution(np.round(offset + t, 3)) == pytest.approx(1e-3)


@pytest.mark.parametrize("offset", [0.0, EPOCH_S])
def test_epoch_stamps_give_the_clock_and_the_lost_samples(offset: float) -> None:
    k, t = _stamps(90.0, 3000, 1.5e-3, [500, 1700, 1701])
    numbers, clock, base = sample_clock(np.round(offset + t, 3))
    assert numbers is not None and base.lost == 3
    np.testing.assert_array_equal(numbers, k)
    assert base.rate_hz == pytest.approx(90.0, rel=1e-5)
    assert np.max(np.abs(clock - offset - k / 90.0)) < 2e-3


@pytest.mark.parametrize(("scale", "unit"), [(1.0, "s"), (1e3, "ms"), (1e6, "us"), (1e9, "ns")])
def test_epoch_units_are_told_by_the_stamps_size(scale: float, unit: str) -> None:
    _, t = _stamps(100.0, 50, 0.0, [])
    assert epoch_unit(np.round((EPOCH_S + t) * scale, 3 if scale == 1.0 else 0)) == unit
    assert epoch_unit(t * scale) is None  # a logger's own clock from power-up


@pytest.mark.parametrize(("scale", "unit"), [(1.0, "s"), (1e3, "ms"), (1e6, "us")])
def test_a_table_of_epoch_stamps_imports_without_units(tmp_path: Path, scale, unit) -> None:
    k, t = _stamps(80.0, 2000, 2e-3, [100])
    stamps = np.round((EPOCH_S + t) * scale, 3 if unit == "s" else 0)
    x = 2e-3 + 1e-3 * np.sin(2 * np.pi * 0.7 * t)
    path = tmp_path / "gripper.csv"
    rows = "\n".join(f"{a:.17g},{350.0 * b:.6g},{b:.6g}" for a, b in zip(stamps, x, strict=True))
    path.write_text("time,force,position\n" + rows + "\n")
    session, report = read_recording(path)
    assert report.units["time"].startswith(unit) and "1970" in report.units["time"]
    assert session.time[0] == 0.0
    assert session.rate_hz == pytest.approx(80.0, rel=1e-3)
    assert session.duration_s == pytest.approx(1999 / 80.0, abs=5e-3)


def test_host_stamps_since_1970_map_the_device_clock_as_well_as_small_ones() -> None:
    """A live recording stamps arrivals with the PC's epoch clock: the map from device
    time is fitted on centred sums, so 1.7e9 s costs it nothing."""
    from tissuecli.core.clock import fit_clock_map

    device = np.arange(0.0, 300.0, 1e-3)
    latency = np.random.default_rng(0).exponential(2e-4, device.size) + 1e-4
    maps = [
        fit_clock_map(device, base + 3.0 + device * (1 + 200e-6) + latency)
        for base in (0.0, EPOCH_S)
    ]
    small, epoch = maps
    assert small is not None and epoch is not None
    assert abs(epoch.drift_ppm - small.drift_ppm) < 0.1 * small.drift_uncertainty_ppm
    assert abs((epoch.offset_s - EPOCH_S) - small.offset_s) < 1e-5


class _Column:
    """Stamps read a slice at a time, as the files layer reads a session's column."""

    def __init__(self, t: np.ndarray) -> None:
        self.t = t
        self.reads = 0

    def __len__(self) -> int:
        return self.t.size

    def __getitem__(self, rows: slice) -> np.ndarray:
        self.reads += 1
        return self.t[rows].copy()


def _kinds(n: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(7)
    i = np.arange(n)
    lost = np.sort(rng.choice(n, n // 20, replace=False))
    return {
        "exact": i / 1000,
        "epoch": EPOCH_S + i / 1000,
        "coarse": np.floor(i * 3.245) / 1000,
        "jitter": i * 3.245e-3 + rng.uniform(-3e-4, 3e-4, n),
        "locked": np.delete(i, [5, 6, 7]) * 1e-3 + rng.uniform(-3.5e-4, 3.5e-4, n - 3),
        "lost": np.delete(i, lost) / 1000,
        "repeated": np.floor(i / 1200 * 1e3) / 1e3,
        "irregular": np.cumsum(rng.exponential(1e-3, n)),
    }


@pytest.mark.parametrize("max_gaps", [1 << 16, 100])
def test_stamps_read_block_by_block_give_the_clock_of_the_whole_array(monkeypatch, max_gaps):
    """Blocks of 4096 stamps stand for a long recording read back from its file: the
    sample numbers, the clock's times and every figure are those of the stamps worked
    on whole, bit for bit (lost samples kept while the period is found, or counted
    by a pass when they are too many to keep)."""
    from tissuecli.core import timebase

    monkeypatch.setattr(timebase, "BLOCK", 4096)
    monkeypatch.setattr(timebase, "MAX_GAPS", max_gaps)
    for kind, t in _kinds(30_000).items():
        whole = timebase.fit_clock(t)
        column = _Column(t)
        streamed = timebase.fit_clock(column)
        passes = column.reads / (t.size // 4096 + 1)
        assert streamed.base == whole.base, kind
        assert streamed.exact == whole.exact, kind
        if whole.base.regular:
            for a, b in zip(streamed.numbers(), whole.numbers(), strict=True):
                np.testing.assert_array_equal(a, b)
            joined = np.concatenate(list(streamed.times()))
            np.testing.assert_array_equal(joined, np.concatenate(list(whole.times())))
            assert np.array_equal(joined, timebase.regularise(t)[0]), kind
        if kind == "exact":
            assert passes <= 7, passes  # a logger's exact stamps: a few passes, no more


@pytest.mark.parametrize("streamed", [False, True])
def test_irregular_stamps_of_a_long_recording_give_the_one_sample_median_rate(
    monkeypatch, streamed: bool
) -> None:
    """Beyond two blocks the typical step comes from an even sample of the steps: it
    must still be the step between neighbouring stamps, not over the sample's stride.
    Blocks of 1024 stamps make 30 000 stamps a long recording (stride 29, so ~1030
    sampled steps). Steps are exponential with mean 1 ms, median ln 2 ms; the median
    of N sampled steps has a standard error of 1/(2 f(m) sqrt(N)) = 1 ms/sqrt(N), 4.5 %
    of it, so 20 % is over four of those, while a step over 29 samples would make the
    rate about 40 times too low."""
    from tissuecli.core import timebase

    monkeypatch.setattr(timebase, "BLOCK", 1024)
    rng = np.random.default_rng(11)
    t = np.cumsum(rng.exponential(1e-3, 30_000))
    fit = timebase.fit_clock(_Column(t) if streamed else t)
    assert not fit.base.regular
    expected = 1.0 / (np.log(2) * 1e-3)
    assert fit.base.rate_hz == pytest.approx(expected, rel=0.2)
    assert fit.base.rate_hz == pytest.approx(1.0 / np.median(np.diff(t)), rel=0.2)
