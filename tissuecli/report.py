"""A self-contained HTML report of a fit: parameters, model choice, plots and diagnostics.

One file, readable offline: styles are inline, figures are embedded as base64
PNG, and there is no script. Figures are drawn on :class:`matplotlib.figure.Figure`
objects with the Agg renderer, so no global pyplot state is touched. Long series
are reduced to at most :data:`MAX_POINTS` plotted points (a min/max envelope keeps
peaks) and the corner plot uses at most :data:`MAX_DRAWS` posterior draws.

Everything is in SI units; columns headed "convenient units" repeat values in
N/mm, N s/mm and g for reading against the literature.
"""

from __future__ import annotations

import base64
import html
import io
import math
import os
import platform
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator, ScalarFormatter
from numpy.typing import NDArray
from scipy.special import logsumexp

from .fit import FitOutcome, fitted_series
from .identify import DECISIVE, BayesianFit, ModelResult, WindowedPinv, design
from .models import PARAMETERS, TissueModel

Array = NDArray[np.float64]

#: Most points drawn per series; longer series are reduced to a min/max envelope.
MAX_POINTS = 5000
#: Most posterior draws in the corner plot.
MAX_DRAWS = 4000
#: Resolution of the embedded figures (dots per inch).
DPI = 110

#: SI unit -> (convenient unit, factor from SI) for the convenience columns.
CONVENIENT: dict[str, tuple[str, float]] = {
    "N/m": ("N/mm", 1e-3),
    "N/m^3": ("N/mm³", 1e-9),
    "N s/m": ("N s/mm", 1e-3),
    "N s^2/m^2": ("N s²/mm²", 1e-6),
    "kg": ("g", 1e3),
}

_ROLE = {"K": "stiffness", "S": "damping", "M": "moving mass"}
_COLOURS = {
    "measured": "#1f5fa8",
    "fitted": "#d9601a",
    "raw": "#b8b8b8",
    "band": "#9fc4e8",
    "pick": "#c0182b",
    "open": "#c0182b",
}

_CSS = """
body{font-family:-apple-system,"Segoe UI",Helvetica,Arial,sans-serif;color:#1d1d1d;
 max-width:1040px;margin:1.5em auto;padding:0 1em;line-height:1.45}
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
figure{margin:1.2em 0}figure img{max-width:100%;height:auto;border:1px solid #e4e4e4}
figcaption{font-size:.92em;color:#333;margin-top:.3em}
.small{font-size:.85em;color:#444}.small ul{margin:.2em 0;padding-left:1.1em}
footer{margin-top:2.5em;border-top:1px solid #ccc;padding-top:.6em;font-size:.85em;color:#444}
code{font-family:Consolas,Menlo,monospace;font-size:.95em}
"""


# --------------------------------------------------------------------------- numbers


def _e(text: object) -> str:
    """HTML-escaped text."""
    return html.escape(str(text), quote=True)


def _finite(v: float | None) -> bool:
    return v is not None and math.isfinite(v)


def _sig(v: float | None, digits: int = 4) -> str:
    """``v`` to ``digits`` significant digits as markup; scientific outside 1e-3 .. 1e5."""
    if v is None:
        return "—"
    if not math.isfinite(v):
        return _e(str(v))
    if v == 0:
        return "0"
    digits = max(1, digits)
    exp = math.floor(math.log10(abs(v)))
    if -3 <= exp < 5 and not (exp >= 4 and exp >= digits):
        v = round(v, digits - 1 - exp) if exp >= digits else v
        text = f"{v:.{max(digits - 1 - exp, 0)}f}"
        if float(text) != 0 and math.floor(math.log10(abs(float(text)))) > exp:
            text = f"{v:.{max(digits - 2 - exp, 0)}f}"  # rounding carried a digit (9.99 -> 10.0)
        return text.replace("-", "−")
    mant, power = f"{v:.{digits - 1}e}".split("e")
    return f"{mant.replace('-', '−')}&#8239;×&#8239;10<sup>{int(power)}</sup>".replace(
        "<sup>-", "<sup>−"
    )


def _fixed(v: float, decimals: int = 2, sign: bool = False) -> str:
    """``v`` with a fixed number of decimals and a true minus sign."""
    if not math.isfinite(v):
        return _e(str(v))
    return (f"{v:+.{decimals}f}" if sign else f"{v:.{decimals}f}").replace("-", "−")


def _at_place(v: float, place: int) -> str:
    """``v`` rounded to the decimal place ``10**place``."""
    if not math.isfinite(v) or v == 0:
        return _sig(v)
    return _sig(v, min(max(math.floor(math.log10(abs(v))) - place + 1, 1), 9))


def _place(sd: float) -> int:
    """Decimal place of the second significant digit of an uncertainty."""
    return math.floor(math.log10(sd)) - 1 if _finite(sd) and sd > 0 else -12


def _with_sd(mean: float, sd: float) -> str:
    """A mean with the digits its SD supports (two significant digits of the SD)."""
    if not (_finite(sd) and sd > 0):
        return _sig(mean, 6)
    return _at_place(mean, _place(sd))


def _power_of_ten(ln_value: float) -> str:
    """``exp(ln_value)`` as markup, without overflow for huge or tiny values."""
    if not math.isfinite(ln_value):
        return "0" if ln_value < 0 else "∞"
    if abs(ln_value) < math.log(1e5):
        return _sig(math.exp(ln_value), 3)
    p10 = ln_value / math.log(10)
    exp = math.floor(p10)
    mant = 10 ** (p10 - exp)
    if round(mant, 1) >= 10:
        mant, exp = 1.0, exp + 1
    return f"{mant:.1f}&#8239;×&#8239;10<sup>{exp}</sup>".replace("<sup>-", "<sup>−")


def _probability(ln_p: float) -> str:
    """A probability given its logarithm: three decimals, or a power of ten when tiny."""
    p = math.exp(ln_p)
    if p >= 1e-3:
        return f"{p:.3f}"
    return "≈ " + _power_of_ten(ln_p)


def _jeffreys(ln_bf: float) -> str:
    """Jeffreys' words for the evidence against a form, from its ln Bayes factor."""
    if ln_bf <= 0:
        return "best"
    for limit, word in (
        (math.log(10**0.5), "barely worth mentioning"),
        (math.log(10.0), "substantial"),
        (DECISIVE, "strong"),
    ):
        if ln_bf < limit:
            return word
    return "decisive"


def _unit(unit: str) -> str:
    """A unit for display: N/m^3 -> N/m³."""
    return unit.replace("^2", "²").replace("^3", "³")


def _unit_tex(unit: str) -> str:
    """A unit for matplotlib mathtext."""
    return unit.replace("^2", "$^2$").replace("^3", "$^3$")


# --------------------------------------------------------------------------- data


@dataclass
class _Series:
    """The samples a report plots, from the Bayesian fit or else the pseudoinverse."""

    time: Array
    raw: Array
    force: Array
    fitted: Array
    x: Array
    model: TissueModel
    source: str
    sigma: float | None
    expected_sd: float | None

    @property
    def residual(self) -> Array:
        return self.force - self.fitted


def _series(outcome: FitOutcome) -> _Series:
    """Measured and fitted force of the best Bayesian form, or of the pseudoinverse."""
    if outcome.bayes is not None:
        est = outcome.bayes
        s = fitted_series(outcome)
        post = est.best_.posterior
        assert post is not None
        return _Series(
            time=s["time"],
            raw=est.kinematics_.force_raw,
            force=s["force"],
            fitted=s["fitted"],
            x=s["x"],
            model=est.best_.model,
            source="posterior mean of the best form",
            sigma=post.sigma_mean,
            expected_sd=_expected_residual_sd(est),
        )
    pinv = outcome.pinv
    assert pinv is not None
    kin = pinv.kinematics_
    fitted = design(pinv.model_, kin, pinv.session_.position) @ pinv.params_
    return _Series(
        time=kin.time,
        raw=kin.force_raw,
        force=kin.force,
        fitted=fitted,
        x=kin.x,
        model=pinv.model_,
        source="pseudoinverse, best window",
        sigma=None,
        expected_sd=None,
    )


def _expected_residual_sd(est: BayesianFit) -> float:
    """Residual SD the best form expects (N): force noise plus position noise through the law.

    With the errors-in-variables correction the posterior noise SD is the force noise
    alone; noise on position reaches the residuals through the design columns too, adding
    ``beta^T C beta / n`` to their variance (C: the correction subtracted from A^T A).
    """
    best = est.best_
    post = best.posterior
    assert post is not None
    sigma = float(post.sigma_mean)
    if not est.eiv or est.sigma_x_ <= 0:
        return sigma
    corr = best.correction
    if corr is None:
        return sigma  # the fit left this form uncorrected
    extra = float(post.mean @ corr @ post.mean) / max(est.kinematics_.time.size, 1)
    return float(np.sqrt(sigma**2 + max(extra, 0.0)))


def _envelope(t: Array, y: Array, max_points: int = MAX_POINTS) -> tuple[Array, Array]:
    """At most ``max_points`` points of a series: the min and max of each bucket, in order."""
    n = y.size
    if n <= max_points:
        return t, y
    b = int(math.ceil(n / (max_points // 2)))
    m = n // b
    block = y[: m * b].reshape(m, b)
    base = np.arange(m) * b
    idx = np.sort(np.column_stack([block.argmin(axis=1), block.argmax(axis=1)]), axis=1)
    idx = (idx + base[:, None]).ravel()
    if m * b < n:
        tail = np.arange(m * b, n)
        ends = sorted({int(np.argmin(y[tail])), int(np.argmax(y[tail]))})
        idx = np.concatenate([idx, tail[ends]])
    return t[idx], y[idx]


def _stride(n: int, max_points: int = MAX_POINTS) -> Array:
    """Evenly spaced indices, at most ``max_points`` of them (for smooth paths)."""
    return np.unique(np.linspace(0, n - 1, min(n, max_points)).astype(int))


# --------------------------------------------------------------------------- figures


def _png(fig: Figure) -> str:
    """Base64 PNG of a figure."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _figure(fig: Figure, anchor: str, title: str, alt: str, caption: str) -> str:
    """A figure as an embedded image with a caption (what to look at)."""
    w, h = fig.get_size_inches()
    data = _png(fig)
    return (
        f'<figure id="{_e(anchor)}"><h3>{_e(title)}</h3>'
        f'<img src="data:image/png;base64,{data}" alt="{_e(alt)}" '
        f'width="{int(w * 96)}" height="{int(h * 96)}">'
        f"<figcaption>{_e(caption)}</figcaption></figure>"
    )


def _new_figure(w: float, h: float) -> Figure:
    """A figure of ``w`` x ``h`` inches with constrained layout (no pyplot)."""
    return Figure(figsize=(w, h), layout="constrained")


def _time_figure(s: _Series) -> Figure:
    fig = _new_figure(9.5, 4.6)
    ax, bx = fig.subplots(2, 1, sharex=True, height_ratios=(3, 1))
    ax.plot(*_envelope(s.time, s.raw), color=_COLOURS["raw"], lw=0.7, label="raw (unfiltered)")
    ax.plot(
        *_envelope(s.time, s.force), color=_COLOURS["measured"], lw=1.3, label="measured (filtered)"
    )
    ax.plot(
        *_envelope(s.time, s.fitted),
        color=_COLOURS["fitted"],
        lw=1.1,
        ls="--",
        label=f"fitted ({s.source})",
    )
    ax.set_ylabel("grasp force F (N)")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper right", fontsize=8, ncols=3, framealpha=0.9)
    lo, hi = float(np.min(s.raw)), float(np.max(s.raw))
    ax.set_ylim(lo - 0.05 * (hi - lo), hi + 0.22 * (hi - lo))  # room for the legend
    bx.plot(*_envelope(s.time, s.x * 1e3), color="#444444", lw=1.0)
    bx.set_ylabel("closure x (mm)")
    bx.set_xlabel("time (s)")
    bx.grid(alpha=0.3)
    bx.set_xlim(s.time[0], s.time[-1])
    return fig


def _loop_figure(s: _Series) -> Figure:
    fig = _new_figure(6.4, 4.8)
    ax = fig.add_subplot()
    i = _stride(s.x.size)
    x, f = s.x[i] * 1e3, s.force[i]
    closing = np.gradient(s.x)[i] >= 0
    ax.plot(
        x,
        np.where(closing, f, np.nan),
        color=_COLOURS["measured"],
        lw=1.3,
        label="measured, closing (loading)",
    )
    ax.plot(
        x,
        np.where(closing, np.nan, f),
        color=_COLOURS["open"],
        lw=1.3,
        label="measured, opening (unloading)",
    )
    ax.plot(x, s.fitted[i], color="k", lw=0.6, ls=(0, (3, 3)), alpha=0.8, label="fitted")
    ax.set_xlabel("jaw closure x (mm)")
    ax.set_ylabel("grasp force F (N)")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)
    return fig


def _residual_figure(s: _Series) -> Figure:
    r = s.residual * 1e3
    fig = _new_figure(9.5, 3.4)
    gs = fig.add_gridspec(1, 2, width_ratios=(4, 1))
    ax = fig.add_subplot(gs[0])
    hx = fig.add_subplot(gs[1])
    rms = float(np.sqrt(np.mean(r**2)))
    ax.plot(
        *_envelope(s.time, r),
        color=_COLOURS["measured"],
        lw=0.7,
        label=f"residual, RMS {rms:.3g} mN",
    )
    ax.axhline(0, color="k", lw=0.8)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("residual, measured − fitted (mN)")
    ax.set_xlim(s.time[0], s.time[-1])
    ax.grid(alpha=0.3)
    hx.hist(
        r,
        bins=min(80, max(15, int(np.sqrt(r.size)))),
        orientation="horizontal",
        density=True,
        color=_COLOURS["band"],
        edgecolor="none",
        label="histogram",
    )
    curves = []
    if s.sigma is not None and s.expected_sd is not None:
        if abs(s.expected_sd / s.sigma - 1) > 0.01:
            curves.append((s.expected_sd * 1e3, "expected residual SD", "-"))
        curves.append((s.sigma * 1e3, "posterior noise SD σ", "--" if curves else "-"))
    else:
        curves.append((rms, "residual RMS", "-"))
    top = max(sd for sd, _, _ in curves)
    grid = np.linspace(min(r.min(), -4 * top), max(r.max(), 4 * top), 300)
    for sd, what, ls in curves:
        hx.plot(
            np.exp(-0.5 * (grid / sd) ** 2) / (sd * np.sqrt(2 * np.pi)),
            grid,
            ls=ls,
            color=_COLOURS["fitted"] if ls == "-" else "k",
            lw=1.3,
            label=f"Gaussian, {what} {sd:.3g} mN",
        )
    hx.set_xlabel("density (1/mN)")
    hx.tick_params(labelleft=False)
    hx.grid(alpha=0.3)
    lo, hi = float(grid[0]), float(grid[-1])
    for a in (ax, hx):
        a.set_ylim(lo, hi + 0.3 * (hi - lo))  # room for the legend
    handles, labels = (
        a + b
        for a, b in zip(ax.get_legend_handles_labels(), hx.get_legend_handles_labels(), strict=True)
    )
    ax.legend(handles, labels, loc="upper right", fontsize=8, ncols=2, framealpha=0.9)
    return fig


def _axis_scale(values: Array) -> tuple[float, str]:
    """A power-of-ten factor that keeps tick labels short, and its label prefix."""
    top = float(np.max(np.abs(values))) if values.size else 0.0
    if top == 0 or 1e-2 <= top < 1e4:
        return 1.0, ""
    p = 3 * math.floor(math.log10(top) / 3)
    return 10.0 ** (-p), f"10$^{{{p}}}$ "


def _tidy_axis(axis: Any) -> None:
    axis.set_major_locator(MaxNLocator(4))
    fmt = ScalarFormatter(useOffset=False)
    fmt.set_scientific(False)
    axis.set_major_formatter(fmt)


def _corner_figure(draws: Array, model: TissueModel, mean: Array, ci: Array) -> Figure:
    """Corner plot: 1-D histograms on the diagonal, 2-D scatter of pairs below it."""
    p = len(PARAMETERS)
    units = model.units
    scaled, labels = [], []
    for j, name in enumerate(PARAMETERS):
        factor, prefix = _axis_scale(draws[:, j])
        scaled.append(factor)
        labels.append(f"{name} ({prefix}{_unit_tex(units[name])})")
    v = draws[:, :p] * np.array(scaled)
    fig = _new_figure(7.6, 7.0)
    axes = fig.subplots(p, p, squeeze=False, sharex="col")
    for i in range(p):
        for j in range(p):
            ax = axes[i, j]
            if j > i:
                ax.set_visible(False)
                continue
            if i == j:
                ax.hist(v[:, j], bins=40, color=_COLOURS["band"], edgecolor="none")
                ax.axvline(mean[j] * scaled[j], color=_COLOURS["measured"], lw=1.3)
                for q in ci[j]:
                    ax.axvline(q * scaled[j], color=_COLOURS["measured"], lw=0.9, ls="--")
                ax.set_yticks([])
            else:
                ax.scatter(
                    v[:, j],
                    v[:, i],
                    s=2,
                    alpha=0.25,
                    color=_COLOURS["measured"],
                    linewidths=0,
                    rasterized=True,
                )
                rho = float(np.corrcoef(draws[:, j], draws[:, i])[0, 1])
                ax.text(
                    0.03,
                    0.95,
                    f"ρ = {rho:+.2f}",
                    transform=ax.transAxes,
                    va="top",
                    fontsize=8,
                    bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "none"},
                )
                _tidy_axis(ax.yaxis)
            _tidy_axis(ax.xaxis)
            ax.tick_params(labelsize=8)
            if i == p - 1:
                ax.set_xlabel(labels[j])
                ax.tick_params(axis="x", labelrotation=30)
            else:
                ax.tick_params(labelbottom=False)
            if j == 0 and i > 0:
                ax.set_ylabel(labels[i])
            elif j > 0 and i != j:
                ax.tick_params(labelleft=False)
    for i in range(p):
        for j in range(i):
            axes[i, j].set_ylim(axes[i, i].get_xlim())
    return fig


def _windows_figure(pinv: WindowedPinv, band: ModelResult | None) -> Figure:
    """Per-window pseudoinverse estimates against the Bayesian posterior mean +- 2 SD."""
    t = pinv.kinematics_.time
    n = pinv.window_samples_
    m = pinv.windows_.shape[0]
    centre = np.array([t[min(i * n + n // 2, t.size - 1)] for i in range(m)])
    best = pinv.best_window_
    units = pinv.model_.units
    fig = _new_figure(9.5, 5.6)
    axes = fig.subplots(2, 2, sharex=True).ravel()
    panels = [
        (name, pinv.windows_[:, j], _unit_tex(units[name])) for j, name in enumerate(PARAMETERS)
    ]
    panels.append(("residual RMS", pinv.residuals_ * 1e3, "mN"))
    post = band.posterior if band is not None else None
    for k, (ax, (name, values, unit)) in enumerate(zip(axes, panels, strict=True)):
        factor, prefix = _axis_scale(values)
        ax.plot(
            centre,
            values * factor,
            "o-",
            color=_COLOURS["measured"],
            ms=4,
            lw=0.8,
            label="each window",
        )
        ax.plot(
            centre[best],
            values[best] * factor,
            "*",
            color=_COLOURS["pick"],
            ms=15,
            label=f"chosen window (index {best})",
        )
        if k < 3:
            ax.axhline(
                pinv.pooled_[k] * factor, color="k", lw=0.9, ls=":", label="all windows pooled"
            )
            if post is not None:
                mu, sd = post.mean[k] * factor, post.sd[k] * factor
                ax.axhspan(
                    mu - 2 * sd,
                    mu + 2 * sd,
                    color=_COLOURS["band"],
                    alpha=0.6,
                    label="Bayesian mean ± 2 SD",
                )
                ax.axhline(mu, color=_COLOURS["fitted"], lw=1.1)
        ax.set_ylabel(f"{name} ({prefix}{unit})")
        ax.grid(alpha=0.3)
        _tidy_axis(ax.yaxis)
        if k >= 2:
            ax.set_xlabel("window centre time (s)")
    axes[0].legend(fontsize=7, loc="best")
    return fig


# --------------------------------------------------------------------------- html parts


def _table(
    head: Sequence[str],
    rows: Sequence[Sequence[str]],
    numeric: Sequence[bool],
    classes: Sequence[str] | None = None,
) -> str:
    """A table; ``head`` is text (escaped), cells are markup already."""
    th = "".join(f"<th>{_e(h)}</th>" for h in head)
    body = []
    for k, row in enumerate(rows):
        cls = f' class="{classes[k]}"' if classes and classes[k] else ""
        tds = "".join(
            f'<td class="n">{c}</td>' if num else f"<td>{c}</td>"
            for c, num in zip(row, numeric, strict=True)
        )
        body.append(f"<tr{cls}>{tds}</tr>")
    return f'<div class="wide"><table><tr>{th}</tr>{"".join(body)}</table></div>'


def _meta_table(items: Sequence[tuple[str, str]]) -> str:
    rows = "".join(f"<tr><th>{_e(k)}</th><td>{v}</td></tr>" for k, v in items)
    return f'<table class="meta">{rows}</table>'


def _term_labels(model: TissueModel) -> dict[str, str]:
    return {"K": model.f0.label, "S": model.f1.label, "M": "ẍ"}


def _formula(model: TissueModel, values: Sequence[str]) -> str:
    labels = _term_labels(model)
    terms = " + ".join(
        f"{v}&#8201;{_e(labels[n])}" for n, v in zip(PARAMETERS, values, strict=True)
    )
    units = model.units
    return (
        f'<div class="formula">F = {terms}</div>'
        f'<p class="units">F in N, x in m, ẋ in m/s, ẍ in m/s²; '
        f"K in {_e(_unit(units['K']))}, S in {_e(_unit(units['S']))}, "
        f"M in {_e(_unit(units['M']))}.</p>"
    )


def _convenient(value: float, unit: str) -> tuple[str, float] | None:
    if unit not in CONVENIENT:
        return None
    name, factor = CONVENIENT[unit]
    return name, value * factor


def _header(outcome: FitOutcome, s: _Series) -> str:
    doc = outcome.document
    session = outcome.session
    data = doc.get("data", {})
    if outcome.bayes is not None and outcome.pinv is not None:
        how = (
            f"Bayesian model choice over {len(outcome.bayes.results_)} form(s), and the "
            "windowed pseudoinverse"
        )
    elif outcome.bayes is not None:
        how = f"Bayesian model choice over {len(outcome.bayes.results_)} form(s)"
    else:
        how = "windowed pseudoinverse (point estimates, no uncertainty)"
    x_mm = session.position * 1e3
    items = [
        ("Session", _e(session.name or "(unnamed)")),
        ("File", _e(data.get("file") or "—")),
        ("Tissue", _e(data.get("tissue") or "—")),
        ("Samples", _e(f"{len(session):,}")),
        ("Duration", f"{_sig(session.duration_s, 4)} s"),
        ("Sample rate", f"{_sig(session.rate_hz, 4)} Hz"),
        ("Jaw closure range", f"{_sig(float(x_mm.min()), 3)} to {_sig(float(x_mm.max()), 3)} mm"),
        (
            "Force range",
            f"{_sig(float(session.force.min()), 3)} to {_sig(float(session.force.max()), 3)} N",
        ),
        ("Identification", _e(how)),
        ("Software", _e(doc.get("software", ""))),
    ]
    model = s.model
    if outcome.bayes is not None:
        best = outcome.bayes.best_
        post = best.posterior
        assert post is not None
        values = [_with_sd(post.mean[j], post.sd[j]) for j in range(len(PARAMETERS))]
        chosen = (
            f"<p>Chosen form: <b>{_e(best.name)}</b> "
            f"(posterior probability {_probability(_ln_probabilities(outcome.bayes)[0])}), "
            "posterior means:</p>"
        )
    else:
        pinv = outcome.pinv
        assert pinv is not None
        values = [_sig(v, 4) for v in pinv.params_]
        chosen = (
            f"<p>Form: <b>{_e(pinv.model_.name)}</b> (given, not chosen), "
            "estimate of the best window:</p>"
        )
    title = f"Tissue identification: {session.name or 'session'}"
    return f"<h1>{_e(title)}</h1>{_meta_table(items)}{chosen}{_formula(model, values)}"


def _ln_probabilities(est: BayesianFit) -> Array:
    """ln posterior probability of each form (equal prior odds), in ``results_`` order."""
    ln_z = np.array([r.ln_evidence for r in est.results_])
    return ln_z - logsumexp(ln_z)


def _warnings_box(outcome: FitOutcome) -> str:
    warnings = list(outcome.document.get("warnings", []))
    if outcome.bayes is None:
        warnings.append(
            "Point estimates only: the windowed pseudoinverse gives no uncertainty "
            "and no model choice; the Bayesian fit gives both."
        )
        items = "".join(f"<li>{_e(w)}</li>" for w in warnings)
        return f'<div class="box warn"><b>Note</b><ul>{items}</ul></div>'
    if not warnings:
        return (
            '<div class="box ok"><b>No warnings.</b> Every parameter of the chosen form is '
            "identified: its 95 % interval stays clear of zero and its SD is below 25 % "
            "of its value.</div>"
        )
    items = "".join(f"<li>{_e(w)}</li>" for w in warnings)
    return f'<div class="box warn"><b>Warnings ({len(warnings)})</b><ul>{items}</ul></div>'


def _parameters_bayes(est: BayesianFit, s: _Series) -> str:
    best = est.best_
    post = best.posterior
    assert post is not None
    units = best.model.units
    labels = _term_labels(best.model)
    rows = []
    for j, name in enumerate(PARAMETERS):
        mean, sd = float(post.mean[j]), float(post.sd[j])
        lo, hi = (float(q) for q in post.ci95[j])
        place = _place(sd)
        conv = _convenient(mean, units[name])
        if conv is not None:
            cname, factor = CONVENIENT[units[name]]
            cplace = place + round(math.log10(factor))
            conv_cell = (
                f"{_at_place(mean * factor, cplace)} "
                f"[{_at_place(lo * factor, cplace)}, {_at_place(hi * factor, cplace)}]"
                f" {_e(cname)}"
            )
        else:
            conv_cell = "—"
        rel = f"{100 * sd / abs(mean):.2g} %" if mean != 0 else "—"
        rows.append(
            [
                f"<b>{name}</b> · {_e(labels[name])} <span class='small'>"
                f"({_e(_ROLE[name])})</span>",
                _with_sd(mean, sd),
                _sig(sd, 2),
                f"[{_at_place(lo, place)}, {_at_place(hi, place)}]",
                _e(_unit(units[name])),
                rel,
                conv_cell,
            ]
        )
    sig = post.samples[:, -1] if post.samples.shape[0] > 1 else np.empty(0)
    sig_sd = float(np.std(sig, ddof=1)) * 1e3 if sig.size > 1 else float("nan")
    lo, hi = (1e3 * q for q in post.sigma_ci95)
    place = _place(sig_sd)
    rows.append(
        [
            "<b>σ</b> noise SD of the filtered force",
            _with_sd(post.sigma_mean * 1e3, sig_sd),
            _sig(sig_sd, 2),
            f"[{_at_place(lo, place)}, {_at_place(hi, place)}]",
            "mN",
            f"{100 * sig_sd / (post.sigma_mean * 1e3):.2g} %",
            "—",
        ]
    )
    table = _table(
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
        f"<p class='small'>Form <b>{_e(best.name)}</b>; posterior from "
        f"{_e('the closed form (exact)' if best.status == 'exact' else 'emcee sampling')}. "
        "Means and intervals are shown to the second significant digit of their SD. "
        "The noise SD σ is of the force after the same smoothing as the kinematics"
    )
    if s.expected_sd is not None and abs(s.expected_sd / post.sigma_mean - 1) > 0.01:
        rms = float(np.sqrt(np.mean(s.residual**2)))
        note += (
            f"; with the errors-in-variables correction it excludes position noise, which "
            f"the fit expects to raise the residual SD to {_sig(s.expected_sd * 1e3, 3)} mN "
            f"(observed residual RMS {_sig(rms * 1e3, 3)} mN)"
        )
    return table + note + ".</p>"


def _parameters_pinv(pinv: WindowedPinv) -> str:
    units = pinv.model_.units
    labels = _term_labels(pinv.model_)
    rows = []
    for j, name in enumerate(PARAMETERS):
        w = pinv.windows_[:, j]
        spread = float(np.std(w, ddof=1)) if w.size > 1 else float("nan")
        conv = _convenient(float(pinv.params_[j]), units[name])
        rows.append(
            [
                f"<b>{name}</b> · {_e(labels[name])} <span class='small'>"
                f"({_e(_ROLE[name])})</span>",
                _sig(float(pinv.params_[j]), 4),
                _sig(float(pinv.pooled_[j]), 4),
                _sig(float(np.mean(w)), 4),
                _sig(spread, 2),
                _e(_unit(units[name])),
                f"{_sig(conv[1], 4)} {_e(conv[0])}" if conv else "—",
            ]
        )
    return _table(
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


def _comparison(est: BayesianFit) -> str:
    results = est.results_
    top = results[0].ln_evidence
    ln_p = _ln_probabilities(est)
    sampler = any(r.ln_evidence_sampler is not None for r in results)
    head = ["form", "law", "ln evidence (exact)"]
    if sampler:
        head += ["ln evidence (stepping-stone)", "sampler − exact"]
    head += [
        "posterior probability",
        "ln BF vs best",
        "BF vs best",
        "evidence against (Jeffreys)",
        "method",
        "note",
        "cond",
        "cond (scaled)",
        "residual RMS (mN)",
    ]
    rows, classes = [], []
    for r, lp in zip(results, ln_p, strict=True):
        lbf = top - r.ln_evidence
        labels = _term_labels(r.model)
        law = _e(f"K {labels['K']} + S {labels['S']} + M ẍ")
        row = [f"<b>{_e(r.name)}</b>", law, _fixed(r.ln_evidence)]
        if sampler:
            if r.ln_evidence_sampler is None:
                row += ["—", "—"]
            else:
                row += [
                    _fixed(r.ln_evidence_sampler),
                    _fixed(r.ln_evidence_sampler - r.ln_evidence, sign=True),
                ]
        flags = (
            (
                "<div class='small'>flags:<ul>"
                + "".join(f"<li>{_e(f)}</li>" for f in r.flags)
                + "</ul></div>"
            )
            if r.flags
            else ""
        )
        row += [
            _probability(float(lp)),
            _fixed(lbf),
            _power_of_ten(lbf),
            _e(_jeffreys(lbf)),
            _e(r.status),
            f"<span class='small'>{_e(r.reason)}</span>{flags}",
            _sig(r.cond, 3),
            _sig(r.cond_scaled, 3),
            _sig(r.residual_rms * 1e3, 3),
        ]
        rows.append(row)
        classes.append("best" if r is est.best_ else "")
    numeric = (
        [False, False, True]
        + ([True, True] if sampler else [])
        + [True, True, True, False, False, False, True, True, True]
    )
    explain = (
        "<p class='small'>Forms are ranked by their evidence (marginal likelihood), with "
        "equal prior probability for each form. The Bayes factor (BF) against the best is "
        "Z<sub>best</sub> / Z<sub>form</sub>; on Jeffreys' scale a ln BF above "
        f"{DECISIVE:.1f} (100 : 1) is decisive. <i>exact</i>: closed-form posterior; "
        "<i>emcee</i>: sampled because the positivity bound cuts the closed form, or on "
        "request; <i>skipped</i>: decisively behind, so not sampled (its evidence is still "
        "exact). cond: condition number of the design matrix, raw (depends on units) and "
        "with unit-norm columns (collinearity of the terms alone).</p>"
    )
    if sampler:
        explain += (
            "<p class='small'>Stepping-stone is an independent, sampler-based estimate of "
            "the same evidence; differences well below 1 confirm the exact value.</p>"
        )
    return _table(head, rows, numeric, classes) + explain


def _pinv_table(pinv: WindowedPinv, est: BayesianFit | None) -> str:
    """The pseudoinverse against the Bayesian posterior of the same form."""
    units = pinv.model_.units
    match = _matching(pinv, est)
    head = ["parameter", "best window", "all windows pooled", "unit (SI)"]
    if match is not None:
        head += ["Bayesian mean ± SD", "best window − Bayesian mean (in SD)"]
    rows = []
    for j, name in enumerate(PARAMETERS):
        row = [
            f"<b>{name}</b>",
            _sig(float(pinv.params_[j]), 4),
            _sig(float(pinv.pooled_[j]), 4),
            _e(_unit(units[name])),
        ]
        if match is not None and match.posterior is not None:
            mu, sd = float(match.posterior.mean[j]), float(match.posterior.sd[j])
            z = (pinv.params_[j] - mu) / sd if sd > 0 else float("nan")
            row += [f"{_with_sd(mu, sd)} ± {_sig(sd, 2)}", _fixed(z, 1, sign=True)]
        rows.append(row)
    numeric = [False, True, True, False] + ([True, True] if match is not None else [])
    return _table(head, rows, numeric) + _pinv_info(pinv)


def _pinv_info(pinv: WindowedPinv) -> str:
    rms = float(pinv.residuals_[pinv.best_window_]) * 1e3
    return (
        f"<p class='small'>Form {_e(pinv.model_.name)}; {pinv.windows_.shape[0]} windows "
        f"of {pinv.window_samples_} samples; chosen window index {pinv.best_window_} "
        f"(from 0; smallest residual, {_sig(rms, 3)} mN RMS); "
        f"condition number of its design {_sig(pinv.cond_, 3)}, scaled "
        f"{_sig(pinv.cond_scaled_, 3)}.</p>"
    )


def _matching(pinv: WindowedPinv, est: BayesianFit | None) -> ModelResult | None:
    """The Bayesian result of the pseudoinverse's form, if that form was fitted."""
    if est is None:
        return None
    for r in est.results_:
        if r.name == pinv.model_.name and r.posterior is not None:
            return r
    return None


def _diagnostics(outcome: FitOutcome) -> str:
    est, pinv = outcome.bayes, outcome.pinv
    kin = est.kinematics_ if est is not None else pinv.kinematics_  # type: ignore[union-attr]
    n = len(outcome.session)
    grid = len((est or pinv).session_)  # type: ignore[union-attr]
    trimmed = (kin.window - 1) // 2
    holes = grid - 2 * trimmed - kin.time.size  # beside lost or clipped samples
    used = f"{kin.time.size:,} of {n:,} ({trimmed:,} trimmed at each edge, where the filter "
    used += f"is one-sided; {holes:,} beside lost or clipped samples)" if holes else "is one-sided)"
    g = kin.noise_gain
    items = [
        ("Differentiator", f"<code>{_e(kin.method)}</code>"),
        ("Cutoff (−3 dB)", f"{_sig(kin.cutoff_hz, 3)} Hz"),
        (
            "Noise gain",
            f"position {_sig(g[0], 3)}, velocity {_sig(g[1], 3)} 1/s, "
            f"acceleration {_sig(g[2], 3)} 1/s² "
            "<span class='small'>(output SD per unit SD of white input noise)</span>",
        ),
        ("Samples used", used),
    ]
    if est is not None:
        tau_ms = est.tau_ / max(outcome.session.rate_hz, 1e-300) * 1e3
        items += [
            (
                "Residual autocorrelation time",
                f"{_sig(est.tau_, 3)} samples ({_sig(tau_ms, 3)} ms)",
            ),
            ("Effective samples", f"{_sig(est.n_eff_, 3)} (samples used / autocorrelation time)"),
            (
                "Position noise SD",
                f"{_sig(est.sigma_x_ * 1e6, 3)} µm "
                f"(errors-in-variables correction "
                f"{'on' if est.eiv else 'off'})",
            ),
            (
                "Settings",
                _e(
                    f"sampler {est.sampler}, seed {est.seed}, forms {est.forms}, "
                    f"decisive ln BF {est.decisive:.2f}"
                ),
            ),
        ]
    if pinv is not None:
        items.append(
            (
                "Pseudoinverse",
                _e(
                    f"form {pinv.model_.name}, window {pinv.window_s:g} s "
                    f"({pinv.window_samples_} samples), "
                    f"{pinv.windows_.shape[0]} windows"
                ),
            )
        )
    out = _meta_table(items)
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
                tau_text = ", ".join(
                    f"{lab} {_sig(t, 3)}" for lab, t in zip(("K", "S", "M", "σ"), tau, strict=False)
                )
                steps = int(d.get("steps", 0))
                need = 50 * max(tau) if tau else float("nan")
                conv = d.get("converged")
                rows.append(
                    [
                        f"<b>{_e(r.name)}</b>",
                        f"{steps:,}",
                        _e(d.get("walkers", "—")),
                        _e(tau_text),
                        _sig(d.get("acceptance"), 2),
                        f"{'yes' if conv else '<b>no</b>'} "
                        f"<span class='small'>({steps:,} vs 50 τ = {_sig(need, 3)})</span>",
                        _e(d.get("independent_samples", "—")),
                    ]
                )
            out += "<h3>Sampler (emcee)</h3>" + _table(
                [
                    "form",
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
                "<p class='small'>No form needed sampling: every posterior in this report "
                "is closed-form, so there are no chain diagnostics.</p>"
            )
    return out


def _how_to_read(outcome: FitOutcome) -> str:
    law = (
        "<p>The tissue law is <i>F = K f0(x) + S f1(ẋ) + M ẍ</i>: a stiffness term in jaw "
        "closure x, a damping term in closing speed ẋ and an inertia term in acceleration "
        "ẍ. "
    )
    if outcome.bayes is not None:
        body = (
            "Each candidate form (a stiffness law f0 with a damping law f1, such as x³ with ẋ) "
            "is fitted to the whole session; its evidence weighs how well it fits against how "
            "flexible it is, and the chosen form is the one with the highest evidence. "
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


def _provenance(outcome: FitOutcome) -> str:
    import emcee
    import matplotlib
    import scipy

    doc = outcome.document
    when = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")
    parts = [
        f"{_e(doc.get('software', ''))}",
        _e(f"parameter format {doc.get('format', '')} version {doc.get('version', '')}"),
        _e(
            f"Python {platform.python_version()}, numpy {np.__version__}, scipy "
            f"{scipy.__version__}, emcee {emcee.__version__}, matplotlib {matplotlib.__version__}"
        ),
        _e(f"generated {when}"),
    ]
    return "<footer><b>Provenance:</b> " + " · ".join(parts) + "</footer>"


# --------------------------------------------------------------------------- report


def render_report(outcome: FitOutcome) -> str:
    """The report as one HTML document (str).

    Parameters
    ----------
    outcome : FitOutcome
        What :func:`tissuecli.fit.fit_session` returned: a Bayesian fit, a
        windowed pseudoinverse, or both.

    Returns
    -------
    str
        A complete, self-contained HTML document.
    """
    s = _series(outcome)
    est, pinv = outcome.bayes, outcome.pinv
    sections = [
        ("parameters", "Parameters"),
        ("comparison", "Model comparison"),
        ("plots", "Plots"),
        ("diagnostics", "Diagnostics"),
        ("reading", "How to read this report"),
    ]
    nav = " · ".join(f'<a href="#{a}">{_e(t)}</a>' for a, t in sections)
    parts = [_header(outcome, s), f'<p class="small">Contents: {nav}</p>']

    parts.append("<h2 id='parameters'>Parameters</h2>")
    parts.append(_parameters_bayes(est, s) if est is not None else _parameters_pinv(pinv))  # type: ignore[arg-type]
    parts.append(_warnings_box(outcome))

    parts.append("<h2 id='comparison'>Model comparison</h2>")
    if est is not None:
        parts.append(_comparison(est))
    else:
        assert pinv is not None
        parts.append(
            f"<p>Only the form {_e(pinv.model_.name)} was fitted, by the windowed "
            "pseudoinverse, so there is no comparison between forms.</p>"
        )
        parts.append(_pinv_info(pinv))

    parts.append("<h2 id='plots'>Plots</h2>")
    figs = [
        (
            _time_figure(s),
            "plot-time",
            "Force over time",
            "measured and fitted grasp force against time",
            "The dashed fitted force should lie on the measured (filtered) force throughout; "
            "the grey trace is the raw signal before smoothing.",
        ),
        (
            _loop_figure(s),
            "plot-loop",
            "Force against jaw closure",
            "grasp force against jaw closure, measured and fitted",
            "The loop opens because damping adds force while closing and removes it while "
            "opening; the fitted loop should trace the measured one, including its curvature.",
        ),
        (
            _residual_figure(s),
            "plot-residuals",
            "Residuals",
            "residual force over time and its histogram",
            "Residuals should look like noise: no drift or pattern repeating with the squeezes, "
            "and a histogram matching the solid Gaussian"
            + (
                " of the SD the fit expects (force noise σ plus position noise carried through the "
                "law; σ alone is dashed)."
                if s.sigma is not None
                and s.expected_sd is not None
                and abs(s.expected_sd / s.sigma - 1) > 0.01
                else " of the posterior noise SD."
                if s.sigma is not None
                else " of the residual RMS."
            ),
        ),
    ]
    if est is not None:
        post = est.best_.posterior
        assert post is not None
        draws = post.samples
        if draws.shape[0] > MAX_DRAWS:
            keep = np.random.default_rng(0).choice(draws.shape[0], MAX_DRAWS, replace=False)
            draws = draws[np.sort(keep)]
        if draws.shape[0] >= 20:
            figs.append(
                (
                    _corner_figure(draws, est.best_.model, post.mean, post.ci95),
                    "plot-corner",
                    f"Posterior of K, S, M ({est.best_.name})",
                    "corner plot of the posterior draws of K, S and M",
                    f"{draws.shape[0]:,} posterior draws in SI units; solid lines: means, "
                    "dashed: 95 % intervals. Look for compact clouds away from zero; ρ is "
                    "the correlation between two parameters (near ±1: the data separate "
                    "them poorly).",
                )
            )
        else:
            parts.append(
                "<p>Too few posterior draws inside the positivity bounds for a corner plot.</p>"
            )
    if pinv is not None:
        match = _matching(pinv, est)
        figs.append(
            (
                _windows_figure(pinv, match),
                "plot-windows",
                "Windowed pseudoinverse, per window",
                "pseudoinverse estimates of K, S, M and residual RMS for each window",
                "Each point is one window's estimate; the star is the window the paper's "
                "method keeps (smallest residual)"
                + (
                    "; the shaded band is the Bayesian posterior mean ± 2 SD of the same "
                    "form. Points far outside the band show how much one window can mislead."
                    if match is not None
                    else "."
                ),
            )
        )
    for k, (fig, anchor, title, alt, caption) in enumerate(figs):
        parts.append(_figure(fig, anchor, f"{chr(ord('a') + k)}. {title}", alt, caption))
        if anchor == "plot-windows" and est is not None:
            parts.append(_pinv_table(pinv, est))  # type: ignore[arg-type]

    parts.append("<h2 id='diagnostics'>Diagnostics</h2>")
    parts.append(_diagnostics(outcome))
    parts.append("<h2 id='reading'>How to read this report</h2>")
    parts.append(_how_to_read(outcome))
    parts.append(_provenance(outcome))

    title = f"Tissue identification: {outcome.session.name or 'session'}"
    return (
        "<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'>"
        "<meta name='viewport' content='width=device-width, initial-scale=1'>"
        f"<title>{_e(title)}</title><style>{_CSS}</style></head><body>"
        + "\n".join(parts)
        + "</body></html>\n"
    )


def write_report(path: str | os.PathLike[str], outcome: FitOutcome) -> None:
    """Write the HTML report of a fit to ``path``.

    Parameters
    ----------
    path : str or os.PathLike
        Where to write; an existing file is replaced.
    outcome : FitOutcome
        What :func:`tissuecli.fit.fit_session` returned.
    """
    text = render_report(outcome)
    path = Path(path)
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)
