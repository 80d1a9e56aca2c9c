"""HDF5 files that are not what they seem: every read gives a result or one clean line.

Properties run derandomized (deterministic suite); ``benchmarks/malformed_files.py``
runs the same generator much longer and counts the outcomes.
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings

from tissuecli.app.fit import fit_file
from tissuecli.app.transfer import export_csv
from tissuecli.core.errors import StorageError, TissueError
from tissuecli.formats.hdf5 import read_group
from tissuecli.formats.sessions import list_sessions, read_session, write_session

sys.path.insert(0, str(Path(__file__).parent))
from _malformed import Spec, clean, specs, write_spec  # noqa: E402
from test_storage import make_raw, make_session  # noqa: E402

from ..conftest import assert_clean_error, tissuecli_here  # noqa: E402

SETTINGS = settings(
    max_examples=200,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)


#: the fits already run on each class of readable data in this test run
_FITTED: set[tuple[object, ...]] = set()


def fit_once(spec: Spec, path: Path, name: str | None, options: dict[str, str]) -> None:
    """``fit_file(path, name, **options)`` ends in a result or one clean line.

    The law search and the sampler (0.5-3 s of CPU a readable file) see only the
    samples: they run once in a test run for each class of readable data (the kinds of
    the three datasets drawn, the rows read, the converter) and options. Later files of
    a class differ in noise and attributes, which the reading and the outcome see: those
    still run, through a one-term fit that takes neither. A class whose fit failed is
    not recorded, so a replayed example runs the same fit."""
    try:
        session = read_session(path, name)
    except TissueError:
        key = None  # the fit stops at the same read, in a few milliseconds
    else:
        columns = tuple(spec.columns.values())
        key = (tuple(sorted(options.items())), columns, len(session), repr(session.adc))
    clean(lambda: fit_file(path, name, **(options if key not in _FITTED else {"forms": "x"})))
    if key is not None:
        _FITTED.add(key)


def _valid_columns(spec: Spec) -> bool:
    return (
        spec.corruption == "none"
        and spec.root != "foreign"
        and all(kind in ("float64", "int32") for kind in spec.columns.values())
        and (spec.raw is None or all(kind in ("valid", "missing") for kind in spec.raw.values()))
        and not {"schema_version"} & set(spec.attrs)
    )


@SETTINGS
@given(spec=specs())
def test_sessions_fit_and_export_of_malformed_files_never_raise_a_traceback(spec: Spec) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "m.h5"
        write_spec(path, spec)
        listed = clean(lambda: list_sessions(path))
        # the session found by itself, then by name: both read, export and fit; the
        # first fit reads the file through the same path into one quick form (which may
        # take the sampler), the second runs the default structure search
        for name, options in ((None, {"forms": "x,xdot"}), (spec.name, {})):
            clean(lambda name=name: read_session(path, name, raw=True))
            clean(lambda name=name: export_csv(path, name, Path(tmp) / "out.csv"))
            fit_once(spec, path, name, options)
        if listed == "ok":
            rows = {r["name"]: r for r in list_sessions(path)}
            # a damaged session is listed as such, never skipped
            assert spec.name in rows
            row = rows[spec.name]
            json.dumps(row, allow_nan=False)  # --json output stays valid JSON
            if row["status"].startswith("damaged"):
                with pytest.raises(StorageError, match="is damaged"):
                    read_session(path, spec.name)
            if _valid_columns(spec):
                assert not row["status"].startswith("damaged"), row
                if "rows_committed" not in spec.attrs and "complete" not in spec.attrs:
                    assert row["samples"] == spec.n


@settings(max_examples=60, deadline=None, derandomize=True)
@given(spec=specs())
def test_export_writes_three_values_per_row_or_refuses(spec: Spec) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        path, out = Path(tmp) / "m.h5", Path(tmp) / "out.csv"
        write_spec(path, spec)
        if clean(lambda: export_csv(path, spec.name, out)) == "ok":
            lines = out.read_text().splitlines()
            assert lines[0] == "time,force,position"
            assert all(line.count(",") == 2 for line in lines[1:])


def _session_file(tmp_path: Path, mutate: object) -> Path:
    """A valid recorded session, then changed with plain h5py by `mutate(group)`."""
    path = tmp_path / "s.h5"
    session = make_session("s1", n=300, tissue="liver", frames_lost=2)
    session.meta["calibration"] = {
        "force": {"gain": 0.01, "offset": 0.0},
        "position": {"gain": 1e-6, "offset": 0.0},
    }
    write_session(path, session, raw=make_raw(300))
    with h5py.File(path, "a") as f:
        mutate(f["sessions/s1"])  # type: ignore[operator]
    return path


def _replace(key: str, data: object):  # noqa: ANN202
    def mutate(g: h5py.Group) -> None:
        del g[key]
        g[key] = data

    return mutate


@pytest.mark.parametrize(
    ("mutate", "needle"),
    [
        (_replace("force", np.array([b"1.0"] * 300)), "dataset force holds text; expected numbers"),
        (_replace("time", np.zeros(300, dtype=[("a", "f8")])), "dataset time holds compound"),
        (_replace("position", np.ones(300, dtype=bool)), "dataset position holds booleans"),
        (_replace("force", np.float64(1.0)), "dataset force is a single value"),
        (_replace("force", np.zeros((300, 2))), "dataset force has shape (300, 2); expected (n,)"),
        (_replace("raw/counts", np.zeros((300, 3), np.int16)), "dataset raw/counts has shape"),
        (_replace("raw/counts", np.zeros((300, 2))), "raw/counts holds floating-point numbers"),
        (lambda g: g.__delitem__("position"), "dataset position is missing"),
    ],
)
def test_damaged_sessions_name_the_file_the_session_and_the_dataset(
    tmp_path: Path, mutate: object, needle: str
) -> None:
    path = _session_file(tmp_path, mutate)
    with pytest.raises(StorageError) as err:
        read_session(path)
    message = str(err.value)
    assert str(path) in message and '"s1"' in message and needle.split(";")[0] in message
    (row,) = list_sessions(path)
    assert row["status"].startswith("damaged: dataset") and row["samples"] is None


def test_attributes_of_the_wrong_type_are_ignored_and_reported(tmp_path: Path) -> None:
    def mutate(g: h5py.Group) -> None:
        g.attrs["frames_lost"] = "three"
        g.attrs["complete"] = "yes"
        g.attrs["rows_committed"] = np.int64(120)
        g.attrs["tissue"] = np.array([1, 2])

    path = _session_file(tmp_path, mutate)
    (row,) = list_sessions(path)
    # 'complete' unreadable: trusted no further than rows_committed, like a crashed session
    assert row["status"] == "incomplete" and row["samples"] == 120
    assert row["frames_lost"] == 0 and row["tissue"] == ""
    assert {w.split()[1] for w in row["warnings"]} == {"frames_lost", "complete", "tissue"}
    s = read_session(path)
    assert len(s) == 120 and "frames_lost" not in s.meta and len(s.meta["warnings"]) == 3


def test_matlab_style_one_element_arrays_and_integral_doubles_are_numbers(tmp_path: Path) -> None:
    def mutate(g: h5py.Group) -> None:
        g.attrs["frames_lost"] = np.array([[4.0]])
        g.attrs["complete"] = np.array([1], dtype=np.uint8)

    (row,) = list_sessions(_session_file(tmp_path, mutate))
    assert row["frames_lost"] == 4 and row["status"] == "complete" and row["warnings"] == []


def test_a_dataset_claiming_more_rows_than_the_file_holds_is_damage(tmp_path: Path) -> None:
    def mutate(g: h5py.Group) -> None:
        for key in ("time", "force", "position", "raw"):
            del g[key]
        for key in ("time", "force", "position"):
            g.create_dataset(key, shape=(10**12,), maxshape=(None,), chunks=(4096,), dtype="f8")

    path = _session_file(tmp_path, mutate)
    with pytest.raises(StorageError, match="claims 1000000000000 rows"):
        read_session(path)


def test_truncated_file_is_called_damaged_not_busy(tmp_path: Path) -> None:
    path = tmp_path / "s.h5"
    write_session(path, make_session("a", n=5000))
    data = path.read_bytes()
    for cut in (100, 2000, len(data) // 2, len(data) - 1):
        path.write_bytes(data[:cut])
        for call in (lambda: list_sessions(path), lambda: read_session(path)):
            with pytest.raises(StorageError) as err:
                call()
            assert "damaged or truncated" in str(err.value)
            assert "another program" not in str(err.value)


def test_read_group_refuses_text_columns(tmp_path: Path) -> None:
    path = tmp_path / "p.h5"
    with h5py.File(path, "w") as f:
        g = f.create_group("plays/p")
        g["time"] = np.arange(3.0)
        g["V"] = np.array([b"a", b"b", b"c"])
    with pytest.raises(StorageError, match="dataset V holds text"):
        read_group(path, "plays/p")


def test_command_line_on_damaged_files(tmp_path: Path) -> None:
    text = _session_file(tmp_path, _replace("force", np.array([b"1.0"] * 300)))
    listed = tissuecli_here("sessions", str(text))
    assert listed.returncode == 0, listed.stderr
    assert "damaged" in listed.stdout and "force holds text" in listed.stdout
    rows = json.loads(tissuecli_here("sessions", str(text), "--json").stdout)
    assert rows[0]["status"].startswith("damaged: dataset force holds text")
    assert_clean_error(tissuecli_here("fit", str(text)), "is damaged", "force holds text")
    out = tmp_path / "x.csv"
    assert_clean_error(
        tissuecli_here("export", str(text), "--csv", str(out)), "is damaged", "force holds text"
    )
    assert not out.exists()

    truncated = tmp_path / "cut.h5"
    truncated.write_bytes(text.read_bytes()[:3000])
    for args in (["sessions"], ["fit"], ["export", "--csv", str(out)]):
        assert_clean_error(tissuecli_here(args[0], str(truncated), *args[1:]), "truncated")

    (tmp_path / "m").mkdir()
    missing = _session_file(tmp_path / "m", lambda g: g.__delitem__("time"))
    listed = tissuecli_here("sessions", str(missing))
    assert listed.returncode == 0 and "time is missing" in listed.stdout, listed.stdout

    (tmp_path / "w").mkdir()
    odd = _session_file(tmp_path / "w", lambda g: g.attrs.__setitem__("frames_lost", "three"))
    listed = tissuecli_here("sessions", str(odd))
    (line,) = [ln for ln in listed.stdout.splitlines() if ln.startswith("s1 ")]
    assert "complete" in line and "(attribute frames_lost is text" in line, line
