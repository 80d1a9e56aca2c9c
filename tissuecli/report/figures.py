"""The report's figures: drawn on :class:`matplotlib.figure.Figure` objects with the Agg
renderer (no global pyplot state), reduced to at most :data:`MAX_POINTS` points per
series (a min/max envelope keeps peaks), embedded as base64 PNG."""

from __future__ import annotations

import base64
import io
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator, ScalarFormatter
from numpy.typing import NDArray

from ..core.terms import Law
from ..identify.bayes import ModelResult
from ..identify.outcome import FitOutcome
from ..identify.pinv import WindowedPinv
from .numbers import esc, unit_tex

Array = NDArray[np.float64]


#: Most points drawn per series; longer series are reduced to a min/max envelope.
MAX_POINTS = 5000


#: Most posterior draws in the corner plot.
MAX_DRAWS = 4000


#: Resolution of the embedded figures (dots per inch).
DPI = 110


COLOURS = {
    "measured": "#1f5fa8",
    "fitted": "#d9601a",
    "raw": "#b8b8b8",
    "band": "#9fc4e8",
    "pick": "#c0182b",
    "open": "#c0182b",
}


@dataclass
class Series:
    """The samples a report plots, from the Bayesian fit or else the pseudoinverse."""

    time: Array
    raw: Array
    force: Array
    fitted: Array
    x: Array
    model: Law
    source: str
    sigma: float | None
    expected_sd: float | None
    v: Array | None = None  # filtered speed, m/s
    band_sd: Array | None = None  # SD of the predicted force, N
    elastic: Array | None = None  # the fitted position terms' force (stiffness, contact), N

    @property
    def residual(self) -> Array:
        return self.force - self.fitted


def series(outcome: FitOutcome) -> Series:
    """Measured and fitted force of the best Bayesian form, or of the pseudoinverse,
    as the estimator predicts it."""
    est, pinv = outcome.bayes, outcome.pinv
    if est is not None:
        post = est.best_.posterior
        assert post is not None
        kin = est.kinematics_
        parts = est.contributions()
        elastic = [j for j, t in enumerate(est.best_.model.terms) if t.role == "stiffness"]
        return Series(
            time=kin.time,
            raw=kin.force_raw,
            force=kin.force,
            fitted=parts.sum(axis=1),
            x=kin.x,
            model=est.best_.model,
            source="posterior mean of the best law",
            sigma=post.sigma_mean,
            expected_sd=est.expected_residual_sd_,
            v=kin.v,
            band_sd=est.predictive_sd(),
            elastic=parts[:, elastic].sum(axis=1) if elastic else None,
        )
    assert pinv is not None
    kin = pinv.kinematics_
    return Series(
        time=kin.time,
        raw=kin.force_raw,
        force=kin.force,
        fitted=pinv.predict(),
        x=kin.x,
        model=pinv.model_,
        source="pseudoinverse, best window",
        sigma=None,
        expected_sd=None,
    )


def envelope(t: Array, y: Array, max_points: int = MAX_POINTS) -> tuple[Array, Array]:
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


def broken(t: Array, y: Array) -> tuple[Array, Array]:
    """``t, y`` with a NaN wherever the time jumps by more than three typical steps, so
    that a line is not drawn across a gap (between grasps, over a hole)."""
    if t.size < 3:
        return t, y
    steps = np.diff(t)
    cut = np.flatnonzero(steps > 3 * np.median(steps)) + 1
    return np.insert(t.astype(float), cut, np.nan), np.insert(y.astype(float), cut, np.nan)


def stride(n: int, max_points: int = MAX_POINTS) -> Array:
    """Evenly spaced indices, at most ``max_points`` of them (for smooth paths)."""
    return np.unique(np.linspace(0, n - 1, min(n, max_points)).astype(int))


def png(fig: Figure) -> str:
    """Base64 PNG of a figure."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def figure_html(fig: Figure, anchor: str, title: str, alt: str, caption: str) -> str:
    """A figure as an embedded image with a caption (what to look at)."""
    w, h = fig.get_size_inches()
    data = png(fig)
    return (
        f'<figure id="{esc(anchor)}"><h3>{esc(title)}</h3>'
        f'<img src="data:image/png;base64,{data}" alt="{esc(alt)}" '
        f'width="{int(w * 96)}" height="{int(h * 96)}">'
        f"<figcaption>{esc(caption)}</figcaption></figure>"
    )


def new_figure(w: float, h: float) -> Figure:
    """A figure of ``w`` x ``h`` inches with constrained layout (no pyplot)."""
    return Figure(figsize=(w, h), layout="constrained")


def time_figure(s: Series) -> Figure:
    fig = new_figure(9.5, 4.6)
    ax, bx = fig.subplots(2, 1, sharex=True, height_ratios=(3, 1))
    ax.plot(
        *broken(*envelope(s.time, s.raw)), color=COLOURS["raw"], lw=0.7, label="raw (unfiltered)"
    )
    ax.plot(
        *broken(*envelope(s.time, s.force)),
        color=COLOURS["measured"],
        lw=1.3,
        label="measured (filtered)",
    )
    if s.band_sd is not None:
        i = stride(s.time.size)
        t = broken(s.time[i], s.fitted[i])[0]
        lo = broken(s.time[i], s.fitted[i] - 1.96 * s.band_sd[i])[1]
        hi = broken(s.time[i], s.fitted[i] + 1.96 * s.band_sd[i])[1]
        ax.fill_between(t, lo, hi, color=COLOURS["band"], alpha=0.5, lw=0,
                        label="95 % predictive band")  # fmt: skip
    ax.plot(
        *broken(*envelope(s.time, s.fitted)),
        color=COLOURS["fitted"],
        lw=1.1,
        ls="--",
        label=f"fitted ({s.source})",
    )
    ax.set_ylabel("grasp force F (N)")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper right", fontsize=8, ncols=3, framealpha=0.9)
    lo, hi = float(np.min(s.raw)), float(np.max(s.raw))
    ax.set_ylim(lo - 0.05 * (hi - lo), hi + 0.22 * (hi - lo))  # room for the legend
    bx.plot(*broken(*envelope(s.time, s.x * 1e3)), color="#444444", lw=1.0)
    bx.set_ylabel("closure x (mm)")
    bx.set_xlabel("time (s)")
    bx.grid(alpha=0.3)
    bx.set_xlim(s.time[0], s.time[-1])
    return fig


def loop_figure(s: Series) -> Figure:
    fig = new_figure(6.4, 4.8)
    ax = fig.add_subplot()
    i = stride(s.x.size)
    x, f = s.x[i] * 1e3, s.force[i]
    closing = np.gradient(s.x)[i] >= 0
    ax.plot(
        x,
        np.where(closing, f, np.nan),
        color=COLOURS["measured"],
        lw=1.3,
        label="measured, closing (loading)",
    )
    ax.plot(
        x,
        np.where(closing, np.nan, f),
        color=COLOURS["open"],
        lw=1.3,
        label="measured, opening (unloading)",
    )
    ax.plot(x, s.fitted[i], color="k", lw=0.6, ls=(0, (3, 3)), alpha=0.8, label="fitted")
    ax.set_xlabel("jaw closure x (mm)")
    ax.set_ylabel("grasp force F (N)")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)
    return fig


def residual_figure(s: Series) -> Figure:
    r = s.residual * 1e3
    fig = new_figure(9.5, 3.4)
    gs = fig.add_gridspec(1, 2, width_ratios=(4, 1))
    ax = fig.add_subplot(gs[0])
    hx = fig.add_subplot(gs[1])
    rms = float(np.sqrt(np.mean(r**2)))
    ax.plot(
        *broken(*envelope(s.time, r)),
        color=COLOURS["measured"],
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
        color=COLOURS["band"],
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
            color=COLOURS["fitted"] if ls == "-" else "k",
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


def binned(u: Array, r: Array, bins: int = 30) -> tuple[Array, Array, Array]:
    """Centres, means and standard errors of ``r`` in equal-count bins of ``u``."""
    order = np.argsort(u)
    groups = [g for g in np.array_split(order, bins) if g.size > 1]
    centre = np.array([float(np.mean(u[g])) for g in groups])
    mean = np.array([float(np.mean(r[g])) for g in groups])
    se = np.array([float(np.std(r[g], ddof=1)) / np.sqrt(g.size) for g in groups])
    return centre, mean, se


def residual_map_figure(s: Series) -> Figure:
    """Residuals against closure and against speed, with binned means: a wrong stiffness
    or damping form leaves a curve there where the time plot shows only noise."""
    assert s.v is not None
    fig = new_figure(9.5, 3.4)
    axes = fig.subplots(1, 2, sharey=True)
    r = s.residual * 1e3
    i = stride(r.size, 4000)
    for ax, u, label in (
        (axes[0], s.x * 1e3, "jaw closure x (mm)"),
        (axes[1], s.v * 1e3, "closing speed ẋ (mm/s)"),
    ):
        ax.plot(u[i], r[i], ".", ms=1.5, color=COLOURS["raw"], label="residuals")
        c, m, se = binned(u, r)
        ax.errorbar(c, m, yerr=2 * se, color=COLOURS["fitted"], lw=1.2, capsize=0,
                    label="binned mean ± 2 SE")  # fmt: skip
        ax.axhline(0, color="k", lw=0.8)
        ax.set_xlabel(label)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("residual (mN)")
    axes[0].legend(loc="upper left", fontsize=8)
    return fig


def elastic_figure(s: Series) -> Figure:
    """The elastic force against closure: the measured force minus every fitted term
    but the position ones (a partial residual), with the fitted position terms."""
    assert s.elastic is not None
    fig = new_figure(6.4, 4.4)
    ax = fig.add_subplot()
    partial = s.force - (s.fitted - s.elastic)
    i = stride(s.x.size, 4000)
    ax.plot(s.x[i] * 1e3, partial[i], ".", ms=1.5, color=COLOURS["measured"],
            label="measured − fitted non-elastic terms")  # fmt: skip
    order = np.argsort(s.x)
    j = order[stride(order.size)]
    ax.plot(s.x[j] * 1e3, s.elastic[j], color=COLOURS["fitted"], lw=1.4, label="fitted elastic")
    ax.set_xlabel("jaw closure x (mm)")
    ax.set_ylabel("elastic force (N)")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)
    return fig


def relaxation_figure(model: Law, coef: Array, shape_ci: dict[str, list[float]]) -> Figure:
    """The law's force after a 1 mm step in closure (the relaxation function): each term
    with memory answers as it declares (:meth:`~tissuecli.core.terms.Term.step_response`;
    a relaxation branch decays as e^(-t/tau)) on top of the position terms; the band spans
    the memory terms' shape parameters' 95 % intervals."""
    fig = new_figure(6.4, 4.2)
    ax = fig.add_subplot()
    taus = [s for t in model.terms if t.memory for s in t.time_scales()]
    t = np.logspace(np.log10(min(taus) / 30), np.log10(max(taus) * 30), 300)

    def response(which: int) -> Array:
        out = np.zeros_like(t)
        for term, c in zip(model.terms, coef, strict=True):
            if term.memory:
                if which >= 0:
                    term = term.bind({n: shape_ci[n][which] if n in shape_ci else term.shape[n]
                                      for n in term.shapes})  # fmt: skip
                out += c * term.step_response(t, 1e-3)
            elif term.rendered and term.variable == "x":
                out += c * term.step_response(t, 1e-3)
        return out

    ax.fill_between(t, response(0), response(1), color=COLOURS["band"], alpha=0.6, lw=0,
                    label="time constants' 95 % intervals")  # fmt: skip
    ax.plot(t, response(-1), color=COLOURS["fitted"], lw=1.5, label="posterior mean")
    for tau in taus:
        ax.axvline(tau, color="k", lw=0.6, ls=":")
    ax.set_xscale("log")
    ax.set_xlabel("time after the step (s)")
    ax.set_ylabel("force after a 1 mm step (N)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(loc="upper right", fontsize=8)
    return fig


def axis_scale(values: Array) -> tuple[float, str]:
    """A power-of-ten factor that keeps tick labels short, and its label prefix."""
    top = float(np.max(np.abs(values))) if values.size else 0.0
    if top == 0 or 1e-2 <= top < 1e4:
        return 1.0, ""
    p = 3 * math.floor(math.log10(top) / 3)
    return 10.0 ** (-p), f"10$^{{{p}}}$ "


def tidy_axis(axis: Any) -> None:
    axis.set_major_locator(MaxNLocator(4))
    fmt = ScalarFormatter(useOffset=False)
    fmt.set_scientific(False)
    axis.set_major_formatter(fmt)


def corner_figure(draws: Array, model: Law, mean: Array, ci: Array) -> Figure:
    """Corner plot: 1-D histograms on the diagonal, 2-D scatter of pairs below it."""
    p = len(model.terms)
    scaled, labels = [], []
    for j, t in enumerate(model.terms):
        factor, prefix = axis_scale(draws[:, j])
        scaled.append(factor)
        labels.append(f"{t.symbol} ({prefix}{unit_tex(t.unit)})")
    v = draws[:, :p] * np.array(scaled)
    fig = new_figure(2.5 * p + 0.1, 2.3 * p + 0.1)
    axes = fig.subplots(p, p, squeeze=False, sharex="col")
    for i in range(p):
        for j in range(p):
            ax = axes[i, j]
            if j > i:
                ax.set_visible(False)
                continue
            if i == j:
                ax.hist(v[:, j], bins=40, color=COLOURS["band"], edgecolor="none")
                ax.axvline(mean[j] * scaled[j], color=COLOURS["measured"], lw=1.3)
                for q in ci[j]:
                    ax.axvline(q * scaled[j], color=COLOURS["measured"], lw=0.9, ls="--")
                ax.set_yticks([])
            else:
                ax.scatter(
                    v[:, j],
                    v[:, i],
                    s=2,
                    alpha=0.25,
                    color=COLOURS["measured"],
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
                tidy_axis(ax.yaxis)
            tidy_axis(ax.xaxis)
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


def windows_figure(pinv: WindowedPinv, band: ModelResult | None) -> Figure:
    """Per-window pseudoinverse estimates against the Bayesian posterior mean +- 2 SD."""
    t = pinv.kinematics_.time
    n = pinv.window_samples_
    m = pinv.windows_.shape[0]
    centre = np.array([t[min(i * n + n // 2, t.size - 1)] for i in range(m)])
    best = pinv.best_window_
    terms = pinv.model_.terms
    rows = (len(terms) + 2) // 2
    fig = new_figure(9.5, 2.8 * rows)
    axes = fig.subplots(rows, 2, sharex=True).ravel()
    panels = [(t.symbol, pinv.windows_[:, j], unit_tex(t.unit)) for j, t in enumerate(terms)]
    panels.append(("residual RMS", pinv.residuals_ * 1e3, "mN"))
    for ax in axes[len(panels) :]:
        ax.set_visible(False)
    post = band.posterior if band is not None else None
    for k, (ax, (name, values, unit)) in enumerate(zip(axes, panels, strict=False)):
        factor, prefix = axis_scale(values)
        ax.plot(
            centre,
            values * factor,
            "o-",
            color=COLOURS["measured"],
            ms=4,
            lw=0.8,
            label="each window",
        )
        ax.plot(
            centre[best],
            values[best] * factor,
            "*",
            color=COLOURS["pick"],
            ms=15,
            label=f"chosen window (index {best})",
        )
        if k < len(terms):
            ax.axhline(
                pinv.pooled_[k] * factor, color="k", lw=0.9, ls=":", label="all windows pooled"
            )
            if post is not None:
                mu, sd = post.mean[k] * factor, post.sd[k] * factor
                ax.axhspan(
                    mu - 2 * sd,
                    mu + 2 * sd,
                    color=COLOURS["band"],
                    alpha=0.6,
                    label="Bayesian mean ± 2 SD",
                )
                ax.axhline(mu, color=COLOURS["fitted"], lw=1.1)
        ax.set_ylabel(f"{name} ({prefix}{unit})")
        ax.grid(alpha=0.3)
        tidy_axis(ax.yaxis)
        if k >= len(panels) - 2:
            ax.set_xlabel("window centre time (s)")
    axes[0].legend(fontsize=7, loc="best")
    return fig
