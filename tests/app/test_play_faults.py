"""A play says what it knows: the rules that make it faulty, and a loop made to miss its
deadlines on purpose (a controller that stalls) ending in exit status 1 after the summary
and the log are written."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import h5py
import pytest
from click.testing import CliRunner

import tissuecli.app.play as app_play
from tissuecli.app.faults import (
    MAX_MISSED_FRACTION,
    TRACKING_ALLOWANCE_M,
    classify_faults,
    play_faults,
)
from tissuecli.app.play import PlayFaults, play_file
from tissuecli.app.summaries import play_lines
from tissuecli.cli import cli
from tissuecli.core.errors import EXIT_OFF_RATE, EXIT_WATCHDOG, RenderError
from tissuecli.core.terms import Law
from tissuecli.core.tissue import Tissue
from tissuecli.formats.jsonfile import write_json
from tissuecli.formats.params import tissue_to_dict
from tissuecli.sim.process import SimulatorProcess

CLEAN = {
    "frames": 5000,
    "loop_rate_hz": 999.0,
    "period_p99_ms": 1.1,
    "missed_periods": 10,
    "frames_lost": 0,
    "frames_bad": 0,
    "watchdog_frames": 0,
    "nonfinite_frames": 0,
    "tracking_max_m": 50e-6,
    "tracking_bound_m": 40e-6,
    "saturated_fraction": 0.0,
    "unrenderable_fraction": 0.01,
    "check": {"soft_gap_m": 0.0},
}


def test_a_clean_play_has_no_faults():
    assert play_faults(CLEAN, 1000.0) == []


@pytest.mark.parametrize(
    ("change", "needle"),
    [
        ({"watchdog_frames": 76}, "watchdog cut the solenoid on 76 frame(s)"),
        ({"loop_rate_hz": 915.0, "period_p99_ms": 5.0}, "915.0 Hz, 8.5 % off 1000 Hz"),
        ({"loop_rate_hz": 1021.0}, "2.1 % off"),
        ({"missed_periods": 400}, "400 periods passed without a frame (8.0 %"),
        (
            {"stale_frames": 400, "stale_run_max": 9},
            "the display ran 400 periods on a late answer (8.0 % of 5000, longest run 9)",
        ),
        ({"unanswered_frames": 400}, "400 frames reached the host too late to answer (8.0 %"),
        ({"frames_lost": 200, "frames_bad": 60}, "260 frame(s) lost or corrupt"),
        ({"nonfinite_frames": 1}, "non-finite"),
        ({"tracking_max_m": 1.62e-3, "tracking_bound_m": 0.74e-3}, "reached 1.62 mm"),
        ({"saturated_fraction": 0.19}, "19.0 % of frames saturated"),
        ({"unrenderable_fraction": 0.67}, "67.0 % of frames unrenderable"),
    ],
)
def test_each_rule_makes_a_play_faulty(change, needle):
    faults = play_faults({**CLEAN, **change}, 1000.0)
    assert len(faults) == 1 and needle in faults[0], faults


def test_rules_stop_at_their_limits():
    at_limits = {
        **CLEAN,
        "loop_rate_hz": 980.0,  # 2.0 % off
        "missed_periods": MAX_MISSED_FRACTION * CLEAN["frames"],
        "stale_frames": MAX_MISSED_FRACTION * CLEAN["frames"],
        "tracking_max_m": 40e-6 + 0.3e-3 + TRACKING_ALLOWANCE_M,
        "check": {"soft_gap_m": 0.3e-3},  # where the display can only show its spring
        "saturated_fraction": 0.05,
        "unrenderable_fraction": 0.3,
    }
    assert play_faults(at_limits, 1000.0) == []
    # a display that reports its late answers is believed over the host's own count
    assert play_faults({**CLEAN, "stale_frames": 10, "unanswered_frames": 400}, 1000.0) == []
    # a summary with missing or null figures (an empty play) is not a fault by itself
    assert play_faults({"frames": 0, "tracking_bound_m": None}, 1000.0) == []


def test_faults_are_shown_loudly_in_the_play_lines():
    lines = play_lines({**CLEAN, "faults": ["the loop ran at 915.0 Hz"]})
    assert "FAULT: the loop ran at 915.0 Hz" in lines
    assert lines[-1].startswith("the display did not render the tissue as checked")
    assert not any("FAULT" in line for line in play_lines({**CLEAN, "faults": []}))


# --------------------------------------------------------------------------- a stalling loop

STALL_EVERY = 300  # frames
STALL_S = 0.012  # 12 periods at 1 kHz: more than the display's 5-period watchdog


@pytest.fixture
def stalling_controller(monkeypatch: pytest.MonkeyPatch) -> None:
    """The controller sleeps 12 ms every 300 frames: deadlines are missed by construction,
    whatever the machine's load, and the display's watchdog must cut the solenoid."""
    original = app_play.Controller.update
    calls = {"n": 0}

    def update(self: Any, *args: Any, **kwargs: Any) -> Any:
        calls["n"] += 1
        if calls["n"] % STALL_EVERY == 0:
            time.sleep(STALL_S)
        return original(self, *args, **kwargs)

    monkeypatch.setattr(app_play.Controller, "update", update)


@pytest.fixture
def display(tmp_path: Path) -> Iterator[SimulatorProcess]:
    # the firmware's 5-period watchdog, not one lengthened to the port's round trips
    with SimulatorProcess("display", tmp_path / "display", ["--watchdog-periods", "5"]) as d:
        yield d


@pytest.fixture
def params(tmp_path: Path) -> Path:
    path = tmp_path / "tissue.json"
    write_json(path, tissue_to_dict(Tissue(Law.paper("x", "xdot"), 600.0, 3.0, 0.05)))
    return path


def test_a_stalling_loop_is_faulty_after_its_summary_and_log_are_written(
    stalling_controller, display, params, tmp_path
):
    summary, log = tmp_path / "summary.json", tmp_path / "plays.h5"
    with pytest.raises(PlayFaults) as info:
        play_file(params, str(display.link), 1.5, summary=summary, log=log, name="stalled")
    assert isinstance(info.value, RenderError)  # the command line's one-line error, exit 1
    message = str(info.value)
    assert message.startswith("the play was faulty: the display's watchdog cut the solenoid")
    assert f"summary {summary} and log {log} written" in message and "\n" not in message
    written = json.loads(summary.read_text())
    assert written == info.value.summary
    assert written["verdict"] == "faulty" and written["watchdog_frames"] > 0
    assert written["faults"][0].startswith("the display's watchdog")
    with h5py.File(log, "r") as f:
        attrs = f["plays/stalled"].attrs
        assert bool(attrs["complete"]) and attrs["verdict"] == "faulty"


def test_the_command_prints_the_figures_then_exits_4(stalling_controller, display, params):
    result = CliRunner().invoke(
        cli, ["play", str(params), "--port", str(display.link), "--duration", "1.5"]
    )
    assert result.exit_code == EXIT_WATCHDOG, result.output
    lines = result.output.strip().splitlines()
    assert any(line.startswith("played 1.") for line in lines), result.output
    assert any(line.startswith("FAULT: the display's watchdog") for line in lines)
    assert lines[-1].startswith("Error: the play was faulty: the display's watchdog")
    assert "Traceback" not in result.output


# ------------------------------------------------------------- a host that cannot keep up

SLOW_S = 0.0015  # each frame takes the host 1.5 periods at 1 kHz


@pytest.fixture
def slow_controller(monkeypatch: pytest.MonkeyPatch) -> None:
    """The controller takes 1.5 ms a frame: a host that cannot keep up with a 1 kHz
    display by construction, whatever the machine's load (a load only slows it more)."""
    original = app_play.Controller.update

    def update(self: Any, *args: Any, **kwargs: Any) -> Any:
        time.sleep(SLOW_S)
        return original(self, *args, **kwargs)

    monkeypatch.setattr(app_play.Controller, "update", update)


def test_a_host_that_cannot_keep_up_is_off_its_rate(slow_controller, display, params, tmp_path):
    summary = tmp_path / "summary.json"
    with pytest.raises(PlayFaults) as info:
        play_file(params, str(display.link), 1.0, summary=summary)
    s = info.value.summary
    # it ran the display's frames through the loop at 1 / 1.5 ms at best ...
    assert 0 < s["loop_rate_hz"] < 1.02 / SLOW_S
    assert any(f.startswith("the loop ran at") and "% off 1000 Hz" in f for f in s["faults"])
    # ... and the display, which reports it, ran most periods on a late answer
    assert s["stale_frames"] > MAX_MISSED_FRACTION * s["frames"]
    assert any("periods on a late answer" in f for f in s["faults"]), s["faults"]
    assert EXIT_OFF_RATE in {code for code, _ in classify_faults(s, 1000.0)}
