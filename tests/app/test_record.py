"""record on real pseudo-terminals: counts, physics, faults, clocks, stops and crashes."""

from __future__ import annotations

import signal
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from tissuecli import formats
from tissuecli.app.record import record
from tissuecli.core.errors import DeviceError, SessionExists
from tissuecli.sim.synth import CLOCK_HZ, ForcepsModel, Sensors

from ..conftest import assert_clean_error, popen, tissuecli


def _wait_for_rows(path: Path, rows: int, timeout: float = 120.0) -> None:
    """Until the recording in ``path`` holds ``rows`` samples. Not a timing test: the
    bound is for a recorder that never gets there, and a loaded machine may take a
    minute to start the command and its simulator."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            if sum(r["samples"] for r in formats.list_sessions(path)) >= rows:
                return
        except Exception:  # the writer may be between flushes
            pass
        time.sleep(0.1)
    raise AssertionError(f"{path} never reached {rows} rows")


def test_clean_line_records_every_frame_with_the_right_physics(forceps, tmp_path):
    sim = forceps("--seed", "3")
    out = tmp_path / "g.h5"
    res = record(str(sim.link), out, "s1", duration_s=2.0, tissue="liver")
    assert (res.samples, res.lost_frames, res.bad_frames) == (2000, 0, 0)
    s = formats.read_session(out, raw=True)
    assert len(s) == 2000 and s.meta["tissue"] == "liver" and s.meta["complete"]
    np.testing.assert_allclose(np.diff(s.time), 1e-3, rtol=1e-3)
    # the stored values are the simulator's physics, read through its 8-bit ADC
    model = ForcepsModel(seed=3)
    k = (s.meta["raw"]["raw/device_clock"] / (CLOCK_HZ / model.rate_hz)).round().astype(int)
    x, _, _, f = model.truth(k)
    sens = Sensors()
    cal = sens.calibration
    bound_x = 5 * np.hypot(sens.position_noise_m, cal.position.gain / np.sqrt(12))
    bound_f = 5 * np.hypot(sens.force_noise_n, cal.force.gain / np.sqrt(12))
    assert np.max(np.abs(s.position - x)) < bound_x
    assert np.max(np.abs(s.force - f)) < bound_f


def test_listeners_see_every_stored_sample_as_it_is_written(forceps, tmp_path):
    sim = forceps("--seed", "4")
    out = tmp_path / "g.h5"
    blocks = []
    res = record(str(sim.link), out, "s1", duration_s=1.0, on_samples=blocks.append)
    assert len(blocks) > 1, "samples should reach listeners in blocks while recording"
    s = formats.read_session(out)
    assert sum(len(b.time) for b in blocks) == res.samples == len(s)
    np.testing.assert_array_equal(np.concatenate([b.force for b in blocks]), s.force)
    np.testing.assert_array_equal(np.concatenate([b.position for b in blocks]), s.position)
    host = np.concatenate([b.host_time for b in blocks])
    assert np.all(np.diff(host) >= 0)


def test_corrupt_and_dropped_frames_are_counted_and_recording_resumes(forceps, tmp_path):
    sim = forceps("--corrupt", "0.03", "--drop", "0.02", "--seed", "5")
    out = tmp_path / "g.h5"
    res = record(str(sim.link), out, "faulty", duration_s=3.0)
    s = formats.read_session(out, raw=True)
    seq = s.meta["raw"]["raw/sequence"].astype(np.int64)
    span = int(seq[-1] - seq[0] + 1)
    # every frame is either stored or counted lost, and the bad ones were seen
    assert res.samples + res.lost_frames == span
    assert res.bad_frames > 0.5 * 0.03 * span
    assert res.lost_frames > 0.02 * span * 0.5
    assert np.all(np.diff(seq) > 0)


def test_clock_drift_is_estimated_from_the_arrivals(forceps, tmp_path):
    sim = forceps("--drift-ppm", "500")
    res = record(str(sim.link), tmp_path / "g.h5", "drift", duration_s=4.0)
    assert res.clock_map is not None
    # within 100 ppm, or within 3 of its own stated standard errors where a loaded
    # machine delays the arrivals the estimate rests on
    cm = res.clock_map
    assert abs(cm.drift_ppm - 500) < max(100.0, 3 * cm.drift_uncertainty_ppm)
    # 4 s cannot resolve a drift to 50 ppm with arrivals in 1 ms batches: time stays put
    assert res.time_rescaled == res.clock_map.resolved
    s = formats.read_session(tmp_path / "g.h5", "drift")
    assert s.meta["clock_map"]["time_rescaled"] == res.time_rescaled
    if not res.time_rescaled:
        np.testing.assert_allclose(s.time, np.arange(len(s)) * 1e-3, atol=1e-12)


def test_existing_session_is_refused_and_file_untouched(forceps, tmp_path):
    sim = forceps()
    out = tmp_path / "g.h5"
    record(str(sim.link), out, "a", duration_s=0.5)
    before = out.read_bytes()
    with pytest.raises(SessionExists):
        record(str(sim.link), out, "a", duration_s=0.5)
    assert out.read_bytes() == before


def test_missing_port_is_one_line_and_exit_1(tmp_path):
    result = tissuecli(
        "record",
        "--port",
        str(tmp_path / "nope"),
        "--out",
        str(tmp_path / "g.h5"),
        "--duration",
        "1",
    )
    assert_clean_error(result, "cannot open", "simulate forceps")
    assert not (tmp_path / "g.h5").exists()


def test_device_that_never_identifies_needs_calibration(tmp_path):
    with pytest.raises(DeviceError, match="--calibration"):
        record("loop://", tmp_path / "g.h5", "x", duration_s=1)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_signal_stops_cleanly_and_loses_nothing(forceps, tmp_path, sig):
    sim = forceps()
    out = tmp_path / "g.h5"
    proc = popen("record", "--port", str(sim.link), "--out", str(out), "--session", "live")
    _wait_for_rows(out, 500)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=20)
    assert proc.returncode == 128 + sig, err  # the session kept, the signal told
    s = formats.read_session(out, "live", raw=True)
    assert s.meta["complete"] and "signal" in s.meta["stop_reason"]
    assert s.meta["frames_lost"] == 0 and s.meta["frames_good"] == len(s)
    seq = s.meta["raw"]["raw/sequence"].astype(np.int64)
    assert np.all(np.diff(seq) == 1)


def test_kill_9_leaves_a_readable_file_with_everything_flushed(forceps, tmp_path):
    sim = forceps()
    out = tmp_path / "g.h5"
    proc = popen("record", "--port", str(sim.link), "--out", str(out), "--session", "crash")
    _wait_for_rows(out, 1500)
    flushed = formats.list_sessions(out)[0]["samples"]
    proc.kill()
    proc.communicate(timeout=10)
    with h5py.File(out, "r"):
        pass
    s = formats.read_session(out, "crash", raw=True)
    assert len(s) >= flushed >= 1500
    seq = s.meta["raw"]["raw/sequence"].astype(np.int64)
    assert np.all(np.diff(seq) == 1)
    assert not s.meta["complete"]


def test_device_vanishing_mid_session_saves_data_and_exits_nonzero(forceps, tmp_path):
    sim = forceps()
    out = tmp_path / "g.h5"
    proc = popen("record", "--port", str(sim.link), "--out", str(out), "--session", "gone")
    _wait_for_rows(out, 800)
    sim.stop(signal.SIGKILL)
    _, err = proc.communicate(timeout=20)
    assert proc.returncode == 7 and "Traceback" not in err  # a device lost: exit 7
    assert "lost" in err and "saved" in err
    s = formats.read_session(out, "gone")
    assert len(s) >= 800 and s.meta["stop_reason"].startswith("device lost")


@pytest.mark.slow
@pytest.mark.parametrize("rate", [1000, 10000])
def test_sixty_seconds_lose_no_frame(forceps, tmp_path, rate):
    sim = forceps("--rate", str(rate))
    res = record(str(sim.link), tmp_path / "g.h5", "long", duration_s=60.0)
    assert (res.samples, res.lost_frames, res.bad_frames) == (60 * rate, 0, 0)


def test_a_display_is_not_recorded(tmp_path):
    from tissuecli.sim.process import SimulatorProcess

    with SimulatorProcess("display", tmp_path / "display") as disp:
        result = tissuecli(
            "record", "--port", str(disp.link), "--out", str(tmp_path / "g.h5"), "--duration", "1"
        )
    assert_clean_error(result, "not a forceps")
    assert not (tmp_path / "g.h5").exists()


def test_one_record_service_refuses_what_its_protocol_cannot_use(tmp_path) -> None:
    """``record`` serves both protocols: an unknown one, or a text logger's reading
    options beside the binary protocol, are refused before any port is opened or file
    written."""
    from tissuecli.app.record import record as record_any
    from tissuecli.core.errors import InputError

    out = tmp_path / "r.h5"
    with pytest.raises(InputError, match="unknown protocol 'serial'"):
        record_any("/nonexistent", out, "s", protocol="serial")
    with pytest.raises(InputError, match="--columns is for --protocol text"):
        record_any("/nonexistent", out, "s", columns="time=1,force=2,position=3")
    with pytest.raises(InputError, match="--jaw-length is for --protocol text"):
        record_any("/nonexistent", out, "s", jaw_length_m=0.02)
    assert not out.exists()
