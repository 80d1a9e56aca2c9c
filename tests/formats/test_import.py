"""Recordings from other loggers: every class of foreign file a lab has, read into SI."""

from __future__ import annotations

import json
import math
from pathlib import Path

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy import io

from tissuecli.core.errors import InputError
from tissuecli.core.timebase import regularise
from tissuecli.core.units import STANDARD_GRAVITY, parse_quantity, parse_units
from tissuecli.formats.recording import read_recording

from ..conftest import assert_clean_error, tissuecli_here

N = 400
T = np.arange(N) * 1e-3
F = 1.0 + np.sin(2 * np.pi * 2 * T)  # N
X = 3e-3 + 1e-3 * np.cos(2 * np.pi * 2 * T)  # m


def _table(path: Path, header: str, rows: np.ndarray, sep: str = ",", eol: str = "\n") -> Path:
    lines = [header] if header else []
    lines += [sep.join(repr(float(v)) for v in row) for row in rows]
    path.write_text(eol.join(lines) + eol)
    return path


def _check(session, t=T, f=F, x=X) -> None:
    np.testing.assert_allclose(session.time, t - t[0], atol=1e-12)
    np.testing.assert_allclose(session.force, f, rtol=1e-12)
    np.testing.assert_allclose(session.position, x, rtol=1e-12)


@pytest.mark.parametrize(
    ("sep", "eol"), [(",", "\n"), ("\t", "\r\n"), (";", "\n"), ("|", "\n"), ("  ", "\r\n")]
)
def test_delimiters_and_line_ends(tmp_path: Path, sep: str, eol: str) -> None:
    path = _table(
        tmp_path / "a.txt", sep.join(["time", "force", "position"]), np.c_[T, F, X], sep, eol
    )
    session, report = read_recording(path)
    _check(session)
    assert not report.warnings


def test_bom_comments_preamble_junk_and_extra_columns(tmp_path: Path) -> None:
    rows = [
        f"{i},{t!r},{f!r},{x!r},21.5"
        for i, (t, f, x) in enumerate(zip(T.tolist(), F.tolist(), X.tolist(), strict=True))
    ]
    text = "\n".join(
        ["Logger 2.1", "# calibrated 2024-01-01", "sample,time,force,position,temp_C", *rows[:200],
         "% pause", *rows[200:], "399,0.39"]
    )  # fmt: skip
    path = tmp_path / "log.csv"
    path.write_bytes(b"\xef\xbb\xbf" + text.encode())
    session, report = read_recording(path)
    _check(session)
    assert "ignored columns: 'sample', 'temp_C'" in report.lines()
    notes = " ".join(report.notes)
    assert "BOM" in notes and "2 comment" in notes and "1 preamble" in notes
    assert "1 junk line(s) skipped (line 405)" in notes


@pytest.mark.parametrize(
    ("header", "units", "scale"),
    [
        ("t_ms,force_g,closure_mm", None, (1e3, 1 / (1e-3 * STANDARD_GRAVITY), 1e3)),
        ("Time (s),Force [N],Position [um]", None, (1.0, 1.0, 1e6)),
        ("t,load,displacement", "time=ms,force=mN,position=mm", (1e3, 1e3, 1e3)),
        ("timestamp,f,x", "mm,gf", (1.0, 1 / (1e-3 * STANDARD_GRAVITY), 1e3)),
    ],
)
def test_header_names_and_units(tmp_path: Path, header: str, units, scale) -> None:
    rows = np.c_[T * scale[0], F * scale[1], X * scale[2]]
    session, _ = read_recording(_table(tmp_path / "u.csv", header, rows), units=units)
    _check(session)


def test_columns_by_name_or_index_in_any_order(tmp_path: Path) -> None:
    path = _table(tmp_path / "o.csv", "a,b,c,d", np.c_[X, np.zeros(N), T, F])
    session, report = read_recording(path, columns="time=c,force=4,position=a")
    _check(session)
    assert report.columns == {"time": "c", "force": "d", "position": "a"}
    bare = _table(tmp_path / "bare.csv", "", np.c_[T, F, X])  # no header: time, force, position
    _check(read_recording(bare)[0])


def test_decimal_commas_with_semicolons(tmp_path: Path) -> None:
    path = tmp_path / "eu.csv"
    path.write_text(
        "Zeit;Kraft;Weg\n"
        + "".join(
            f"{t!r};{f!r};{x!r}\n".replace(".", ",")
            for t, f, x in zip(T.tolist(), F.tolist(), X.tolist(), strict=True)
        )
    )
    session, _ = read_recording(path, columns="time=Zeit,force=Kraft,position=Weg")
    _check(session)


def test_matlab_v5_v73_and_npz(tmp_path: Path) -> None:
    io.savemat(tmp_path / "a.mat", {"t": T, "F": F, "x": X, "fs": 1000.0})
    _check(read_recording(tmp_path / "a.mat", columns="time=t,force=F,position=x")[0])
    io.savemat(tmp_path / "s.mat", {"rec": {"time": T, "force": F, "position": X}})
    s, report = read_recording(
        tmp_path / "s.mat", columns="time=rec.time,force=rec.force,position=rec.position"
    )
    _check(s)
    with h5py.File(tmp_path / "b.mat", "w", userblock_size=512) as f:  # as MATLAB -v7.3 saves
        f["data"] = np.c_[T, F, X].T  # column-major: stored transposed
    _check(
        read_recording(tmp_path / "b.mat", columns="time=data:1,force=data:2,position=data:3")[0]
    )
    np.savez(tmp_path / "c.npz", time=T, force=F, position=X)
    _check(read_recording(tmp_path / "c.npz")[0])


@pytest.mark.parametrize("unit", ["deg", "rad"])
def test_jaw_angle_becomes_closure_at_the_tips(tmp_path: Path, unit: str) -> None:
    theta = np.deg2rad(30 + 10 * np.sin(T * 7))  # angle between the jaws
    shown = np.rad2deg(theta) if unit == "deg" else theta
    path = _table(tmp_path / "j.csv", f"time,force,angle_{unit}", np.c_[T, F, shown])
    with pytest.raises(InputError, match="--jaw-length"):
        read_recording(path)
    session, report = read_recording(path, jaw_length_m=0.02)
    _check(session, x=-2 * 0.02 * np.sin(theta / 2))
    assert not report.warnings


def test_rate_for_files_without_time(tmp_path: Path) -> None:
    path = _table(tmp_path / "r.csv", "force,position", np.c_[F, X])
    with pytest.raises(InputError, match="--rate"):
        read_recording(path)
    _check(read_recording(path, rate_hz=1000.0)[0])


def test_unit_mistakes_are_named(tmp_path: Path) -> None:
    path = _table(tmp_path / "mm.csv", "time,force,position", np.c_[T, F * 102, X * 1e3])
    _, report = read_recording(path)
    text = " ".join(report.warnings)
    assert "--units position=mm" in text and "--units force=gf" in text
    ms = _table(tmp_path / "ms.csv", "time,force,position", np.c_[T * 1e3, F, X])
    assert "--units time=ms" in " ".join(read_recording(ms)[1].warnings)


def test_coarse_and_jittery_stamps_are_put_back_on_their_clock() -> None:
    rng = np.random.default_rng(0)
    true = np.arange(3000) * 3.245e-3
    for stamps in (np.floor(true * 1e3) / 1e3, true + rng.uniform(-3e-4, 3e-4, true.size)):
        time, base = regularise(stamps)
        assert base.regular and base.rate_hz == pytest.approx(1 / 3.245e-3, rel=1e-4)
        np.testing.assert_allclose(np.diff(time), np.diff(true), rtol=1e-4)
    lost = np.delete(true, [10, 11, 500])
    time, base = regularise(lost)
    assert base.lost == 3 and np.allclose(np.diff(time)[9], 3 * 3.245e-3, rtol=1e-4)
    dup = np.floor(np.arange(2400) / 1200 * 1e3) / 1e3  # 1.2 kHz on a millisecond clock
    time, base = regularise(dup)
    assert base.regular and base.repaired == 400 and np.all(np.diff(time) > 0)
    back = np.arange(100) * 1e-3
    back[50] = 0.01
    with pytest.raises(InputError, match="goes back at line 52"):
        regularise(back, np.arange(100) + 2)


def test_import_cli_reports_what_it_did(tmp_path: Path) -> None:
    path = _table(tmp_path / "l.csv", "t_ms,force_g,closure_mm", np.c_[T * 1e3, F * 102, X * 1e3])
    out = tissuecli_here("import", str(path), "--out", str(tmp_path / "g.h5"), "--session", "l")
    assert out.returncode == 0, out.stderr
    assert "time <- 't_ms' in ms (from the header 't_ms')" in out.stdout
    bad = tissuecli_here(
        "import", str(path), "--out", str(tmp_path / "g.h5"), "--session", "m", "--jaw-length", "x"
    )
    assert_clean_error(bad, "--jaw-length")
    assert parse_quantity("2 cm", "length", "--jaw-length") == pytest.approx(0.02)
    assert parse_units("position=deg").position_is_angle


DELIMS = st.sampled_from([",", "\t", ";", " ", "|"])


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    sep=DELIMS,
    eol=st.sampled_from(["\n", "\r\n"]),
    bom=st.booleans(),
    comments=st.integers(0, 3),
    junk=st.integers(0, 3),
    header=st.booleans(),
    extra=st.integers(0, 2),
    n=st.integers(20, 200),
)
def test_any_sane_table_reads_back_its_numbers(
    tmp_path: Path, sep, eol, bom, comments, junk, header, extra, n
) -> None:
    rng = np.random.default_rng(n)
    t = np.arange(n) * 1e-3
    cols = [t, rng.normal(size=n), rng.normal(size=n) * 1e-3] + [rng.normal(size=n)] * extra
    names = ["time", "force", "position"] + [f"extra{i}" for i in range(extra)]
    lines = [f"# comment {i}" for i in range(comments)]
    if header:
        lines.append(sep.join(names))
    lines += [sep.join(repr(float(c[i])) for c in cols) for i in range(n)]
    lines += ["garbage line"] * junk
    raw = eol.join(lines).encode()
    (tmp_path / "p.txt").write_bytes((b"\xef\xbb\xbf" if bom else b"") + raw)
    columns = None if header else "time=1,force=2,position=3"
    session, report = read_recording(tmp_path / "p.txt", columns=columns)
    np.testing.assert_allclose(session.force, cols[1])
    np.testing.assert_allclose(session.position, cols[2])
    assert len(session) == n
    if junk:
        assert any(f"{junk} junk" in note for note in report.notes)


@settings(
    max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(data=st.binary(max_size=2000) | st.text(max_size=2000).map(str.encode))
def test_any_bytes_give_a_session_or_one_clean_error(tmp_path: Path, data: bytes) -> None:
    path = tmp_path / "x.csv"
    path.write_bytes(data)
    try:
        session, _ = read_recording(path)
    except InputError as exc:
        assert "\n" not in str(exc) and len(str(exc)) < 400
    else:
        session.validate()
        assert all(math.isfinite(v) for v in session.time)


WORDS = st.text(alphabet="ABCDEFGHIJKLMNOPQRSTUVWXYZ_-", min_size=1, max_size=8)


@settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    sep=st.sampled_from([",", "\t", ";"]),
    where=st.lists(st.integers(0, 3), min_size=1, max_size=2),
    word=WORDS,
    clock=st.booleans(),
)
def test_text_columns_are_named_and_clock_times_read(
    tmp_path: Path, sep: str, where: list[int], word: str, clock: bool
) -> None:
    """A logger's status or label columns are kept out of the numbers; a time column of
    clock times (crossing midnight) is read in seconds."""
    start = 23 * 3600 + 59 * 60 + 59.8  # 0.2 s before midnight
    stamps = [
        f"{int(s // 3600) % 24:02d}:{int(s % 3600 // 60):02d}:{s % 60:06.3f}" for s in start + T
    ]
    names = ["time", "force", "position"]
    cols: list[list[str]] = [
        stamps if clock else [repr(float(v)) for v in T],
        [repr(float(v)) for v in F],
        [repr(float(v)) for v in X],
    ]
    for k, i in enumerate(sorted(where)):
        names.insert(i + k, f"note{k}")
        cols.insert(i + k, [word] * N)
    lines = [sep.join(names)] + [sep.join(c[r] for c in cols) for r in range(N)]
    (tmp_path / "t.txt").write_text("\n".join(lines))
    session, report = read_recording(tmp_path / "t.txt")
    _check(session)
    assert any("text column(s)" in note and "note0" in note for note in report.notes)
    with pytest.raises(InputError, match="holds text"):
        read_recording(tmp_path / "t.txt", columns="force=note0")


def test_a_column_that_grows_the_other_way_takes_a_signed_unit(tmp_path: Path) -> None:
    path = _table(tmp_path / "s.csv", "time,force,position", np.c_[T, F, -X * 1e3])
    session, _ = read_recording(path, units="position=-mm")
    _check(session)
    with pytest.raises(InputError, match="cannot be negative"):
        read_recording(path, units="time=-s")


@pytest.mark.parametrize("name", ["gap", "opening", "jaw gap (m)"])
def test_an_opening_is_turned_into_closure(tmp_path: Path, name: str) -> None:
    path = _table(tmp_path / "g.csv", f"time,force,{name}", np.c_[T, F, -X])
    session, report = read_recording(path)
    _check(session)
    assert any("grows as the jaws open" in note for note in report.notes)


def test_fit_reads_a_recording_directly_as_import_would(tmp_path: Path) -> None:
    """One command for a newcomer: fit FILE.csv equals import then fit, to the digit."""
    from tissuecli.core.tissue import DEFAULT_TISSUE
    from tissuecli.sim.synth import random_session

    s, _ = random_session(DEFAULT_TISSUE, seed=3, duration_s=4.0)
    path = _table(
        tmp_path / "lab.csv",
        "t_ms;force_g;closure_mm",
        np.c_[s.time * 1e3, s.force / 9.80665e-3, s.position * 1e3],
        sep=";",
    )
    direct = tissuecli_here(
        "fit", str(path), "--forms", "x,xdot", "--out", str(tmp_path / "a.json")
    )
    assert direct.returncode == 0, direct.stderr
    assert "read as another logger's recording" in direct.stdout
    h5 = tmp_path / "lab.h5"
    assert tissuecli_here("import", str(path), "--out", str(h5)).returncode == 0
    stored = tissuecli_here("fit", str(h5), "--forms", "x,xdot", "--out", str(tmp_path / "b.json"))
    assert stored.returncode == 0, stored.stderr
    a, b = (json.loads((tmp_path / f"{n}.json").read_text())["law"] for n in "ab")
    assert [t["mean"] for t in a["terms"]] == [t["mean"] for t in b["terms"]]
    # reading options belong to recordings: a session file says so
    assert_clean_error(tissuecli_here("fit", str(h5), "--units", "mm"), "tissuecli session file")


def test_rows_after_a_preamble_and_far_into_the_head_are_read(tmp_path) -> None:
    """The sniffer classifies only the head's first lines: a logger's preamble
    still leads to its header and its rows."""
    from tissuecli.formats.tables import sniff_table

    path = tmp_path / "preamble.csv"
    preamble = "".join(f"setting {i}: value {i}\n" for i in range(20))
    rows = "".join(f"{i / 1000:.3f},{0.1 * i:.3f},{0.001 * i:.4f}\n" for i in range(5000))
    path.write_text(preamble + "time,force,position\n" + rows)
    layout = sniff_table(path)
    assert layout.first_line == 22
    assert layout.names == ["time", "force", "position"]
    assert layout.format.endswith("20 preamble line(s)")
