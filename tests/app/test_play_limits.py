"""The display's limits rule every command: a profile asking more than the display
reports is refused with both numbers, and no command the display receives exceeds its
reported v_max (a property over random tissues and profiles, against the simulated
display's firmware on a real pty)."""

from __future__ import annotations

import tempfile
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tissuecli.app.play import play
from tissuecli.core.errors import DeviceError, RenderError
from tissuecli.core.terms import Law
from tissuecli.core.tissue import Tissue
from tissuecli.hw.realtime import StopFlag
from tissuecli.render.profile import PAPER_DISPLAY, DisplayProfile, exceeded_limits
from tissuecli.sim.display import simulate_display
from tissuecli.sim.port import VirtualPort

LINEAR = Law.paper("x", "xdot")


@contextmanager
def display(profile: DisplayProfile, load_kg: float = 0.0) -> Iterator[tuple[str, dict[str, Any]]]:
    """A simulated display reporting (and running) ``profile``, in a thread, with
    ``load_kg`` resting on its piston (the finger otherwise); yields its port and, after
    the block, its counters."""
    with tempfile.TemporaryDirectory() as tmp:
        link = Path(tmp) / "display"
        port = VirtualPort(link)
        stop = StopFlag()
        counters: dict[str, Any] = {}

        def run() -> None:
            counters.update(simulate_display(profile, port, stop=stop, load_kg=load_kg))

        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        try:
            yield str(link), counters
        finally:
            stop.set(0)
            thread.join(10)
            port.close()


def test_a_profile_above_the_display_is_refused_with_both_numbers():
    asked = replace(PAPER_DISPLAY, v_max=100.0, alpha=1e-4)
    with display(PAPER_DISPLAY) as (url, counters), pytest.raises(DeviceError) as info:
        play(Tissue(LINEAR, 600.0, 3.0, 0.05), url, 0.2, profile=asked, realtime=False)
    message = str(info.value)
    assert "\n" not in message
    assert "v_max 100 V > 1.5 V" in message
    assert counters["commands"] == 0  # refused before a single command


def test_limits_compare_voltage_stroke_and_pull():
    assert exceeded_limits(PAPER_DISPLAY, PAPER_DISPLAY) == []
    low = replace(PAPER_DISPLAY, v_max=1.0, stroke=0.01, alpha=1.0)
    assert exceeded_limits(low, PAPER_DISPLAY) == []
    over = exceeded_limits(replace(PAPER_DISPLAY, stroke=0.02, alpha=2.0), PAPER_DISPLAY)
    assert over == ["stroke 0.02 m > 0.015 m", "force alpha v_max^2 4.5 N > 2.648 N"]


factor = st.floats(0.6, 1.6)


@settings(
    max_examples=20,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
@given(
    K=st.floats(200.0, 1500.0),
    S=st.floats(0.5, 5.0),
    M=st.floats(0.02, 0.2),
    load=st.floats(0.05, 0.3),
    reported=st.fixed_dictionaries(
        {"Kp": factor, "alpha": factor, "Mp": factor, "v_max": st.floats(1.0, 3.0)}
    ),
    asked=st.one_of(
        st.none(),
        st.fixed_dictionaries({"v_max": st.floats(0.1, 1.2), "alpha": st.floats(0.3, 1.2)}),
        st.fixed_dictionaries({"v_max": st.floats(1.01, 100.0)}),
        st.fixed_dictionaries({"stroke": st.floats(1.01, 3.0)}),
    ),
)
def test_no_command_exceeds_the_reported_v_max(K, S, M, reported, asked, load):
    shown = replace(
        PAPER_DISPLAY,
        Kp=PAPER_DISPLAY.Kp * reported["Kp"],
        alpha=PAPER_DISPLAY.alpha * reported["alpha"],
        Mp=PAPER_DISPLAY.Mp * reported["Mp"],
        v_max=reported["v_max"],
    )
    profile = None
    if asked is not None:  # factors of the display's own constants
        profile = replace(shown, **{k: getattr(shown, k) * f for k, f in asked.items()})
    over = exceeded_limits(profile, shown) if profile is not None else []
    # a weight presses the piston from the start, so the law asks for a pull at once
    with display(shown, load_kg=load) as (url, counters):
        try:
            play(
                Tissue(LINEAR, K, S, M),
                url,
                0.25,
                profile=profile,
                realtime=False,
                idle_timeout_s=2.0,
            )
        except DeviceError as exc:
            assert over, exc  # refused only for asking more than the display reports
            assert "\n" not in str(exc) and "reports" in str(exc)
        except RenderError:
            assert not over  # judged (and refused) only within the display's limits
        else:
            assert not over
    if over:
        assert counters["commands"] == 0
    elif counters["max_command_volts"] is not None:
        assert counters["max_command_volts"] <= shown.v_max


class _Wire:
    """A link that keeps what is sent."""

    def __init__(self) -> None:
        self.sent: list[float] = []

    def send(self, message: Any) -> None:
        self.sent.append(message.volts)


def test_every_command_is_clamped_before_it_is_sent_and_counted():
    from tissuecli.app.play import HostLoop
    from tissuecli.render.check import check
    from tissuecli.render.controller import Controller

    tissue = Tissue(LINEAR, 600.0, 3.0, 0.05)
    gains = check(tissue, PAPER_DISPLAY, 1000.0).gains
    wire = _Wire()
    player = HostLoop(
        wire,  # type: ignore[arg-type]
        Controller(tissue, PAPER_DISPLAY, 1000.0, gains),
        PAPER_DISPLAY,
        1000.0,
        1e6,
        None,
    )
    for volts in (0.5, 70.9, -1.0, float("nan"), 1.5):
        player.send(volts)
    assert wire.sent == [0.5, 1.5, 0.0, 0.0, 1.5]
    assert player.clamped == 3


def test_the_refusal_the_docs_quote_is_what_play_prints(tmp_path: Path):
    import json
    import re

    from click.testing import CliRunner

    from tissuecli.cli import cli
    from tissuecli.core.tissue import DEFAULT_TISSUE
    from tissuecli.formats.params import tissue_to_dict

    docs = Path(__file__).resolve().parents[2] / "docs" / "calibration.md"
    block = next(
        b
        for b in re.findall(r"```(?:console)?\n(.*?)```", docs.read_text(), re.S)
        if "--profile big" in b
    )
    command, expected = [line.strip() for line in block.strip().splitlines()]
    (tmp_path / "liver.json").write_text(json.dumps(tissue_to_dict(DEFAULT_TISSUE)))
    (tmp_path / "big.json").write_text('{"v_max": 100, "alpha": 0.0001}')
    with display(PAPER_DISPLAY) as (url, counters):
        args = command.removeprefix("$ tissuecli ").replace("/tmp/display", url).split()
        args = [str(tmp_path / a) if a.endswith(".json") else a for a in args]
        res = CliRunner().invoke(cli, args)
    assert res.exit_code == 1
    assert res.output.strip() == expected.replace("/tmp/display", url)
    assert counters["commands"] == 0


def test_the_play_log_counts_the_clamps(tmp_path: Path):
    from tissuecli import formats

    log = tmp_path / "play.h5"
    with display(PAPER_DISPLAY) as (url, counters):
        summary = play(
            Tissue(LINEAR, 600.0, 3.0, 0.05),
            url,
            0.3,
            log=log,
            name="clamps",
            realtime=False,
            idle_timeout_s=2.0,
        )
    _, attrs = formats.read_group(log, "plays/clamps")
    assert attrs["clamped_commands"] == summary["clamped_commands"] == 0
    assert counters["max_command_volts"] <= PAPER_DISPLAY.v_max
