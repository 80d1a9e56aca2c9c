"""An input file is data, never a pointer: HDF5 datasets whose values live in another file
(external raw storage) or are mapped from other datasets (virtual datasets) are refused
in one line naming the dataset, and the other file is never opened or read."""

from __future__ import annotations

import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from tissuecli.app.fit import fit_file
from tissuecli.app.transfer import export_csv, import_recording
from tissuecli.core.errors import TissueError
from tissuecli.formats.hdf5 import read_group
from tissuecli.formats.recording import read_recording
from tissuecli.formats.sessions import list_sessions, read_session, write_session

sys.path.insert(0, str(Path(__file__).parent))
from _watch import watch  # noqa: E402
from test_storage import make_session  # noqa: E402

from ..conftest import assert_clean_error, tissuecli  # noqa: E402

N = 300


def _secret(tmp_path: Path) -> Path:
    """A private file of the user's, 8 bytes per sample."""
    path = tmp_path / "private.txt"
    path.write_bytes(b"password" * N)
    return path


def _external(g: h5py.Group, key: str, secret: Path) -> None:
    del g[key]
    g.create_dataset(key, shape=(N,), dtype="f8", external=[(str(secret), 0, 8 * N)])


def _virtual(g: h5py.Group, key: str, secret: Path) -> None:
    source = secret.with_suffix(".h5")
    with h5py.File(source, "w") as f:
        f["x"] = np.arange(N, dtype=float)
    del g[key]
    layout = h5py.VirtualLayout(shape=(N,), dtype="f8")
    layout[:] = h5py.VirtualSource(str(source), "x", shape=(N,))
    g.create_virtual_dataset(key, layout)


KINDS = {"external": (_external, "external storage"), "virtual": (_virtual, "virtual dataset")}


def _pointer_file(tmp_path: Path, kind: str, key: str, foreign: bool = False) -> tuple[Path, Path]:
    secret = _secret(tmp_path)
    path = tmp_path / "s.h5"
    write_session(path, make_session("s1", n=N))
    with h5py.File(path, "a") as f:
        if foreign:  # another logger's file: plain datasets at the root
            del f["sessions"]
            for name in list(f.attrs):
                del f.attrs[name]
            g = f.create_group("rec")
            for q in ("time", "force", "position"):
                g[q] = np.arange(N, dtype=float) * 1e-3
        else:
            g = f["sessions/s1"]
        KINDS[kind][0](g, key, secret)
    watched = secret.with_suffix(".h5") if kind == "virtual" else secret
    return path, watched


@pytest.mark.parametrize("kind", sorted(KINDS))
@pytest.mark.parametrize("key", ["time", "force"])
def test_pointer_datasets_are_refused_and_never_followed(
    tmp_path: Path, kind: str, key: str
) -> None:
    path, secret = _pointer_file(tmp_path, kind, key)
    needle = KINDS[kind][1]
    try:
        with watch(secret) as touched:
            (row,) = list_sessions(path)
            for call in (
                lambda: read_session(path),
                lambda: export_csv(path, "s1", tmp_path / "out.csv"),
                lambda: fit_file(path),
                lambda: read_group(path, "sessions/s1"),
            ):
                with pytest.raises(TissueError) as err:
                    call()
                assert f"dataset {key}" in str(err.value) and needle in str(err.value)
    except OSError as exc:  # no inotify here
        pytest.skip(f"inotify unavailable: {exc}")
    assert row["status"].startswith("damaged") and needle in row["status"], row
    assert row["samples"] is None
    assert not (tmp_path / "out.csv").exists()
    assert (touched.opens, touched.reads) == (0, 0)


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_other_programs_files_with_pointers_are_refused(tmp_path: Path, kind: str) -> None:
    path, secret = _pointer_file(tmp_path, kind, "force", foreign=True)
    try:
        with watch(secret) as touched:
            with pytest.raises(TissueError, match=f"/rec/force.*{KINDS[kind][1]}"):
                import_recording(path, tmp_path / "o.h5")
            result = tissuecli("fit", str(path), "--columns", "force=/rec/force")
    except OSError as exc:
        pytest.skip(f"inotify unavailable: {exc}")
    assert_clean_error(result, "/rec/force", KINDS[kind][1])
    assert (touched.opens, touched.reads) == (0, 0)
    assert not (tmp_path / "o.h5").exists()


def test_external_links_in_other_programs_files_are_never_followed(tmp_path: Path) -> None:
    secret = tmp_path / "other.h5"
    with h5py.File(secret, "w") as f:
        f["force"] = np.arange(N, dtype=float)
    path = tmp_path / "linked.h5"
    with h5py.File(path, "w") as f:
        f["rec/time"] = np.arange(N) * 1e-3
        f["rec/position"] = np.zeros(N)
        f["rec/force"] = h5py.ExternalLink(str(secret), "/force")
    try:
        with watch(secret) as touched:
            with pytest.raises(TissueError, match="no column for force"):
                read_recording(path)
    except OSError as exc:
        pytest.skip(f"inotify unavailable: {exc}")
    assert (touched.opens, touched.reads) == (0, 0)


def test_command_line_lists_and_refuses(tmp_path: Path) -> None:
    path, _ = _pointer_file(tmp_path, "external", "force")
    listed = tissuecli("sessions", str(path))
    assert listed.returncode == 0 and "external storage" in listed.stdout, listed.stdout
    out = tmp_path / "o.csv"
    assert_clean_error(
        tissuecli("export", str(path), "--session", "s1", "--csv", str(out)),
        "dataset force",
        "external storage",
    )
    assert not out.exists()
