"""import, export, sessions and their bad-input messages, through the command line."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from tissuecli import formats
from tissuecli.cli import cli

from ..conftest import assert_clean_error


def run(*args: str):
    return CliRunner().invoke(cli, list(args))


def _csv(path, rows, header="time,force,position"):
    path.write_text(header + "\n" + "\n".join(",".join(str(v) for v in r) for r in rows) + "\n")
    return path


def test_import_in_mm_gf_equals_import_in_si(tmp_path):
    t = np.arange(100) * 1e-3
    x = 1e-3 + 1e-3 * np.sin(t * 7)
    f = 300 * x
    _csv(tmp_path / "si.csv", zip(t, f, x, strict=True))
    gf = f / 9.80665e-3
    _csv(tmp_path / "mm.csv", zip(t * 1e3, gf, x * 1e3, strict=True))
    h5 = tmp_path / "g.h5"
    assert (
        run("import", str(tmp_path / "si.csv"), "--out", str(h5), "--session", "si").exit_code == 0
    )
    r = run(
        "import",
        str(tmp_path / "mm.csv"),
        "--out",
        str(h5),
        "--session",
        "mm",
        "--units",
        "gf,ms,mm",
    )
    assert r.exit_code == 0, r.output
    a, b = formats.read_session(h5, "si"), formats.read_session(h5, "mm")
    for name in ("time", "force", "position"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=1e-12)


def test_export_round_trips_exactly(tmp_path):
    t = np.arange(50) * 1e-3
    _csv(tmp_path / "in.csv", zip(t, np.cos(t), np.sin(t) * 1e-3, strict=True))
    h5 = tmp_path / "g.h5"
    run("import", str(tmp_path / "in.csv"), "--out", str(h5), "--session", "a")
    r = run("export", str(h5), "--csv", str(tmp_path / "out.csv"))
    assert r.exit_code == 0, r.output
    back = np.loadtxt(tmp_path / "out.csv", delimiter=",", skiprows=1)
    np.testing.assert_array_equal(back[:, 0], t)
    np.testing.assert_array_equal(back[:, 1], np.cos(t))
    assert (tmp_path / "out.csv").read_text().startswith("time,force,position\n")


def test_sessions_table_and_json(tmp_path):
    h5 = tmp_path / "g.h5"
    for name, n in (("a", 100), ("b", 250)):
        _csv(
            tmp_path / f"{name}.csv",
            zip(np.arange(n) * 2e-3, np.ones(n), np.ones(n) * 1e-3, strict=True),
        )
        run("import", str(tmp_path / f"{name}.csv"), "--out", str(h5), "--session", name)
    rows = json.loads(run("sessions", str(h5), "--json").output)
    assert [(r["name"], r["samples"]) for r in rows] == [("a", 100), ("b", 250)]
    assert rows[1]["rate_hz"] == pytest.approx(500.0)
    table = run("sessions", str(h5)).output
    assert "b" in table and "250" in table


ROWS = [(i * 1e-3, 1.0 + i, 1e-3 * i) for i in range(50)]


@pytest.mark.parametrize(
    "header,rows,needle",
    [
        ("a,b,c", ROWS, "no column for time"),
        ("time,force,position", ROWS[:20] + [(0.001, 1, 1)] + ROWS[20:], "goes back at line 22"),
        ("time,force,position", [("abc", 1, 1)] * 50, "holds text, not numbers"),
        ("time,force,position", [("abc", "x", 1)] * 50, "no rows of numbers"),
        ("time,force,position", ROWS[:2], "too few"),
        ("time,force,position", ROWS[:20] + [("x", "y", "z")] * 30, "do not parse"),
    ],
)
def test_bad_csv_is_one_clear_line(tmp_path, header, rows, needle):
    path = _csv(tmp_path / "bad.csv", rows, header)
    r = run("import", str(path), "--out", str(tmp_path / "g.h5"), "--session", "x")
    assert_clean_error(r, needle)
    assert not (tmp_path / "g.h5").exists()


def test_a_few_bad_rows_are_skipped_and_reported(tmp_path):
    rows = ROWS[:10] + [(0.0105, "nan", 1)] + ROWS[11:]
    path = _csv(tmp_path / "some.csv", rows, "t,f,x")
    r = run("import", str(path), "--out", str(tmp_path / "g.h5"), "--session", "x")
    assert r.exit_code == 0, r.output
    assert "1 junk line(s) skipped (line 12)" in r.output and "imported 49 samples" in r.output


def test_existing_session_name_is_refused(tmp_path):
    path = _csv(tmp_path / "a.csv", ROWS)
    h5 = tmp_path / "g.h5"
    run("import", str(path), "--out", str(h5), "--session", "x")
    r = run("import", str(path), "--out", str(h5), "--session", "x")
    assert_clean_error(r, "already exists")


@pytest.mark.parametrize(
    "args,needle",
    [
        (["sessions", "missing.h5"], "does not exist"),
        (["export", "missing.h5", "--csv", "o.csv"], "does not exist"),
        (["import", "missing.csv", "--out", "g.h5", "--session", "x"], "does not exist"),
        (
            ["import", "a.csv", "--out", "g.h5", "--session", "x", "--units", "furlong"],
            "unknown unit",
        ),
        (["record", "--out", "g.h5"], "--port"),
    ],
)
def test_bad_arguments_exit_1_without_traceback(tmp_path, monkeypatch, args, needle):
    monkeypatch.chdir(tmp_path)
    _csv(tmp_path / "a.csv", ROWS)
    assert_clean_error(run(*args), needle)


def test_export_needs_session_when_there_are_several(tmp_path):
    h5 = tmp_path / "g.h5"
    path = _csv(tmp_path / "a.csv", ROWS)
    run("import", str(path), "--out", str(h5), "--session", "one")
    run("import", str(path), "--out", str(h5), "--session", "two")
    assert_clean_error(run("export", str(h5), "--csv", str(tmp_path / "o.csv")), "--session")


def test_import_of_counts_with_a_calibration_equals_import_in_si(tmp_path):
    """``import --calibration`` reads the same file as ``record --calibration``: force and
    position columns of ADC counts turned to N and m by its gains and offsets."""
    t = np.arange(200) * 1e-3
    x = 1e-3 + 1e-3 * np.sin(t * 7)
    f = 300 * x
    _csv(tmp_path / "si.csv", zip(t, f, x, strict=True))
    cal = {
        "force": {"gain": 0.02, "offset": -0.5, "unit": "N"},
        "position": {"gain": -5e-6, "offset": 2e-3, "unit": "m"},
    }
    (tmp_path / "cal.json").write_text(json.dumps(cal))
    counts_f = (f - cal["force"]["offset"]) / cal["force"]["gain"]
    counts_x = (x - cal["position"]["offset"]) / cal["position"]["gain"]
    _csv(tmp_path / "counts.csv", zip(t * 1e3, counts_f, counts_x, strict=True), "t_ms,adc0,adc1")
    h5 = tmp_path / "g.h5"
    r = run("import", str(tmp_path / "si.csv"), "--out", str(h5), "--session", "si")
    assert r.exit_code == 0, r.output
    args = ["import", str(tmp_path / "counts.csv"), "--out", str(h5), "--session", "counts"]
    cols = ["--columns", "force=adc0,position=adc1", "--calibration", str(tmp_path / "cal.json")]
    r = run(*args, *cols)
    assert r.exit_code == 0, r.output
    assert "counts (--calibration)" in r.output
    a, b = formats.read_session(h5, "si"), formats.read_session(h5, "counts")
    for name in ("time", "force", "position"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=1e-9, atol=1e-12)
    # --units may name the time unit only: the calibration makes force and position SI
    r = run(*args[:-1], "counts-2", *cols, "--units", "force=gf")
    assert r.exit_code == 1 and "time only" in r.output
    assert_clean_error(r)
    # the calibration file is an input: never written over
    r = run("import", str(tmp_path / "counts.csv"), "--out", str(tmp_path / "cal.json"), *cols)
    assert r.exit_code == 1 and json.loads((tmp_path / "cal.json").read_text()) == cal
