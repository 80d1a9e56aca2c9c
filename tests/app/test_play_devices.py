"""A new kind of display is one :class:`~tissuecli.hw.device.Display` class and a registry
entry: ``play`` opens it by its kind, and the haptic loop (read, compute, command) runs
over it as over the built-in display, ending at 0 V and STOP."""

from __future__ import annotations

import math

import pytest

from tissuecli.app.play import HostLoop, open_display, play
from tissuecli.core.errors import DeviceError, InputError
from tissuecli.core.terms import Law
from tissuecli.core.tissue import Tissue
from tissuecli.hw.device import device_class
from tissuecli.hw.protocol import Encoder, Message, SetVoltage
from tissuecli.render.profile import PAPER_DISPLAY

from .fakedisplay import CLOCK_HZ, RATE_HZ, InProcessDisplay


class BenchDisplay(InProcessDisplay):
    """An Encoder frame per millisecond of wall-clock time since START, the piston
    pressed 2 mm down and released once a second. It keeps what the host sent."""

    kind = "bench-display"
    role = "a bench display lives in the test's own process"

    def reset(self) -> None:
        self.volts: list[float] = []

    def poll(self) -> list[Message]:
        if self.started is None:
            return []
        due = self.due()
        frames: list[Message] = []
        while self.n < due:
            x = 1e-3 * (1.0 - math.cos(2.0 * math.pi * self.n / RATE_HZ))
            counts = round(x / self.profile.resolution)
            last = self.volts[-1] if self.volts else 0.0
            frames.append(Encoder(self.n, self.n * CLOCK_HZ // int(RATE_HZ), counts, last, 0))
            self.n += 1
        return frames

    def send(self, message: Message) -> None:
        assert isinstance(message, SetVoltage)
        self.volts.append(message.volts)


@pytest.fixture
def bench(registered_device) -> type[BenchDisplay]:
    return registered_device(BenchDisplay)


def test_a_new_display_is_opened_by_its_kind_and_checked(bench) -> None:
    assert device_class("bench-display") is bench
    display = open_display("bench", kind="bench-display", rate_hz=RATE_HZ)
    assert isinstance(display, bench) and display.profile == PAPER_DISPLAY
    with pytest.raises(DeviceError, match="runs its loop at 1000 Hz; pass --rate 1000"):
        open_display("bench", kind="bench-display", rate_hz=500.0)
    with pytest.raises(InputError, match="a forceps is not a display"):
        open_display("bench", kind="forceps")


def test_the_haptic_loop_runs_over_a_new_display(bench) -> None:
    tissue = Tissue(Law.paper("x", "xdot"), 600.0, 3.0, 0.0)
    summary = play(
        tissue,
        "bench",
        0.5,
        device="bench-display",
        loop="plain",
        realtime=False,
        idle_timeout_s=5.0,  # a starved machine may hold this process for a while
    )
    dev = bench.opened
    assert dev is not None
    # read, compute, command: an answer to each batch of frames (or missed period)
    assert summary["frames"] >= 0.5 * RATE_HZ - 1
    assert summary["commands_sent"] == len(dev.volts)  # the 0 V before STOP included
    assert 1 < summary["commands_sent"] <= summary["frames"] + summary["missed_periods"] + 1
    assert summary["frames_bad"] == 0 and summary["tracking_bound_m"] > 0
    # the pressed piston is pushed back; the loop always ends at 0 V, then STOP
    assert max(dev.volts) > 0.0
    assert dev.volts[-1] == 0.0
    assert dev.commands[0] == "start" and dev.commands[-1] == "stop"
    assert summary["verdict"] in ("as checked", "faulty")  # faulty only when starved


def test_a_loop_composed_by_hand_runs_over_the_device(bench) -> None:
    """``live`` composes the same loop around its own rendering; so can a lab's code."""
    from tissuecli.hw.realtime import StopFlag
    from tissuecli.hw.stream import Stream
    from tissuecli.render.check import check
    from tissuecli.render.controller import Controller

    tissue = Tissue(Law.paper("x", "xdot"), 600.0, 3.0, 0.0)
    display = open_display("bench", kind="bench-display", rate_hz=RATE_HZ)
    gains = check(tissue, display.profile, RATE_HZ).gains
    loop = HostLoop(
        display,
        Controller(tissue, display.profile, RATE_HZ, gains),
        display.profile,
        RATE_HZ,
        CLOCK_HZ,
        None,
    )
    stream = Stream(
        display,
        Encoder,
        stop=StopFlag(),
        idle_timeout_s=5.0,
        before_stop=lambda: loop.send(0.0),
    )
    summary = loop.run(stream, 0.2, None)
    assert summary["frames"] >= 0.2 * RATE_HZ - 1
    assert display.volts[-1] == 0.0 and display.commands[-1] == "stop"
