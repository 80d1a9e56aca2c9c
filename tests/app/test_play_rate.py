"""What "the loop ran off its rate" counts: the display's frames the host ran through
the loop per second, and the periods the display ran on a late answer as the display
reports them (``FLAG_STALE``), not the host's answers per second: frames sent on time
that reach the host together are each run through the loop and answered once, by the
answer to the newest."""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Any

import pytest

from tissuecli.app.faults import MAX_MISSED_FRACTION, MAX_RATE_ERROR, classify_faults
from tissuecli.app.play import Rendering, play
from tissuecli.app.summaries import play_lines
from tissuecli.core.flags import FLAG_STALE
from tissuecli.core.terms import Law
from tissuecli.core.tissue import Tissue
from tissuecli.hw.protocol import Encoder, Message, SetModel, SetVoltage
from tissuecli.render.check import check
from tissuecli.render.controller import Controller
from tissuecli.render.profile import PAPER_DISPLAY

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
        assert type(message) is SetVoltage
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


class ModelledDisplay(BunchedDisplay):
    """A display that says it renders late answers from their local model: it keeps
    every command the host sends, and the piston moves (a ramp), so the law's slopes are
    taken where the tissue is pressed."""

    kind = "modelled-display"
    extra_info = {"stale_flag": True, "local_model": True}

    def reset(self) -> None:
        super().reset()
        self.messages: list[Message] = []

    def poll(self) -> list[Message]:
        frames = super().poll()
        # a ramp 1 mm deep at 10 mm/s: a grasp, where the solenoid pulls
        return [replace(f, position=min(int(f.seq * 10), 1000)) for f in frames]  # type: ignore[type-var]

    def send(self, message: Message) -> None:
        self.messages.append(message)
        super().send(SetVoltage(message.seq, message.volts))  # type: ignore[attr-defined]


@pytest.fixture
def modelled(registered_device) -> type[ModelledDisplay]:
    return registered_device(ModelledDisplay)


def test_a_display_with_a_local_model_is_sent_the_laws_slopes_and_a_plain_zero_last(modelled):
    """Every answer to a display that states ``local_model`` carries the pull and the
    law's slopes (V^2 units): the tissue's stiffness less the display's spring, and its
    damping less the piston's plus the error feedback's share; the last command, the
    fail-safe 0 V, carries none, so nothing is rendered from a model after it."""
    modelled.every = 0
    s = play(TISSUE, "modelled", 0.3, device=modelled.kind, idle_timeout_s=5.0)
    dev = modelled.opened
    # this display never renders from the model (late periods it flags are stale)
    assert dev is not None and s["modelled_frames"] == 0 and s["late_run_max"] is not None
    answers = dev.messages[:-1]
    assert answers and all(isinstance(m, SetModel) for m in answers)
    last = dev.messages[-1]
    assert type(last) is SetVoltage and last.volts == 0.0
    p, gains = PAPER_DISPLAY, s["gains"]
    k = (TISSUE.K - p.Kp) / p.alpha
    c = (TISSUE.S - p.b + gains["Cv"] * (gains["M"] - p.Mp) / gains["M"]) / p.alpha
    for m in answers[50:]:  # the controller settled
        assert isinstance(m, SetModel)
        assert m.du_dx == pytest.approx(k, rel=1e-3) and m.du_dv == pytest.approx(c, rel=1e-3)
        if 0.0 < m.volts < p.v_max:  # the pull as asked, where the solenoid renders it
            assert m.u == pytest.approx(m.volts**2, rel=1e-4)


def test_a_display_without_a_local_model_is_sent_plain_voltages(bunched):
    bunched.every = 0
    play(TISSUE, "bunched", 0.2, device=bunched.kind, idle_timeout_s=5.0)
    # BunchedDisplay.send asserts every command is a plain SetVoltage
    assert bunched.opened is not None and bunched.opened.received


def test_late_answers_within_the_local_model_are_counted_not_judged() -> None:
    """From a display with a local model, the periods it rendered from the model are
    reported; only those beyond it count against the 5 % bound."""
    base = {"frames": 2000, "loop_rate_hz": 1000.0, "stale_run_max": 2, "late_run_max": 30}
    ok = classify_faults({**base, "stale_frames": 20, "modelled_frames": 300}, 1000.0)
    assert ok == []
    faulty = classify_faults({**base, "stale_frames": 120, "modelled_frames": 0}, 1000.0)
    assert [text for _, text in faulty] == [
        "the display ran 120 periods on a late answer beyond its local model "
        "(6.0 % of 2000, longest run 2)"
    ]
    lines = play_lines({**base, "stale_frames": 20, "modelled_frames": 300})
    assert any(
        "320 on a late answer (longest run 30), 300 of them rendered from the display's "
        "local model and 20 beyond it (longest run 2)" in line
        for line in lines
    )


def test_no_model_is_sent_with_an_answer_that_is_not_the_laws_own() -> None:
    """An answer changed after the controller (``live`` switched off, its passivity
    controller) is sent without a model, so a late answer is not rendered as the law
    where the answer was not; the law's own answer, 0 V where it asks the solenoid to
    push included, is."""
    p = PAPER_DISPLAY
    ctrl = Controller(TISSUE, p, RATE_HZ, check(TISSUE, p, RATE_HZ).gains)
    rendering = Rendering(ctrl)
    step = ctrl.update(1e-3, 0.0, 1.0 / RATE_HZ)
    step = ctrl.update(1e-3, step.volts, 1.0 / RATE_HZ)
    assert 0.0 < step.volts < p.v_max
    model = rendering.local_model(step, step.volts, p)
    assert model is not None and model[0] == pytest.approx(step.volts**2)
    assert rendering.local_model(step, 0.0, p) is None  # switched off
    assert rendering.local_model(step, 0.5 * step.volts, p) is None  # changed
    pushing = replace(step, volts=0.0, pull=-0.2)
    model = rendering.local_model(pushing, 0.0, p)
    assert model is not None and model[0] == pytest.approx(-0.2 / p.alpha)
