"""The batch commands as a user runs them: fit many sessions into a catalogue, list and
export it, compare its tissues, classify a new grasp; exit codes and last lines that
tell the truth. The fits run in processes of their own, as typed (they start workers);
the commands that read the catalogue run in this one, to spare an interpreter's start
for each."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tissuecli.app.study import write_study
from tissuecli.sim.study import GROUPS, StudyDesign

from ..conftest import assert_clean_error, tissuecli, tissuecli_here


@pytest.fixture(scope="module")
def fitted(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A study of two tissues far apart (250 and 520 N/m), fitted into a catalogue."""
    where = tmp_path_factory.mktemp("batch")
    study = where / "study.h5"
    design = StudyDesign(
        groups={k: GROUPS[k] for k in ("fat", "tumour")}, specimens=3, sessions=2,
        duration_s=2.0, seed=2,
    )  # fmt: skip
    write_study(study, design)
    db = where / "t.db"
    r = tissuecli("fit", str(study), "--catalogue", str(db), "--forms", "x,xdot", "--jobs", "1")
    assert r.returncode == 0, r.stderr
    lines = r.stdout.strip().splitlines()
    assert lines[-1] == f"no failures; catalogue {db} holds 12 fit(s)"
    assert lines[-2].startswith("12 of 12 session(s) fitted on this process")
    return study, db


def test_repeat_refits_nothing_and_failures_set_the_exit_code(
    fitted: tuple[Path, Path], tmp_path: Path
) -> None:
    study, db = fitted
    r = tissuecli("fit", str(study), "--catalogue", str(db), "--forms", "x,xdot")
    assert r.returncode == 0, r.stderr
    assert "0 of 12 session(s) fitted" in r.stdout and "12 already in the catalogue" in r.stdout
    broken = tmp_path / "broken.csv"
    broken.write_text("time,force,position\n0,1,2\n")
    r = tissuecli("fit", str(broken), str(study), "--catalogue", str(db), "--forms", "x,xdot")
    assert r.returncode == 1
    lines = r.stdout.strip().splitlines()
    assert lines[-1].startswith("1 of 13 session(s) failed (listed above)")
    assert any(line.startswith(f"failed: {broken}: ") for line in lines)
    assert "Traceback" not in r.stderr


def test_one_fit_options_refused_for_many(fitted: tuple[Path, Path], tmp_path: Path) -> None:
    study, _ = fitted
    r = tissuecli_here("fit", str(study), "--out", str(tmp_path / "p.json"))
    assert_clean_error(r, "--plots write one fit")


def test_catalogue_lists_and_exports(fitted: tuple[Path, Path], tmp_path: Path) -> None:
    _, db = fitted
    r = tissuecli_here("catalogue", str(db), "--where", "tissue=tumour")
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().splitlines()[-1] == "6 fit(s)"
    r = tissuecli_here("catalogue", str(db), "--json")
    rows = [json.loads(line) for line in r.stdout.splitlines()]
    assert len(rows) == 12 and {row["tissue"] for row in rows} == {"fat", "tumour"}
    out = tmp_path / "t.csv"
    assert (
        tissuecli_here("catalogue", str(db), "--export", "csv", "--out", str(out)).returncode == 0
    )
    assert len(out.read_text().splitlines()) == 13
    assert_clean_error(
        tissuecli_here("catalogue", str(db), "--export", "csv", "--out", str(out)), "exists"
    )
    assert_clean_error(tissuecli_here("catalogue", str(tmp_path / "none.db")), "no catalogue")


def test_compare_reports_and_classify(fitted: tuple[Path, Path], tmp_path: Path) -> None:
    study, db = fitted
    report, js = tmp_path / "c.html", tmp_path / "c.json"
    r = tissuecli_here(
        "compare", "--catalogue", str(db), "--report", str(report), "--json", str(js)
    )
    assert r.returncode == 0, r.stderr
    c = json.loads(js.read_text())
    (pair,) = c["pairs"]
    assert (pair["a"], pair["b"]) == ("tumour", "fat")
    assert pair["p_a_greater"] > 0.99 and pair["verdict"] == "different"
    assert len(c["sessions"]) == 12 and len(c["specimens"]) == 6
    html = report.read_text()
    assert "Forest plot" in html and "data:image/png;base64," in html
    assert f"tumour  fat        {pair['p_a_greater']:.3f}" in r.stdout
    assert_clean_error(
        tissuecli_here("compare", "--catalogue", str(db), "--json", str(js)), "exists"
    )
    r = tissuecli_here("classify", str(study), "--session", "tumour-03-02", "--catalogue", str(db))
    assert r.returncode == 0, r.stderr
    header, row = r.stdout.strip().splitlines()
    assert header.split()[1:3] == ["fat", "tumour"]
    probs = [float(p) for p in row.split()[1:3]]
    assert sum(probs) == pytest.approx(1, abs=2e-3) and row.split()[-1] == "tumour"


def test_compare_asks_which_settings(fitted: tuple[Path, Path], tmp_path: Path) -> None:
    study, db = fitted
    mixed = tmp_path / "mixed.db"
    mixed.write_bytes(db.read_bytes())
    r = tissuecli("fit", str(study), "--catalogue", str(mixed), "--forms", "paper")
    assert r.returncode == 0, r.stderr
    assert_clean_error(tissuecli_here("compare", "--catalogue", str(mixed)), "--settings")
