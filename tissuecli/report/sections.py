"""The report's sections as HTML: header and formula, parameter tables, model comparison,
pseudoinverse tables, diagnostics, how to read it, and provenance."""

from __future__ import annotations

import math
import platform
from collections.abc import Sequence
from datetime import datetime, timezone
from importlib import metadata

import numpy as np
from numpy.typing import NDArray

from .._version import __version__
from ..core.terms import Law, Term
from ..identify.bayes import DECISIVE, BayesianFit, ModelResult
from ..identify.outcome import FitOutcome
from ..identify.pinv import WindowedPinv
from .figures import Series
from .numbers import (
    CONVENIENT,
    at_place,
    convenient,
    esc,
    fixed,
    jeffreys,
    place,
    probability,
    sig,
    unit_html,
    with_sd,
)

Array = NDArray[np.float64]
SOFTWARE = f"tissuecli {__version__}"


ROLE = {
    "stiffness": "stiffness",
    "damping": "damping",
    "friction": "dry friction",
    "inertia": "moving mass",
    "offset": "offset",
}


CSS = """
body{font-family:-apple-system,"Segoe UI",Helvetica,Arial,sans-serif;color:#1d1d1d;
 max-width:1200px;margin:1.5em auto;padding:0 1em;line-height:1.45}
h1{font-size:1.55em;margin-bottom:.2em}h2{font-size:1.25em;border-bottom:1px solid #ccc;
 padding-bottom:.2em;margin-top:1.8em}h3{font-size:1.05em;margin-top:1.4em}
table{border-collapse:collapse;margin:.6em 0;font-size:.92em}
th,td{border:1px solid #d4d4d4;padding:.25em .55em;vertical-align:top}
th{background:#f2f2f2;text-align:left}td.n{text-align:right;font-variant-numeric:tabular-nums;
 white-space:nowrap}tr.best td{background:#eef6ee}
.wide{overflow-x:auto}.meta th{width:13em}
.formula{font-size:1.3em;font-family:"Cambria Math",Cambria,Georgia,serif;background:#f7f7f7;
 border-left:4px solid #1f5fa8;padding:.45em .8em;margin:.6em 0}
.units{color:#555;font-size:.9em}
.box{border:1px solid;border-radius:4px;padding:.5em .9em;margin:.8em 0}
.warn{background:#fff6df;border-color:#e0b243}.ok{background:#eef6ee;border-color:#8dbf8d}
.info{background:#eef3fa;border-color:#9fb8dc}
.box ul{margin:.3em 0;padding-left:1.3em}
figure{margin:1.2em 0;min-width:0}figure img{max-width:100%;height:auto;border:1px solid #e4e4e4;
 box-sizing:border-box}
figcaption{font-size:.92em;color:#333;margin-top:.3em}
.small{font-size:.85em;color:#444}.small ul{margin:.2em 0;padding-left:1.1em}
footer{margin-top:2.5em;border-top:1px solid #ccc;padding-top:.6em;font-size:.85em;color:#444}
code{font-family:Consolas,Menlo,monospace;font-size:.95em}
.plots{display:grid;grid-template-columns:repeat(auto-fit,minmax(min(100%,440px),1fr));
 gap:0 1.4em;align-items:start}.plots figure{margin:.6em 0}.plots h3{margin:.2em 0}
.plots .span{grid-column:1/-1}
details{margin:.6em 0}summary{cursor:pointer;color:#1f5fa8}
table.full{width:100%}td.note{min-width:16em;max-width:30em}
td.why{min-width:18em}.lead{font-size:1.1em;margin:.4em 0}
"""


def table(
    head: Sequence[str],
    rows: Sequence[Sequence[str]],
    numeric: Sequence[bool],
    classes: Sequence[str] | None = None,
    *,
    cell_classes: Sequence[str] | None = None,
    full: bool = False,
) -> str:
    """A table; ``head`` is text (escaped), cells are markup already; ``cell_classes``
    per column (e.g. ``note`` for a wide text column), ``full`` spans the page."""
    th = "".join(f"<th>{esc(h)}</th>" for h in head)
    extra = list(cell_classes) if cell_classes else [""] * len(head)
    body = []
    for k, row in enumerate(rows):
        cls = f' class="{classes[k]}"' if classes and classes[k] else ""
        tds = "".join(
            f'<td class="{" ".join(filter(None, ("n" if num else "", more)))}">{c}</td>'
            if num or more else f"<td>{c}</td>"
            for c, num, more in zip(row, numeric, extra, strict=True)
        )  # fmt: skip
        body.append(f"<tr{cls}>{tds}</tr>")
    wide = ' class="full"' if full else ""
    return f'<div class="wide"><table{wide}><tr>{th}</tr>{"".join(body)}</table></div>'


def meta_table(items: Sequence[tuple[str, str]]) -> str:
    rows = "".join(f"<tr><th>{esc(k)}</th><td>{v}</td></tr>" for k, v in items)
    return f'<table class="meta">{rows}</table>'


def term_cell(t: Term) -> str:
    """A coefficient's row label: its symbol, its term and its role."""
    return (
        f"<b>{esc(t.symbol)}</b> · {esc(t.label)} <span class='small'>"
        f"({esc(ROLE.get(t.role, t.role))})</span>"
    )


def law_text(law: Law) -> str:
    """The law in symbols: ``K x + S ẋ + M ẍ``."""
    return " + ".join(
        t.symbol if t.role == "offset" else f"{t.symbol} {t.label}" for t in law.terms
    )


def formula(model: Law, values: Sequence[str]) -> str:
    terms = " + ".join(
        v if t.role == "offset" else f"{v}&#8201;{esc(t.label)}"
        for t, v in zip(model.terms, values, strict=True)
    )
    units = ", ".join(f"{esc(t.symbol)} in {esc(unit_html(t.unit))}" for t in model.terms)
    return (
        f'<div class="formula">F = {terms}</div>'
        f'<p class="units">F in N, x in m, ẋ in m/s, ẍ in m/s²; {units}.</p>'
    )


def session_table(outcome: FitOutcome, s: Series) -> str:
    """What was fitted and how: the session's figures and the method."""
    session = outcome.session
    if outcome.bayes is not None and outcome.pinv is not None:
        how = (
            f"Bayesian model choice over {len(outcome.bayes.results_)} law(s), and the "
            "windowed pseudoinverse"
        )
    elif outcome.bayes is not None:
        how = f"Bayesian model choice over {len(outcome.bayes.results_)} law(s)"
    else:
        how = "windowed pseudoinverse (point estimates, no uncertainty)"
    x_mm = session.position * 1e3
    items = [
        ("Session", esc(session.name or "(unnamed)")),
        ("File", esc(session.meta.get("file") or "—")),
        ("Tissue", esc(session.meta.get("tissue") or "—")),
        ("Samples", esc(f"{len(session):,}")),
        ("Duration", f"{sig(session.duration_s, 4)} s"),
        ("Sample rate", f"{sig(session.rate_hz, 4)} Hz"),
        ("Jaw closure range", f"{sig(float(x_mm.min()), 3)} to {sig(float(x_mm.max()), 3)} mm"),
        (
            "Force range",
            f"{sig(float(session.force.min()), 3)} to {sig(float(session.force.max()), 3)} N",
        ),
        ("Identification", esc(how)),
        ("Software", esc(SOFTWARE)),
    ]
    return meta_table(items)


def header(outcome: FitOutcome, s: Series) -> str:
    """The title, the chosen law and its formula: what the reader came for."""
    session = outcome.session
    model = s.model
    facts = (
        f"{len(session):,} samples, {sig(session.duration_s, 4)} s at {sig(session.rate_hz, 4)} Hz"
    )
    if session.meta.get("tissue"):
        facts = f"{esc(session.meta['tissue'])}; {facts}"
    if outcome.bayes is not None:
        best = outcome.bayes.best_
        post = best.posterior
        assert post is not None
        values = [with_sd(post.mean[j], post.sd[j]) for j in range(len(best.model.terms))]
        chosen = (
            f"<p class='lead'>Chosen law: <b>{esc(best.name)}</b> "
            f"(posterior probability {probability(ln_probabilities(outcome.bayes)[0])} among "
            f"{len(outcome.bayes.results_)} laws), posterior means:</p>"
        )
    else:
        pinv = outcome.pinv
        assert pinv is not None
        values = [sig(v, 4) for v in pinv.params_]
        chosen = (
            f"<p class='lead'>Form: <b>{esc(pinv.model_.name)}</b> (given, not chosen), "
            "estimate of the best window:</p>"
        )
    title = f"Tissue identification: {session.name or 'session'}"
    return f"<h1>{esc(title)}</h1><p class='small'>{facts}</p>{chosen}{formula(model, values)}"


def folded(summary: str, body: str, *, open_: bool = False) -> str:
    """``body`` folded under a one-line ``summary`` (HTML ``<details>``, no script)."""
    return f"<details{' open' if open_ else ''}><summary>{esc(summary)}</summary>{body}</details>"


def law_name(name: str) -> str:
    """A law's name, escaped, that may wrap after each ``+``."""
    return "+<wbr>".join(esc(part) for part in name.split("+"))


def ln_probabilities(est: BayesianFit) -> Array:
    """ln posterior probability of each law (equal prior odds), in ``results_`` order."""
    ln_z = np.array([r.ln_evidence for r in est.results_])
    top = ln_z.max()
    return ln_z - (top + np.log(np.sum(np.exp(ln_z - top))))


def warnings_box(outcome: FitOutcome) -> str:
    warnings = outcome.warnings
    if outcome.bayes is None:
        warnings.append(
            "Point estimates only: the windowed pseudoinverse gives no uncertainty "
            "and no model choice; the Bayesian fit gives both."
        )
        items = "".join(f"<li>{esc(w)}</li>" for w in warnings)
        return f'<div class="box warn"><b>Note</b><ul>{items}</ul></div>'
    if not warnings:
        return (
            '<div class="box ok"><b>No warnings.</b> Every coefficient of the chosen law is '
            "identified: its 95 % interval stays clear of zero and its SD is below 25 % "
            "of its value.</div>"
        )
    items = "".join(f"<li>{esc(w)}</li>" for w in warnings)
    return f'<div class="box warn"><b>Warnings ({len(warnings)})</b><ul>{items}</ul></div>'


def parameters_bayes(est: BayesianFit, s: Series) -> str:
    best = est.best_
    post = best.posterior
    assert post is not None
    rows = []
    for j, t in enumerate(best.model.terms):
        mean, sd = float(post.mean[j]), float(post.sd[j])
        lo, hi = (float(q) for q in post.ci95[j])
        digit = place(sd)
        conv = convenient(mean, t.unit)
        if conv is not None:
            cname, factor = CONVENIENT[t.unit]
            cplace = digit + round(math.log10(factor))
            conv_cell = (
                f"{at_place(mean * factor, cplace)} "
                f"[{at_place(lo * factor, cplace)}, {at_place(hi * factor, cplace)}]"
                f" {esc(cname)}"
            )
        else:
            conv_cell = "—"
        rel = f"{100 * sd / abs(mean):.2g} %" if mean != 0 else "—"
        rows.append(
            [
                term_cell(t),
                with_sd(mean, sd),
                sig(sd, 2),
                f"[{at_place(lo, digit)}, {at_place(hi, digit)}]",
                esc(unit_html(t.unit)),
                rel,
                conv_cell,
            ]
        )
    for name, sp in (best.shape_posterior or {}).items():
        # Shape parameters are marginalised, not point-estimated: their posterior comes
        # from the quadrature weights, so they get the same columns as the coefficients.
        mean, sd = float(sp["mean"]), float(sp["sd"])
        lo, hi = (float(q) for q in sp["ci95"])
        digit = place(sd) if sd > 0 else place(abs(mean) * 1e-3 or 1e-3)
        declared = best.model.shape_parameter(name)
        unit = declared.unit
        rows.append(
            [
                f"<b>{esc(name)}</b> {esc(declared.meaning)}",
                with_sd(mean, sd),
                sig(sd, 2),
                f"[{at_place(lo, digit)}, {at_place(hi, digit)}]",
                esc(unit_html(unit)),
                f"{100 * sd / abs(mean):.2g} %" if mean != 0 else "—",
                "—",
            ]
        )
    draws = post.samples[:, -1] if post.samples.shape[0] > 1 else np.empty(0)
    sig_sd = float(np.std(draws, ddof=1)) * 1e3 if draws.size > 1 else float("nan")
    lo, hi = (1e3 * q for q in post.sigma_ci95)
    digit = place(sig_sd)
    rows.append(
        [
            "<b>σ</b> noise SD of the filtered force",
            with_sd(post.sigma_mean * 1e3, sig_sd),
            sig(sig_sd, 2),
            f"[{at_place(lo, digit)}, {at_place(hi, digit)}]",
            "mN",
            f"{100 * sig_sd / (post.sigma_mean * 1e3):.2g} %",
            "—",
        ]
    )
    grid = table(
        [
            "parameter",
            "mean",
            "SD",
            "95 % interval",
            "unit (SI)",
            "SD / mean",
            "mean [95 % interval], convenient units",
        ],
        rows,
        [False, True, True, True, False, True, True],
    )
    note = (
        f"<p class='small'>Form <b>{esc(best.name)}</b>; posterior from "
        f"{esc('the closed form (exact)' if best.status == 'exact' else 'emcee sampling')}. "
        "Means and intervals are shown to the second significant digit of their SD. "
        "The noise SD σ is of the force after the same smoothing as the kinematics"
    )
    if s.expected_sd is not None and abs(s.expected_sd / post.sigma_mean - 1) > 0.01:
        rms = float(np.sqrt(np.mean(s.residual**2)))
        note += (
            f"; with the errors-in-variables correction it excludes position noise, which "
            f"the fit expects to raise the residual SD to {sig(s.expected_sd * 1e3, 3)} mN "
            f"(observed residual RMS {sig(rms * 1e3, 3)} mN)"
        )
    return grid + note + ".</p>"


def parameters_pinv(pinv: WindowedPinv) -> str:
    rows = []
    for j, t in enumerate(pinv.model_.terms):
        w = pinv.windows_[:, j]
        spread = float(np.std(w, ddof=1)) if w.size > 1 else float("nan")
        conv = convenient(float(pinv.params_[j]), t.unit)
        rows.append(
            [
                term_cell(t),
                sig(float(pinv.params_[j]), 4),
                sig(float(pinv.pooled_[j]), 4),
                sig(float(np.mean(w)), 4),
                sig(spread, 2),
                esc(unit_html(t.unit)),
                f"{sig(conv[1], 4)} {esc(conv[0])}" if conv else "—",
            ]
        )
    return table(
        [
            "parameter",
            "best window",
            "all windows pooled",
            "mean over windows",
            "SD over windows",
            "unit (SI)",
            "best window, convenient units",
        ],
        rows,
        [False, True, True, True, True, False, True],
    )


#: laws the comparison shows open: the best, then the next while they hold probability
SHOWN_LAWS = (3, 5)
#: a law with less posterior probability than this is not shown open beyond the first 3
SHOWN_PROBABILITY = 1e-3


def comparison(est: BayesianFit) -> str:
    """The best few laws with their probabilities and one short reason each, then the
    full table folded."""
    results = est.results_
    ln_p = ln_probabilities(est)
    least, most = SHOWN_LAWS
    shown = [
        k for k in range(len(results))
        if k < least or (k < most and math.exp(ln_p[k]) >= SHOWN_PROBABILITY)
    ]  # fmt: skip
    top = results[0].ln_evidence
    rows = [
        [
            f"<b>{law_name(results[k].name)}</b>",
            probability(float(ln_p[k])),
            fixed(top - results[k].ln_evidence),
            esc(short_reason(results[k], est.best_, top - results[k].ln_evidence)),
        ]
        for k in shown
    ]
    classes = ["best" if results[k] is est.best_ else "" for k in shown]
    best_few = table(
        ["law", "posterior probability", "ln BF vs best", "why"],
        rows,
        [False, True, True, False],
        classes,
        cell_classes=["", "", "", "why"],
    )
    rest = len(results) - len(shown)
    intro = (
        f"<p>{len(results)} laws were scored by their exact evidence; "
        + (f"the best {len(shown)} are shown, the other {rest} are below." if rest else
           "all are shown.")
        + "</p>"
    )  # fmt: skip
    return (
        intro
        + best_few
        + folded(
            f"All {len(results)} laws: evidence, Bayes factors, method, conditioning, notes",
            full_comparison(est),
        )
    )


def short_reason(r: ModelResult, best: ModelResult, ln_bf: float) -> str:
    """Why a law ranks where it does, in a few words: what it adds to or lacks from the
    best law, whether it fits better, and Jeffreys' word for the evidence against it."""
    if r is best:
        why = "highest evidence: fits as well as any law with no term the data do not need"
        return f"{why}; {r.flags[0]}" if r.flags else why
    mine, theirs = set(r.name.split("+")), set(best.name.split("+"))
    added, lacks = sorted(mine - theirs), sorted(theirs - mine)
    fits_worse = r.residual_rms > best.residual_rms * 1.001
    parts = []
    if lacks:
        parts.append("lacks " + ", ".join(lacks))
    if added:
        parts.append("adds " + ", ".join(added))
    what = " and ".join(parts) or "another form of the same terms"
    if fits_worse:
        verdict = (
            f"fits worse (residual {sig(r.residual_rms * 1e3, 3)} mN against "
            f"{sig(best.residual_rms * 1e3, 3)})"
        )
    else:
        verdict = "fits no better, so its extra freedom costs evidence"
    return f"{what}: {verdict}; evidence against it: {jeffreys(ln_bf)}"


def full_comparison(est: BayesianFit) -> str:
    """Every law scored, with its evidence, method, conditioning and the fit's notes."""
    results = est.results_
    top = results[0].ln_evidence
    ln_p = ln_probabilities(est)
    sampler = any(r.ln_evidence_sampler is not None for r in results)
    head = ["law", "ln evidence (exact)"]
    if sampler:
        head += ["ln evidence (stepping-stone)", "sampler − exact"]
    head += [
        "posterior probability",
        "ln BF vs best",
        "evidence against (Jeffreys)",
        "method",
        "cond (scaled)",
        "residual RMS (mN)",
        "note",
    ]
    rows, classes = [], []
    for r, lp in zip(results, ln_p, strict=True):
        lbf = top - r.ln_evidence
        row = [f"<b>{law_name(r.name)}</b>", fixed(r.ln_evidence)]
        if sampler:
            if r.ln_evidence_sampler is None:
                row += ["—", "—"]
            else:
                row += [
                    fixed(r.ln_evidence_sampler),
                    fixed(r.ln_evidence_sampler - r.ln_evidence, sign=True),
                ]
        flags = (
            (
                "<div class='small'>flags:<ul>"
                + "".join(f"<li>{esc(f)}</li>" for f in r.flags)
                + "</ul></div>"
            )
            if r.flags
            else ""
        )
        row += [
            probability(float(lp)),
            fixed(lbf),
            esc(jeffreys(lbf)),
            esc(r.status),
            sig(r.cond_scaled, 3),
            sig(r.residual_rms * 1e3, 3),
            f"<span class='small'>{esc(r.reason)}</span>{flags}",
        ]
        rows.append(row)
        classes.append("best" if r is est.best_ else "")
    numeric = (
        [False, True]
        + ([True, True] if sampler else [])
        + [True, True, False, False, True, True, False]
    )
    explain = (
        "<p class='small'>Forms are ranked by their evidence (marginal likelihood), with "
        "equal prior probability for each law. The Bayes factor (BF) against the best is "
        "Z<sub>best</sub> / Z<sub>law</sub>; on Jeffreys' scale a ln BF above "
        f"{DECISIVE:.1f} (100 : 1) is decisive. <i>exact</i>: closed-form posterior; "
        "<i>emcee</i>: sampled because the positivity bound cuts the closed form, or on "
        "request; <i>skipped</i>: decisively behind, so not sampled (its evidence is still "
        "exact). cond (scaled): condition number of the design matrix with unit-norm "
        "columns (collinearity of the terms alone).</p>"
    )
    if sampler:
        explain += (
            "<p class='small'>Stepping-stone is an independent, sampler-based estimate of "
            "the same evidence; differences well below 1 confirm the exact value.</p>"
        )
    cells = [""] * (len(head) - 1) + ["note"]
    return table(head, rows, numeric, classes, cell_classes=cells, full=True) + explain


def pinv_table(pinv: WindowedPinv, est: BayesianFit | None) -> str:
    """The pseudoinverse against the Bayesian posterior of the same law."""
    match = matching(pinv, est)
    head = ["parameter", "best window", "all windows pooled", "unit (SI)"]
    if match is not None:
        head += ["Bayesian mean ± SD", "best window − Bayesian mean (in SD)"]
    rows = []
    for j, t in enumerate(pinv.model_.terms):
        row = [
            f"<b>{esc(t.symbol)}</b>",
            sig(float(pinv.params_[j]), 4),
            sig(float(pinv.pooled_[j]), 4),
            esc(unit_html(t.unit)),
        ]
        if match is not None and match.posterior is not None:
            mu, sd = float(match.posterior.mean[j]), float(match.posterior.sd[j])
            z = (pinv.params_[j] - mu) / sd if sd > 0 else float("nan")
            row += [f"{with_sd(mu, sd)} ± {sig(sd, 2)}", fixed(z, 1, sign=True)]
        rows.append(row)
    numeric = [False, True, True, False] + ([True, True] if match is not None else [])
    return table(head, rows, numeric) + pinv_info(pinv)


def pinv_info(pinv: WindowedPinv) -> str:
    rms = float(pinv.residuals_[pinv.best_window_]) * 1e3
    return (
        f"<p class='small'>Form {esc(pinv.model_.name)}; {pinv.windows_.shape[0]} windows "
        f"of {pinv.window_samples_} samples; chosen window index {pinv.best_window_} "
        f"(from 0; smallest residual, {sig(rms, 3)} mN RMS); "
        f"condition number of its design {sig(pinv.cond_, 3)}, scaled "
        f"{sig(pinv.cond_scaled_, 3)}.</p>"
    )


def matching(pinv: WindowedPinv, est: BayesianFit | None) -> ModelResult | None:
    """The Bayesian result of the pseudoinverse's law, if that law was fitted."""
    if est is None:
        return None
    for r in est.results_:
        if r.name == pinv.model_.name and r.posterior is not None:
            return r
    return None


def diagnostics(outcome: FitOutcome) -> str:
    est, pinv = outcome.bayes, outcome.pinv
    kin = est.kinematics_ if est is not None else pinv.kinematics_  # type: ignore[union-attr]
    n = len(outcome.session)
    grid = len((est or pinv).session_)  # type: ignore[union-attr]
    trimmed = (kin.window - 1) // 2
    holes = grid - 2 * trimmed - kin.time.size  # beside lost or clipped samples
    used = f"{kin.time.size:,} of {n:,} ({trimmed:,} trimmed at each edge, where the filter "
    beside = (
        "outside the fitted grasps or beside lost or clipped samples"
        if outcome.fitted_grasps
        else "beside lost or clipped samples"
    )
    used += f"is one-sided; {holes:,} {beside})" if holes else "is one-sided)"
    g = kin.noise_gain
    items = [
        ("Differentiator", f"<code>{esc(kin.method)}</code>"),
        ("Cutoff (−3 dB)", f"{sig(kin.cutoff_hz, 3)} Hz"),
        (
            "Noise gain",
            f"position {sig(g[0], 3)}, velocity {sig(g[1], 3)} 1/s, "
            f"acceleration {sig(g[2], 3)} 1/s² "
            "<span class='small'>(output SD per unit SD of white input noise)</span>",
        ),
        ("Samples used", used),
    ]
    if est is not None:
        tau_ms = est.tau_ / max(outcome.session.rate_hz, 1e-300) * 1e3
        items += [
            (
                "Residual autocorrelation time",
                f"{sig(est.tau_, 3)} samples ({sig(tau_ms, 3)} ms)",
            ),
            ("Effective samples", f"{sig(est.n_eff_, 3)} (samples used / autocorrelation time)"),
            (
                "Position noise SD",
                f"{sig(est.sigma_x_ * 1e6, 3)} µm "
                f"(errors-in-variables correction "
                f"{'on' if est.eiv else 'off'})",
            ),
            (
                "Settings",
                esc(
                    f"sampler {est.sampler}, seed {est.seed}, forms {est.forms}, "
                    f"decisive ln BF {est.decisive:.2f}"
                ),
            ),
        ]
    if pinv is not None:
        items.append(
            (
                "Pseudoinverse",
                esc(
                    f"law {pinv.model_.name}, window {pinv.window_s:g} s "
                    f"({pinv.window_samples_} samples), "
                    f"{pinv.windows_.shape[0]} windows"
                ),
            )
        )
    out = meta_table(items) + grasps_table(outcome)
    if est is not None:
        out += (
            "<p class='small'>Why the effective sample count is smaller than the sample "
            "count: the smoothing filter makes neighbouring residuals alike, so the "
            "likelihood is tempered by 1/τ to count only independent information; "
            "treating every sample as independent would make the intervals too narrow.</p>"
        )
        sampled = [r for r in est.results_ if r.status == "emcee" and r.posterior is not None]
        if sampled:
            rows = []
            for r in sampled:
                d = r.posterior.diagnostics  # type: ignore[union-attr]
                tau = list(d.get("tau", []))
                labels = [t.symbol for t in r.model.terms] + ["σ"]
                tau_text = ", ".join(
                    f"{lab} {sig(t, 3)}" for lab, t in zip(labels, tau, strict=False)
                )
                steps = int(d.get("steps", 0))
                need = 50 * max(tau) if tau else float("nan")
                conv = d.get("converged")
                rows.append(
                    [
                        f"<b>{esc(r.name)}</b>",
                        f"{steps:,}",
                        esc(d.get("walkers", "—")),
                        esc(tau_text),
                        sig(d.get("acceptance"), 2),
                        f"{'yes' if conv else '<b>no</b>'} "
                        f"<span class='small'>({steps:,} vs 50 τ = {sig(need, 3)})</span>",
                        esc(d.get("independent_samples", "—")),
                    ]
                )
            out += "<h3>Sampler (emcee)</h3>" + table(
                [
                    "law",
                    "steps",
                    "walkers",
                    "autocorrelation time τ (steps)",
                    "acceptance fraction",
                    "converged (chain > 50 τ)",
                    "independent draws",
                ],
                rows,
                [False, True, True, False, True, False, True],
            )
        else:
            out += (
                "<p class='small'>No law needed sampling: every posterior in this report "
                "is closed-form, so there are no chain diagnostics.</p>"
            )
    return out


def grasps_table(outcome: FitOutcome) -> str:
    """The grasps found against the free-jaw baseline, and which were fitted ("" for a
    session in contact throughout)."""
    contact = outcome.contact
    if contact.all_contact:
        return ""
    fitted = set(outcome.fitted_grasps)
    rows = [
        [
            str(i),
            fixed(g.start_s, 3),
            fixed(g.end_s, 3),
            fixed(g.duration_s, 2),
            sig(g.peak_force_n, 3),
            "yes" if i in fitted else "no",
        ]
        for i, g in enumerate(contact.grasps, 1)
    ]
    return (
        f"<h3>Grasps</h3><p>{esc(contact.describe())}. A sample is in contact while the "
        "smoothed force stands above the free-jaw baseline (the force sensor's offset) by "
        "more than a few noise SDs; only filtered samples whose whole window lies in a "
        "fitted grasp are fitted (<code>--grasps</code> chooses), and with every grasp "
        "those of jaws near their most open where they read an offset (the sensor's "
        "alone).</p>"
        + table(
            [
                "grasp",
                "start (s)",
                "end (s)",
                "duration (s)",
                "peak force above baseline (N)",
                "fitted",
            ],
            rows,
            [True, True, True, True, True, False],
        )
    )


def how_to_read(outcome: FitOutcome) -> str:
    law = (
        "<p>The tissue law is a sum of terms, each a coefficient times a function of jaw "
        "closure x, closing speed ẋ or acceleration ẍ: the paper's <i>F = K f0(x) + S f1(ẋ) + "
        "M ẍ</i>, and terms real tissue and sensors need beyond it (hardening x³, dry friction "
        "sign(ẋ), a force offset). "
    )
    if outcome.bayes is not None:
        body = (
            "Each candidate law (a set of terms, such as x³ with ẋ and ẍ) is fitted to the "
            "whole session; its evidence weighs how well it fits against how flexible it is, "
            "and the chosen law is the one with the highest evidence. "
            "The parameter table gives posterior means with their SD and 95 % intervals; a "
            "parameter is trustworthy when its interval is narrow and well away from zero and "
            "no warning names it. The plots should show the fitted force on top of the measured "
            "one, residuals without structure (no repeated pattern, histogram close to the "
            "Gaussian) and compact posterior clouds. "
        )
        if outcome.pinv is not None:
            body += (
                "The paper's windowed pseudoinverse fits each window separately: the "
                "spread of its window estimates shows how much one window's answer can "
                "vary, to be read against the Bayesian band. "
            )
    else:
        body = (
            "Only the paper's windowed pseudoinverse ran: it fits one given form to each "
            "window separately and keeps the window with the smallest residual. It gives "
            "no uncertainty and no choice between forms; the spread of the window estimates "
            "is the only indication of how much the answer can vary. "
        )
    return (
        law + body + "All values are in SI units; only the columns marked convenient units "
        "convert to N/mm, N s/mm and g.</p>"
    )


def provenance() -> str:
    """Software and library versions and the time of writing (no library is imported
    just to ask its version)."""
    when = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")
    libs = ", ".join(
        f"{name} {_version(name)}" for name in ("numpy", "scipy", "emcee", "matplotlib")
    )
    parts = [
        esc(SOFTWARE),
        esc(f"Python {platform.python_version()}, {libs}"),
        esc(f"generated {when}"),
    ]
    return "<footer><b>Provenance:</b> " + " · ".join(parts) + "</footer>"


def _version(distribution: str) -> str:
    try:
        return metadata.version(distribution)
    except metadata.PackageNotFoundError:
        return "(not installed)"
