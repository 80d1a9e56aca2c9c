"""The ``catalogue``, ``compare`` and ``classify`` services: the catalogue's fits read as
one scalar quantity per session and set in the hierarchical model of
:mod:`tissuecli.identify.hierarchy`."""

from __future__ import annotations

import math
import os
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..core.errors import InputError
from ..core.terms import Law
from ..core.units import parse_quantity
from ..formats.atomic import write_text_atomic
from ..formats.catalogue import Catalogue, Entry, export, parse_where, table
from ..formats.jsonfile import write_json
from ..formats.outputs import Output, check_outputs
from ..identify.hierarchy import Estimates, Hierarchy, classify_probabilities, steady_force

#: the prior SD of the group means on the log scale: a tissue's typical value within a
#: factor e of the all-group mean (one SD); jaw-scale stiffness spans 100-1350 N/m
LOG_PRIOR_SD = 1.0


def list_catalogue(
    path: str | os.PathLike[str],
    where: Iterable[str] = (),
    *,
    export: str | None = None,
    out: str | os.PathLike[str] | None = None,
) -> tuple[list[str], list[list[Any]]]:
    """The catalogue's fits as a table (:func:`~tissuecli.formats.catalogue.table`),
    filtered by ``where`` (``tissue=liver``); exported to ``out`` if asked."""
    with Catalogue(path, create=False) as cat:
        entries = cat.entries(parse_where(where))
    if export is not None:
        assert out is not None
        _export(entries, out, export)
    return table(entries)


def _export(entries: Sequence[Entry], out: str | os.PathLike[str], fmt: str) -> None:
    export(entries, out, fmt)


# -- quantities ----------------------------------------------------------------------------


@dataclass(frozen=True)
class Quantity:
    """A scalar read from each fit's posterior: a coefficient (``symbol``) or the force at
    ``closure_m`` while closing at ``speed_m_s``."""

    text: str
    symbol: str | None = None
    closure_m: float = 0.0
    speed_m_s: float = 0.0

    @property
    def label(self) -> str:
        if self.symbol is not None:
            return f"coefficient {self.symbol}"
        return (
            f"force at {self.closure_m * 1e3:g} mm closure, closing at "
            f"{self.speed_m_s * 1e3:g} mm/s"
        )

    def of(self, e: Entry) -> tuple[float, float] | None:
        """Posterior mean and variance in this fit, or None if it has no posterior or its
        law lacks the coefficient."""
        if e.cov is None or not e.terms:
            return None
        if self.symbol is not None:
            if self.symbol not in e.symbols:
                return None
            j = e.symbols.index(self.symbol)
            return e.mean[j], float(e.cov[j][j])
        law = Law.of(e.terms)
        if law.shape_names:
            law = law.bind(e.shape)
        return steady_force(law, e.mean, e.cov, self.closure_m, self.speed_m_s)

    def unit(self, entries: Sequence[Entry]) -> str:
        if self.symbol is None:
            return "N"
        for e in entries:
            if self.symbol in e.symbols:
                return e.units[e.symbols.index(self.symbol)]
        return ""


def parse_quantity_spec(text: str) -> Quantity:
    """``K`` (a coefficient) or ``force:x=3mm,v=20mm/s`` (``v`` may be 0)."""
    text = text.strip()
    if not text.startswith("force"):
        if not re.fullmatch(r"[A-Za-z][A-Za-z0-9]*", text):
            raise InputError(
                f"--quantity {text[:30]!r}: give a coefficient such as K or force:x=3mm,v=20mm/s"
            )
        return Quantity(text, symbol=text)
    _, _, spec = text.partition(":")
    parts = dict(p.split("=", 1) for p in spec.split(",") if "=" in p)
    if set(parts) - {"x", "v"} or "x" not in parts:
        raise InputError(
            f"--quantity {text[:40]!r}: give force:x=CLOSURE,v=SPEED, e.g. force:x=3mm,v=20mm/s"
        )
    x = parse_quantity(parts["x"], "length", "--quantity x")
    v_text = parts.get("v", "0").strip()
    if v_text in ("0", "0.0"):
        v = 0.0
    else:
        num = v_text.removesuffix("/s")
        if num == v_text:
            raise InputError(f"--quantity v={v_text[:20]!r}: give a speed such as 20mm/s or 0")
        v = parse_quantity(num, "length", "--quantity v")
    return Quantity(text, closure_m=x, speed_m_s=v)


def _label(e: Entry, by: str) -> str:
    value = e.row.get(by) if by in e.row else e.row["labels"].get(by, "")
    return str(value or "")


def select(
    catalogue: str | os.PathLike[str],
    where: Iterable[str],
    settings_id: str | None,
) -> list[Entry]:
    """The fits to compare: filtered, and all made with one set of settings."""
    filters = parse_where(where)
    if settings_id:
        filters["settings_id"] = settings_id
    with Catalogue(catalogue, create=False) as cat:
        entries = cat.entries(filters)
    if not entries:
        raise InputError(f"no fits in {catalogue} match; list them with tissuecli catalogue")
    ids: dict[str, int] = {}
    for e in entries:
        ids[e.row["settings_id"]] = ids.get(e.row["settings_id"], 0) + 1
    if len(ids) > 1:
        listed = ", ".join(f"{k} ({n} fits)" for k, n in ids.items())
        raise InputError(
            f"the fits were made with {len(ids)} different settings ({listed}); pick one "
            "with --settings ID"
        )
    return entries


def estimates(
    entries: Sequence[Entry], by: str, quantity: Quantity, scale: str
) -> tuple[Estimates, list[str], list[str]]:
    """The sessions' estimates of ``quantity`` (on ``scale``), their names, and notes on
    the fits left out."""
    values, var, groups, specimens, names = [], [], [], [], []
    no_label = no_value = 0
    for e in entries:
        g = _label(e, by)
        if not g:
            no_label += 1
            continue
        got = quantity.of(e)
        if got is None or not all(map(math.isfinite, got)):
            no_value += 1
            continue
        m, v = got
        if scale == "log":
            if m <= 0:
                raise InputError(
                    f"{quantity.label} is {m:.3g} in {e.row['session']}: not positive, so it "
                    "has no logarithm; compare with --scale linear"
                )
            m, v = math.log(m), v / m**2
        values.append(m)
        var.append(v)
        groups.append(g)
        specimens.append(e.row["specimen"] or e.row["session"])
        names.append(e.row["session"])
    notes = []
    if no_label:
        notes.append(f"{no_label} fit(s) without a {by} label left out")
    if no_value:
        what = "a posterior" if quantity.symbol is None else f"the coefficient {quantity.symbol}"
        notes.append(f"{no_value} fit(s) without {what} left out")
    if len(set(groups)) < 1 or len(values) < 2:
        raise InputError(
            f"fewer than two sessions with a {by} label and {quantity.label}; label the "
            "sessions (HDF5 attributes or fit --manifest) or choose another --quantity"
        )
    return Estimates.of(values, var, groups, specimens), names, notes


def _model(e: Estimates, scale: str, prior_sd: float | None) -> Hierarchy:
    if prior_sd is None and scale == "log":
        prior_sd = LOG_PRIOR_SD
    return Hierarchy(prior_sd=prior_sd).fit(e)


# -- compare -------------------------------------------------------------------------------


def compare_catalogue(
    catalogue: str | os.PathLike[str],
    *,
    by: str = "tissue",
    where: Iterable[str] = (),
    settings_id: str | None = None,
    quantity: str = "force:x=3mm,v=20mm/s",
    scale: str = "log",
    prior_sd: float | None = None,
    report: str | os.PathLike[str] | None = None,
    json_out: str | os.PathLike[str] | None = None,
    force: bool = False,
) -> dict[str, Any]:
    """Compare the catalogue's groups (sessions labelled ``by``) on one quantity.

    ``prior_sd`` is the SD of the group means' prior on the modelled scale (default:
    :data:`LOG_PRIOR_SD` on the log scale; on the linear scale the values' own spread,
    see :class:`~tissuecli.identify.hierarchy.Hierarchy`).

    Returns
    -------
    dict
        The comparison, JSON-ready (docs/formats.md): ``quantity``, ``scale``, ``groups``,
        ``pairs``, ``specimens``, ``sessions``, ``variation``, ``notes``.
    """
    check_outputs(
        [Output(report, "--report") if report else None,
         Output(json_out, "--json") if json_out else None],
        [catalogue],
        force=force,
    )  # fmt: skip
    q = parse_quantity_spec(quantity)
    entries = select(catalogue, where, settings_id)
    est, names, notes = estimates(entries, by, q, scale)
    if len(est.groups) < 2:
        raise InputError(f"only one {by} ({est.groups[0]}) among the fits: nothing to compare")
    h = _model(est, scale, prior_sd)
    back = math.exp if scale == "log" else (lambda u: u)
    groups = []
    for gi, g in enumerate(est.groups):
        lo, hi = h.group_interval(gi)
        groups.append(
            {
                "name": g,
                "specimens": int(np.sum(est.specimen_group == gi)),
                "sessions": int(np.sum(est.group == gi)),
                "mean": back(h.group_mean_[gi]),
                "ci95": [back(lo), back(hi)],
                "posterior_mean_scaled": float(h.group_mean_[gi]),
                "posterior_sd_scaled": float(h.group_sd_[gi]),
            }
        )
    pairs = []
    for i in range(len(est.groups)):
        for j in range(len(est.groups)):
            if i >= j:
                continue
            a, b = (i, j) if h.group_mean_[i] >= h.group_mean_[j] else (j, i)
            d, lo, hi = h.difference_interval(a, b)
            ln_bf = h.ln_bayes_same(a, b)
            pairs.append(
                {
                    "a": est.groups[a],
                    "b": est.groups[b],
                    "p_a_greater": h.prob_greater(a, b),
                    "difference": back(d) if scale == "log" else d,
                    "ci95": [back(lo), back(hi)] if scale == "log" else [lo, hi],
                    "difference_kind": "ratio a/b" if scale == "log" else "a - b",
                    "ln_bayes_same": ln_bf,
                    "verdict": "same" if ln_bf > 0 else "different",
                }
            )
    specimens = [
        {
            "name": s.split("/", 1)[1],
            "group": est.groups[int(est.specimen_group[k])],
            "mean": back(h.specimen_mean_[k]),
            "ci95": [
                back(h.specimen_mean_[k] - 1.96 * h.specimen_sd_[k]),
                back(h.specimen_mean_[k] + 1.96 * h.specimen_sd_[k]),
            ],
        }
        for k, s in enumerate(est.specimens)
    ]
    sessions = [
        {
            "name": names[n],
            "group": est.groups[int(est.group[n])],
            "specimen": est.specimens[int(est.specimen[n])].split("/", 1)[1],
            "mean": back(est.value[n]),
            "ci95": [
                back(est.value[n] - 1.96 * math.sqrt(est.var[n])),
                back(est.value[n] + 1.96 * math.sqrt(est.var[n])),
            ],
        }
        for n in range(est.value.size)
    ]
    result = {
        "format": "tissuecli-comparison",
        "version": 1,
        "quantity": {"spec": q.text, "label": q.label, "unit": q.unit(entries)},
        "scale": scale,
        "by": by,
        "settings_id": entries[0].row["settings_id"],
        "model": {
            "prior_mean_scaled": h.m0_,
            "prior_sd_scaled": h.s0_,
            "ln_evidence": h.ln_evidence_,
        },
        "variation": {
            "between_specimens_sd_scaled": h.tau_mean_,
            "between_sessions_sd_scaled": h.omega_mean_,
        },
        "groups": groups,
        "pairs": pairs,
        "specimens": specimens,
        "sessions": sessions,
        "notes": notes,
    }
    if json_out is not None:
        write_json(json_out, result)
    if report is not None:
        from ..report.compare import render_comparison  # matplotlib only for a report

        write_text_atomic(report, render_comparison(result))
    return result


def compare_lines(c: dict[str, Any]) -> list[str]:
    """A terminal summary of :func:`compare_catalogue`'s result."""
    q, unit = c["quantity"], c["quantity"]["unit"]
    n_spec = sum(g["specimens"] for g in c["groups"])
    lines = [
        f"{q['label']} ({unit}), {c['scale']} scale: {len(c['sessions'])} sessions of "
        f"{n_spec} specimens in {len(c['groups'])} groups by {c['by']}"
    ]
    w = max(6, *(len(g["name"]) for g in c["groups"]))
    lines.append(f"{'group':<{w}}  specimens  sessions  {'mean':>10}  95 % interval")
    for g in c["groups"]:
        lo, hi = g["ci95"]
        lines.append(
            f"{g['name']:<{w}}  {g['specimens']:9d}  {g['sessions']:8d}  {g['mean']:10.4g}  "
            f"[{lo:.4g}, {hi:.4g}]"
        )
    v = c["variation"]
    if c["scale"] == "log":
        lines.append(
            f"specimens of a group differ by {100 * v['between_specimens_sd_scaled']:.1f} % "
            f"(SD), sessions of a specimen by {100 * v['between_sessions_sd_scaled']:.1f} %"
        )
    else:
        lines.append(
            f"specimens of a group differ by {v['between_specimens_sd_scaled']:.4g} {unit} "
            f"(SD), sessions of a specimen by {v['between_sessions_sd_scaled']:.4g} {unit}"
        )
    kind = "A/B" if c["scale"] == "log" else "A - B"
    lines.append(
        f"{'A':<{w}}  {'B':<{w}}  P(A > B)  {kind:>8}  95 % interval        ln BF(same)  verdict"
    )
    for p in c["pairs"]:
        lo, hi = p["ci95"]
        lines.append(
            f"{p['a']:<{w}}  {p['b']:<{w}}  {p['p_a_greater']:8.3f}  {p['difference']:8.4g}  "
            f"{f'[{lo:.4g}, {hi:.4g}]':<20} {p['ln_bayes_same']:11.1f}  {p['verdict']}"
        )
    lines.extend(f"note: {n}" for n in c["notes"])
    return lines


# -- classify ------------------------------------------------------------------------------


def classify_file(
    path: str | os.PathLike[str],
    *,
    session: str | None,
    catalogue: str | os.PathLike[str],
    by: str = "tissue",
    where: Iterable[str] = (),
    settings_id: str | None = None,
    quantities: Sequence[str] = ("force:x=3mm,v=20mm/s",),
    scale: str = "log",
    prior_sd: float | None = None,
) -> tuple[list[str], list[tuple[str, list[float]]]]:
    """Fit each session of ``path`` with the catalogue's settings and give the
    probability of each group.

    Returns
    -------
    groups : list of str
    rows : list of (session name, probabilities)
    """
    import json

    from ..formats.catalogue import Catalogue as _Cat
    from .batch import SETTINGS, expand_inputs
    from .transfer import load_session

    entries = select(catalogue, where, settings_id)
    qs = [parse_quantity_spec(t) for t in quantities]
    with _Cat(catalogue, create=False) as cat:
        settings = json.loads(cat.settings()[entries[0].row["settings_id"]])
    models, names = [], None
    for q in qs:
        est, _, _ = estimates(entries, by, q, scale)
        if names is None:
            names = list(est.groups)
        elif list(est.groups) != names:
            raise InputError(
                "the quantities cover different groups; choose quantities every fit has"
            )
        models.append(_model(est, scale, prior_sd))
    assert names is not None
    from ..formats.params import _finite as finite_tree
    from ..formats.params import document
    from ..identify.outcome import fit_session

    rows = []
    for item in expand_inputs([os.fspath(path)], session):
        data, _ = load_session(item.file, item.session)
        outcome = fit_session(data, **{k: settings[k] for k in SETTINGS if k in settings})
        doc = finite_tree(document(outcome))
        law = doc.get("law") or {}
        entry = Entry(
            row={},
            terms=[t["term"] for t in law.get("terms", [])],
            symbols=[t["symbol"] for t in law.get("terms", [])],
            units=[t["unit"] for t in law.get("terms", [])],
            shape={s["name"]: s["mean"] for s in law.get("shape") or []},
            mean=[t["mean"] for t in law.get("terms", [])],
            cov=law.get("cov"),
        )
        lps = []
        for q, h in zip(qs, models, strict=True):
            got = q.of(entry)
            if got is None:
                raise InputError(f"{item}: its fit has no {q.label}; choose another --quantity")
            m, v = got
            if scale == "log":
                if m <= 0:
                    raise InputError(f"{item}: {q.label} is not positive; use --scale linear")
                m, v = math.log(m), v / m**2
            lps.append(h.ln_predictive([m], [v]))
        rows.append((data.name, [float(p) for p in classify_probabilities(lps)[0]]))
    return names, rows
