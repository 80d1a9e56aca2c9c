"""Text loggers' lines: the dialects, sniffing, malformed lines, and device stamps."""

from __future__ import annotations

import os
import pty
import time
import tty

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tissuecli.hw.text import (
    DIALECTS,
    WRAP,
    Delimited,
    MalformedLine,
    SerialPlotter,
    StampChecker,
    Teleplot,
    TextLink,
    sniff_dialect,
)


def _read_all(dialect, lines):
    rows, bad = [], 0
    for line in lines:
        try:
            row = dialect.read(line)
        except MalformedLine:
            bad += 1
            continue
        if row:
            rows.append(row)
    return rows, bad


def test_delimited_with_a_header_reads_names_and_skips_the_header_again():
    lines = ["t_ms,force_N,closure_mm", "1,0.5,2.0", "2,0.6,2.1", "t_ms,force_N,closure_mm"]
    d = sniff_dialect(lines)
    assert isinstance(d, Delimited) and d.header
    assert d.names == ["t_ms", "force_N", "closure_mm"]
    rows, bad = _read_all(d, [*lines, "3,0.7", "4;0.8;2", "5,x,2", "6,0.9,2.2"])
    assert bad == 3
    assert [r["t_ms"] for r in rows] == [1, 2, 6]


@pytest.mark.parametrize("sep", [",", "\t", ";", " "])
def test_delimited_without_a_header_names_columns_by_position(sep):
    lines = [sep.join(str(i * k) for k in (1, 2, 3)) for i in range(1, 10)]
    d = sniff_dialect(lines)
    assert isinstance(d, Delimited) and not d.header and d.names == ["1", "2", "3"]
    assert d.read(lines[2]) == {"1": 3.0, "2": 6.0, "3": 9.0}


def test_serial_plotter_pairs_in_any_separator():
    lines = ["force:1.5 pos:2", "force:1.6,pos:2.1", "force:1.7\tpos:2.2"]
    d = sniff_dialect(lines)
    assert isinstance(d, SerialPlotter) and d.names == ["force", "pos"]
    rows, bad = _read_all(d, [*lines, "force: pos:", "force:1.8 pos:?", "1.9 2.3"])
    assert bad == 2 and len(rows) == 3 and rows[1] == {"force": 1.6, "pos": 2.1}


def test_teleplot_gathers_a_row_over_lines_with_units_and_stamps():
    lines = [">pos:10:3§mm", ">force:11:1.2§N", ">pos:11:3.1§mm", ">force:12:1.3§N", ">pos:12:3"]
    d = sniff_dialect(lines)
    assert isinstance(d, Teleplot)
    # the sniff began mid-row: the row starts where the stamp changes
    assert d.names == ["t_ms", "force", "pos"] and d.units == {"force": "N", "pos": "mm"}
    d.select(["t_ms", "force", "pos"])
    more = [
        ">force:13:1x",
        ">pos:13:3",
        ">:a log line",
        ">state:on|t",
        ">force:14:1.4",
        ">pos:14:3",
    ]
    rows, bad = _read_all(d, lines + more)
    assert bad == 1 and d.dropped == 1
    assert rows == [
        {"force": 1.2, "pos": 3.1, "t_ms": 11.0},
        {"force": 1.3, "pos": 3.0, "t_ms": 12.0},
        {"force": 1.4, "pos": 3.0, "t_ms": 14.0},
    ]


def test_teleplot_counts_a_row_cut_short():
    d = sniff_dialect([">force:1", ">pos:2", ">force:1", ">pos:2"])
    d.select(["force", "pos"])
    rows, bad = _read_all(d, [">force:1", ">pos:2", ">force:3", ">force:4", ">pos:5"])
    assert rows == [{"force": 1.0, "pos": 2.0}, {"force": 4.0, "pos": 5.0}]
    assert (bad, d.incomplete) == (0, 1)


def test_lines_of_no_dialect_are_refused_in_words():
    with pytest.raises(MalformedLine, match="not delimited numbers"):
        sniff_dialect(["hello world", "starting up", "ok"])


@settings(max_examples=200, deadline=None)
@given(st.lists(st.text(max_size=60), min_size=1, max_size=20), st.sampled_from(sorted(DIALECTS)))
def test_any_line_is_read_or_refused_never_crashes(lines, name):
    d = sniff_dialect(["t,force,pos", "1,2,3", "2,3,4"]) if name == "delimited" else None
    if name == "plotter":
        d = sniff_dialect(["force:1 pos:2", "force:1 pos:2"])
    if name == "teleplot":
        d = sniff_dialect([">force:1", ">pos:2", ">force:1"])
        d.select(d.names)
    for line in lines:
        try:
            row = d.read(line)
        except MalformedLine:
            continue
        assert row is None or all(isinstance(v, float) for v in row.values())


def test_stamps_wrap_like_a_32_bit_counter():
    c = StampChecker()
    raw = [WRAP - 3000 + 1000 * i for i in range(3)] + [1000 * i - 0 for i in range(3)]
    out = [c(r) for r in raw]
    assert out == [WRAP - 3000 + 1000 * i for i in range(6)]
    assert (c.wraps, c.rejected, c.restarts) == (1, 0, 0)


def test_a_stamp_that_goes_back_or_leaps_is_rejected_alone():
    c = StampChecker()
    raw = [1000 * i for i in range(20)]
    raw[10] = 3  # back
    raw[15] = 14_000_000_000  # two lines run together
    out = [c(r) for r in raw]
    assert out[10] is None and out[15] is None
    assert [o for o in out if o is not None] == [r for i, r in enumerate(raw) if i not in (10, 15)]
    assert (c.rejected, c.restarts, c.pauses) == (2, 0, 0)


def test_a_device_reset_is_continued_and_a_pause_kept():
    c = StampChecker()
    out = [c(r) for r in [1000 * i for i in range(20)]]
    out += [c(r) for r in (5, 1005, 2005, 3005)]  # reset: the first two held back, dropped
    assert out[20:22] == [None, None] and out[22] == 22000  # 5 continues at 20000
    assert c.restarts == 1
    later = [c(r) for r in (10_000_000, 10_001_000, 10_002_000, 10_003_000)]  # a pause
    assert later[:2] == [None, None] and later[2] is not None and c.pauses == 1


def test_a_text_link_reads_lines_drops_the_first_partial_one_and_counts_junk():
    master, slave = pty.openpty()
    tty.setraw(slave)
    name = os.ttyname(slave)
    link = TextLink(name)
    try:
        os.write(master, b"tail of a line\n1,2,3\r\n" + b"\xff\xfe\n" + b"x" * 600 + b"\n4,5,6\n")
        got = []
        deadline = time.monotonic() + 5
        while len(got) < 2 and time.monotonic() < deadline:
            got += link.poll()
        assert [ln.text for ln in got] == ["1,2,3", "4,5,6"]
        assert (link.undecodable, link.overlong) == (1, 1)
        assert [ln.number for ln in got] == [1, 4]
    finally:
        link.close()
        os.close(master)
        os.close(slave)


def test_teleplot_without_stamps_begins_rows_where_arrivals_say():
    # the sniff began mid-row (a closure first); the rows arrive a period apart
    lines = [(">pos:1", 0.0)] + [
        (f">{name}:{k}", 0.01 * k) for k in range(1, 6) for name in ("force", "pos")
    ]
    d = sniff_dialect([text for text, _ in lines])
    assert d.names == ["pos", "force"]  # the guess from the text alone
    d.align(lines)
    d.select(["force", "pos"])
    rows, bad = _read_all(d, [text for text, _ in lines])
    assert bad == 0 and rows[0] == {"force": 1.0, "pos": 1.0}
    assert all(r["force"] == r["pos"] for r in rows)
