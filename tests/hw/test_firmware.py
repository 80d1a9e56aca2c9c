"""The reference firmware's portable C core, built with the system C compiler and driven
from the Python host through a pseudo-terminal: frames byte-identical both ways, the
forceps recorded by `record`, the display's watchdog cutting on silence, and its text
logger recorded by `record --protocol text`."""

from __future__ import annotations

import json
import math
import os
import pty
import shutil
import signal
import struct
import subprocess
import time
import tty
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from tissuecli import formats
from tissuecli.app.record import record
from tissuecli.hw.link import Link
from tissuecli.hw.protocol import (
    FLAG_STALE,
    FLAG_WATCHDOG,
    Command,
    Encoder,
    Info,
    Sample,
    SetVoltage,
    decode_frame,
    encode,
)

ROOT = Path(__file__).resolve().parents[2]
FIRMWARE = ROOT / "firmware"
SOURCES = [FIRMWARE / "core" / "tc_protocol.c", FIRMWARE / "core" / "tc_device.c"]
FLAGS = ["-std=c99", "-Wall", "-Wextra", "-Wpedantic", "-Werror", "-O2"]


@pytest.fixture(scope="module")
def host_build(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The firmware core and its PC harness, compiled once."""
    cc = shutil.which(os.environ.get("CC", "cc"))
    if cc is None:
        pytest.skip("no C compiler (cc) on this machine: apt-get install gcc")
    out = tmp_path_factory.mktemp("firmware") / "tc_host"
    build = subprocess.run(
        [cc, *FLAGS, *map(str, SOURCES), str(FIRMWARE / "host" / "tc_host.c"), "-o", str(out)]
        + ["-lm"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert build.returncode == 0, build.stderr
    return out


@contextmanager
def device(binary: Path, *args: str) -> Iterator[tuple[str, subprocess.Popen[str]]]:
    """The compiled core behind a pseudo-terminal: its path for the host, and the process."""
    master, slave = pty.openpty()
    tty.setraw(slave)
    proc = subprocess.Popen(
        [str(binary), *args], stdin=master, stdout=master, stderr=subprocess.PIPE, text=True
    )
    try:
        yield os.ttyname(slave), proc
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        if proc.stderr is not None:
            proc.stderr.close()
        os.close(master)
        os.close(slave)


def _read(link: Link, n: int, within_s: float = 10.0) -> bytes:
    out = b""
    deadline = time.monotonic() + within_s
    while len(out) < n and time.monotonic() < deadline:
        out += link.read_bytes()
    return out


def _random_messages(rng: np.random.Generator, n: int) -> list:
    out = []
    for _ in range(n):
        kind = int(rng.integers(5))
        u32 = lambda: int(rng.integers(0, 2**32))  # noqa: E731
        if kind == 0:
            out.append(Sample(u32(), u32(), *map(int, rng.integers(-(2**15), 2**15, 2))))
        elif kind == 1:
            volts = float(np.float32(rng.normal(0, 3)))
            out.append(Encoder(u32(), u32(), int(rng.integers(-(2**31), 2**31)), volts, 3))
        elif kind == 2:
            out.append(SetVoltage(u32(), float(np.float32(rng.uniform(-10, 10)))))
        elif kind == 3:
            out.append(Command(int(rng.integers(0, 256))))
        else:
            # long runs without a zero byte exercise COBS's 254-byte blocks
            out.append(Info({"model": "x" * int(rng.integers(0, 600)), "k": u32()}))
    return out


def test_frames_come_back_byte_identical_through_the_c_core(host_build):
    rng = np.random.default_rng(7)
    messages = _random_messages(rng, 300)
    frames = [encode(m) for m in messages]
    with device(host_build, "echo") as (path, _), Link(path) as link:
        sent = back = b""
        for i, frame in enumerate(frames):
            junk = b"\x13\x37garbage\x00" if i % 50 == 25 else b""  # resynchronised at 0x00
            link._port.write(junk + frame)
            sent += frame
            # read as it comes back, so that neither side's buffer overflows
            back += _read(link, len(sent) - len(back), within_s=2.0)
        back += _read(link, len(sent) - len(back))
    assert back == sent
    # what came back decodes to what was sent
    got = [decode_frame(f) for f in back.split(b"\x00")[:-1]]
    assert got == messages


def test_the_c_forceps_is_recorded_by_the_python_host(host_build, tmp_path):
    rate = 1000.0
    with device(host_build, "forceps", "1000") as (path, proc):
        # C to Python: every frame on the line is what the reference encoder makes of it
        with Link(path) as link:
            info = link.identify()
            assert info is not None and info["device"] == "forceps" and info["adc_bits"] == 12
            link.command("start")
            raw = _read(link, 17 * 200)
            link.command("stop")
        frames = raw.split(b"\x00")[1:-1]  # the first may be cut by START's timing
        assert len(frames) > 100
        for frame in frames:
            assert encode(decode_frame(frame)) == frame + b"\x00"
        out = tmp_path / "c.h5"
        res = record(path, out, "c", duration_s=2.0, identify=False)
    assert res.bad_frames == 0 and res.lost_frames == 0
    assert res.samples == pytest.approx(2.0 * rate, abs=2)
    s = formats.read_session(out, raw=True)
    k = s.meta["raw"]["raw/sequence"].astype(np.int64)
    # the counts are the C core's ADC, calibrated by the constants its Info reported
    closure = 0.5 - 0.5 * np.cos(np.pi * k / rate)
    counts = s.meta["raw"]["raw/counts"].astype(np.int64)
    assert np.max(np.abs(counts[:, 1] - np.rint(-1800 + 3600 * closure))) <= 1
    cal = info["calibration"]
    np.testing.assert_allclose(
        s.force, cal["force"]["gain"] * counts[:, 0] + cal["force"]["offset"], rtol=1e-6
    )


def _encoder_frames(link: Link, within_s: float) -> list[Encoder]:
    out: list[Encoder] = []
    deadline = time.monotonic() + within_s
    while time.monotonic() < deadline:
        out += [m for m in link.poll() if isinstance(m, Encoder)]
    return out


def _until(link: Link, seen: Callable[[Encoder], bool], within_s: float = 10.0) -> list[Encoder]:
    """Encoder frames read until one is ``seen``: the display keeps its own clock and
    the frames queue in the pseudo-terminal, so a starved test reads them late, never
    differently; the bound is only for a display that never shows it."""
    out: list[Encoder] = []
    deadline = time.monotonic() + within_s
    while time.monotonic() < deadline:
        out += [m for m in link.poll() if isinstance(m, Encoder)]
        if any(seen(m) for m in out):
            return out
    raise AssertionError(f"no such frame in {within_s} s ({len(out)} frames read)")


def test_the_c_display_clamps_to_v_max_and_its_watchdog_cuts_on_silence(host_build):
    with device(host_build, "display", "1000", "3.0") as (path, proc):
        with Link(path, kind="display") as link:
            info = link.identify()
            assert info is not None and info["device"] == "display"
            link.command("start")
            _until(link, lambda m: True)  # started
            # a command is applied at the next period, clamped to [0, v_max], NaN read as
            # 0 (and clears a cut, so the frames after it show it unflagged whatever the
            # host's scheduling)
            for i, (volts, applied) in enumerate(((1.25, 1.25), (100.0, 3.0), (-2.0, 0.0))):
                link.send(SetVoltage(i, volts))
                _until(link, lambda m, a=applied: m.volts == a and not m.flags & FLAG_WATCHDOG)
            link.send(SetVoltage(5, 1.0))
            _until(link, lambda m: m.volts == 1.0)
            link.send(SetVoltage(6, math.nan))
            _until(link, lambda m: m.volts == 0.0 and not m.flags & FLAG_WATCHDOG)
            link.send(SetVoltage(99, 2.0))
            # then silence: after 5 periods at 2 V the solenoid is cut. A starved test may
            # send the 2 V after the silence since the NaN was already cut, so the cut is
            # judged from the first frame that shows the 2 V on the display's own clock.
            frames = _until(link, lambda m: m.volts == 2.0)
            frames = frames[next(i for i, m in enumerate(frames) if m.volts == 2.0) :]
            if not any(m.flags & FLAG_WATCHDOG for m in frames):
                frames += _until(link, lambda m: bool(m.flags & FLAG_WATCHDOG))
            cut = next(i for i, m in enumerate(frames) if m.flags & FLAG_WATCHDOG)
            assert frames[cut].volts == 0.0
            assert cut > 0 and all(m.volts == 2.0 for m in frames[:cut])
            assert frames[cut].clock - frames[0].clock >= 5 * 1000 - 1  # display clock, us
            # a command clears it
            link.send(SetVoltage(100, 0.5))
            _until(link, lambda m: m.volts == 0.5 and not m.flags & FLAG_WATCHDOG)
            link.command("stop")


def test_the_c_display_flags_the_periods_run_on_a_late_answer(host_build):
    """A SetVoltage is numbered by the Encoder frame it answers: the periods after an
    old answer are flagged stale until the answer to the frame before arrives."""
    with device(host_build, "display", "1000", "3.0") as (path, proc):
        with Link(path, kind="display") as link:
            assert (link.identify() or {}).get("stale_flag") is True
            link.command("start")
            first = _until(link, lambda m: True)
            assert not any(m.flags & FLAG_STALE for m in first)  # not yet armed
            link.send(SetVoltage((first[-1].seq - 10) & 0xFFFFFFFF, 1.0))  # an old answer
            later = _until(link, lambda m: bool(m.flags & FLAG_STALE))
            later += _encoder_frames(link, 0.02)
            flagged = [i for i, m in enumerate(later) if m.flags & FLAG_STALE]
            assert all(m.flags & FLAG_STALE for m in later[flagged[0] :])
            # answered frame by frame, some periods run on the answer to the frame before
            # (every one when neither side is held up)
            fresh = 0
            deadline = time.monotonic() + 10.0
            while time.monotonic() < deadline and fresh < 5:
                frames = [m for m in link.poll() if isinstance(m, Encoder)]
                if frames:
                    fresh += sum(not m.flags & FLAG_STALE for m in frames)
                    link.send(SetVoltage(frames[-1].seq, 1.0))
            assert fresh >= 5
            link.command("stop")


def test_a_silent_display_host_trips_the_watchdog_only_once_armed(host_build):
    with device(host_build, "display", "1000", "3.0") as (path, proc):
        with Link(path, kind="display") as link:
            link.command("start")
            frames = _until(link, lambda m: True)  # started, never commanded
            frames += _encoder_frames(link, 0.02)
            assert not any(m.flags & FLAG_WATCHDOG for m in frames)
            link.send(SetVoltage(0, 1.0))
            frames = _until(link, lambda m: bool(m.flags & FLAG_WATCHDOG))
            # on the display's own clock, at least 5 periods passed between the last
            # frame at 1 V and the first cut
            on = [m for m in frames if m.volts == 1.0]
            first_cut = next(m for m in frames if m.flags & FLAG_WATCHDOG)
            if on:
                assert first_cut.clock - on[0].clock >= 5 * 1000 - 1
            link.command("stop")
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=5)
    assert "watchdog trips" in err and " 0 watchdog trips" not in err


def test_the_c_text_logger_at_1_khz_loses_no_line_and_counts_every_broken_one(host_build, tmp_path):
    rate, every = 1000.0, 97
    with device(host_build, "text", "1000", str(every)) as (path, _):
        out = tmp_path / "t.h5"
        res = record(path, out, "t", protocol="text", duration_s=3.0, identify=False)
    load, cores = os.getloadavg()[0], os.cpu_count() or 1
    if res.lost_frames and load > cores:
        pytest.skip(f"host starved of CPU (load {load:.1f} on {cores} cores): lines lost")
    assert res.lost_frames == 0
    s = formats.read_session(out)
    k0 = round(s.meta["device_stamp_first"] * rate / 1e6)
    k = k0 + np.rint(s.time * rate).astype(np.int64)
    window = np.arange(k0, k[-1] + 1)
    broken = window % every == every - 1
    assert set(window[~broken]) == set(k)
    # a broken line just before the first sample kept or just after the last one is
    # counted too, though it falls outside the span of samples
    edges = int((k0 - 1) % every == every - 1) + int((k[-1] + 1) % every == every - 1)
    assert s.meta["lines_malformed"] == res.bad_frames
    assert int(broken.sum()) <= res.bad_frames <= int(broken.sum()) + edges
    assert broken.sum() > 0
    # header reprinted every second: ignored, not malformed
    assert s.meta["lines_ignored"] >= 2
    # the closure the C core printed: its ADC through its calibration constants, in mm
    counts = np.rint(-1800 + 3600 * (0.5 - 0.5 * np.cos(np.pi * k / rate)))
    gain = 15.5e-3 / 4095
    np.testing.assert_allclose(s.position, gain * counts + 7.25e-3 - gain * 0.5, atol=2e-7)


def test_the_core_formats_numbers_without_printf(host_build, tmp_path):
    """The text line of one sample, checked against Python's formatting."""
    with device(host_build, "text", "200", "0") as (path, _), Link(path) as link:
        raw = _read(link, 2000, within_s=5)
    lines = raw.decode().splitlines()[1:-1]
    rows = [ln.split(",") for ln in lines if not ln.startswith("t_us")]
    assert rows and all(len(r) == 3 for r in rows)
    for t, f, x in rows:
        assert len(f.split(".")[1]) == 5 and len(x.split(".")[1]) == 4
        json.loads(t)
        struct.pack("<f", float(f))


@pytest.mark.parametrize(
    ("sketch", "defines"), [("forceps", []), ("forceps", ["-DTEXT_MODE=1"]), ("display", [])]
)
def test_the_arduino_sketches_build_against_the_arduino_api(host_build, tmp_path, sketch, defines):
    """Each sketch is valid C++ against the Arduino functions it uses (a stand-in board,
    firmware/host/arduino_stub); the text forceps' lines are read by the text dialect."""
    cxx = shutil.which(os.environ.get("CXX", "c++"))
    if cxx is None:
        pytest.skip("no C++ compiler (c++) on this machine: apt-get install g++")
    objects = []
    for source in SOURCES:
        obj = tmp_path / (source.stem + ".o")
        subprocess.run(["cc", *FLAGS, "-c", str(source), "-o", str(obj)], check=True)
        objects.append(str(obj))
    stub = FIRMWARE / "host" / "arduino_stub"
    out = tmp_path / sketch
    build = subprocess.run(
        [cxx, "-std=c++11", "-Wall", "-Wextra", "-Werror", "-O2", *defines, "-I", str(stub)]
        + ["-x", "c++", "-include", "Arduino.h", str(FIRMWARE / sketch / f"{sketch}.ino")]
        + ["-x", "none", str(stub / "stub.cpp"), *objects, "-o", str(out)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert build.returncode == 0, build.stderr
    printed = subprocess.run([str(out)], capture_output=True, timeout=60).stdout
    if defines:
        from tissuecli.hw.text import sniff_dialect

        lines = printed.decode().splitlines()
        dialect = sniff_dialect(lines[:50])
        assert dialect.names == ["t_us", "force_N", "closure_mm"]
        assert all(dialect.read(line) for line in lines[1:200])
    else:
        assert printed == b""  # frames only after START, which nobody sent


def test_play_closes_its_loop_over_the_c_display(host_build):
    """`play` identifies the C display, answers its Encoder frames and stops it; every
    frame decodes, and any watchdog cut the host's scheduling caused is reported."""
    from tissuecli.app.play import play
    from tissuecli.core.tissue import DEFAULT_TISSUE

    with device(host_build, "display", "1000", "3.0") as (path, _):
        result = play(DEFAULT_TISSUE, path, 1.0, realtime=False, idle_timeout_s=1.0)
    assert result["frames"] > 0 and result["frames_bad"] == 0
    assert result["commands_sent"] > 0
    if result["watchdog_frames"]:
        assert any("watchdog" in fault for fault in result["faults"])
