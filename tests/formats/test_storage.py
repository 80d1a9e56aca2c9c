"""HDF5 storage: round trips, refusals, helpful errors and crash safety."""

from __future__ import annotations

import hashlib
import json
import queue
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tissuecli.core.errors import InputError, SessionExists, StorageError
from tissuecli.core.session import Session
from tissuecli.formats.hdf5 import Column, read_group
from tissuecli.formats.hdf5 import from_attr as _from_attr
from tissuecli.formats.hdf5 import to_attr as _to_attr
from tissuecli.formats.sessions import (
    check_new_session,
    list_sessions,
    read_session,
    session_names,
    session_writer,
    write_session,
)
from tissuecli.formats.writer import SeriesWriter

CHILD = Path(__file__).with_name("_writer_child.py")
sys.path.insert(0, str(CHILD.parent))
from _writer_child import CALIBRATION, expected_rows  # noqa: E402

CAL = {"force": {"gain": 0.002, "offset": -0.1}, "position": {"gain": 2e-6, "offset": 1e-4}}


def make_session(name: str, n: int = 500, rate: float = 1000.0, **meta: Any) -> Session:
    t = np.arange(n) / rate
    return Session(
        time=t, force=np.sin(t) + 2.0, position=1e-3 * np.cos(t), name=name, meta=dict(meta)
    )


def make_raw(n: int) -> dict[str, np.ndarray]:
    i = np.arange(n)
    return {
        "counts": np.stack([i % 2000, -(i % 700)], axis=1).astype(np.int16),
        "sequence": i.astype(np.uint32),
        "device_clock": 7 * i + 2**40,
        "host_time": i * 1e-3 + 0.123,
    }


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


# --------------------------------------------------------------------------- round trips


def test_round_trip_is_exact_and_every_dataset_has_a_unit(tmp_path: Path) -> None:
    path = tmp_path / "s.h5"
    meta = {
        "tissue": "liver",
        "note": "ex vivo, 21 °C",
        "frames_lost": 3,
        "clock_map": {"slope": 1.0000012, "offset": -0.25},
        "tags": ["a", "b"],
        "mixed": [1, "x", 2.5],
        "port": None,
        "calibration": CAL,
    }
    session = make_session("liver-1", n=1234, **meta)
    raw = make_raw(1234)
    write_session(path, session, raw=raw)

    back = read_session(path, "liver-1", raw=True)
    assert back.name == "liver-1"
    for label in ("time", "force", "position"):
        np.testing.assert_array_equal(getattr(back, label), getattr(session, label))
        assert getattr(back, label).dtype == np.float64
    assert sorted(back.meta["raw"]) == sorted(f"raw/{key}" for key in raw)
    for key, value in raw.items():
        np.testing.assert_array_equal(back.meta["raw"][f"raw/{key}"], value)
    assert back.meta["raw"]["raw/counts"].dtype == np.int16
    assert back.meta["calibration"] == CAL
    for key in ("tissue", "note", "frames_lost", "clock_map", "tags", "mixed", "port"):
        assert back.meta[key] == meta[key], key
    assert back.meta["complete"] is True
    assert back.meta["file"] == str(path)
    assert back.meta["source"] == "device"
    assert back.meta["schema_version"] == 1

    with h5py.File(path, "r") as f:
        assert f.attrs["schema_version"] == 1
        assert str(f.attrs["software"]).startswith("tissuecli ")
        datasets: list[h5py.Dataset] = []
        f.visititems(lambda _n, o: datasets.append(o) if isinstance(o, h5py.Dataset) else None)
        assert len(datasets) == 7
        for ds in datasets:
            assert "unit" in ds.attrs, ds.name
        g = f["sessions/liver-1"]
        assert g["time"].attrs["unit"] == "s"
        assert g["force"].attrs["unit"] == "N"
        assert g["position"].attrs["unit"] == "m"
        assert g["force"].attrs["resolution"] == CAL["force"]["gain"]
        np.testing.assert_array_equal(g["raw/counts"].attrs["conversion"], [0.002, 2e-6])
        assert g["time"].compression is None and g["time"].maxshape == (None,)
        # plain readers see JSON for dicts
        assert json.loads(g.attrs["clock_map"]) == meta["clock_map"]


def test_imported_session_without_raw(tmp_path: Path) -> None:
    path = tmp_path / "s.h5"
    write_session(path, make_session("csv", n=10, source="import"))
    back = read_session(path, raw=True)
    assert len(back) == 10
    assert back.meta["raw"] == {} and back.meta["calibration"] == {}
    with h5py.File(path, "r") as f:
        g = f["sessions/csv"]
        assert "raw" not in g
        assert g["force"].attrs["conversion"] == 1.0 and g["force"].attrs["offset"] == 0.0
        assert np.isnan(g["force"].attrs["resolution"])


def test_duplicate_name_is_refused_and_file_untouched(tmp_path: Path) -> None:
    path = tmp_path / "s.h5"
    write_session(path, make_session("a", n=100))
    before = sha(path)
    with pytest.raises(
        SessionExists,
        match=r'session "a" already exists in .*s\.h5; choose '
        r"another --session name",
    ):
        write_session(path, make_session("a", n=50))
    with pytest.raises(SessionExists):
        session_writer(path, "a", meta={}, calibration=None)
    assert sha(path) == before
    assert len(read_session(path, "a")) == 100


def test_check_new_session(tmp_path: Path) -> None:
    path = tmp_path / "s.h5"
    check_new_session(path, "a")  # no file yet: fine
    assert not path.exists()
    write_session(path, make_session("a", n=5))
    check_new_session(path, "b")
    with pytest.raises(SessionExists, match='"a" already exists'):
        check_new_session(path, "a")
    with pytest.raises(InputError):
        check_new_session(path, "x/y")
    with pytest.raises(StorageError, match="directory does not exist"):
        check_new_session(tmp_path / "nope" / "s.h5", "a")
    (tmp_path / "t.txt").write_text("x")
    with pytest.raises(StorageError, match="not an HDF5 file"):
        check_new_session(tmp_path / "t.txt", "a")


def test_bad_session_names_are_input_errors(tmp_path: Path) -> None:
    for name in ("", "a/b", ".."):
        with pytest.raises(InputError):
            write_session(tmp_path / "s.h5", make_session(name, n=3))
    with pytest.raises(InputError, match="shape"):
        write_session(tmp_path / "s.h5", Session(np.arange(3.0), np.zeros(2), np.zeros(3), "x"))


def test_several_sessions_and_list(tmp_path: Path) -> None:
    path = tmp_path / "s.h5"
    write_session(
        path,
        make_session(
            "late", n=2001, rate=1000.0, tissue="liver", start_utc="2026-03-02T10:00:00+00:00"
        ),
    )
    write_session(
        path,
        make_session(
            "early",
            n=501,
            rate=250.0,
            tissue="kidney",
            start_utc="2026-03-01T10:00:00+00:00",
            frames_lost=4,
            frames_bad=2,
            source="demo",
        ),
    )
    write_session(path, make_session("csv", n=11, rate=10.0), raw=None)

    assert sorted(session_names(path)) == ["csv", "early", "late"]
    rows = {r["name"]: r for r in list_sessions(path)}
    assert [r["name"] for r in list_sessions(path)][:2] == ["early", "late"]
    assert rows["late"]["samples"] == 2001
    assert rows["late"]["duration_s"] == pytest.approx(2.0)
    assert rows["late"]["rate_hz"] == pytest.approx(1000.0)
    assert rows["late"]["tissue"] == "liver"
    assert rows["early"]["samples"] == 501
    assert rows["early"]["duration_s"] == pytest.approx(2.0)
    assert rows["early"]["rate_hz"] == pytest.approx(250.0)
    assert (rows["early"]["frames_lost"], rows["early"]["frames_bad"]) == (4, 2)
    assert rows["early"]["source"] == "demo"
    assert rows["csv"]["rate_hz"] == pytest.approx(10.0)
    assert rows["csv"]["source"] == "import" and rows["csv"]["frames_lost"] == 0
    assert all(r["complete"] is True for r in rows.values())
    assert rows["early"]["start_utc"] == "2026-03-01T10:00:00+00:00"
    assert len(read_session(path, "early")) == 501


# --------------------------------------------------------------------------- helpful errors


def test_no_name_with_several_sessions_lists_them(tmp_path: Path) -> None:
    path = tmp_path / "s.h5"
    write_session(path, make_session("one", n=5))
    assert read_session(path).name == "one"
    write_session(path, make_session("two", n=5))
    with pytest.raises(StorageError, match="--session NAME") as err:
        read_session(path)
    assert "one" in str(err.value) and "two" in str(err.value)
    with pytest.raises(StorageError, match='no session "three".*available: .*one') as err:
        read_session(path, "three")
    assert "two" in str(err.value)


def test_missing_non_hdf5_and_empty_files(tmp_path: Path) -> None:
    with pytest.raises(StorageError, match="does not exist"):
        read_session(tmp_path / "missing.h5")
    with pytest.raises(StorageError, match="does not exist"):
        list_sessions(tmp_path / "missing.h5")
    text = tmp_path / "data.csv"
    text.write_text("time,force,position\n0,1,2\n")
    for call in (
        lambda: read_session(text),
        lambda: list_sessions(text),
        lambda: write_session(text, make_session("x", n=3)),
    ):
        with pytest.raises(StorageError, match="not an HDF5 file"):
            call()
    assert text.read_text().startswith("time,force")  # never overwritten
    with pytest.raises(StorageError, match="is a directory"):
        read_session(tmp_path)
    with pytest.raises(StorageError, match="directory does not exist"):
        write_session(tmp_path / "nope" / "s.h5", make_session("x", n=3))
    empty = tmp_path / "empty.h5"
    h5py.File(empty, "w").close()
    assert list_sessions(empty) == [] and session_names(empty) == []
    with pytest.raises(StorageError, match="holds no sessions"):
        read_session(empty)


def test_unreadable_errors_are_single_lines(tmp_path: Path) -> None:
    text = tmp_path / "x.h5"
    text.write_bytes(b"\x00" * 100)
    with pytest.raises(StorageError) as err:
        read_session(text)
    assert "\n" not in str(err.value)
    assert err.value.__cause__ is None and err.value.__suppress_context__


# --------------------------------------------------------------------------- writer behaviour


def test_generic_writer_without_fsync_and_read_group(tmp_path: Path) -> None:
    path = tmp_path / "p.h5"
    cols = [
        Column("t", "float64", (), {"unit": "s"}),
        Column("cmd/volts", "float32", (3,), {"unit": "V"}),
    ]
    with SeriesWriter(
        path,
        "plays/p1",
        cols,
        {"script": {"steps": [1, 2]}},
        flush_interval_s=0.0,
        fsync=False,
        kind="play",
    ) as w:
        for k in range(5):
            w.append(
                {
                    "t": np.arange(k * 10, k * 10 + 10) * 0.01,
                    "cmd/volts": np.full((10, 3), k, np.float32),
                }
            )
            assert w.rows_flushed == w.rows == (k + 1) * 10
        w.set_attrs(steps_done=5)
    columns, attrs = read_group(path, "plays/p1")
    np.testing.assert_array_equal(columns["t"], np.arange(50) * 0.01)
    assert columns["cmd/volts"].shape == (50, 3) and columns["cmd/volts"].dtype == np.float32
    assert attrs["script"] == {"steps": [1, 2]} and attrs["steps_done"] == 5
    assert attrs["complete"] is True
    with pytest.raises(SessionExists, match='play "p1" already exists.*--play name'):
        SeriesWriter(path, "plays/p1", cols, {}, kind="play")
    with pytest.raises(StorageError, match="no group /plays/p2"):
        read_group(path, "plays/p2")


def test_append_flushes_by_time_and_set_attrs_waits_for_flush(tmp_path: Path) -> None:
    path = tmp_path / "s.h5"
    block = {k: v[:10] for k, v in expected_rows(0, 10).items()}
    with session_writer(path, "s", meta={}, calibration=CALIBRATION, flush_interval_s=0.05) as w:
        w.append(block)
        assert (w.rows, w.rows_flushed) == (10, 0)
        w.set_attrs(frames_lost=7)
        time.sleep(0.06)
        assert w.maybe_flush() is True
        assert w.rows_flushed == 10
        w.append(block)
        assert w.rows == 20
    s = read_session(path)
    assert len(s) == 20 and s.meta["frames_lost"] == 7


def test_append_rejects_malformed_blocks(tmp_path: Path) -> None:
    rows = expected_rows(0, 4)
    with session_writer(tmp_path / "s.h5", "s", meta={}, calibration=None) as w:
        with pytest.raises(ValueError, match="missing"):
            w.append({k: v for k, v in rows.items() if k != "force"})
        with pytest.raises(ValueError, match="rows"):
            w.append({**rows, "force": rows["force"][:3]})
        with pytest.raises(ValueError, match="integers"):
            w.append({**rows, "raw/sequence": rows["raw/sequence"] + 0.5})
        with pytest.raises(ValueError, match="shape"):
            w.append({**rows, "raw/counts": rows["raw/counts"][:, 0]})
        assert w.rows == 0
        w.append(rows)
    assert len(read_session(tmp_path / "s.h5")) == 4


def test_exceptions_close_the_writer_with_the_right_status(tmp_path: Path) -> None:
    path = tmp_path / "s.h5"
    rows = expected_rows(0, 100)
    with pytest.raises(RuntimeError):
        with session_writer(path, "err", meta={}, calibration=None) as w:
            w.append(rows)
            raise RuntimeError("device exploded")
    with pytest.raises(KeyboardInterrupt):
        with session_writer(path, "ctrl-c", meta={}, calibration=None) as w:
            w.append(rows)
            raise KeyboardInterrupt
    with session_writer(path, "ok", meta={}, calibration=None) as w:
        w.append(rows)
        w.set_attrs(stop_reason="user")
    err, ctrl_c, ok = (read_session(path, n) for n in ("err", "ctrl-c", "ok"))
    assert len(err) == len(ctrl_c) == len(ok) == 100
    assert err.meta["complete"] is False
    assert err.meta["stop_reason"] == "error: RuntimeError: device exploded"
    assert ctrl_c.meta["complete"] is True and ctrl_c.meta["stop_reason"] == "interrupted"
    assert ok.meta["complete"] is True and ok.meta["stop_reason"] == "user"


def test_crashed_group_is_cut_to_committed_rows(tmp_path: Path) -> None:
    path = tmp_path / "s.h5"
    with session_writer(path, "s", meta={}, calibration=None) as w:
        w.append(expected_rows(0, 300))
        w.flush()
        w.close(complete=False)
    # what a kill during a flush can leave: datasets longer than committed, unequal lengths
    with h5py.File(path, "a") as f:
        g = f["sessions/s"]
        for name in (
            "time",
            "position",
            "raw/counts",
            "raw/sequence",
            "raw/device_clock",
            "raw/host_time",
        ):
            g[name].resize(350, axis=0)
        g["force"].resize(400, axis=0)
    s = read_session(path, raw=True)
    assert len(s) == 300 and all(len(v) == 300 for v in s.meta["raw"].values())
    np.testing.assert_array_equal(s.force, expected_rows(0, 300)["force"])
    with h5py.File(path, "a") as f:
        del f["sessions/s"].attrs["rows_committed"]
    assert len(read_session(path)) == 350  # without the counter: the shortest column
    assert list_sessions(path)[0]["samples"] == 350


def test_writer_rewrite_replaces_a_column_before_completion(tmp_path: Path) -> None:
    path = tmp_path / "s.h5"
    w = session_writer(path, "s", meta={}, calibration=None, raw=False)
    w.append({"time": np.arange(20) * 1e-3, "force": np.ones(20), "position": np.zeros(20)})
    corrected = np.arange(20) * 1.001e-3
    w.rewrite("time", corrected, clock="drift-corrected")
    with pytest.raises(ValueError, match="values for 20 rows"):
        w.rewrite("time", corrected[:5])
    w.close()
    s = read_session(path)
    np.testing.assert_array_equal(s.time, corrected)
    with h5py.File(path, "r") as f:
        assert f["sessions/s/time"].attrs["unit"] == "s"
        assert f["sessions/s/time"].attrs["clock"] == "drift-corrected"


_text = st.text(
    st.characters(blacklist_categories=("Cs",), blacklist_characters="\x00"), max_size=20
)
_values = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**62), 2**62),
    st.floats(allow_nan=False, allow_infinity=False),
    _text.filter(lambda s: s[:1] not in "{["),
    st.lists(_text, min_size=1, max_size=4),
    st.lists(st.integers(-1000, 1000), max_size=4),
    st.dictionaries(_text, st.one_of(st.integers(-1000, 1000), _text), max_size=3),
)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(value=_values)
def test_attributes_round_trip(value: Any) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        with h5py.File(Path(tmp) / "a.h5", "w") as f:
            f.attrs["v"] = _to_attr(value)
            back = _from_attr(f.attrs["v"])
    assert back == value and type(back) is type(value)


# --------------------------------------------------------------------------- crash safety


class Child:
    """The writer child process, with its stdout lines collected by a thread."""

    def __init__(self, path: Path, *args: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, str(CHILD), str(path), *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            bufsize=1,
        )
        self.lines: queue.Queue[str] = queue.Queue()
        self.pump = threading.Thread(target=self._pump, daemon=True)
        self.pump.start()

    def _pump(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.put(line.strip())

    def wait_flushes(self, count: int, timeout: float = 10.0) -> int:
        """Wait for `count` 'flushed N' lines; return the last N."""
        deadline = time.monotonic() + timeout
        seen, last = 0, 0
        while seen < count:
            try:
                line = self.lines.get(timeout=max(deadline - time.monotonic(), 0.01))
            except queue.Empty:
                self.proc.kill()
                raise AssertionError(f"child stalled: {self.proc.stderr.read()}") from None
            if line.startswith("flushed "):
                seen, last = seen + 1, int(line.split()[1])
        return last

    def last_line(self, timeout: float = 10.0) -> str:
        """Wait for the child to end; return its last stdout line."""
        self.proc.wait(timeout=timeout)
        self.pump.join(timeout=timeout)
        lines = [""]
        while not self.lines.empty():
            lines.append(self.lines.get())
        return lines[-1]


def assert_expected(session: Session) -> None:
    n = len(session)
    exp = expected_rows(0, n)
    np.testing.assert_array_equal(session.time, exp["time"])
    np.testing.assert_array_equal(session.force, exp["force"])
    np.testing.assert_array_equal(session.position, exp["position"])
    for key in ("raw/counts", "raw/sequence", "raw/device_clock", "raw/host_time"):
        np.testing.assert_array_equal(session.meta["raw"][key], exp[key])


def test_kill9_keeps_every_flushed_row(tmp_path: Path) -> None:
    rng = random.Random(1)
    for k in range(5):
        path = tmp_path / f"kill{k}.h5"
        # odd runs skip fsync: a kill -9 keeps the OS page cache, so nothing may be lost
        child = Child(path, "--interval", "0.02", *(["--no-fsync"] if k % 2 else []))
        try:
            last = child.wait_flushes(3)
            time.sleep(rng.uniform(0.0, 0.03))  # kill at a random point of the loop
        finally:
            child.proc.send_signal(signal.SIGKILL)
            child.proc.wait(timeout=10)
        with h5py.File(path, "r") as f:  # plain HDF5 opens the crashed file
            assert f["sessions/crash"].attrs["complete"] == np.False_
        s = read_session(path, raw=True)
        assert len(s) >= last > 0
        assert s.meta["complete"] is False and "stop_reason" not in s.meta
        assert_expected(s)


def test_sigterm_closes_cleanly_and_loses_nothing(tmp_path: Path) -> None:
    path = tmp_path / "term.h5"
    child = Child(path, "--interval", "0.02")
    try:
        flushed = child.wait_flushes(3)
        # a session being recorded can be read: its committed rows, exact
        live = read_session(path, raw=True)
        assert len(live) >= flushed and live.meta["complete"] is False
        assert_expected(live)
        assert list_sessions(path)[0]["samples"] >= flushed
        # but a second writer gets a clear message, not a traceback
        with pytest.raises(StorageError, match="being written by another program"):
            session_writer(path, "other", meta={}, calibration=None)
    finally:
        child.proc.send_signal(signal.SIGTERM)
    line = child.last_line()
    assert child.proc.returncode == 0 and line.startswith("total "), line
    total = int(line.split()[1])
    s = read_session(path, raw=True)
    assert len(s) == total > 0
    assert s.meta["complete"] is True and s.meta["stop_reason"] == "interrupted"
    assert_expected(s)
