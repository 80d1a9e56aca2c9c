"""Other programs' binary recordings, written by their own libraries: generic HDF5 (h5py),
NWB (h5py in the NWB layout, and pynwb if installed) and LabVIEW TDMS (npTDMS)."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

from tissuecli.app.transfer import import_recording
from tissuecli.core.errors import InputError
from tissuecli.formats.recording import read_recording
from tissuecli.formats.sessions import list_sessions, read_session

from ..conftest import assert_clean_error, tissuecli

N = 2000
T = np.arange(N) * 1e-3
F = 1.0 + np.sin(2 * np.pi * 2 * T)  # N
X = 3e-3 + 1e-3 * np.cos(2 * np.pi * 2 * T)  # m


def _check(session, f=F, x=X) -> None:
    np.testing.assert_allclose(session.time, T, atol=1e-9)
    np.testing.assert_allclose(session.force, f, rtol=1e-12)
    np.testing.assert_allclose(session.position, x, rtol=1e-12)


def test_generic_hdf5_by_dataset_path_and_by_name(tmp_path: Path) -> None:
    path = tmp_path / "logger.h5"
    with h5py.File(path, "w") as f:
        f["data/t"] = T * 1e3
        f["data/t"].attrs["unit"] = "ms"
        f["data/f"] = F
        f["data/x"] = X * 1e3
        f["data/x"].attrs["units"] = "millimeters"
        f["meta/temperature"] = np.arange(7.0)
    s, report = read_recording(path, columns="time=/data/t,force=/data/f,position=data/x")
    _check(s)
    assert report.units["time"].startswith("ms") and report.units["position"].startswith("mm")
    named = tmp_path / "named.h5"
    with h5py.File(named, "w") as f:
        g = f.create_group("run1")
        g["time"], g["force"], g["position"] = T, F, X
    s, report = read_recording(named)
    _check(s)
    assert report.columns == {"time": "/run1/time", "force": "/run1/force",
                              "position": "/run1/position"}  # fmt: skip


def test_a_file_without_the_signals_is_refused_naming_what_it_holds(tmp_path: Path) -> None:
    path = tmp_path / "other.h5"
    with h5py.File(path, "w") as f:
        f["camera/frames"] = np.zeros((5, 4, 4), np.uint8)
        f["eeg/voltage"] = np.arange(100.0)
        f["eeg/stamp"] = np.arange(100.0)
    with pytest.raises(InputError, match="no column for time and force and position among "
                       "'/eeg/stamp', '/eeg/voltage'"):  # fmt: skip
        read_recording(path)
    empty = tmp_path / "empty.h5"
    with h5py.File(empty, "w") as f:
        f["labels"] = np.array([b"a", b"b"])
    with pytest.raises(InputError, match="holds no numeric signal.*it holds: /labels"):
        read_recording(empty)
    assert_clean_error(
        tissuecli("import", str(path), "--out", str(tmp_path / "o.h5")),
        "no column for time and force and position",
        "/eeg/voltage",
    )


def _nwb_layout(path: Path, timestamps: bool) -> None:
    """The NWB layout written with h5py: TimeSeries groups with data in their unit after
    conversion, and timestamps or starting_time with its rate."""
    with h5py.File(path, "w") as f:
        f.attrs["nwb_version"] = "2.7.0"
        for name, values, unit, conversion in (
            ("grasp_force", F / 1e-3, "newtons", 1e-3),  # stored in mN, converted to N
            ("jaw_position", X, "meters", 1.0),
        ):
            g = f.create_group(f"acquisition/{name}")
            g.attrs["neurodata_type"] = "TimeSeries"
            d = g.create_dataset("data", data=values)
            d.attrs.update(unit=unit, conversion=conversion, offset=0.0, resolution=-1.0)
            if timestamps:
                g["timestamps"] = T + 100.0
            else:
                st = g.create_dataset("starting_time", data=100.0)
                st.attrs.update(rate=1000.0, unit="seconds")


@pytest.mark.parametrize("timestamps", [True, False])
def test_nwb_time_series(tmp_path: Path, timestamps: bool) -> None:
    path = tmp_path / "rec.nwb"
    _nwb_layout(path, timestamps)
    s, report = read_recording(path)
    _check(s)
    assert report.columns["force"] == "/acquisition/grasp_force"
    assert report.units["force"].startswith("N")
    out = tmp_path / "o.h5"
    imported, _ = import_recording(path, out, "nwb")
    assert imported.samples == N and list_sessions(out)[0]["samples"] == N
    _check(read_session(out, "nwb"))


def test_nwb_written_by_pynwb(tmp_path: Path) -> None:
    pynwb = pytest.importorskip("pynwb")
    from datetime import datetime, timezone

    nwb = pynwb.NWBFile(
        session_description="grasp", identifier="g1",
        session_start_time=datetime(2024, 1, 1, tzinfo=timezone.utc),
    )  # fmt: skip
    nwb.add_acquisition(
        pynwb.TimeSeries(name="force", data=F * 1e3, unit="mN", conversion=1.0, timestamps=T)
    )
    nwb.add_acquisition(pynwb.TimeSeries(name="position", data=X * 1e3, unit="mm", timestamps=T))
    path = tmp_path / "pynwb.nwb"
    with pynwb.NWBHDF5IO(str(path), "w") as io:
        io.write(nwb)
    s, report = read_recording(path)
    _check(s)
    assert report.units["force"].startswith("mN")


def test_tdms_written_by_nptdms(tmp_path: Path) -> None:
    nptdms = pytest.importorskip("nptdms")
    path = tmp_path / "rig.tdms"
    with nptdms.TdmsWriter(str(path)) as w:
        w.write_segment([
            nptdms.ChannelObject("Untitled", "Force", F * 1e3,
                                 properties={"unit_string": "mN", "wf_increment": 1e-3}),
            nptdms.ChannelObject("Untitled", "Position", X * 1e3,
                                 properties={"unit_string": "mm", "wf_increment": 1e-3}),
        ])  # fmt: skip
    # an index file beside it is another file: never read
    (tmp_path / "rig.tdms_index").write_bytes(b"TDSh" + b"\0" * 64)
    s, report = read_recording(path)
    _check(s)
    assert report.columns["force"] == "Untitled/Force"
    assert report.columns["time"] == "Untitled/Force/time"
    bad = tmp_path / "bad.tdms"
    bad.write_bytes(b"TDSm" + b"\x07" * 40)
    with pytest.raises(InputError, match="bad.tdms"):
        read_recording(bad)
