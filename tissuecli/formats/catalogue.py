"""The catalogue of fits: a SQLite database (standard library) of every session fitted,
the settings, the chosen law, its coefficients' posterior, the evidence, the held-out
score and the session's labels; docs/formats.md gives the schema.

One process writes it (the batch's parent; workers return the rows of their fits), one
row per (session content, settings) key. A batch commits the fits that arrived in the
last half second together (:meth:`Catalogue.add_many`), so that an interrupted batch
keeps what it finished but for that last half second.
"""

from __future__ import annotations

import csv
import json
import math
import os
import sqlite3
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from .._version import __version__
from ..core.errors import InputError, StorageError
from .atomic import atomic_file, os_error_cause
from .outputs import Output, check_outputs

FORMAT = "tissuecli-catalogue"
VERSION = 1
#: labels every fit carries as columns (empty when unknown); others go to ``labels``
LABELS = ("tissue", "specimen", "operator", "note")

SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS fits (
    id INTEGER PRIMARY KEY,
    key TEXT NOT NULL UNIQUE,
    file TEXT NOT NULL,
    session TEXT NOT NULL,
    content_sha256 TEXT NOT NULL,
    settings_id TEXT NOT NULL,
    settings TEXT NOT NULL,
    fitted_utc TEXT NOT NULL,
    software TEXT NOT NULL,
    fit_s REAL,
    tissue TEXT NOT NULL DEFAULT '',
    specimen TEXT NOT NULL DEFAULT '',
    operator TEXT NOT NULL DEFAULT '',
    note TEXT NOT NULL DEFAULT '',
    labels TEXT NOT NULL DEFAULT '{}',
    law TEXT,
    law_probability REAL,
    shape TEXT NOT NULL DEFAULT '{}',
    coef_mean TEXT,
    coef_cov TEXT,
    ln_evidence REAL,
    noise_sd_N REAL,
    samples INTEGER,
    duration_s REAL,
    rate_hz REAL,
    r2_held_out REAL,
    rms_held_out_N REAL,
    warnings TEXT NOT NULL DEFAULT '[]',
    document TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS fits_tissue ON fits (tissue, specimen);
CREATE TABLE IF NOT EXISTS coefficients (
    fit_id INTEGER NOT NULL REFERENCES fits (id) ON DELETE CASCADE,
    position INTEGER NOT NULL,
    term TEXT NOT NULL,
    symbol TEXT NOT NULL,
    unit TEXT NOT NULL,
    mean REAL,
    sd REAL,
    ci95_low REAL,
    ci95_high REAL,
    PRIMARY KEY (fit_id, position)
);
CREATE TABLE IF NOT EXISTS evidence (
    fit_id INTEGER NOT NULL REFERENCES fits (id) ON DELETE CASCADE,
    law TEXT NOT NULL,
    ln_evidence REAL,
    probability REAL,
    method TEXT,
    PRIMARY KEY (fit_id, law)
);
"""

#: columns of ``fits`` shown and exported (the whole parameter document stays inside)
COLUMNS = (
    "id", "file", "session", "tissue", "specimen", "operator", "note", "law",
    "law_probability", "ln_evidence", "noise_sd_N", "samples", "duration_s", "rate_hz",
    "r2_held_out", "rms_held_out_N", "settings_id", "fitted_utc", "fit_s", "content_sha256",
)  # fmt: skip
FILTERABLE = (*LABELS, "law", "session", "file", "settings_id")


@dataclass(frozen=True)
class Entry:
    """One fit as the catalogue returns it.

    Attributes
    ----------
    row : dict
        The ``fits`` columns of :data:`COLUMNS`, plus ``labels`` (dict).
    terms : list of str
        Term names of the chosen law, in order.
    symbols, units : list of str
    shape : dict of str to float
        The chosen law's shape parameters (SI).
    mean : list of float
        Posterior mean of the coefficients, SI.
    cov : list of list of float, or None
        Their posterior covariance (None for a fit without a posterior, ``--method pinv``).
    """

    row: dict[str, Any]
    terms: list[str]
    symbols: list[str]
    units: list[str]
    shape: dict[str, float]
    mean: list[float]
    cov: list[list[float]] | None


def _finite(x: Any) -> float | None:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


@dataclass(frozen=True)
class FitRows:
    """What the catalogue stores of one parameter document, ready to insert: made by
    :func:`fit_rows` (in a batch, by the worker that fitted, so that the one writing
    process only inserts).

    Attributes
    ----------
    columns : dict
        The ``fits`` columns taken from the document (law, coefficients, evidence,
        validation, the document itself as JSON).
    coefficients : list of tuple
        ``coefficients`` rows without ``fit_id``: position, term, symbol, unit, mean,
        sd, ci95_low, ci95_high.
    evidence : list of tuple
        ``evidence`` rows without ``fit_id``: law, ln_evidence, probability, method.
    """

    columns: dict[str, Any]
    coefficients: list[tuple[Any, ...]]
    evidence: list[tuple[Any, ...]]


def fit_rows(document: Mapping[str, Any]) -> FitRows:
    """The catalogue's rows for a parameter document (:func:`~.params.document`)."""
    law = document.get("law") or {}
    terms = list(law.get("terms") or [])
    shape = {s["name"]: _finite(s.get("mean")) for s in law.get("shape") or []}
    noise = document.get("noise") or {}
    data = document.get("data") or {}
    val = document.get("validation") or {}
    name = law.get("name")
    ev = document.get("evidence") or {}
    probs = document.get("probabilities") or {}
    cov = law.get("cov")
    columns = {
        "law": name,
        "law_probability": _finite(law.get("probability")),
        "shape": json.dumps(shape),
        "coef_mean": json.dumps([_finite(t.get("mean")) for t in terms]),
        "coef_cov": json.dumps(cov) if cov is not None else None,
        "ln_evidence": _finite((ev.get(name) or {}).get("ln_evidence")) if name else None,
        "noise_sd_N": _finite(noise.get("sd")),
        "samples": data.get("samples"),
        "duration_s": _finite(data.get("duration_s")),
        "rate_hz": _finite(data.get("rate_hz")),
        "r2_held_out": _finite(val.get("r2_held_out")),
        "rms_held_out_N": _finite(val.get("rms_N")),
        "warnings": json.dumps(list(document.get("warnings") or [])),
        "document": json.dumps(document),
    }
    coefficients = [
        (
            j, t.get("term", ""), t.get("symbol", ""), t.get("unit", ""),
            _finite(t.get("mean")), _finite(t.get("sd")),
            *(_finite(c) for c in (t.get("ci95") or [None, None])),
        )
        for j, t in enumerate(terms)
    ]  # fmt: skip
    evidence = [
        (law_name, _finite(e.get("ln_evidence")), _finite(probs.get(law_name)), e.get("method"))
        for law_name, e in ev.items()
    ]
    return FitRows(columns, coefficients, evidence)


@dataclass(frozen=True)
class Fit:
    """One fit to store: the session, the settings, the labels and the rows of its
    parameter document (:func:`fit_rows`)."""

    key: str
    file: str
    session: str
    content_sha256: str
    settings: dict[str, Any]
    settings_id: str
    labels: dict[str, str]
    rows: FitRows
    fitted_utc: str
    fit_s: float | None = None


class Catalogue:
    """A catalogue file, opened (and created if ``create``) for reading and writing.

    Raises
    ------
    StorageError
        If the file is not a SQLite catalogue of tissuecli's, or cannot be opened.
    InputError
        If it does not exist and ``create`` is False.
    """

    def __init__(self, path: str | os.PathLike[str], *, create: bool = True) -> None:
        self.path = os.fspath(path)
        exists = os.path.exists(self.path)
        if not exists and not create:
            raise InputError(f"no catalogue {self.path}; make one with fit --catalogue")
        if not exists:
            check_outputs([Output(self.path, "--catalogue", appends=True)])
        try:
            self.db = sqlite3.connect(self.path, timeout=60.0)
            self.db.execute("PRAGMA foreign_keys = ON")
            if exists:
                self._check()
            else:
                self.db.executescript(SCHEMA)
                with self.db:
                    self.db.executemany(
                        "INSERT INTO meta VALUES (?, ?)",
                        [("format", FORMAT), ("version", str(VERSION)),
                         ("software", f"tissuecli {__version__}")],
                    )  # fmt: skip
        except sqlite3.Error as exc:
            raise StorageError(f"cannot open the catalogue {self.path}: {exc}") from None

    def _check(self) -> None:
        try:
            found = dict(self.db.execute("SELECT key, value FROM meta").fetchall())
        except sqlite3.DatabaseError:
            raise StorageError(
                f"{self.path} is not a tissuecli catalogue; give a new file or one "
                "written by fit --catalogue"
            ) from None
        if found.get("format") != FORMAT:
            raise StorageError(f"{self.path} is not a tissuecli catalogue (no format {FORMAT})")
        if int(found.get("version", "0")) > VERSION:
            raise StorageError(
                f"{self.path} is catalogue version {found.get('version')}; this tissuecli "
                f"reads up to {VERSION}: upgrade tissuecli"
            )

    def close(self) -> None:
        self.db.close()

    def __enter__(self) -> Catalogue:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- writing (the parent only) ---------------------------------------------------------

    def keys(self) -> set[str]:
        """Keys of every fit held."""
        return {k for (k,) in self.db.execute("SELECT key FROM fits")}

    def add(
        self,
        *,
        key: str,
        file: str,
        session: str,
        content_sha256: str,
        settings: Mapping[str, Any],
        settings_id: str,
        labels: Mapping[str, str],
        document: Mapping[str, Any] | FitRows,
        fitted_utc: str,
        fit_s: float | None = None,
    ) -> int:
        """Store one fit from its parameter document (:func:`~.params.document`, or the
        rows :func:`fit_rows` made of it), replacing a fit of the same key; the new row's
        id. Committed at once: see :meth:`add_many` for many fits in one transaction."""
        return self.add_many(
            [
                Fit(key, file, session, content_sha256, dict(settings), settings_id,
                    dict(labels), document if isinstance(document, FitRows)
                    else fit_rows(document), fitted_utc, fit_s)
            ]
        )[0]  # fmt: skip

    def add_many(self, fits: Sequence[Fit]) -> list[int]:
        """Store many fits in one transaction (one write to the disk for all of them),
        each replacing a fit of the same key; their new rows' ids, in order."""
        ids = []
        software = f"tissuecli {__version__}"
        try:
            with self.db:
                for f in fits:
                    r = f.rows
                    row = {
                        "key": f.key,
                        "file": f.file,
                        "session": f.session,
                        "content_sha256": f.content_sha256,
                        "settings_id": f.settings_id,
                        "settings": json.dumps(f.settings, sort_keys=True),
                        "fitted_utc": f.fitted_utc,
                        "software": software,
                        "fit_s": f.fit_s,
                        **{k: str(f.labels.get(k, "") or "") for k in LABELS},
                        "labels": json.dumps(f.labels, sort_keys=True),
                        **r.columns,
                    }
                    self.db.execute("DELETE FROM fits WHERE key = ?", (f.key,))
                    cur = self.db.execute(
                        f"INSERT INTO fits ({', '.join(row)}) VALUES ({', '.join('?' * len(row))})",
                        list(row.values()),
                    )
                    fit_id = int(cur.lastrowid or 0)
                    self.db.executemany(
                        "INSERT INTO coefficients VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                        [(fit_id, *c) for c in r.coefficients],
                    )
                    self.db.executemany(
                        "INSERT INTO evidence VALUES (?, ?, ?, ?, ?)",
                        [(fit_id, *e) for e in r.evidence],
                    )
                    ids.append(fit_id)
        except sqlite3.Error as exc:
            raise StorageError(f"cannot write the catalogue {self.path}: {exc}") from None
        return ids

    def keys_by_place(self, settings_id: str) -> dict[tuple[str, str], set[str]]:
        """The keys of the fits made with the settings ``settings_id``, by (file, session)
        as stored: what a batch expects an input to hash to if it is already fitted."""
        out: dict[tuple[str, str], set[str]] = {}
        for file, session, key in self.db.execute(
            "SELECT file, session, key FROM fits WHERE settings_id = ?", (settings_id,)
        ):
            out.setdefault((file, session), set()).add(key)
        return out

    def relabel(self, key: str, labels: Mapping[str, str]) -> bool:
        """Set the labels of the fit ``key`` (labels change without a refit); whether they
        changed."""
        new = {k: str(labels.get(k, "") or "") for k in LABELS}
        blob = json.dumps(dict(labels), sort_keys=True)
        with self.db:
            cur = self.db.execute(
                f"UPDATE fits SET {', '.join(f'{k} = ?' for k in new)}, labels = ? "
                f"WHERE key = ? AND NOT ({' AND '.join(f'{k} IS ?' for k in new)} "
                "AND labels IS ?)",
                [*new.values(), blob, key, *new.values(), blob],
            )
        return cur.rowcount > 0

    # -- reading ---------------------------------------------------------------------------

    def entries(self, where: Mapping[str, str] | None = None) -> list[Entry]:
        """The fits whose columns equal ``where``'s values (keys in :data:`FILTERABLE`),
        oldest first."""
        clauses, args = [], []
        for k, v in (where or {}).items():
            if k not in FILTERABLE:
                raise InputError(
                    f"cannot filter on {k!r}; filter on {', '.join(FILTERABLE)} (e.g. tissue=liver)"
                )
            clauses.append(f"{k} = ?")
            args.append(v)
        sql = f"SELECT {', '.join(COLUMNS)}, labels, shape, coef_mean, coef_cov, id FROM fits"
        if clauses:
            sql += " WHERE " + " AND ".join(clauses)
        sql += " ORDER BY id"
        out = []
        try:
            rows = self.db.execute(sql, args).fetchall()
            coefs: dict[int, list[tuple[str, str, str]]] = {}
            for fit_id, term, symbol, unit in self.db.execute(
                "SELECT fit_id, term, symbol, unit FROM coefficients ORDER BY fit_id, position"
            ):
                coefs.setdefault(fit_id, []).append((term, symbol, unit))
        except sqlite3.DatabaseError as exc:
            raise StorageError(f"cannot read the catalogue {self.path}: {exc}") from None
        n = len(COLUMNS)
        for r in rows:
            row = dict(zip(COLUMNS, r[:n], strict=True))
            labels, shape, mean, cov, fit_id = r[n:]
            row["labels"] = json.loads(labels)
            c = coefs.get(fit_id, [])
            out.append(
                Entry(
                    row=row,
                    terms=[t for t, _, _ in c],
                    symbols=[s for _, s, _ in c],
                    units=[u for _, _, u in c],
                    shape={k: float(v) for k, v in json.loads(shape).items() if v is not None},
                    mean=[math.nan if v is None else float(v) for v in json.loads(mean or "[]")],
                    cov=json.loads(cov) if cov else None,
                )
            )
        return out

    def settings(self) -> dict[str, str]:
        """Each settings id with its settings (JSON)."""
        return dict(self.db.execute("SELECT DISTINCT settings_id, settings FROM fits"))


def table(entries: Sequence[Entry]) -> tuple[list[str], list[list[Any]]]:
    """One row per fit: :data:`COLUMNS`, then each coefficient's mean and SD by symbol
    with its unit (``K_mean [N/m]``), empty where a fit's law lacks it."""
    coef_cols: dict[str, str] = {}
    for e in entries:
        for s, u in zip(e.symbols, e.units, strict=True):
            coef_cols.setdefault(s, u)
    header = list(COLUMNS)
    for s, u in coef_cols.items():
        header += [f"{s}_mean [{u}]", f"{s}_sd [{u}]"]
    rows = []
    for e in entries:
        sd = (
            [math.sqrt(max(e.cov[j][j], 0.0)) for j in range(len(e.symbols))]
            if e.cov
            else [None] * len(e.symbols)
        )
        by = {s: (m, d) for s, m, d in zip(e.symbols, e.mean, sd, strict=True)}
        row = [e.row[c] for c in COLUMNS]
        for s in coef_cols:
            row += list(by.get(s, (None, None)))
        rows.append(row)
    return header, rows


def export(entries: Sequence[Entry], path: str | os.PathLike[str], fmt: str) -> None:
    """Write :func:`table` to ``path`` as ``csv`` or ``parquet`` (pyarrow); never over an
    existing file."""
    if os.path.lexists(path):
        raise InputError(
            f"--out {path} exists; an export never replaces a file: choose another path"
        )
    check_outputs([Output(path, "--out")])
    header, rows = table(entries)
    if fmt == "csv":
        try:
            with atomic_file(path) as fh:
                w = csv.writer(fh)
                w.writerow(header)
                w.writerows([["" if v is None else v for v in r] for r in rows])
        except OSError as exc:
            raise StorageError(f"cannot write {path}: {os_error_cause(exc)}") from None
        return
    if fmt != "parquet":
        raise InputError(f"unknown export format {fmt!r}; choose csv or parquet")
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        raise InputError(
            "--export parquet needs pyarrow: pip install pyarrow, or use --export csv"
        ) from None
    columns = {h: [r[i] for r in rows] for i, h in enumerate(header)}
    tmp = f"{os.fspath(path)}.part"
    try:
        pq.write_table(pa.table(columns), tmp)
        if os.path.exists(path):
            raise InputError(f"--out {path} appeared while exporting; nothing replaced")
        os.replace(tmp, path)
    except OSError as exc:
        raise StorageError(f"cannot write {path}: {os_error_cause(exc)}") from None
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def parse_where(items: Iterable[str]) -> dict[str, str]:
    """``["tissue=liver", ...]`` as a dict; one line on a bad item."""
    out = {}
    for item in items:
        k, sep, v = item.partition("=")
        if not sep or not k.strip():
            raise InputError(f"--where {item!r}: give COLUMN=VALUE, e.g. tissue=liver")
        out[k.strip()] = v.strip()
    return out
