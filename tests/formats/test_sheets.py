"""Spreadsheets (each sheet a session, or one chosen with --sheet) and text tables whose
header and units row are in a legacy encoding (GBK, Shift-JIS, cp1252) or UTF-16."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import h5py
import numpy as np
import pytest

from tissuecli.core.errors import InputError
from tissuecli.formats.recording import read_recording
from tissuecli.formats.sheets import data_sheets, read_sheet

from ..conftest import assert_clean_error, tissuecli_here

N = 300
T = np.arange(N) * 1e-3  # s
F = 1.0 + np.sin(2 * np.pi * 3 * T)  # N
X = 3e-3 + 1e-3 * np.cos(2 * np.pi * 3 * T)  # m


def _workbook(path: Path) -> Path:
    """Two specimens on two sheets (a title row, names, a units row: ms, gf, mm), a sheet
    of notes, and an empty sheet."""
    openpyxl = pytest.importorskip("openpyxl")
    book = openpyxl.Workbook()
    first = book.active
    first.title = "liver A"
    second = book.create_sheet("kidney B")
    for sheet, scale in ((first, 1.0), (second, 2.0)):
        sheet.append([f"specimen {sheet.title}, 2026-11-26"])
        sheet.append(["Time", "Force", "Closure", "status"])
        sheet.append(["ms", "gf", "mm", ""])
        for t, f, x in zip(T, F, X, strict=True):
            sheet.append([t * 1e3, scale * f / 9.80665e-3, x * 1e3, "ok"])
    notes = book.create_sheet("notes")
    notes.append(["operator", "ana"])
    book.create_sheet("empty")
    book.save(path)
    return path


def test_each_sheet_with_data_is_a_session_named_after_it(tmp_path: Path) -> None:
    book = _workbook(tmp_path / "specimens.xlsx")
    assert data_sheets(book) == ["liver A", "kidney B"]
    result = tissuecli_here("import", str(book), "--out", str(tmp_path / "s.h5"))
    assert result.returncode == 0, result.stderr
    assert "session 'liver A'" in result.stdout and "session 'kidney B'" in result.stdout
    assert "from the units row: 'gf'" in result.stdout
    with h5py.File(tmp_path / "s.h5", "r") as f:
        assert sorted(f["sessions"]) == ["kidney B", "liver A"]
        for name, scale in (("liver A", 1.0), ("kidney B", 2.0)):
            g = f["sessions"][name]
            np.testing.assert_allclose(g["time"][:], T, atol=1e-9)
            np.testing.assert_allclose(g["force"][:], scale * F, rtol=1e-9)
            np.testing.assert_allclose(g["position"][:], X, rtol=1e-9)


def test_a_sheet_is_chosen_by_name_for_fit_and_import(tmp_path: Path) -> None:
    book = _workbook(tmp_path / "specimens.xlsx")
    session, report = read_recording(book, sheet="kidney B")
    np.testing.assert_allclose(session.force, 2 * F, rtol=1e-9)
    assert report.notes[0] == "sheet 'kidney B' of 4 ('liver A', 'kidney B', 'notes', 'empty')"
    assert "text column(s), not numbers: 'status'" in report.notes
    result = tissuecli_here(
        "import", str(book), "--out", str(tmp_path / "s.h5"), "--sheet", "liver A"
    )
    assert result.returncode == 0 and "session 'liver A'" in result.stdout, result.stderr


def test_a_workbook_of_several_sheets_needs_one_named_to_be_fitted(tmp_path: Path) -> None:
    book = _workbook(tmp_path / "specimens.xlsx")
    assert_clean_error(
        tissuecli_here("fit", str(book), "--forms", "x,xdot"),
        "2 sheets with data ('liver A', 'kidney B')",
        "--sheet NAME",
    )
    assert_clean_error(
        tissuecli_here("fit", str(book), "--sheet", "spleen"),
        "no sheet 'spleen'",
        "'liver A', 'kidney B', 'notes', 'empty'",
    )
    assert_clean_error(
        tissuecli_here("import", str(book), "--out", str(tmp_path / "s.h5"), "--session", "x"),
        "2 sheets with data",
    )


def test_an_ods_workbook_reads_as_an_xlsx_one(tmp_path: Path) -> None:
    pd = pytest.importorskip("pandas")
    pytest.importorskip("odf")
    path = tmp_path / "rig.ods"
    frame = pd.DataFrame({"t [s]": T, "load [N]": F, "displacement [mm]": X * 1e3})
    with pd.ExcelWriter(path, engine="odf") as writer:
        frame.to_excel(writer, sheet_name="run 1", index=False)
        (frame * [1, 3, 1]).to_excel(writer, sheet_name="run 2", index=False)
    assert data_sheets(path) == ["run 1", "run 2"]
    session, _ = read_recording(path, sheet="run 2")
    np.testing.assert_allclose(session.force, 3 * F, rtol=1e-9)
    np.testing.assert_allclose(session.position, X, rtol=1e-9)
    with pytest.raises(InputError, match="choose one with --sheet NAME"):
        read_recording(path)


def test_clock_cells_are_a_time_column_and_junk_rows_are_counted(tmp_path: Path) -> None:
    openpyxl = pytest.importorskip("openpyxl")
    book = openpyxl.Workbook()
    sheet = book.active
    sheet.title = "log"
    sheet.append(["time", "force", "position"])
    start = dt.datetime(2026, 11, 26, 23, 59, 59)
    for k, (f, x) in enumerate(zip(F, X, strict=True)):
        sheet.append([start + dt.timedelta(milliseconds=10 * k), f, x])
        if k == 50:
            sheet.append(["sensor reset", None, None])
    book.save(tmp_path / "log.xlsx")
    table = read_sheet(tmp_path / "log.xlsx")
    assert table.junk == [53] and "1 junk row(s) skipped (row 53)" in table.notes
    session, _ = read_recording(tmp_path / "log.xlsx")
    np.testing.assert_allclose(session.time, np.arange(N) * 0.01, atol=1e-6)  # past midnight


def test_a_file_that_is_not_a_workbook_is_refused_in_one_line(tmp_path: Path) -> None:
    path = tmp_path / "fake.xlsx"
    path.write_bytes(b"PK\x03\x04 not really a zip")
    assert_clean_error(tissuecli_here("fit", str(path)), "as a spreadsheet")
    csv = tmp_path / "a.csv"
    csv.write_text("time,force,position\n0,1,2\n1,2,3\n2,3,4\n")
    assert_clean_error(tissuecli_here("fit", str(csv), "--sheet", "x"), "not a spreadsheet")


# -- header and units rows in any common encoding

ROWS = "".join(f"{t:.3f},{f:.6f},{x * 1e3:.6f}\n" for t, f, x in zip(T, F, X, strict=True))


@pytest.mark.parametrize(
    ("encoding", "names", "units"),
    [
        ("gbk", "时间,力,位移", "s,N,mm"),
        ("gbk", "时间 (秒),载荷,位移", "s,N,mm"),
        ("shift_jis", "時間,荷重,変位", "s,N,mm"),
        ("shift_jis", "時刻,荷重,ストローク", "[s],[N],[mm]"),
        ("cp1252", "Zeit,Kraft,Déplacement", "s,N,mm"),
        ("utf-16", "时间,力,位移", "s,N,mm"),
        ("utf-8-sig", "時間,荷重,変位", "s,N,mm"),
    ],
)
def test_a_header_in_a_legacy_encoding_with_a_units_row_under_it(
    tmp_path: Path, encoding: str, names: str, units: str
) -> None:
    path = tmp_path / "log.csv"
    path.write_bytes(f"# logger export\n{names}\n{units}\n{ROWS}".encode(encoding))
    session, report = read_recording(path)
    np.testing.assert_allclose(session.force, F, atol=1e-6)
    np.testing.assert_allclose(session.position, X, atol=1e-9)
    assert report.units["position"].startswith("mm (from the units row")
    assert "a units row" in report.notes[0]
    if encoding in ("gbk", "shift_jis"):
        label = {"gbk": "GBK", "shift_jis": "Shift-JIS"}[encoding]
        assert label in report.notes[0], report.notes
