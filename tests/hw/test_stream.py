"""The acquisition skeleton's judgement of a silent device against a descheduled host."""

from __future__ import annotations

from typing import Any

import pytest

from tissuecli.core.errors import DeviceLost
from tissuecli.hw import stream as stream_module
from tissuecli.hw.protocol import Sample
from tissuecli.hw.realtime import StopFlag
from tissuecli.hw.stream import Stream


class Clock:
    """A monotonic clock the test moves by hand, s."""

    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


class Link:
    """A device that sends nothing until told to, then one Sample per poll."""

    url = "scripted"

    def __init__(self) -> None:
        self.sending = False

    def command(self, name: str) -> None:
        pass

    def poll(self) -> list[Any]:
        return [Sample(1, 1000, 0, 0)] if self.sending else []


@pytest.fixture
def clock(monkeypatch: pytest.MonkeyPatch) -> Clock:
    c = Clock()
    monkeypatch.setattr(stream_module.time, "monotonic", c)
    return c


def test_a_host_descheduled_after_an_empty_poll_does_not_lose_a_device_before_its_first_frame(
    clock: Clock,
) -> None:
    link = Link()
    with Stream(link, Sample, stop=StopFlag(), idle_timeout_s=0.25) as s:
        clock.t += 0.01
        assert s.poll() == []
        clock.t += 0.4  # descheduled between the empty poll and the check
        s.check_idle(clock.t)  # the device was heard silent for 10 ms only
        link.sending = True
        assert len(s.poll()) == 1


def test_a_device_silent_through_polls_is_still_lost(clock: Clock) -> None:
    link = Link()
    with Stream(link, Sample, stop=StopFlag(), idle_timeout_s=0.25) as s:
        for _ in range(24):  # polls heard nothing for up to 240 ms
            clock.t += 0.01
            assert s.poll() == []
            s.check_idle(clock.t)
        clock.t += 0.02
        s.poll()
        with pytest.raises(DeviceLost, match="no Sample frame from scripted for 250 ms"):
            s.check_idle(clock.t)
