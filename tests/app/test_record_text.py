"""record --protocol text from the simulated text logger on a real pseudo-terminal:
every line accounted for at 1 kHz, each dialect, stamps or none, a wrapping counter."""

from __future__ import annotations

import os
import re
from functools import partial

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tissuecli import formats
from tissuecli.app.record import record as record_any
from tissuecli.core.errors import DeviceError, InputError
from tissuecli.sim.synth import ForcepsModel
from tissuecli.sim.textlogger import TextLogger

from ..conftest import assert_clean_error, tissuecli

#: the text logger's recording: the one record service with the text protocol
record = partial(record_any, protocol="text")

STARVED = "host starved of CPU (load average {:.1f} on {} cores): {} lines lost to a full port"


def _starved(lost: int) -> None:
    """Skip, with the reason, when lines were lost on a machine too busy to read them."""
    load, cores = os.getloadavg()[0], os.cpu_count() or 1
    if lost and load > cores:
        pytest.skip(STARVED.format(load, cores, lost))


def _text(forceps, *args: str):
    return forceps("--protocol", "text", "--seed", "5", *args)


def test_every_line_at_1_khz_is_a_sample_or_a_counted_malformed_line(forceps, tmp_path):
    rate, broken = 1000.0, 0.01
    sim = _text(forceps, "--rate", "1000", "--broken", str(broken))
    out = tmp_path / "t.h5"
    res = record(str(sim.link), out, "s", duration_s=3.0, identify=False)
    _starved(res.lost_frames)
    assert res.lost_frames == 0
    s = formats.read_session(out)
    meta = s.meta
    # which samples the logger printed: from the first kept stamp on, one a period
    logger = TextLogger(ForcepsModel(seed=5, rate_hz=rate), broken=broken)
    k0 = int(meta["device_stamp_first"] * rate // 1e6)
    k = k0 + np.rint(s.time * rate).astype(int)
    assert np.all(np.diff(k) >= 1)
    window = np.arange(k0, k[-1] + 1)
    printed_broken = logger.broken_at(window)
    # every slot is a sample or a broken line, and every broken line was counted
    assert set(window[~printed_broken]) == set(k)
    assert meta["lines_malformed"] == res.bad_frames == int(printed_broken.sum()) > 0
    assert meta["samples_missing"] == int(printed_broken.sum())
    # the values are the simulator's, through the ADC and 5 decimals
    x, _, _, f = ForcepsModel(seed=5, rate_hz=rate).truth(k)
    assert np.max(np.abs(s.force - f)) < 0.05
    assert np.max(np.abs(s.position - x)) < 1e-4
    assert meta["complete"] and meta["protocol"] == "text"


@pytest.mark.parametrize(
    ("args", "stamped"),
    [
        (("--format", "plotter", "--stamps", "ms", "--rate", "500"), True),
        (("--format", "teleplot", "--stamps", "us", "--rate", "250"), True),
        (("--format", "teleplot", "--stamps", "none", "--rate", "100"), False),
        (("--format", "csv", "--stamps", "none", "--rate", "60", "--header-every", "0.5"), False),
    ],
)
def test_each_dialect_records_with_or_without_device_stamps(forceps, tmp_path, args, stamped):
    sim = _text(forceps, *args, "--broken", "0")
    rate = float(args[args.index("--rate") + 1])
    out = tmp_path / "t.h5"
    res = record(str(sim.link), out, "s", duration_s=1.5, identify=False)
    _starved(res.lost_frames)
    s = formats.read_session(out)
    assert res.bad_frames == 0 and res.lost_frames == 0
    assert res.samples >= 1.5 * rate - 2
    assert s.meta["time_base"].startswith("device stamps") == stamped
    # on a regular clock at the logger's rate: fitted to arrivals within 2 %
    np.testing.assert_allclose(
        np.median(np.diff(s.time)), 1 / rate, rtol=0.02 if not stamped else 1e-3
    )
    assert 0 < s.position.max() < 0.02 and s.force.max() > 0.1  # mm and N read as such


def test_a_wrapping_micros_counter_is_unwrapped(forceps, tmp_path):
    # micros() starts 2.5 s before its wrap: the recording crosses it
    sim = _text(forceps, "--rate", "500", "--broken", "0", "--clock-start", str(2**32 - 2_500_000))
    out = tmp_path / "t.h5"
    res = record(str(sim.link), out, "s", duration_s=3.0, identify=False)
    _starved(res.lost_frames)
    s = formats.read_session(out)
    if res.faults.clock_wraps == 0:
        pytest.skip("the logger started too late to cross its wrap while recording (slow start)")
    assert res.lost_frames == 0 and res.faults.frames_rejected == 0
    np.testing.assert_allclose(np.diff(s.time), 1 / 500, rtol=1e-3)


def test_calibration_turns_printed_counts_into_si(forceps, tmp_path):
    from tissuecli.core.calibration import Calibration, Channel

    rate = 200.0
    sim = _text(forceps, "--rate", "200", "--broken", "0")
    cal = Calibration(force=Channel(2.0, 0.5, "N"), position=Channel(1e-3, 0.0, "m"))
    out = tmp_path / "t.h5"
    opts = {"identify": False, "duration_s": 1.0}
    record(str(sim.link), out, "s", calibration=cal, **opts)
    s = formats.read_session(out)
    k = int(s.meta["device_stamp_first"] * rate // 1e6) + np.rint(s.time * rate).astype(int)
    x, _, _, f = ForcepsModel(seed=5, rate_hz=rate).truth(k)
    # the printed N and mm read as counts: 2 N a count plus 0.5 N, 1 mm a count
    assert np.max(np.abs(s.force - (2.0 * f + 0.5))) < 0.1
    assert np.max(np.abs(s.position - x)) < 1e-4
    with pytest.raises(InputError, match="time only"):
        record(str(sim.link), tmp_path / "x.h5", "s", calibration=cal, units="mm", **opts)


def test_a_silent_port_and_a_port_of_frames_are_refused_in_words(forceps, tmp_path):
    sim = forceps("--seed", "1")  # binary: silent until START, which text never sends
    with pytest.raises(DeviceError, match="printed no line"):
        record(str(sim.link), tmp_path / "t.h5", "s", duration_s=1.0)
    assert not (tmp_path / "t.h5").exists()


def test_the_command_line_records_text_and_says_what_it_counted(forceps, tmp_path):
    sim = _text(forceps, "--rate", "200", "--broken", "0.02")
    out = tmp_path / "t.h5"
    r = tissuecli(
        "record", "--port", str(sim.link), "--protocol", "text", "--out", str(out),
        "--duration", "1", "--quiet", "--no-identify",
    )  # fmt: skip
    m = re.search(r"(\d+) lines received, (\d+) malformed, (\d+) lost", r.stdout)
    assert m is not None, r.stdout
    # malformed or lost lines are samples lost: exit 3 after the summary (docs/usage.md)
    assert r.returncode == (3 if int(m.group(2)) + int(m.group(3)) else 0), r.stderr
    assert "time: device stamps" in r.stdout
    bad = tissuecli(
        "record", "--port", str(sim.link), "--out", str(tmp_path / "u.h5"), "--units", "mm",
    )  # fmt: skip
    assert_clean_error(bad, "--units is for --protocol text")


_JUNK = st.one_of(
    st.text(max_size=40),
    st.sampled_from(["", "# note", "t_us,force_N,closure_mm", "1,2", "1,2,3,4", "x,1,2"]),
    st.builds(lambda t: f"{t},0.5,1.5", st.integers(-(2**33), 2**33)),
    st.builds(
        lambda f, x: f"7,{f!r},{x!r}",
        st.floats(allow_nan=False, width=64),
        st.floats(allow_nan=False, width=64),
    ),
)


@settings(max_examples=150, deadline=None)
@given(st.lists(_JUNK, max_size=60))
def test_every_line_is_a_sample_malformed_ignored_or_a_rejected_stamp(lines):
    """Whatever a logger prints, each line is accounted for exactly once, and nothing
    but those counts comes of a bad line."""
    from tissuecli.app.record_text import _Lines
    from tissuecli.hw.text import Line, sniff_dialect

    head = ["t_us,force_N,closure_mm"] + [f"{1000 * i},0.5,1.5" for i in range(10)]
    reader = _Lines(sniff_dialect(head), "test", None, None, None, None, head)
    got = [Line(text, i + 1, float(i)) for i, text in enumerate(lines)]
    (t, force, position, host), bad = reader.take(got)
    assert t.size + reader.malformed + reader.ignored + reader.stamps.rejected == len(lines)
    assert np.all(np.isfinite(force)) and np.all(np.isfinite(position))
    assert np.all(np.diff(t) >= 0)


def test_columns_units_and_jaw_length_are_the_imports():
    """`--columns`, `--units` and `--jaw-length` read text lines as `import` reads files:
    an angle between the jaws becomes the closure at the tips, grams-force newtons."""
    from tissuecli.app.record_text import _Lines
    from tissuecli.hw.text import Line, sniff_dialect

    head = [f"ms:{i} F:{10 * i} ang:{i}" for i in range(20)]
    reader = _Lines(
        sniff_dialect(head), "test", "time=ms,force=F,position=ang",
        "time=ms,force=gf,position=deg", 0.02, None, head,
    )  # fmt: skip
    (t, force, position, _), bad = reader.take([Line(x, i, 0.0) for i, x in enumerate(head)])
    assert bad == 0 and reader.reading.report.columns == {
        "time": "ms", "force": "F", "position": "ang",
    }  # fmt: skip
    np.testing.assert_allclose(t, np.arange(20) * 1e-3)
    np.testing.assert_allclose(force, np.arange(20) * 10 * 9.80665e-3)
    np.testing.assert_allclose(position, -2 * 0.02 * np.sin(np.radians(np.arange(20)) / 2))
    with pytest.raises(InputError, match="jaw-length"):
        _Lines(sniff_dialect(head), "test", "position=ang", "position=deg", None, None, head)


def test_a_signal_stops_cleanly_and_kill_9_leaves_what_was_flushed(forceps, tmp_path):
    """The same crash-safe writer as frames: Ctrl-C closes the session complete; a
    killed recorder leaves a readable file with every flushed row."""
    import signal

    import h5py

    from ..conftest import popen
    from .test_record import _wait_for_rows

    sim = _text(forceps, "--rate", "1000")
    out = tmp_path / "t.h5"
    args = ("record", "--port", str(sim.link), "--protocol", "text", "--out", str(out))
    proc = popen(*args, "--session", "live", "--no-identify")
    _wait_for_rows(out, 500)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=20)
    assert proc.returncode in (130, 3), err  # 128 + SIGINT, or lines lost on the way
    s = formats.read_session(out, "live")
    assert s.meta["complete"] and "signal" in s.meta["stop_reason"]
    assert s.meta["frames_good"] == len(s) and np.all(np.diff(s.time) > 0)
    proc = popen(*args, "--session", "crash", "--no-identify")
    _wait_for_rows(out, len(s) + 1500)
    proc.kill()
    proc.communicate(timeout=10)
    with h5py.File(out, "r"):
        pass
    crashed = formats.read_session(out, "crash")
    assert len(crashed) >= 1000 and not crashed.meta["complete"]
