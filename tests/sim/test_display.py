"""The simulated display's watchdog judged against its own port: the limit it states, how it
was set, its bounds, and the firmware's limit kept when asked for."""

from __future__ import annotations

import contextlib
import math
import os
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from tissuecli.app.faults import classify_faults
from tissuecli.app.play import watchdog_periods
from tissuecli.core.errors import EXIT_WATCHDOG, InputError
from tissuecli.hw.link import open_device
from tissuecli.hw.protocol import (
    FLAG_MODEL,
    FLAG_STALE,
    START,
    Command,
    Encoder,
    FrameDecoder,
    SetModel,
    SetVoltage,
    encode,
)
from tissuecli.render.profile import PAPER_DISPLAY
from tissuecli.sim import display as display_module
from tissuecli.sim.display import (
    CATCH_UP_S,
    MODEL_HORIZON_PERIODS,
    PROBES,
    ROUND_TRIP_MARGIN,
    SIM_WATCHDOG_FLOOR_S,
    SIM_WATCHDOG_MAX_S,
    WATCHDOG_PERIODS,
    _Firmware,
    display_info,
    run_simulated_display,
    simulate_display,
    watchdog_limit,
)
from tissuecli.sim.port import VirtualPort
from tissuecli.sim.process import SimulatorProcess


def test_no_round_trip_timed_keeps_the_firmwares_limit() -> None:
    periods, basis = watchdog_limit([], 1e-3)
    assert periods == WATCHDOG_PERIODS and "as the firmware" in basis


def test_the_limit_is_the_firmwares_plus_the_margin_over_the_longest_round_trip() -> None:
    trips = [0.3e-3] * (PROBES - 1) + [5e-3]
    periods, basis = watchdog_limit(trips, 1e-3)
    assert periods == WATCHDOG_PERIODS + math.ceil(ROUND_TRIP_MARGIN * 5)
    assert f"watchdog {periods} periods ({periods:g} ms)" in basis
    assert "5.00 ms longest" in basis and "0.30 ms median" in basis
    assert f"at most {SIM_WATCHDOG_MAX_S * 1e3:g} ms" in basis


def test_quick_start_up_round_trips_do_not_set_a_limit_under_the_floor() -> None:
    # 100 quick round trips once said 6 periods, and the watchdog then cut a host
    # that kept time when the port held a frame for a few ms beside busy processes
    periods, basis = watchdog_limit([0.2e-3] * PROBES, 1e-3)
    assert periods == round(SIM_WATCHDOG_FLOOR_S / 1e-3) > WATCHDOG_PERIODS + 1
    assert f"at least {SIM_WATCHDOG_FLOOR_S * 1e3:g} ms" in basis
    # at a slower rate the floor is still a time, never fewer than the firmware's periods
    assert watchdog_limit([0.2e-3] * PROBES, 10e-3)[0] == WATCHDOG_PERIODS


def test_too_few_round_trips_are_not_enough_to_judge_by() -> None:
    periods, basis = watchdog_limit([0.2e-3] * (PROBES // 2), 1e-3)
    assert periods == round(SIM_WATCHDOG_MAX_S / 1e-3)
    assert f"fewer than {PROBES} timed" in basis


def test_a_saturated_machine_gives_the_bound_whatever_the_sample_showed() -> None:
    periods, basis = watchdog_limit([0.1e-3, 0.2e-3], 1e-3, saturated=True)
    assert periods == round(SIM_WATCHDOG_MAX_S / 1e-3)
    assert "no CPU to spare" in basis and "0.20 ms longest" in basis


@given(
    st.lists(st.floats(0.0, 10.0, allow_nan=False), max_size=2 * PROBES),
    st.sampled_from([1e-4, 5e-4, 1e-3, 2e-3, 0.1]),
    st.booleans(),
)
def test_the_limit_never_falls_below_the_firmwares_nor_passes_its_bound(
    trips: list[float], period: float, saturated: bool
) -> None:
    periods, _ = watchdog_limit(trips, period, saturated)
    assert WATCHDOG_PERIODS <= periods
    assert periods <= max(WATCHDOG_PERIODS, int(SIM_WATCHDOG_MAX_S / period))
    if trips:
        assert periods * period >= min(SIM_WATCHDOG_FLOOR_S, SIM_WATCHDOG_MAX_S) - 1e-12


def test_round_trips_through_the_port_are_timed_before_a_link_is_made(tmp_path: Path) -> None:
    port = VirtualPort()
    try:
        trips = port.round_trips(20, interval_s=0.0, budget_s=0.5)
        # a starved machine may use the budget before the 20th probe; each direction of
        # a probe waits at most the budget
        assert 1 <= len(trips) <= 20 and all(0 < t <= 2 * 0.5 + 0.2 for t in trips)
        assert port.link is None
        port.publish(tmp_path / "d")
        assert (tmp_path / "d").is_symlink() and port.path == str(tmp_path / "d")
    finally:
        port.close()
    assert not (tmp_path / "d").is_symlink()  # its own link removed on close


def _stated(link: Path) -> dict:
    device, info = open_device(str(link), "display")
    device.close()
    assert info is not None
    return info


def test_a_simulated_display_states_its_limit_judged_at_start_up(tmp_path: Path) -> None:
    with SimulatorProcess("display", tmp_path / "d"):
        info = _stated(tmp_path / "d")
    assert WATCHDOG_PERIODS <= info["watchdog_periods"] <= SIM_WATCHDOG_MAX_S / 1e-3
    assert watchdog_periods(info) == info["watchdog_periods"]
    # and the scheduling its loop obtained, so a host can say whether it ran elevated
    assert info["scheduler"] in ("SCHED_FIFO", "SCHED_OTHER")


def test_the_firmwares_limit_is_kept_when_asked_for(tmp_path: Path) -> None:
    with SimulatorProcess("display", tmp_path / "d", ["--watchdog-periods", "5"]):
        assert _stated(tmp_path / "d")["watchdog_periods"] == 5


def test_a_watchdog_of_no_period_is_refused() -> None:
    with pytest.raises(InputError, match="--watchdog-periods 0 must be 1 or more"):
        run_simulated_display(None, watchdog_periods=0, duration_s=0.01)


def test_a_display_that_states_no_limit_is_held_to_the_firmwares() -> None:
    info = display_info(PAPER_DISPLAY, 1000.0)
    assert watchdog_periods(info) == WATCHDOG_PERIODS
    del info["watchdog_periods"]
    assert watchdog_periods(info) == WATCHDOG_PERIODS
    assert watchdog_periods({"watchdog_periods": "many"}) == WATCHDOG_PERIODS


def test_a_watchdog_fault_names_the_limit_the_display_stated() -> None:
    summary = {"frames": 1000, "loop_rate_hz": 1000.0, "watchdog_frames": 3}
    [(code, text)] = classify_faults({**summary, "watchdog_periods": 23}, 1000.0)
    assert code == EXIT_WATCHDOG and "stopped answering for 23 periods (23 ms)" in text
    [(_, text)] = classify_faults(summary, 1000.0)
    assert "stopped answering for 5 periods (5 ms)" in text


def _stalled_once(
    monkeypatch: pytest.MonkeyPatch, stall_s: float, at_tick: int = 50
) -> list[float]:
    """The display's process descheduled for ``stall_s`` once, inside its ``at_tick``-th
    integration step; returns the gaps between steps that the machine added (s), the
    deliberate stall taken out, filled in as the display runs."""
    step, calls, last, gaps = display_module.piston_step, [0], [0.0], [0.0]

    def stalling(*args, **kwargs):  # type: ignore[no-untyped-def]
        calls[0] += 1
        now = time.monotonic()
        if calls[0] > 1:
            gaps.append(now - last[0])
        if calls[0] == at_tick:
            time.sleep(stall_s)
        last[0] = time.monotonic()  # the deliberate stall is not the machine's
        return step(*args, **kwargs)

    monkeypatch.setattr(display_module, "piston_step", stalling)
    return gaps


def test_a_display_woken_late_runs_the_ticks_it_owes_and_keeps_its_rate(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    gaps = _stalled_once(monkeypatch, 0.008)
    # any stall the machine adds is caught up too (an ordinary thread here)
    monkeypatch.setattr(display_module, "CATCH_UP_S", 1.0)
    port = VirtualPort()
    cpu0, wall0 = time.process_time(), time.monotonic()
    try:
        counters = simulate_display(PAPER_DISPLAY, port, duration_s=0.2)
    finally:
        port.close()
    cpu, wall = time.process_time() - cpu0, time.monotonic() - wall0
    if counters["missed_deadlines"] and max(gaps) > display_module.CATCH_UP_S:
        # deadlines are skipped only beyond the catch-up: the machine itself held this
        # process off its loop for longer than that between two steps
        pytest.skip(
            f"the machine held the display off its loop for {max(gaps):.2f} s between two "
            f"steps (catch-up {display_module.CATCH_UP_S:g} s): {counters['missed_deadlines']} "
            f"deadlines skipped; {cpu:.2f} s CPU in {wall:.2f} s, load {os.getloadavg()[0]:.1f}"
        )
    # all 200 ticks run (none skipped), at least 6 of the 8 periods the stall took owed
    assert counters["missed_deadlines"] == 0, (counters, max(gaps), cpu, wall)
    assert counters["late_ticks"] >= 6


def test_a_slow_start_is_no_deadline_missed(monkeypatch: pytest.MonkeyPatch) -> None:
    """The collector's pass on entering the loop (a second in a large process on a loaded
    machine) comes before the schedule starts: no tick is skipped for it."""
    gaps = _stalled_once(monkeypatch, 0.0)
    entered = display_module.realtime

    @contextlib.contextmanager
    def slow_entry() -> Iterator[None]:
        with entered():
            time.sleep(0.5)  # a collector's pass in a large heap
            yield

    monkeypatch.setattr(display_module, "realtime", slow_entry)
    port = VirtualPort()
    try:
        counters = simulate_display(PAPER_DISPLAY, port, duration_s=0.2)
    finally:
        port.close()
    if max(gaps) > 0.2:
        pytest.skip(f"the machine held the display off its loop for {max(gaps):.2f} s")
    # a schedule started before the pause would skip its 500 periods at the first tick
    assert counters["missed_deadlines"] < 200, counters


def test_a_display_stalled_beyond_its_catch_up_skips_and_counts_the_ticks(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    _stalled_once(monkeypatch, 2 * CATCH_UP_S)
    port = VirtualPort()
    try:
        counters = simulate_display(PAPER_DISPLAY, port, duration_s=0.2)
    finally:
        port.close()
    assert counters["missed_deadlines"] >= CATCH_UP_S / 1e-3  # said, not run in a burst


def test_ticks_run_to_catch_up_do_not_count_towards_the_watchdog() -> None:
    port = VirtualPort()
    try:
        fw = _Firmware(PAPER_DISPLAY, port, 1000.0, lambda t: 0.0, None, watchdog_periods=5)
        fw.streaming = fw.armed = True
        for _ in range(20):  # a burst after the display's own stall: the host is not silent
            fw.tick(late=True)
        assert fw.trips == 0
        for _ in range(6):  # on time, no answer for more than 5 periods: cut
            fw.tick()
        assert fw.trips == 1 and fw.volts == 0.0
    finally:
        port.close()


@contextlib.contextmanager
def _firmware_bench() -> Iterator[tuple[Any, Any, Any]]:
    """A display firmware stepped by hand behind a pseudo-terminal: the firmware, a
    ``send(message)`` from the host, and a ``tick(late=False, x=None)`` that runs one
    period (the piston at ``x`` if given) and returns the Encoder frame it sent."""
    port = VirtualPort()
    host = os.open(port.name, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        fw = _Firmware(PAPER_DISPLAY, port, 1000.0, lambda t: 0.0, None, watchdog_periods=50)
        decoder = FrameDecoder()

        def send(message: Any) -> None:
            os.write(host, encode(message))
            time.sleep(0.02)  # through the pseudo-terminal

        def tick(late: bool = False, x: float | None = None) -> Encoder:
            if x is not None:
                fw.x = x  # the piston, where the test puts it
            fw.receive()
            fw.tick(late)
            time.sleep(0.02)
            got = [m for m in decoder.feed(os.read(host, 4096)) if isinstance(m, Encoder)]
            return got[-1]

        yield fw, send, tick
    finally:
        os.close(host)
        port.close()


def test_a_period_not_run_on_the_answer_to_the_frame_before_is_flagged_stale() -> None:
    """The host numbers each SetVoltage by the frame it answers; the display flags each
    period whose voltage is not the answer to the frame before, but not a tick it runs
    late to catch up (counted apart)."""
    with _firmware_bench() as (fw, send, tick):
        send(Command(START))
        first = tick()
        assert not first.flags & FLAG_STALE  # not yet commanded
        send(SetVoltage(first.seq, 1.0))  # the answer to the frame before
        second = tick()
        assert not second.flags & FLAG_STALE and second.volts == 1.0
        assert tick().flags & FLAG_STALE  # no answer to the second frame came
        send(SetVoltage(second.seq, 1.0))  # an answer, but not to the frame before
        assert tick().flags & FLAG_STALE
        assert not tick(late=True).flags & FLAG_STALE  # run to catch up: counted apart
        assert fw.ages[0] == 1 and sum(fw.ages[1:]) == 2 and sum(fw.ages_late) == 1


def test_a_late_answer_is_rendered_from_its_local_model_within_the_horizon() -> None:
    """Once an answer is late, a display sent SetModel applies the answer's pull moved by
    its slopes over what the encoder saw since the tick the answer was meant for
    (``FLAG_MODEL``, not stale), clamped to what the solenoid can do, for up to
    :data:`MODEL_HORIZON_PERIODS`; beyond, it holds its voltage and flags the periods
    stale. A plain SetVoltage carries no model."""
    with _firmware_bench() as (fw, send, at):

        def tick(x: float, late: bool = False) -> Encoder:
            return at(late, x)

        send(Command(START))
        first = tick(0.0)
        send(SetModel(first.seq, 1.0, u=1.0, du_dx=1000.0, du_dv=1.0))
        second = tick(0.0)
        assert second.volts == 1.0 and not second.flags & (FLAG_STALE | FLAG_MODEL)
        # late: 0.1 mm deeper at 0.1 m/s, u = 1 + 1000 * 1e-4 + 1.0 * 0.1
        third = tick(1e-4)
        assert third.flags & FLAG_MODEL and not third.flags & FLAG_STALE
        assert third.volts == pytest.approx(math.sqrt(1.2), rel=1e-6)
        # still within the horizon, at rest there: u = 1 + 1000 * 1e-4
        for _ in range(MODEL_HORIZON_PERIODS - 1):
            frame = tick(1e-4)
            assert frame.flags & FLAG_MODEL and frame.volts == pytest.approx(math.sqrt(1.1))
        held = tick(-2e-3)  # beyond the horizon: held, and stale
        assert held.flags & FLAG_STALE and not held.flags & FLAG_MODEL
        assert held.volts == pytest.approx(math.sqrt(1.1))
        assert not tick(-2e-3, late=True).flags & (FLAG_STALE | FLAG_MODEL)  # catching up
        assert fw.modelled == MODEL_HORIZON_PERIODS
        # an answer whose model asks the solenoid to push: 0 V, not a negative root
        now = tick(0.0)
        send(SetModel(now.seq, 0.5, u=0.25, du_dx=1000.0, du_dv=0.0))
        assert tick(0.0).volts == 0.5
        assert tick(-1e-3).volts == 0.0  # u = 0.25 - 1
        # ... and one past v_max: v_max
        now = tick(0.0)
        send(SetModel(now.seq, 1.0, u=1.0, du_dx=1e5, du_dv=0.0))
        tick(0.0)
        assert tick(1e-3).volts == PAPER_DISPLAY.v_max
        # a plain SetVoltage: no model, so a late answer is stale again
        now = tick(0.0)
        send(SetVoltage(now.seq, 0.7))
        tick(0.0)
        late = tick(1e-3)
        assert late.flags & FLAG_STALE and late.volts == pytest.approx(0.7)


def test_the_display_says_it_renders_from_a_local_model() -> None:
    info = display_info(PAPER_DISPLAY, 1000.0)
    assert info["local_model"] is True
    assert info["model_horizon_periods"] == MODEL_HORIZON_PERIODS == WATCHDOG_PERIODS
