"""The catalogue: a fit's parameter document in and out, labels changed in place,
foreign files refused, exports that never replace a file."""

from __future__ import annotations

import csv
import sqlite3
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tissuecli.core.errors import InputError, StorageError
from tissuecli.core.tissue import DEFAULT_TISSUE
from tissuecli.formats.catalogue import Catalogue, Fit, export, fit_rows, parse_where, table
from tissuecli.formats.params import document
from tissuecli.identify.outcome import fit_session
from tissuecli.sim.synth import random_session


@pytest.fixture(scope="module")
def doc() -> dict:
    session, _ = random_session(DEFAULT_TISSUE, seed=3, duration_s=2.0)
    return document(fit_session(session, forms="x,xdot", hold_out=0.3))


def _add(cat: Catalogue, doc: dict, key: str, **labels: str) -> int:
    return cat.add(
        key=key,
        file="/data/a.h5",
        session="s1",
        content_sha256="c" * 64,
        settings={"forms": "x,xdot"},
        settings_id="abc",
        labels={"tissue": "liver", "specimen": "L1", **labels},
        document=doc,
        fitted_utc="2026-01-01T00:00:00+00:00",
        fit_s=0.5,
    )


def test_round_trip(tmp_path: Path, doc: dict) -> None:
    path = tmp_path / "t.db"
    with Catalogue(path) as cat:
        _add(cat, doc, "k1", site="left lobe")
    with Catalogue(path, create=False) as cat:
        (e,) = cat.entries()
        assert cat.keys() == {"k1"}
    law = doc["law"]
    assert e.terms == [t["term"] for t in law["terms"]]
    assert e.symbols == ["K", "S", "M"] and e.units == ["N/m", "N s/m", "kg"]
    np.testing.assert_array_equal(e.mean, [t["mean"] for t in law["terms"]])
    np.testing.assert_array_equal(e.cov, law["cov"])
    assert e.row["tissue"] == "liver" and e.row["labels"]["site"] == "left lobe"
    assert e.row["r2_held_out"] == doc["validation"]["r2_held_out"]
    assert e.row["law"] == law["name"]
    # the normalised tables hold the same numbers
    db = sqlite3.connect(path)
    sd = [r[0] for r in db.execute("SELECT sd FROM coefficients ORDER BY position")]
    np.testing.assert_allclose(sd, [t["sd"] for t in law["terms"]])
    (n,) = db.execute("SELECT count(*) FROM evidence").fetchone()
    assert n == len(doc["evidence"])


def test_many_fits_in_one_transaction_as_one_by_one(tmp_path: Path, doc: dict) -> None:
    one = tmp_path / "one.db"
    with Catalogue(one) as cat:
        for k in ("k1", "k2", "k3"):
            _add(cat, doc, k)
    many = tmp_path / "many.db"
    rows = fit_rows(doc)  # as a batch's worker makes them
    with Catalogue(many) as cat:
        ids = cat.add_many(
            [
                Fit(k, "/data/a.h5", "s1", "c" * 64, {"forms": "x,xdot"}, "abc",
                    {"tissue": "liver", "specimen": "L1"}, rows,
                    "2026-01-01T00:00:00+00:00", 0.5)
                for k in ("k1", "k2", "k3")
            ]
        )  # fmt: skip
        assert ids == [1, 2, 3]

    def dump(path: Path) -> list[list[tuple]]:
        db = sqlite3.connect(path)
        tables = ("fits", "coefficients", "evidence", "meta")
        return [db.execute(f"SELECT * FROM {t} ORDER BY 1, 2").fetchall() for t in tables]

    assert dump(one) == dump(many)


def test_same_key_replaces_and_labels_change_in_place(tmp_path: Path, doc: dict) -> None:
    with Catalogue(tmp_path / "t.db") as cat:
        _add(cat, doc, "k1")
        _add(cat, doc, "k1")
        _add(cat, doc, "k2", tissue="kidney")
        assert len(cat.entries()) == 2
        assert [e.row["tissue"] for e in cat.entries({"tissue": "kidney"})] == ["kidney"]
        assert cat.relabel("k1", {"tissue": "spleen", "specimen": "S9"})
        assert not cat.relabel("k1", {"tissue": "spleen", "specimen": "S9"})
        assert cat.entries({"specimen": "S9"})[0].row["tissue"] == "spleen"
        with pytest.raises(InputError, match="cannot filter"):
            cat.entries({"document": "x"})


def test_foreign_files_are_refused(tmp_path: Path) -> None:
    text = tmp_path / "notes.db"
    text.write_text("not a database at all, " * 100)
    with pytest.raises(StorageError, match="not a tissuecli catalogue"):
        Catalogue(text)
    other = tmp_path / "other.db"
    sqlite3.connect(other).execute("CREATE TABLE x (a)").connection.commit()
    with pytest.raises(StorageError, match="not a tissuecli catalogue"):
        Catalogue(other)
    with pytest.raises(InputError, match="no catalogue"):
        Catalogue(tmp_path / "missing.db", create=False)


def test_exports_round_trip_and_never_replace(tmp_path: Path, doc: dict) -> None:
    with Catalogue(tmp_path / "t.db") as cat:
        _add(cat, doc, "k1")
        entries = cat.entries()
    header, rows = table(entries)
    export(entries, tmp_path / "t.csv", "csv")
    with open(tmp_path / "t.csv") as fh:
        got = list(csv.reader(fh))
    assert got[0] == header
    k = header.index("K_mean [N/m]")
    assert float(got[1][k]) == pytest.approx(doc["law"]["terms"][0]["mean"], rel=1e-15)
    with pytest.raises(InputError, match="exists"):
        export(entries, tmp_path / "t.csv", "csv")
    pq = pytest.importorskip("pyarrow.parquet")
    export(entries, tmp_path / "t.parquet", "parquet")
    back = pq.read_table(tmp_path / "t.parquet").to_pydict()
    assert back["K_mean [N/m]"][0] == rows[0][k]
    with pytest.raises(InputError, match="exists"):
        export(entries, tmp_path / "t.parquet", "parquet")


@settings(max_examples=100, deadline=None)  # new draws each run
@given(st.lists(st.text(max_size=30), max_size=4))
def test_bad_filters_are_one_line(items: list[str]) -> None:
    try:
        out = parse_where(items)
    except InputError as exc:
        assert "\n" not in str(exc)
    else:
        assert len(out) <= len(items)
