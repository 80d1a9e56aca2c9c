"""Batch fitting: every session named, the same catalogue from one process, from worker
processes and from a Dask cluster; nothing refitted on a second run; failures listed
without stopping the others; labels from the sessions and from a manifest."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import numpy as np
import pytest

from tissuecli.app.batch import DaskExecutor, Input, content_sha256, expand_inputs, fit_batch
from tissuecli.app.study import write_study
from tissuecli.core.errors import InputError
from tissuecli.formats.catalogue import Catalogue
from tissuecli.formats.sessions import read_session
from tissuecli.identify.outcome import fit_session
from tissuecli.sim.study import GROUPS, StudyDesign

FAST = {"forms": "x,xdot"}


@pytest.fixture(scope="module")
def study(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("study") / "study.h5"
    design = StudyDesign(
        groups={k: GROUPS[k] for k in ("fat", "tumour")}, specimens=2, sessions=2,
        duration_s=2.0, seed=1,
    )  # fmt: skip
    write_study(path, design)
    return path


def _fits(path: Path) -> list[tuple]:
    """What a catalogue says of each session, in a form two runs can be compared by."""
    with Catalogue(path, create=False) as cat:
        return sorted(
            (e.row["session"], e.row["content_sha256"], e.row["law"], e.row["tissue"],
             e.row["specimen"], tuple(e.mean), tuple(map(tuple, e.cov or [])))
            for e in cat.entries()
        )  # fmt: skip


def test_every_session_of_a_file_folder_and_pattern(study: Path, tmp_path: Path) -> None:
    names = [i.session for i in expand_inputs([str(study)])]
    assert len(names) == 8 and names[0] == "fat-01-01"
    assert expand_inputs([str(study.parent)]) == expand_inputs([str(study)])
    assert expand_inputs([str(study.parent / "*.h5"), str(study)]) == expand_inputs([str(study)])
    assert expand_inputs([str(study)], "tumour-02-01") == [Input(str(study), "tumour-02-01")]
    with pytest.raises(InputError, match="no file matches"):
        expand_inputs([str(tmp_path / "*.h5")])
    with pytest.raises(InputError, match="no file"):
        expand_inputs([str(tmp_path / "missing.h5")])


def test_catalogue_holds_each_fit_as_fitted_alone(study: Path, tmp_path: Path) -> None:
    db = tmp_path / "t.db"
    result = fit_batch([str(study)], catalogue=db, jobs=1, **FAST)
    assert len(result.fitted) == 8 and not result.failed and result.catalogue_fits == 8
    with Catalogue(db, create=False) as cat:
        entries = {e.row["session"]: e for e in cat.entries()}
    s = read_session(study, "tumour-01-02")
    alone = fit_session(s, **FAST).bayes.best_.posterior
    e = entries["tumour-01-02"]
    np.testing.assert_array_equal(e.mean, alone.mean)
    np.testing.assert_array_equal(e.cov, alone.cov)
    assert e.row["content_sha256"] == content_sha256(s)
    assert (e.row["tissue"], e.row["specimen"]) == ("tumour", "tumour-01")


def test_second_run_refits_nothing(study: Path, tmp_path: Path) -> None:
    db = tmp_path / "t.db"
    fit_batch([str(study)], catalogue=db, jobs=1, **FAST)
    before = sqlite3.connect(db).execute("SELECT id, fitted_utc FROM fits").fetchall()
    again = fit_batch([str(study)], catalogue=db, jobs=1, **FAST)
    assert (len(again.fitted), len(again.skipped)) == (0, 8)
    assert sqlite3.connect(db).execute("SELECT id, fitted_utc FROM fits").fetchall() == before
    # other settings are another fit; --refit fits again
    other = fit_batch([str(study)], catalogue=db, jobs=1, forms="x,xdot", hold_out=0.3)
    assert len(other.fitted) == 8 and other.catalogue_fits == 16
    forced = fit_batch([str(study)], catalogue=db, jobs=1, refit=True, **FAST)
    assert len(forced.fitted) == 8 and forced.catalogue_fits == 16


def test_manifest_labels_and_relabelling(study: Path, tmp_path: Path) -> None:
    db = tmp_path / "t.db"
    manifest = tmp_path / "labels.csv"
    rel = Path("..") / study.parent.name / study.name  # relative to the manifest
    manifest.write_text(
        f"file,session,tissue,specimen,operator,site\n{rel},,,,,bench A\n"
        f"{rel},fat-01-01,fat,F7,ana,bench B\n"
    )
    fit_batch([str(study)], catalogue=db, manifest=manifest, jobs=1, **FAST)
    with Catalogue(db, create=False) as cat:
        rows = {e.row["session"]: e.row for e in cat.entries()}
    assert rows["fat-01-01"]["specimen"] == "F7" and rows["fat-01-01"]["operator"] == "ana"
    assert rows["fat-01-01"]["labels"]["site"] == "bench B"
    assert rows["fat-01-02"]["specimen"] == "fat-01"  # the session's own label stays
    assert rows["fat-01-02"]["labels"]["site"] == "bench A"
    manifest.write_text(f"file,session,tissue\n{rel},fat-01-01,liver\n")
    again = fit_batch([str(study)], catalogue=db, manifest=manifest, jobs=1, **FAST)
    assert len(again.fitted) == 0 and again.relabelled == 8
    with Catalogue(db, create=False) as cat:
        assert cat.entries({"session": "fat-01-01"})[0].row["tissue"] == "liver"
    bad = tmp_path / "bad.csv"
    bad.write_text("path,tissue\nx.h5,liver\n")
    with pytest.raises(InputError, match="no 'file' column"):
        fit_batch([str(study)], manifest=bad, jobs=1, **FAST)


def test_failures_are_listed_and_the_rest_fitted(study: Path, tmp_path: Path) -> None:
    broken = tmp_path / "broken.csv"
    broken.write_text("time,force,position\n0,1,2\n")
    db = tmp_path / "t.db"
    result = fit_batch([str(broken), str(study)], catalogue=db, jobs=1, **FAST)
    assert len(result.fitted) == 8
    assert [str(i) for i, _ in result.failed] == [str(broken)]
    assert "\n" not in result.failed[0][1]
    with pytest.raises(InputError):
        fit_batch([str(broken), str(study)], jobs=1, on_error="stop", **FAST)


def test_worker_processes_give_the_same_catalogue(study: Path, tmp_path: Path) -> None:
    fit_batch([str(study)], catalogue=tmp_path / "one.db", jobs=1, **FAST)
    fit_batch([str(study)], catalogue=tmp_path / "two.db", jobs=2, **FAST)
    assert _fits(tmp_path / "one.db") == _fits(tmp_path / "two.db")


def test_a_dask_cluster_gives_the_same_catalogue(study: Path, tmp_path: Path) -> None:
    distributed = pytest.importorskip("distributed")
    fit_batch([str(study)], catalogue=tmp_path / "one.db", jobs=1, **FAST)
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
    ) as cluster:
        result = fit_batch(
            [str(study)], catalogue=tmp_path / "dask.db", scheduler=cluster.scheduler_address,
            **FAST,
        )  # fmt: skip
    assert "Dask cluster" in result.executor and len(result.fitted) == 8
    assert _fits(tmp_path / "one.db") == _fits(tmp_path / "dask.db")


def test_unreachable_scheduler_is_one_line() -> None:
    pytest.importorskip("distributed")
    with pytest.raises(InputError, match="cannot reach the Dask scheduler"):
        DaskExecutor("tcp://127.0.0.1:9", timeout_s=1.0)


def test_workers_read_the_sessions_and_the_parent_only_stores(
    study: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import tissuecli.app.batch as batch

    read_here: list[str] = []
    real = batch.load_session

    def counted(*args, **kwargs):  # type: ignore[no-untyped-def]
        read_here.append(str(args[0]))
        return real(*args, **kwargs)

    monkeypatch.setattr(batch, "load_session", counted)
    fit_batch([str(study)], catalogue=tmp_path / "two.db", jobs=2, **FAST)
    assert read_here == []  # every session read in a worker process
    fit_batch([str(study)], catalogue=tmp_path / "one.db", jobs=1, **FAST)
    assert len(read_here) == 8  # in this process, by the same task function
    assert _fits(tmp_path / "one.db") == _fits(tmp_path / "two.db")


def test_an_interrupted_batch_keeps_what_it_fitted(study: Path, tmp_path: Path) -> None:
    db = tmp_path / "t.db"

    def stop_after_three(done: int, total: int, left: float | None) -> None:
        if done == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        fit_batch([str(study)], catalogue=db, jobs=1, progress=stop_after_three, **FAST)
    with Catalogue(db, create=False) as cat:
        assert len(cat.entries()) == 3
    again = fit_batch([str(study)], catalogue=db, jobs=2, **FAST)
    assert (len(again.fitted), len(again.skipped)) == (5, 3)


def test_stop_at_the_first_failure_with_workers(study: Path, tmp_path: Path) -> None:
    broken = tmp_path / "broken.csv"
    broken.write_text("time,force,position\n0,1,2\n")
    with pytest.raises(InputError, match="too few|broken"):
        fit_batch([str(broken), str(study)], jobs=2, on_error="stop", **FAST)
