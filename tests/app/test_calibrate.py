"""calibrate display against a simulated display process over a real pty, whose true
constants differ from those it reports; calibrate forceps from files, prompts and the
live forceps."""

from __future__ import annotations

import json
import math
import os
import re
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st

from tissuecli.app.calibrate import (
    calibrate_display,
    display_lines,
    parse_mass,
    parse_reference,
)
from tissuecli.app.play import play
from tissuecli.cli import cli
from tissuecli.core.errors import DeviceError, DeviceLost, InputError
from tissuecli.core.terms import Law
from tissuecli.core.tissue import Tissue
from tissuecli.formats.params import read_calibration, read_profile
from tissuecli.render.profile import PAPER_DISPLAY, exceeded_limits

DISPLAY = """
import json, sys
from tissuecli.render.profile import profile_from_dict, PAPER_DISPLAY
from tissuecli.sim.display import run_simulated_display
truth = profile_from_dict(json.loads(sys.argv[2]))
counters = run_simulated_display(sys.argv[1], profile=truth, reports=PAPER_DISPLAY,
                                 load_kg=float(sys.argv[3]),
                                 on_ready=lambda p: print(p.path, flush=True))
print(json.dumps(counters), flush=True)
"""


class Display:
    """A simulated display in a process of its own: true constants ``truth``, reporting
    the paper's, with ``mass`` kg resting on its piston."""

    def __init__(self, link: Path, truth: dict, mass: float) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-c", DISPLAY, str(link), json.dumps(truth), str(mass)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        assert self.proc.stdout is not None
        first = self.proc.stdout.readline().strip()
        assert first == str(link), self.proc.stderr.read() if self.proc.stderr else first

    def stop(self) -> dict:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        out, _ = self.proc.communicate(timeout=10)
        return json.loads(out.strip().splitlines()[-1])


#: True constants 20-40 % away from the paper's, both ways.
TRUTHS = [
    pytest.param({"Kp": 0.7, "alpha": 1.3, "Mp": 1.35, "b": 1.4}, id="soft-strong-heavy"),
    pytest.param(
        {"Kp": 1.3, "alpha": 0.7, "Mp": 0.65, "b": 0.75},
        id="stiff-weak-light",
        marks=pytest.mark.slow,  # 20-30 s on a loaded machine, as the first
    ),
]


@pytest.mark.parametrize("factors", TRUTHS)
def test_calibrate_display_recovers_constants_it_is_not_told(tmp_path: Path, factors: dict):
    """Kp, alpha and Mp within 5 %, the damping within 20 % (the bounds a calibration
    is held to; on an idle machine they come within 0.1 %): the display reports the
    paper's constants, so only its motion can tell the truth."""
    truth = replace(PAPER_DISPLAY, **{k: getattr(PAPER_DISPLAY, k) * f for k, f in factors.items()})
    display = Display(tmp_path / "display", {k: getattr(truth, k) for k in factors}, 0.2)
    out = tmp_path / "profile.json"
    try:
        result = calibrate_display(
            str(tmp_path / "display"), out, 0.2, points=6, hold_s=0.8, ringdowns=2, ring_s=1.5
        )
        # the measured profile drives the same display: accepted, within its limits
        played = play(
            Tissue(Law.paper("x", "xdot"), 600.0, 3.0, 0.05),
            str(tmp_path / "display"),
            0.3,
            profile=read_profile(out),
            realtime=False,
            idle_timeout_s=2.0,
        )
    except (DeviceLost, DeviceError) as exc:
        if isinstance(exc, DeviceLost) or "did not answer" in str(exc):
            pytest.skip(
                f"the machine starved the display or this loop ({exc}); load {os.getloadavg()}"
            )
        raise
    finally:
        counters = display.stop()
    assert counters["commands"] > 0 and played["commands_sent"] > 0
    assert counters["max_command_volts"] <= PAPER_DISPLAY.v_max
    measured = read_profile(out)
    for key in ("Kp", "alpha", "Mp"):
        assert getattr(measured, key) == pytest.approx(getattr(truth, key), rel=0.05), key
    assert measured.b == pytest.approx(truth.b, rel=0.2)
    # the limits and the encoder are the display's own: the voltage lowered if the
    # measured solenoid would pull harder than the display reports
    assert exceeded_limits(measured, PAPER_DISPLAY) == []
    assert measured.stroke == PAPER_DISPLAY.stroke
    assert measured.v_max == pytest.approx(
        min(PAPER_DISPLAY.v_max, math.sqrt(PAPER_DISPLAY.max_pull / measured.alpha))
    )
    # each interval holds the truth it was not told (generously: 4 half-widths, as the
    # simulator's integrator is not the exact discretisation the fit assumes)
    for key in ("Kp", "alpha", "Mp"):
        est = getattr(result.fit, key)
        half = 0.5 * (est.hi - est.lo)
        assert abs(est.value - getattr(truth, key)) <= 4 * half + 1e-3 * est.value, key
    data = json.loads(out.read_text())
    assert data["Kp"]["ci95"][0] < data["Kp"]["value"] < data["Kp"]["ci95"][1]
    lines = display_lines(result)
    assert lines[-1] == f"wrote {out}" and any("reported 264.78" in line for line in lines)
    if factors["Kp"] < 1:  # the page's example: the same display
        check_display_docs(lines, str(tmp_path / "display"), out)


def test_calibrate_display_refuses_to_overwrite_before_touching_the_port(tmp_path: Path):
    out = tmp_path / "profile.json"
    out.write_text("{}")
    with pytest.raises(InputError, match="never replaces"):
        calibrate_display(str(tmp_path / "nothing"), out, 0.2)
    assert out.read_text() == "{}"
    runner = CliRunner()
    res = runner.invoke(
        cli,
        ["calibrate", "display", "--port", str(tmp_path / "x"), "--mass", "2 tons", "--out", "p"],
    )
    assert res.exit_code == 1 and "--mass" in res.output


def test_masses_parse_with_units():
    assert parse_mass("200g", "--mass") == pytest.approx(0.2)
    assert parse_mass("0.2", "--mass") == pytest.approx(0.2)
    assert parse_mass("0.2 kg", "--mass") == pytest.approx(0.2)
    for bad in ("", "-1g", "nan", "9kg", "3 lb"):
        with pytest.raises(InputError, match="--mass"):
            parse_mass(bad, "--mass")


GAIN, OFFSET = 0.0235294, -2.0117647  # N per count, N
PGAIN, POFFSET = 6.0784e-05, 0.0072804  # m per count, m


def write_points(tmp_path: Path, seed: int = 1) -> tuple[Path, Path]:
    """Loads (gf) and gaps (mm) against noisy raw counts. Each of the four intervals
    holds the truth 95 % of the time (tests/identify/test_calibration.py counts it);
    seed 1 is one where all four do."""
    rng = np.random.default_rng(seed)
    loads = np.repeat([0, 50, 100, 200, 300, 500], 2)  # grams-force
    raw = (loads * 9.80665e-3 - OFFSET) / GAIN + rng.normal(0, 1.5, loads.size)
    gaps = np.repeat([0, 2, 4, 6, 8, 10], 2)  # mm
    rawp = (gaps * 1e-3 - POFFSET) / PGAIN + rng.normal(0, 0.8, gaps.size)
    f, p = tmp_path / "loads.csv", tmp_path / "gaps.csv"
    f.write_text(
        "load_g,raw\n" + "".join(f"{a},{b:.1f}\n" for a, b in zip(loads, raw, strict=True))
    )
    p.write_text(
        "gap_mm,raw\n" + "".join(f"{a},{b:.1f}\n" for a, b in zip(gaps, rawp, strict=True))
    )
    return f, p


def test_calibrate_forceps_from_files_recovers_gain_and_offset_within_its_intervals(
    tmp_path: Path,
):
    loads, gaps = write_points(tmp_path)
    out = tmp_path / "cal.json"
    runner = CliRunner()
    res = runner.invoke(
        cli,
        ["calibrate", "forceps", "--loads", str(loads), "--gaps", str(gaps), "--out", str(out)],
    )
    assert res.exit_code == 0, res.output
    data = json.loads(out.read_text())
    for name, gain, offset in (("force", GAIN, OFFSET), ("position", PGAIN, POFFSET)):
        lo, hi = data["fit"][name]["gain_ci95"]
        assert lo <= gain <= hi
        lo, hi = data["fit"][name]["offset_ci95"]
        assert lo <= offset <= hi
    cal = read_calibration(out)  # what record --calibration and import --calibration read
    assert cal.force.gain == data["force"]["gain"]
    # never replaced
    again = runner.invoke(
        cli,
        ["calibrate", "forceps", "--loads", str(loads), "--gaps", str(gaps), "--out", str(out)],
    )
    assert again.exit_code == 1 and "never replaces" in again.output
    assert json.loads(out.read_text()) == data


def test_calibrate_forceps_at_prompts_warns_of_a_slow_load_cell(tmp_path: Path):
    out = tmp_path / "cal.json"
    lines = ["0", "85.7", "50g", "105.5", "100 g", "126.1", "oops", "2N", "170.5", ""]
    lines += ["0", "-119.8", "2mm", "-86.8", "5mm", "-37.6", ""]
    res = CliRunner().invoke(
        cli,
        ["calibrate", "forceps", "--out", str(out), "--force-rate", "80"],
        input="\n".join(lines) + "\n",
    )
    assert res.exit_code == 0, res.output
    assert "80 Hz" in res.output and "warning:" in res.output
    data = json.loads(out.read_text())
    assert data["fit"]["force"]["points"] == 4 and data["fit"]["position"]["points"] == 3


FORCEPS = """
import sys
from tissuecli.app.simulate import simulate_forceps
simulate_forceps(sys.argv[1], on_ready=lambda p, t: print(p.path, flush=True))
"""


def test_calibrate_forceps_reads_the_live_forceps_at_each_prompt(tmp_path: Path):
    link = tmp_path / "forceps"
    proc = subprocess.Popen(
        [sys.executable, "-c", FORCEPS, str(link)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == str(link)
        out = tmp_path / "cal.json"
        lines = ["0", "50g", "100g", "", "0", "2mm", "4mm", ""]
        t0 = time.monotonic()
        res = CliRunner().invoke(
            cli,
            ["calibrate", "forceps", "--out", str(out), "--port", str(link), "--frames", "20"],
            input="\n".join(lines) + "\n",
        )
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=10)
    # the simulated forceps squeezes whatever it likes, not our loads: the fit may be
    # refused as flat; either way every reading was taken from the device
    assert res.output.count("mean of 20 samples") == 6, res.output
    assert time.monotonic() - t0 < 60
    assert res.exit_code in (0, 1)
    if res.exit_code == 1:
        assert "do not change" in res.output or "not linear" in res.output


DOCS = Path(__file__).resolve().parents[2] / "docs" / "calibration.md"


def docs_block(after: str) -> str:
    """The first fenced block after the line ``after`` in docs/calibration.md."""
    text = DOCS.read_text()
    start = text.index("```\n", text.index(after)) + 4
    return text[start : text.index("```", start)]


def masked(line: str) -> str:
    """A line with its numbers masked: what must match between the page and a run."""
    return re.sub(r"[-+]?\d[\d.]*(e[-+]?\d+)?", "#", line)


def test_the_forceps_example_of_the_docs_prints_what_the_page_says(tmp_path: Path):
    (tmp_path / "loads.csv").write_text(docs_block("`loads.csv`"))
    (tmp_path / "gaps.csv").write_text(docs_block("`gaps.csv`"))
    block = next(
        b
        for b in re.findall(r"```(?:console)?\n(.*?)```", DOCS.read_text(), re.S)
        if "$ tissuecli" in b
    ).splitlines()
    command, expected = block[0].removeprefix("$ tissuecli ").split(), block[1:]
    cwd = os.getcwd()
    os.chdir(tmp_path)
    try:
        res = CliRunner().invoke(cli, command)
    finally:
        os.chdir(cwd)
    assert res.exit_code == 0, res.output
    assert res.output.splitlines() == expected


def check_display_docs(lines: list[str], url: str, out: Path) -> None:
    """Every line the page shows for the display example, numbers masked, is one the
    run printed (the watchdog's note only if it cut)."""
    printed = {
        masked(line.replace(url, "/tmp/display").replace(str(out), "display.json"))
        for line in lines
    }
    for line in docs_block("After Enter").splitlines():
        if "watchdog" in line and not any("watchdog" in p for p in printed):
            continue
        assert masked(line) in printed, line


@settings(max_examples=300, deadline=None)
@given(st.text(max_size=20))
def test_any_typed_mass_or_reference_is_a_value_or_one_line_error(text: str):
    for parse in (
        lambda t: parse_mass(t, "--mass"),
        lambda t: parse_reference(t, "force"),
        lambda t: parse_reference(t, "position"),
    ):
        try:
            value = parse(text)
        except InputError as exc:
            assert "\n" not in str(exc)
        else:
            assert math.isfinite(value) and value >= 0


def test_bad_point_tables_are_one_line_errors(tmp_path: Path):
    out = tmp_path / "cal.json"
    one = tmp_path / "one.csv"
    one.write_text("load_g\n0\n50\n100\n")
    flat = tmp_path / "flat.csv"
    flat.write_text("load_g,raw\n0,5\n50,5\n100,5\n")
    volts = tmp_path / "volts.csv"
    volts.write_text("load [V],raw\n0,5\n1,6\n2,7\n")
    _, gaps = write_points(tmp_path)
    for bad, words in ((one, "no rows of numbers"), (flat, "do not change"), (volts, "V")):
        res = CliRunner().invoke(
            cli,
            ["calibrate", "forceps", "--loads", str(bad), "--gaps", str(gaps), "--out", str(out)],
        )
        assert res.exit_code == 1 and words in res.output, res.output
        assert len(res.output.strip().splitlines()) == 1 and not out.exists()


def test_simulate_display_refuses_a_bad_load_or_reported_profile(tmp_path: Path):
    runner = CliRunner()
    res = runner.invoke(cli, ["simulate", "display", "--load", "9kg", "--duration", "0.1"])
    assert res.exit_code == 1 and "--load" in res.output
    bad = tmp_path / "bad.json"
    bad.write_text('{"Kp": -1}')
    res = runner.invoke(cli, ["simulate", "display", "--reports", str(bad), "--duration", "0.1"])
    assert res.exit_code == 1 and "Kp" in res.output
    assert len(res.output.strip().splitlines()) == 1


def test_sigterm_during_calibrate_display_leaves_0_v_and_no_file(tmp_path: Path):
    display = Display(tmp_path / "display", {}, 0.2)
    out = tmp_path / "profile.json"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "tissuecli",
            "calibrate",
            "display",
            "--port",
            str(tmp_path / "display"),
            "--mass",
            "200g",
            "--out",
            str(out),
            "--yes",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stderr is not None
        line = proc.stderr.readline()  # the first hold is under way
        assert "held" in line, line + proc.stderr.read()
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=30)
    finally:
        counters = display.stop()
    assert proc.returncode == 1 and "interrupted" in err and "Traceback" not in err
    assert not out.exists()
    assert counters["last_command_volts"] == 0.0


def test_a_mass_that_presses_the_piston_to_its_stop_is_named(tmp_path: Path):
    display = Display(tmp_path / "display", {}, 1.0)  # 9.8 N: 37 mm of a 15 mm stroke
    out = tmp_path / "profile.json"
    try:
        with pytest.raises(InputError, match="mid-stroke"):
            calibrate_display(
                str(tmp_path / "display"), out, 1.0, points=4, hold_s=0.3, ringdowns=1
            )
    except DeviceLost as exc:
        pytest.skip(f"the machine starved the display ({exc}); load {os.getloadavg()}")
    finally:
        counters = display.stop()
    assert not out.exists() and counters["last_command_volts"] == 0.0
