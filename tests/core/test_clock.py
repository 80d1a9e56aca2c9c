"""The repaired time base and the device-to-host clock map, without a device.

TimeBase is fed streams of (seq, clock) pairs that a device could send with valid
CRCs: clean ones with losses and wraps, ones with one fault of each kind, and
arbitrary ones. fit_clock_map is fed arrivals with one-sided latency, quantised to
USB frames, with stalls. Every property runs derandomized.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from tissuecli.core.clock import (
    MAX_UNCERTAINTY_PPM,
    TimeBase,
    fit_clock_map,
    fit_clock_map_lsq,
)

M32 = 0xFFFFFFFF
PERIOD = 1000  # ticks per sample: a 1 MHz clock at 1 kHz
# TimeBase's tolerance is a quarter period plus 0.1 % of the gap; a fault must exceed it
# for every comparison near it (gaps of up to the 32-frame window: 282 ticks)
FAULT = 400


def fixed(max_examples: int = 100) -> settings:
    return settings(
        derandomize=True,
        max_examples=max_examples,
        deadline=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much],
    )


def run(
    seqs: list[int] | np.ndarray,
    clocks: list[int] | np.ndarray,
    *,
    chunk: int = 7,
    limit: float = math.inf,
    period: float | None = PERIOD,
) -> tuple[TimeBase[int], list[int], np.ndarray, np.ndarray]:
    """Feed frames ``chunk`` at a time; the time base, kept indices, ticks, device clocks."""
    tb: TimeBase[int] = TimeBase(period, limit_ticks=limit)
    frames = [
        (int(s) & M32, int(c) & M32, i, 0.0)
        for i, (s, c) in enumerate(zip(seqs, clocks, strict=True))
    ]
    out = []
    for i in range(0, len(frames), chunk):
        out += tb.feed(frames[i : i + chunk])
        if tb.done:
            break
    out += tb.finish()
    return (
        tb,
        [o.payload for o in out],
        np.array([o.ticks for o in out]),
        np.array([o.device_clock for o in out], dtype=np.int64),
    )


u32 = st.integers(0, M32)


@st.composite
def clean_streams(draw: st.DrawFn, min_size: int = 3, max_size: int = 120) -> tuple:
    """A device's frames over a lossy line: start anywhere (so wraps happen), jitter
    within a tenth of a period, frames missing at random (never the first or last)."""
    n = draw(st.integers(min_size, max_size))
    seq0, clock0 = draw(u32), draw(u32)
    jitter = draw(st.lists(st.integers(-100, 100), min_size=n, max_size=n))
    missing = draw(st.sets(st.integers(1, n - 2), max_size=n // 3)) if n > 2 else set()
    k = np.array([i for i in range(n) if i not in missing])
    seqs = (seq0 + k) & M32
    clocks = (clock0 + k * PERIOD + np.array(jitter)[k]) & M32
    return k, seqs, clocks, clock0 + k * PERIOD + np.array(jitter)[k]


@fixed(200)
@given(clean_streams(), st.integers(1, 40))
def test_a_clean_stream_is_kept_whole_on_its_own_clock(stream, chunk):
    k, seqs, clocks, unwrapped = stream
    tb, kept, ticks, device_clock = run(seqs, clocks, chunk=chunk)
    assert kept == list(range(len(k)))
    np.testing.assert_array_equal(ticks, unwrapped - unwrapped[0])
    np.testing.assert_array_equal(device_clock - device_clock[0], unwrapped - unwrapped[0])
    f = tb.faults
    assert (f.clock_jumps, f.clock_steps, f.sequence_restarts, f.frames_rejected) == (0, 0, 0, 0)
    assert f.frames_lost == int(k[-1] - k[0] + 1 - len(k))
    # every genuine wrap of the 32-bit clock is counted, and only those
    assert f.clock_wraps == int(unwrapped[-1] >> 32) - int(unwrapped[0] >> 32)


# one fault, away from the ends so that frames on both sides can confirm the stream
FAULTS = ["jump", "step", "restart", "absurd_seq", "repeat"]


@st.composite
def one_fault(draw: st.DrawFn) -> tuple:
    n = draw(st.integers(12, 60))
    seq0, clock0 = draw(u32), draw(u32)
    kind = draw(st.sampled_from(FAULTS))
    at = draw(st.integers(4, n - 5))
    seqs = [(seq0 + i) & M32 for i in range(n)]
    clocks = [(clock0 + i * PERIOD) & M32 for i in range(n)]
    if kind == "jump":
        # any stamp further than the tolerance from the right one, wrapped or not
        off = draw(st.integers(FAULT, (1 << 32) - FAULT))
        clocks[at] = (clocks[at] + off) & M32
    elif kind == "step":
        off = draw(st.integers(FAULT, (1 << 32) - FAULT))
        clocks[at:] = [(c + off) & M32 for c in clocks[at:]]
    elif kind == "restart":
        new_seq, new_clock = draw(u32), draw(u32)
        # a reset starts elsewhere: none of its numbers may continue the old sequence
        # (a reset that replays the old numbers and stamps looks like repeated frames)
        assume((1 << 24) < (new_seq - seqs[at - 1]) & M32 < (1 << 32) - n)
        seqs[at:] = [(new_seq + i) & M32 for i in range(n - at)]
        clocks[at:] = [(new_clock + i * PERIOD) & M32 for i in range(n - at)]
    elif kind == "absurd_seq":
        s = draw(u32)
        assume(not 0 <= (s - seqs[at - 1]) & M32 <= n)  # not a plausible next number
        seqs[at] = s
    else:  # the frame before ``at`` sent again, once or more
        times = draw(st.integers(1, 3))
        seqs[at:at] = [seqs[at - 1]] * times
        clocks[at:at] = [clocks[at - 1]] * times
    return kind, at, n, seqs, clocks


@fixed(300)
@given(one_fault(), st.integers(1, 40))
def test_one_fault_is_counted_and_moves_no_other_sample(case, chunk):
    kind, at, n, seqs, clocks = case
    tb, kept, ticks, _ = run(seqs, clocks, chunk=chunk)
    f = tb.faults
    assert np.all(np.diff(ticks) > 0)
    # the time base is the clean one: sample i at i periods (a restart continues one
    # period after the last good sample, which is where sample ``at`` belongs anyway)
    expected = {
        "jump": (list(range(n)), (1, 0, 0, 0, 0)),
        "step": (list(range(n)), (0, 1, 0, 0, 0)),
        "restart": (list(range(n)), (0, 0, 1, 0, 0)),
        "absurd_seq": ([i for i in range(n) if i != at], (0, 0, 0, 1, 1)),
        "repeat": (None, (0, 0, 0, len(seqs) - n, 0)),
    }[kind]
    counted = (f.clock_jumps, f.clock_steps, f.sequence_restarts, f.frames_rejected, f.frames_lost)
    assert counted == expected[1]
    if kind == "repeat":
        assert [seqs[i] for i in kept] == [seqs[0] + i & M32 for i in range(n)]
        np.testing.assert_array_equal(ticks, np.arange(n) * PERIOD)
    else:
        assert kept == expected[0]
        np.testing.assert_array_equal(ticks, np.array(expected[0]) * PERIOD)


@fixed(300)
@given(
    st.lists(st.tuples(u32, u32), max_size=80),
    st.integers(1, 40),
    st.one_of(st.just(math.inf), st.integers(1, 100_000).map(float)),
)
def test_any_stream_gives_increasing_time_within_the_limit(frames, chunk, limit):
    seqs = [s for s, _ in frames]
    clocks = [c for _, c in frames]
    tb, kept, ticks, _ = run(seqs, clocks, chunk=chunk, limit=limit)
    assert np.all(np.diff(ticks) > 0)
    assert np.all(ticks < limit)
    assert kept == sorted(kept)  # in arrival order
    f = tb.faults
    assert min(f.as_dict().values()) >= 0
    if not tb.done:
        assert len(kept) + f.frames_rejected == len(frames)


@st.composite
def messy_streams(draw: st.DrawFn) -> tuple[list[int], list[int]]:
    """Clean runs interleaved with the faults above and with random frames."""
    seqs: list[int] = []
    clocks: list[int] = []
    seq, clock = draw(u32), draw(u32)
    for _ in range(draw(st.integers(1, 6))):
        run_len = draw(st.integers(1, 25))
        for _ in range(run_len):
            seq, clock = (seq + 1) & M32, (clock + PERIOD) & M32
            seqs.append(seq)
            clocks.append(clock)
        what = draw(st.sampled_from(["random", "step", "restart", "gap", "jump"]))
        if what == "random":
            for _ in range(draw(st.integers(1, 4))):
                seqs.append(draw(u32))
                clocks.append(draw(u32))
        elif what == "step":
            clock = (clock + draw(u32)) & M32
        elif what == "restart":
            seq, clock = draw(u32), draw(u32)
        elif what == "gap":
            k = draw(st.integers(1, 50))
            seq, clock = (seq + k) & M32, (clock + k * PERIOD) & M32
        else:
            seqs.append((seq + 1) & M32)
            clocks.append(draw(u32))
            seq, clock = (seq + 1) & M32, (clock + PERIOD) & M32
    return seqs, clocks


@fixed(300)
@given(messy_streams(), st.integers(1, 40))
def test_decisions_do_not_depend_on_how_the_stream_is_cut(stream, chunk):
    seqs, clocks = stream
    one = run(seqs, clocks, chunk=1)
    cut = run(seqs, clocks, chunk=chunk)
    whole = run(seqs, clocks, chunk=len(seqs) + 1)
    assert one[1] == cut[1] == whole[1]
    np.testing.assert_array_equal(one[2], cut[2])
    np.testing.assert_array_equal(one[2], whole[2])
    assert one[0].faults == cut[0].faults == whole[0].faults
    assert np.all(np.diff(one[2]) > 0)


@fixed(100)
@given(
    st.sampled_from(["jump", "step", "backwards", "restart"]),
    st.integers(100, 1000),
    st.integers(1, 99),
)
def test_the_duration_is_measured_on_the_repaired_time_base(kind, n_limit, at_percent):
    n = 1200
    seqs = np.arange(n) + 5
    clocks = np.arange(n) * PERIOD + 77
    at = max(4, n_limit * at_percent // 100)
    if kind == "jump":
        clocks[at] += 1 << 31
    elif kind == "step":
        clocks[at:] += 4_000_000  # 4 s forward
    elif kind == "backwards":
        clocks[at:] -= 300_000
    else:
        seqs[at:] = np.arange(n - at) + (1 << 31)
        clocks[at:] = np.arange(n - at) * PERIOD
    tb, kept, ticks, _ = run(seqs, clocks, limit=n_limit * PERIOD)
    assert tb.done
    assert len(kept) == n_limit  # exactly duration x rate, however the clock misbehaved
    np.testing.assert_array_equal(ticks, np.arange(n_limit) * PERIOD)


def test_losses_are_counted_only_among_the_frames_kept():
    rng = np.random.default_rng(3)
    n = 3000
    keep = rng.random(n) > 0.3
    keep[0] = True
    seqs = np.flatnonzero(keep)
    tb, kept, ticks, _ = run(seqs, seqs * PERIOD, chunk=50, limit=1000 * PERIOD)
    last = seqs[len(kept) - 1]
    assert seqs[len(kept)] >= 1000 and last < 1000  # the limit cut the stream
    assert tb.faults.frames_lost == last + 1 - len(kept)


def test_without_a_period_it_is_learnt_from_the_frames():
    seqs = np.arange(50)
    clocks = (np.arange(50) * 250 + 3) & M32
    clocks[20] = 12345678
    tb, kept, ticks, _ = run(seqs, clocks, period=None)
    assert tb.period_ticks == pytest.approx(250)
    assert len(kept) == 50 and tb.faults.clock_jumps == 1
    np.testing.assert_array_equal(ticks, np.arange(50) * 250)


def test_a_stream_of_only_random_frames_keeps_nothing():
    rng = np.random.default_rng(0)
    tb, kept, _, _ = run(rng.integers(0, 1 << 32, 200), rng.integers(0, 1 << 32, 200))
    assert kept == [] and tb.faults.frames_rejected == 200


def test_a_stream_shorter_than_a_confirmation_is_kept():
    tb, kept, ticks, _ = run([7, 8], [100, 1100])
    assert kept == [0, 1] and list(ticks) == [0, PERIOD]


# --------------------------------------------------------------------------- clock map


def arrivals(
    drift_ppm: float,
    duration_s: float,
    rng: np.random.Generator,
    *,
    bursts: int = 0,
    rate_hz: float = 1000.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Device times of the samples and their host arrival times.

    The device samples every 1 ms of its own clock, which runs ``drift_ppm`` fast;
    each sample waits a random one-sided latency, is delivered in 1 ms USB frames of
    arbitrary phase, and read by a host that wakes a little late. Each burst stalls
    delivery for 50-300 ms, then the backlog arrives at once.
    """
    n = int(duration_s * rate_hz)
    device = np.arange(n) / rate_hz
    taken = device / (1.0 + drift_ppm * 1e-6)
    phase = rng.uniform(0, 1e-3)
    host = np.ceil((taken + 0.2e-3 + rng.exponential(0.4e-3, n) - phase) / 1e-3) * 1e-3 + phase
    host += rng.exponential(30e-6, n)
    for _ in range(bursts):
        start, stall = rng.uniform(0, taken[-1]), rng.uniform(0.05, 0.3)
        hit = (host > start) & (host < start + stall)
        host[hit] = start + stall
    return device, np.maximum.accumulate(host)


@pytest.mark.parametrize("seed", range(5))
def test_a_known_drift_is_recovered_despite_latency_and_bursts(seed):
    device, host = arrivals(200.0, 20.0, np.random.default_rng(seed), bursts=2)
    m = fit_clock_map(device, host)
    assert m is not None
    assert abs(m.drift_ppm - 200.0) < 20.0
    assert abs(m.drift_ppm - 200.0) <= 2 * m.drift_uncertainty_ppm
    assert m.resolved and m.drift_uncertainty_ppm <= MAX_UNCERTAINTY_PPM


@pytest.mark.parametrize("seed", range(5))
def test_a_short_session_of_an_exact_clock_reports_no_drift_and_is_not_rescaled(seed):
    device, host = arrivals(0.0, 5.0, np.random.default_rng(seed), bursts=1)
    m = fit_clock_map(device, host)
    assert m is not None
    assert abs(m.drift_ppm) <= m.drift_uncertainty_ppm
    assert not m.resolved


@fixed(40)
@given(
    st.floats(-500.0, 500.0),
    st.floats(2.0, 40.0),
    st.integers(0, 3),
    st.integers(0, 2**32 - 1),
)
def test_the_stated_uncertainty_covers_the_error(drift, duration, bursts, seed):
    device, host = arrivals(drift, duration, np.random.default_rng(seed), bursts=bursts)
    m = fit_clock_map(device, host)
    assert m is not None
    # two standard errors: derandomized examples, so this is a fixed set of sessions
    assert abs(m.drift_ppm - drift) <= 2 * m.drift_uncertainty_ppm
    if m.resolved:
        assert abs(m.drift_ppm - drift) <= 2 * MAX_UNCERTAINTY_PPM


def test_a_stall_at_the_end_of_a_short_session_misleads_least_squares_only():
    device, host = arrivals(0.0, 5.0, np.random.default_rng(1))
    host[-200:] = np.maximum(host[-200:], host[-200] + 0.25)  # the last 0.2 s held 250 ms
    old, new = fit_clock_map_lsq(device, host), fit_clock_map(device, host)
    assert old is not None and new is not None
    assert abs(old.drift_ppm) > 1000  # what the recorder used to store
    assert abs(new.drift_ppm) <= new.drift_uncertainty_ppm and not new.resolved


def test_too_few_samples_give_no_map():
    assert fit_clock_map(np.arange(5.0), np.arange(5.0)) is None
    assert fit_clock_map(np.zeros(20), np.arange(20.0)) is None
