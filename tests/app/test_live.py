"""``live`` with both simulated devices: record, identify online, render, and 0 V when a
device goes; its haptic loop in a process of its own, fed by the recorder's."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from tissuecli.app.live import HapticLoop, live
from tissuecli.core.errors import DeviceLost
from tissuecli.core.terms import Law
from tissuecli.core.tissue import Tissue
from tissuecli.formats.sessions import read_session
from tissuecli.render.check import check
from tissuecli.sim.process import SimulatorProcess

DISPLAY = """
import json, sys
from tissuecli.sim.display import run_simulated_display
counters = run_simulated_display(sys.argv[1], on_ready=lambda p: print(p.path, flush=True))
print(json.dumps(counters), flush=True)
"""

# a recorder's process: starts the haptic loop, hands it a tissue, keeps the forceps
# "alive" and says when the solenoid has done work
PARENT = """
import sys, time
from tissuecli.app.live import HapticLoop
from tissuecli.core.terms import Law
from tissuecli.core.tissue import Tissue
from tissuecli.render.check import check
tissue = Tissue(Law.paper("x", "xdot"), 600.0, 3.0, 0.05)
loop = HapticLoop(sys.argv[1])
loop.render(tissue, check(tissue, loop.profile).gains)
loop.set_active(True)
said = False
while True:
    loop.forceps_alive()
    loop.poll()
    if not said and loop.energy_j > 0.0:
        print(loop.proc.pid, flush=True)
        said = True
    time.sleep(0.005)
"""


@pytest.mark.slow
def test_live_renders_the_confident_estimate_and_scores_it(tmp_path: Path) -> None:
    with (
        SimulatorProcess("forceps", tmp_path / "f") as forceps,
        SimulatorProcess("display", tmp_path / "d") as display,
    ):
        s = live(str(forceps.link), str(display.link), tmp_path / "live.h5", "s1", 10.0)
    assert s["recording"]["samples"] > 9000
    assert read_session(tmp_path / "live.h5", "s1").time.size == s["recording"]["samples"]
    # the simulated forceps grasps K = 350 N/m, S = 3 N s/m: confident, then rendered
    assert s["estimate"]["confident"] and s["rendered"] is not None
    assert s["rendered"]["K"] == pytest.approx(350.0, rel=0.05)
    assert s["first_render_delay_s"] is not None and s["first_render_delay_s"] > 0.0
    assert s["offline"]["K"] == pytest.approx(350.0, rel=0.05)
    assert s["tracking_rms_n"] is not None and s["tracking_rms_n"] < 0.5
    assert s["passivity"]["energy_min_j"] > -2e-3


@pytest.mark.slow
def test_a_forceps_that_goes_ends_live_with_the_recording_kept(tmp_path: Path) -> None:
    with (
        SimulatorProcess("forceps", tmp_path / "f") as forceps,
        SimulatorProcess("display", tmp_path / "d") as display,
    ):
        assert forceps.process is not None
        threading.Timer(6.0, forceps.process.send_signal, (signal.SIGKILL,)).start()
        with pytest.raises(DeviceLost, match="saved"):
            live(str(forceps.link), str(display.link), tmp_path / "live.h5", "s1", 30.0)
        assert display.process is not None and display.process.poll() is None
    assert read_session(tmp_path / "live.h5", "s1").time.size > 3000


@pytest.mark.slow
def test_a_display_that_goes_ends_live_with_the_recording_kept(tmp_path: Path) -> None:
    with (
        SimulatorProcess("forceps", tmp_path / "f") as forceps,
        SimulatorProcess("display", tmp_path / "d") as display,
    ):
        assert display.process is not None
        threading.Timer(5.0, display.process.send_signal, (signal.SIGKILL,)).start()
        t0 = time.monotonic()
        with pytest.raises(DeviceLost, match="display was lost.*saved"):
            live(str(forceps.link), str(display.link), tmp_path / "live.h5", "s1", 30.0)
        assert time.monotonic() - t0 < 15.0  # the recording stopped with the display
    assert read_session(tmp_path / "live.h5", "s1").time.size > 3000


def _ended(pid: int) -> bool:
    """The process is gone or a zombie."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] == "Z"
    except FileNotFoundError:
        return True


@pytest.mark.slow
@pytest.mark.skipif(not os.path.isdir("/proc"), reason="needs /proc")
def test_the_loop_sends_zero_volts_and_ends_when_its_parent_is_killed(tmp_path: Path) -> None:
    link = tmp_path / "display"
    display = subprocess.Popen(
        [sys.executable, "-c", DISPLAY, str(link)], stdout=subprocess.PIPE, text=True
    )
    assert display.stdout is not None
    assert display.stdout.readline().strip() == str(link)
    parent = subprocess.Popen(
        [sys.executable, "-c", PARENT, str(link)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert parent.stdout is not None
        loop_pid = int(parent.stdout.readline())  # the solenoid has pulled
        parent.kill()
        parent.wait(5)
        deadline = time.monotonic() + 5.0
        while not _ended(loop_pid) and time.monotonic() < deadline:
            time.sleep(0.02)
        assert _ended(loop_pid), "the loop outlived its parent"
    finally:
        if parent.poll() is None:
            parent.kill()
        time.sleep(0.05)
        display.send_signal(signal.SIGTERM)
        out, _ = display.communicate(timeout=10)
    counters = json.loads(out.strip().splitlines()[-1])
    assert counters["commands"] > 100
    assert counters["last_command_volts"] == 0.0  # sent by the loop, not the watchdog


@pytest.mark.slow
def test_a_tissue_handed_over_reaches_the_loop_and_is_retargeted(tmp_path: Path) -> None:
    first = Tissue(Law.paper("x", "xdot"), 600.0, 3.0, 0.05)
    softer = Tissue(Law.paper("x", "xdot"), 450.0, 3.0, 0.05)
    with SimulatorProcess("display", tmp_path / "d") as display:
        loop = HapticLoop(str(display.link))
        gains = check(first, loop.profile).gains
        loop.render(first, gains)
        loop.set_active(True)
        t_end = time.monotonic() + 3.0
        handed = False
        while time.monotonic() < t_end:
            loop.forceps_alive()
            assert loop.poll()
            if not handed and time.monotonic() > t_end - 1.5:
                loop.render(softer, gains)
                handed = True
            time.sleep(0.005)
        result = loop.finish()
    assert result["handovers"] == 2 and not result["refused"]
    assert {k: v for k, v in result["rendered"].items() if k != "units"} == softer.describe()
    assert result["first_render"] is not None
    assert result["render"]["frames"] > 1000
    assert result["render"]["realtime"]["loop"] == "process"
