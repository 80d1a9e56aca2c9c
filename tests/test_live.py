"""``live`` with both simulated devices: record, identify online, render, and 0 V when a
device goes."""

from __future__ import annotations

import signal
import threading
from pathlib import Path

import pytest

from tissuecli.app.live import live
from tissuecli.core.errors import DeviceLost
from tissuecli.formats.sessions import read_session
from tissuecli.sim.process import SimulatorProcess


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
