"""What "the loop ran off its rate" counts: the display's frames the host ran through
the loop per second, and the periods the display ran on a late answer as the display
reports them (``FLAG_STALE``), not the host's answers per second: frames sent on time
that reach the host together are each run through the loop and answered once, by the
answer to the newest."""

from __future__ import annotations

import time
from typing import Any

import pytest

from tissuecli.app.faults import MAX_MISSED_FRACTION, MAX_RATE_ERROR
from tissuecli.app.play import play
from tissuecli.core.flags import FLAG_STALE
from tissuecli.core.terms import Law
from tissuecli.core.tissue import Tissue
from tissuecli.hw.protocol import Encoder, Message, SetVoltage

from .fakedisplay import CLOCK_HZ, RATE_HZ, InProcessDisplay

TISSUE = Tissue(Law.paper("x", "xdot"), 600.0, 3.0, 0.0)


class BunchedDisplay(InProcessDisplay):
    """A display whose line holds one frame in every ``every`` until the next is sent, so
    the two reach the host together (as a pseudo-terminal's kernel worker delivers them
    on a busy machine). Each tick runs on the latest SetVoltage received before it and,
    as the simulated display does, raises ``FLAG_STALE`` when that command does not
    answer the frame before."""

    kind = "bunched-display"
    role = "a bunched display lives in the test's own process"
    extra_info = {"stale_flag": True}
    every = 0  # hold one frame in this many (0: none)

    def reset(self) -> None:
        self.received: list[tuple[float, int]] = []  # (when, seq answered)
        self.held: list[Message] = []
        self.stale = 0

    def poll(self) -> list[Message]:
        if self.started is None:
            return []
        due = self.due()
        out: list[Message] = []
        while self.n < due:
            k, tick = self.n, self.started + self.n / RATE_HZ
            answers = [seq for when, seq in self.received if when < tick]
            flags = FLAG_STALE if k and answers and answers[-1] != k - 1 else 0
            self.stale += bool(flags)
            frame = Encoder(k, k * CLOCK_HZ // int(RATE_HZ), 0, 0.0, flags)
            self.n += 1
            if self.every and k % self.every == 1:
                self.held.append(frame)  # held on the line until the next frame
                continue
            out += [*self.held, frame]
            self.held = []
        return out

    def send(self, message: Message) -> None:
        assert isinstance(message, SetVoltage)
        self.received.append((time.monotonic(), message.seq))


@pytest.fixture
def bunched(registered_device) -> type[BunchedDisplay]:
    return registered_device(BunchedDisplay)


def _play(cls: type[BunchedDisplay], every: int) -> dict[str, Any]:
    cls.every = every
    return play(TISSUE, "bunched", 1.0, device=cls.kind, idle_timeout_s=5.0)


def test_frames_that_arrive_together_are_each_run_and_answered_once(bunched):
    """One frame in 40 held back (2.5 %, as on a busy machine): every frame runs through
    the loop at the display's rate; one answer per bunch, so 2.5 % fewer answers, and a
    period on the previous answer for each held frame, which the display reports."""
    s = _play(bunched, 40)
    if s["period_max_ms"] > 20.0:  # 2 % of the play's periods in one stall
        pytest.skip(f"the loop was descheduled for {s['period_max_ms']:.1f} ms")
    dev = bunched.opened
    assert dev is not None
    held = s["frames"] // 40
    assert abs(s["loop_rate_hz"] / RATE_HZ - 1) < MAX_RATE_ERROR
    assert s["unanswered_frames"] >= held - 1
    assert s["answer_rate_hz"] < RATE_HZ * (1 - 0.02)  # what the rate used to count
    assert abs(s["stale_frames"] - dev.stale) <= 1 and s["stale_frames"] >= held - 1
    # a held frame makes one late period; more are this process's own lateness, and
    # then whether the play is faulty depends on how late it was
    if s["stale_frames"] <= held + 1:
        assert not any("Hz" in f or "late answer" in f for f in s["faults"]), s["faults"]


def test_a_display_answered_every_other_period_is_off_its_rate(bunched):
    """Every second frame held back: the host still runs every frame, but the display
    holds each answer for two periods, a 500 Hz loop: the periods on a late answer say so."""
    s = _play(bunched, 2)
    assert abs(s["loop_rate_hz"] / RATE_HZ - 1) < MAX_RATE_ERROR
    assert s["stale_frames"] > 0.4 * s["frames"] > MAX_MISSED_FRACTION * s["frames"]
    assert any("periods on a late answer" in f for f in s["faults"]), s["faults"]
