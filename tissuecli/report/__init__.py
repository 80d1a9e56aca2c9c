"""A self-contained HTML report of a fit: parameters, model choice, plots and diagnostics.

One file, readable offline: styles are inline, figures are embedded as base64 PNG,
and there is no script. :func:`render_report` returns the document as a string;
writing it is the caller's business (``tissuecli.app.fit``). matplotlib is imported
only here, so a fit without a report never loads it.

Everything is in SI units; columns headed "convenient units" repeat values in N/mm,
N s/mm and g for reading against the literature.
"""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from ..identify.bayes import BayesianFit
from ..identify.outcome import FitOutcome
from .figures import (
    MAX_DRAWS,
    Series,
    corner_figure,
    elastic_figure,
    figure_html,
    loop_figure,
    relaxation_figure,
    residual_figure,
    residual_map_figure,
    series,
    time_figure,
    windows_figure,
)
from .numbers import esc
from .sections import (
    CSS,
    comparison,
    diagnostics,
    folded,
    header,
    how_to_read,
    matching,
    parameters_bayes,
    parameters_pinv,
    pinv_info,
    pinv_table,
    provenance,
    session_table,
    warnings_box,
)

__all__ = ["PLOT_FORMATS", "PLOT_NAMES", "plot_files", "render_report"]

#: formats the plots are exported in (``fit --plot-format``)
PLOT_FORMATS = ("png", "svg", "pdf")
#: every plot a report may have, by file name (without extension), in report order
PLOT_NAMES = (
    "plot-time", "plot-loop", "plot-residuals", "plot-residual-map", "plot-elastic",
    "plot-relaxation", "plot-corner", "plot-windows",
)  # fmt: skip


def render_report(outcome: FitOutcome) -> str:
    """The report as one HTML document (str).

    Parameters
    ----------
    outcome : FitOutcome
        What :func:`tissuecli.identify.fit_session` returned: a Bayesian fit, a
        windowed pseudoinverse, or both.

    Returns
    -------
    str
        A complete, self-contained HTML document.
    """
    s = series(outcome)
    est, pinv = outcome.bayes, outcome.pinv
    if est is not None:
        params, compare = parameters_bayes(est, s), comparison(est)
    else:
        assert pinv is not None
        params = parameters_pinv(pinv)
        compare = (
            f"<p>Only the form {esc(pinv.model_.name)} was fitted, by the windowed "
            "pseudoinverse, so there is no comparison between forms.</p>" + pinv_info(pinv)
        )
    # what a reader needs first (the law, its parameters, the plots) is open; the
    # rest is one click away, folded, so that the page reads in a minute
    sections = [
        ("parameters", "Parameters", params + warnings_box(outcome)),
        ("plots", "Plots", '<div class="plots">' + "".join(_plots(outcome, s)) + "</div>"),
        ("comparison", "Model comparison", compare),
        (
            "diagnostics",
            "Session and diagnostics",
            folded(
                "The session, the filter, the grasps and the sampler",
                session_table(outcome, s) + diagnostics(outcome),
            ),
        ),  # fmt: skip
        (
            "reading",
            "How to read this report",
            folded("What each part means", how_to_read(outcome)),
        ),
    ]
    nav = " · ".join(f'<a href="#{a}">{esc(t)}</a>' for a, t, _ in sections)
    parts = [header(outcome, s), f'<p class="small">Contents: {nav}</p>']
    for anchor, title, body in sections:
        parts += [f"<h2 id='{anchor}'>{esc(title)}</h2>", body]
    parts.append(provenance())
    title = f"Tissue identification: {outcome.session.name or 'session'}"
    return (
        "<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'>"
        "<meta name='viewport' content='width=device-width, initial-scale=1'>"
        f"<title>{esc(title)}</title><style>{CSS}</style></head><body>"
        + "\n".join(parts)
        + "</body></html>\n"
    )


def plot_files(outcome: FitOutcome, fmt: str = "png") -> dict[str, bytes]:
    """The report's plots as files: name (``plot-time.png``, ...) -> bytes, in ``fmt``
    (one of :data:`PLOT_FORMATS`), at the report's resolution for PNG."""
    import io

    from .figures import DPI

    if fmt not in PLOT_FORMATS:
        raise ValueError(f"plot format {fmt!r}: choose one of {', '.join(PLOT_FORMATS)}")
    files = {}
    for fig, anchor, *_ in _figures(outcome, series(outcome), [])[0]:
        buf = io.BytesIO()
        fig.savefig(buf, format=fmt, dpi=DPI)
        files[f"{anchor}.{fmt}"] = buf.getvalue()
    return files


def _plots(outcome: FitOutcome, s: Series) -> list[str]:
    """The figures, lettered in order, each with what to look for; the pseudoinverse's
    table follows its figure."""
    figs, parts = _figures(outcome, s, [])
    est, pinv = outcome.bayes, outcome.pinv
    for k, (fig, anchor, title, alt, caption) in enumerate(figs):
        parts.append(figure_html(fig, anchor, f"{chr(ord('a') + k)}. {title}", alt, caption))
        if anchor == "plot-windows" and est is not None:
            parts.append(f'<div class="span">{pinv_table(pinv, est)}</div>')  # type: ignore[arg-type]
    return parts


def _figures(
    outcome: FitOutcome, s: Series, parts: list[str]
) -> tuple[list[tuple[Figure, str, str, str, str]], list[str]]:
    """The figures (figure, anchor, title, alt text, caption), in order; ``parts`` gains
    a note where a figure cannot be drawn."""
    est, pinv = outcome.bayes, outcome.pinv
    figs = [
        (
            time_figure(s),
            "plot-time",
            "Force over time",
            "measured and fitted grasp force against time",
            "The dashed fitted force should lie on the measured (filtered) force throughout; "
            "the grey trace is the raw signal before smoothing.",
        ),
        (
            loop_figure(s),
            "plot-loop",
            "Force against jaw closure",
            "grasp force against jaw closure, measured and fitted",
            "The loop opens because damping adds force while closing and removes it while "
            "opening; the fitted loop should trace the measured one, including its curvature.",
        ),
        (
            residual_figure(s),
            "plot-residuals",
            "Residuals",
            "residual force over time and its histogram",
            _residual_caption(s),
        ),
    ]
    if s.v is not None:
        figs.append(
            (
                residual_map_figure(s),
                "plot-residual-map",
                "Residuals against closure and speed",
                "residual force against jaw closure and against closing speed",
                "The binned means should stay on zero: a curve against closure says the "
                "stiffness form is wrong (x where x + x³ or contact is needed), one against "
                "speed that the damping or friction form is.",
            )
        )
    if s.elastic is not None:
        figs.append(
            (
                elastic_figure(s),
                "plot-elastic",
                "Elastic force against closure",
                "measured force less the fitted damping, inertia and offset, against closure",
                "The points are what the data say the position terms must carry (the "
                "measured force less every other fitted term); the curve is what the "
                "chosen stiffness or contact law gives. Curvature the line misses, or a "
                "contact point where force starts, shows here.",
            )
        )
    best = est.best_ if est is not None else None
    if best is not None and best.model.memory and best.shape_posterior:
        ci = {k: list(v["ci95"]) for k, v in best.shape_posterior.items()}
        assert best.posterior is not None
        figs.append(
            (
                relaxation_figure(best.model, best.posterior.mean, ci),
                "plot-relaxation",
                "Stress relaxation",
                "force after a 1 mm step in closure against time, log scale",
                "The law's force after a sudden 1 mm squeeze held still: each relaxation "
                "branch decays with its time constant (dotted) towards the equilibrium "
                "stiffness. Time constants outside the range the session resolves were not "
                "searched.",
            )
        )
    if est is not None:
        corner = _corner(est)
        if corner is None:
            parts.append(
                "<p>Too few posterior draws inside the positivity bounds for a corner plot.</p>"
            )
        else:
            figs.append(corner)
    if pinv is not None:
        match = matching(pinv, est)
        figs.append(
            (
                windows_figure(pinv, match),
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
    return figs, parts


def _residual_caption(s: Series) -> str:
    text = (
        "Residuals should look like noise: no drift or pattern repeating with the squeezes, "
        "and a histogram matching the solid Gaussian"
    )
    if s.sigma is None:
        return text + " of the residual RMS."
    if s.expected_sd is not None and abs(s.expected_sd / s.sigma - 1) > 0.01:
        return text + (
            " of the SD the fit expects (force noise σ plus position noise carried through the "
            "law; σ alone is dashed)."
        )
    return text + " of the posterior noise SD."


def _corner(est: BayesianFit) -> tuple[Figure, str, str, str, str] | None:
    """The corner plot of the best form's posterior draws, or None with too few draws."""
    post = est.best_.posterior
    assert post is not None
    draws = post.samples
    if draws.shape[0] > MAX_DRAWS:
        keep = np.random.default_rng(0).choice(draws.shape[0], MAX_DRAWS, replace=False)
        draws = draws[np.sort(keep)]
    if draws.shape[0] < 20:
        return None
    return (
        corner_figure(draws, est.best_.model, post.mean, post.ci95),
        "plot-corner",
        f"Posterior of K, S, M ({est.best_.name})",
        "corner plot of the posterior draws of K, S and M",
        f"{draws.shape[0]:,} posterior draws in SI units; solid lines: means, "
        "dashed: 95 % intervals. Look for compact clouds away from zero; ρ is "
        "the correlation between two parameters (near ±1: the data separate "
        "them poorly).",
    )
