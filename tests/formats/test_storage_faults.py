"""Storage faults and files that are not tissuecli's: one line, exit 1, nothing damaged.

A full disk is stood in for by a file-size limit (RLIMIT_FSIZE with SIGXFSZ ignored,
so writes past it fail with EFBIG as they fail with ENOSPC on a full disk): it needs
no root and no mount. ``benchmarks/storage_faults.py`` repeats the trials many times,
and on a real full tmpfs when run as root.
"""

from __future__ import annotations

import errno
import hashlib
import os
import re
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest

from tissuecli.core.errors import StorageError
from tissuecli.formats import space
from tissuecli.formats import writer as writer_module
from tissuecli.formats.hdf5 import read_group
from tissuecli.formats.playlog import PlayLog, check_log
from tissuecli.formats.sessions import (
    check_new_session,
    list_sessions,
    read_session,
    session_writer,
    write_session,
)

sys.path.insert(0, str(Path(__file__).parent))
from _writer_child import CALIBRATION, expected_rows  # noqa: E402
from test_storage import assert_expected, make_session  # noqa: E402

from ..conftest import assert_clean_error, tissuecli  # noqa: E402

CHILD = Path(__file__).with_name("_writer_child.py")


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def run_child(path: Path, limit: int, *extra: str) -> tuple[subprocess.CompletedProcess[str], int]:
    """The writer child under a file-size limit; its result and the last committed count."""
    r = subprocess.run(
        [
            sys.executable,
            str(CHILD),
            str(path),
            "--interval",
            "0",
            "--sleep",
            "0",
            "--block",
            "500",
            "--no-fsync",
            "--fsize-limit",
            str(limit),
            *extra,
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    flushed = [int(line.split()[1]) for line in r.stdout.splitlines() if line.startswith("flushed")]
    return r, (flushed[-1] if flushed else 0)


def assert_one_line(r: subprocess.CompletedProcess[str], *needles: str) -> str:
    # a negative code is a signal: SIGSEGV was the failure before
    assert r.returncode == 1, (r.returncode, r.stderr)
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("Error: "), r.stderr
    assert "Traceback" not in r.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


def assert_file_still_works(path: Path, committed: int) -> None:
    """Committed rows intact and exact; with the limit lifted, a new session goes in too."""
    s = read_session(path, "crash", raw=True)
    assert len(s) >= committed > 0
    assert_expected(s)
    assert s.meta["complete"] is False
    write_session(path, make_session("after", n=5000))
    assert len(read_session(path, "after")) == 5000
    assert len(read_session(path, "crash")) == len(s)
    with h5py.File(path, "r") as f:  # plain HDF5 agrees
        assert f["sessions/crash"].attrs["rows_committed"] == len(s)


@pytest.mark.parametrize("limit", [2_500_000, 4_000_000])
def test_file_size_limit_stops_the_writer_cleanly(tmp_path: Path, limit: int) -> None:
    path = tmp_path / "full.h5"
    r, committed = run_child(path, limit)
    line = assert_one_line(r, "file size limit reached", "rows committed before are saved")
    assert f"the {committed} rows" in line
    s = read_session(path, "crash")
    assert len(s) == committed  # the writer stopped before HDF5 wrote anything more
    assert s.meta["stop_reason"].startswith("storage fault: file size limit reached")
    assert path.stat().st_size <= limit
    assert_file_still_works(path, committed)


@pytest.mark.parametrize("limit", [700_000, 2_500_000])
def test_hdf5_running_into_the_limit_neither_crashes_nor_damages(
    tmp_path: Path, limit: int
) -> None:
    """With the room checks off, HDF5 itself fails mid-flush: the fallback must hold."""
    path = tmp_path / "full.h5"
    r, committed = run_child(path, limit, "--unguarded")
    assert_one_line(r, "file size limit reached")
    assert_file_still_works(path, committed)


def test_a_limit_below_the_headroom_refuses_before_creating_anything(tmp_path: Path) -> None:
    path = tmp_path / "full.h5"
    r, committed = run_child(path, 300_000)
    assert_one_line(r, "file size limit", "leaves no room")
    assert committed == 0 and not path.exists()


def test_a_new_file_without_a_committed_row_is_removed(tmp_path: Path) -> None:
    path = tmp_path / "full.h5"
    r, committed = run_child(path, 150_000, "--unguarded")
    assert_one_line(r, "nothing was saved")
    assert committed == 0 and not path.exists()


def _refuse_after(monkeypatch: pytest.MonkeyPatch, calls: int, cause: str = "disk full") -> None:
    """Make the writer's room check fail from its `calls`-th call on."""
    real = writer_module.make_room
    count = [0]

    def make_room(*args: Any) -> str | None:
        count[0] += 1
        return cause if count[0] >= calls else real(*args)

    monkeypatch.setattr(writer_module, "make_room", make_room)


def test_disk_full_at_a_flush_keeps_committed_rows_and_stops(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "s.h5"
    write_session(path, make_session("earlier", n=100))
    before = read_session(path, "earlier")
    _refuse_after(monkeypatch, 4)  # the start, two flushes, then the disk is full
    w = session_writer(path, "crash", meta={}, calibration=CALIBRATION, flush_interval_s=0)
    w.append(expected_rows(0, 300))
    w.append(expected_rows(300, 600))
    w.set_attrs(frames_lost=3)
    with pytest.raises(StorageError) as err:
        w.append(expected_rows(600, 900))
    message = str(err.value)
    assert "\n" not in message and err.value.__cause__ is None
    assert "disk full" in message and "the 600 rows committed before are saved" in message
    assert w.closed and w.fault is err.value
    with pytest.raises(StorageError, match="disk full"):  # the same error, again
        w.append(expected_rows(900, 910))
    w.rewrite("time", np.zeros(900))  # nothing to do any more
    w.close(complete=True)  # no-op: already closed, still incomplete
    s = read_session(path, "crash", raw=True)
    assert len(s) == 600 and s.meta["complete"] is False and s.meta["frames_lost"] == 3
    assert s.meta["stop_reason"] == "storage fault: disk full"
    assert_expected(s)
    np.testing.assert_array_equal(read_session(path, "earlier").force, before.force)
    assert [r["status"] for r in list_sessions(path)] == ["complete", "incomplete"]


def test_disk_full_before_the_first_row_removes_the_new_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "s.h5"
    _refuse_after(monkeypatch, 2)
    w = session_writer(path, "crash", meta={}, calibration=CALIBRATION, flush_interval_s=0)
    with pytest.raises(StorageError, match="disk full; nothing was saved"):
        w.append(expected_rows(0, 300))
    assert not path.exists()

    _refuse_after(monkeypatch, 1)
    with pytest.raises(StorageError, match="nothing was saved"):
        session_writer(path, "crash", meta={}, calibration=CALIBRATION)
    assert not path.exists()


def test_disk_full_when_adding_to_an_existing_file_leaves_it_byte_identical(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "s.h5"
    write_session(path, make_session("earlier", n=100))
    digest = sha(path)
    _refuse_after(monkeypatch, 1, "disk quota exceeded")
    with pytest.raises(StorageError, match="disk quota exceeded; the file was left as it was"):
        session_writer(path, "new", meta={}, calibration=CALIBRATION)
    assert sha(path) == digest


def test_an_io_error_from_hdf5_is_one_line_and_the_file_still_opens(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A write that fails inside HDF5 (here fsync: EIO) takes the careful way out."""
    path = tmp_path / "s.h5"
    w = session_writer(path, "crash", meta={}, calibration=CALIBRATION, flush_interval_s=0)
    w.append(expected_rows(0, 500))

    def fail(*args: Any) -> None:
        raise OSError(errno.EIO, os.strerror(errno.EIO))

    monkeypatch.setattr(writer_module, "fsync_file", fail)
    with pytest.raises(StorageError, match="input/output error") as err:
        w.append(expected_rows(500, 1000))
    assert "\n" not in str(err.value)
    monkeypatch.undo()
    s = read_session(path, raw=True)  # rows 0-499 were committed before
    assert len(s) >= 500 and s.meta["complete"] is False
    assert_expected(s)


def test_play_log_on_a_full_disk_raises_one_storage_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "plays.h5"
    _refuse_after(monkeypatch, 3)
    log = PlayLog(path, "p", {"rate_hz": 1000.0})
    log.writer.flush_interval_s = 0.0
    for i in range(2000):
        log.add(i * 1e-3, 0.0, 0.0, 0.0, 0.0, 0.0, 0, i)
    with pytest.raises(StorageError, match="disk full") as err:
        log.close(complete=True)
    assert "\n" not in str(err.value) and log.error is err.value
    with pytest.raises(StorageError, match="disk full"):
        log.flush()  # what the control loop meets
    columns, attrs = read_group(path, "plays/p")
    assert attrs["complete"] is False and attrs["stop_reason"] == "storage fault: disk full"
    np.testing.assert_array_equal(columns["counts"], np.arange(len(columns["counts"])))


# --------------------------------------------------------------------------- free space


def _free(monkeypatch: pytest.MonkeyPatch, free: int) -> None:
    """Make every drive report `free` bytes available."""
    real = os.statvfs

    class Stat:
        def __init__(self, st: os.statvfs_result) -> None:
            self.f_frsize, self.f_bavail = 4096, free // 4096
            self.f_bsize, self.f_blocks, self.f_bfree = st.f_bsize, st.f_blocks, free // 4096

    monkeypatch.setattr(os, "statvfs", lambda p: Stat(real(p)))
    monkeypatch.setattr(os, "fstatvfs", lambda fd: Stat(real("/")))
    monkeypatch.setattr(space, "reserve", lambda fd, offset, length: False)


def test_writers_refuse_to_start_without_room(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _free(monkeypatch, 900_000)  # less than the 1 MiB headroom
    path = tmp_path / "s.h5"
    with pytest.raises(StorageError, match=r"not enough free space .*: 0\.9 MB free, 1\.0 MB"):
        check_new_session(path, "a")
    with pytest.raises(StorageError, match="not enough free space for the session"):
        write_session(path, make_session("a", n=10))
    with pytest.raises(StorageError, match="not enough free space for the play log"):
        check_log(path, 1000.0)
    assert not path.exists()

    _free(monkeypatch, 1_700_000)  # 1 kHz: 0.48 MB + 1 MiB fits; 10 kHz: 4.8 MB does not
    session_writer(path, "a", meta={"rate_hz": 1000.0}, calibration=CALIBRATION).close()
    with pytest.raises(StorageError, match=r"1\.7 MB free, 5\.8 MB needed"):
        session_writer(path, "b", meta={"rate_hz": 10000.0}, calibration=CALIBRATION)
    with pytest.raises(StorageError, match="not enough free space for the session"):
        write_session(path, make_session("big", n=40000))  # 10 chunks of 98 kB + 1 MiB
    assert [r["name"] for r in list_sessions(path)] == ["a"]


def test_a_writer_stops_when_free_space_runs_low(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Without fallocate, free space is compared before every flush."""
    _free(monkeypatch, 1_500_000)  # room for the start and the first chunk
    path = tmp_path / "s.h5"
    w = session_writer(path, "crash", meta={}, calibration=CALIBRATION, flush_interval_s=0)
    w.append(expected_rows(0, 100))
    _free(monkeypatch, 1_000_000)
    with pytest.raises(StorageError) as err:
        w.append(expected_rows(100, 5000))
    # the free space, the need and the rule behind it, then what was kept
    assert re.search(
        r"disk full \(1\.0 MB free; the next write needs 1\.[0-9] MB: its data plus 1\.0 MB "
        r"kept in reserve so that the file closes intact\); the 100 rows",
        str(err.value),
    ), err.value
    assert len(read_session(path)) == 100


def test_record_checks_free_space_before_opening_the_device(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, forceps: Callable[..., Any]
) -> None:
    from tissuecli.app import record as record_module

    sim = forceps("--rate", "10000")
    out = tmp_path / "r.h5"
    _free(monkeypatch, 500_000)

    def no_device(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("the device was opened")

    with monkeypatch.context() as m:
        m.setattr(record_module.Forceps, "open", no_device)
        with pytest.raises(StorageError, match="not enough free space"):
            record_module.record(str(sim.link), out, "s", duration_s=1.0)
    # enough for HDF5, not for 10 s at the device's 10 kHz: refused once the rate is known
    _free(monkeypatch, 2_000_000)
    with pytest.raises(StorageError, match="not enough free space"):
        record_module.record(str(sim.link), out, "s", duration_s=1.0)
    assert not out.exists()


def test_play_checks_the_log_before_opening_the_display(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from tissuecli.app import play as play_module
    from tissuecli.core.terms import Law
    from tissuecli.core.tissue import Tissue

    def no_display(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("the display was opened")

    monkeypatch.setattr(play_module, "open_display", no_display)
    tissue = Tissue(Law.paper("x", "xdot"), 600.0, 3.0, 0.05)
    _free(monkeypatch, 500_000)
    with pytest.raises(StorageError, match="not enough free space for the play log"):
        play_module.play(tissue, "/dev/null", 1.0, log=tmp_path / "p.h5")
    foreign = tmp_path / "theirs.h5"
    _foreign(foreign, "dataset")
    with pytest.raises(StorageError, match="not written by tissuecli.*--log"):
        play_module.play(tissue, "/dev/null", 1.0, log=foreign)


# --------------------------------------------------------------------------- foreign files


def _foreign(path: Path, how: str) -> None:
    with h5py.File(path, "w") as f:
        if how == "dataset":
            f["data"] = np.arange(10.0)
        elif how == "root_attr":
            f.attrs["creator"] = "MATLAB"
        elif how == "sessions_without_attrs":
            f.create_group("sessions/x")


@pytest.mark.parametrize("how", ["dataset", "root_attr", "sessions_without_attrs"])
def test_a_foreign_hdf5_file_is_never_written(tmp_path: Path, how: str) -> None:
    path = tmp_path / "theirs.h5"
    _foreign(path, how)
    digest = sha(path)
    for call in (
        lambda: check_new_session(path, "a"),
        lambda: write_session(path, make_session("a", n=10)),
        lambda: session_writer(path, "a", meta={}, calibration=None),
    ):
        with pytest.raises(StorageError, match="was not written by tissuecli.*--out"):
            call()
    for call in (lambda: check_log(path, 1000.0), lambda: PlayLog(path, "p", {})):
        with pytest.raises(StorageError, match="was not written by tissuecli.*--log"):
            call()
    assert sha(path) == digest


def test_import_into_a_foreign_file_is_refused_on_the_command_line(tmp_path: Path) -> None:
    path = tmp_path / "theirs.h5"
    _foreign(path, "dataset")
    digest = sha(path)
    csv = tmp_path / "a.csv"
    csv.write_text("time,force,position\n0,1,0.001\n0.001,1,0.001\n")
    r = tissuecli("import", str(csv), "--out", str(path), "--session", "a")
    assert_clean_error(r, "was not written by tissuecli")
    assert sha(path) == digest


def test_an_empty_hdf5_file_is_fine(tmp_path: Path) -> None:
    path = tmp_path / "empty.h5"
    h5py.File(path, "w").close()
    check_new_session(path, "a")
    write_session(path, make_session("a", n=10))
    assert len(read_session(path, "a")) == 10
    with h5py.File(path, "r") as f:
        assert str(f.attrs["software"]).startswith("tissuecli ")


# --------------------------------------------------------------------------- end to end


@pytest.mark.slow
def test_record_into_a_file_size_limit_ends_in_one_line(
    tmp_path: Path, forceps: Callable[..., Any]
) -> None:
    """The whole command: 20 kHz into a 12 MB limit, about 11 s of recording."""
    import resource
    import signal

    sim = forceps("--rate", "20000")
    out = tmp_path / "r.h5"

    def limit() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (12_000_000, resource.RLIM_INFINITY))

    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "tissuecli",
            "record",
            "--port",
            str(sim.link),
            "--out",
            str(out),
            "--session",
            "s",
            "--duration",
            "60",
            "--quiet",
        ],
        capture_output=True,
        text=True,
        timeout=120,
        preexec_fn=limit,
    )
    assert_clean_error(r, "file size limit reached", "saved in session")
    (row,) = list_sessions(out)
    assert row["status"] == "incomplete" and row["samples"] > 100_000
