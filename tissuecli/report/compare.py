"""A self-contained HTML report of a comparison of tissue groups: a forest plot of every
session, specimen and group, the pairwise table, and the model; the JSON behind it is
the dict :func:`tissuecli.app.compare.compare_catalogue` returns."""

from __future__ import annotations

from typing import Any

from .figures import figure_html, new_figure
from .numbers import esc
from .sections import CSS, provenance

COLOURS = ("#1f5fa8", "#c0392b", "#2e8b57", "#8e44ad", "#d35400", "#16a085", "#7f8c8d")


def forest_figure(c: dict[str, Any]) -> Any:
    """Sessions (small grey), specimens (coloured) and groups (black diamonds), each with
    its 95 % interval, on one axis, grouped and ordered by group then specimen."""
    sessions, specimens, groups = c["sessions"], c["specimens"], c["groups"]
    rows = len(sessions) + len(specimens) + len(groups)
    fig = new_figure(8.0, min(max(3.0, 0.06 * rows + 1.5), 40.0))
    ax = fig.add_subplot()
    y = 0.0
    ticks, labels = [], []
    for gi, g in enumerate(groups):
        colour = COLOURS[gi % len(COLOURS)]
        for s in (s for s in specimens if s["group"] == g["name"]):
            for sess in (
                x for x in sessions if x["group"] == g["name"] and x["specimen"] == s["name"]
            ):
                ax.plot(sess["ci95"], [y, y], color="#b0b0b0", lw=0.8)
                ax.plot([sess["mean"]], [y], "o", color="#909090", ms=2)
                y += 1
            ax.plot(s["ci95"], [y, y], color=colour, lw=1.6)
            ax.plot([s["mean"]], [y], "s", color=colour, ms=4)
            y += 1.5
        ax.plot(g["ci95"], [y, y], color="black", lw=2.4)
        ax.plot([g["mean"]], [y], "D", color="black", ms=7)
        ticks.append(y)
        labels.append(f"{g['name']} (group)")
        y += 3
    if c["scale"] == "log":
        ax.set_xscale("log")
    ax.set_yticks(ticks, labels)
    ax.invert_yaxis()
    ax.set_xlabel(f"{c['quantity']['label']} ({c['quantity']['unit']})")
    ax.grid(axis="x", alpha=0.3)
    return fig


def render_comparison(c: dict[str, Any]) -> str:
    """The comparison as one HTML document (str)."""
    q = c["quantity"]
    unit = esc(q["unit"])
    kind = "A/B" if c["scale"] == "log" else "A − B"
    group_rows = "".join(
        f"<tr><td>{esc(g['name'])}</td><td class='n'>{g['specimens']}</td>"
        f"<td class='n'>{g['sessions']}</td><td class='n'>{g['mean']:.4g}</td>"
        f"<td class='n'>[{g['ci95'][0]:.4g}, {g['ci95'][1]:.4g}]</td></tr>"
        for g in c["groups"]
    )
    pair_rows = "".join(
        f"<tr><td>{esc(p['a'])}</td><td>{esc(p['b'])}</td><td class='n'>{p['p_a_greater']:.3f}</td>"
        f"<td class='n'>{p['difference']:.4g}</td>"
        f"<td class='n'>[{p['ci95'][0]:.4g}, {p['ci95'][1]:.4g}]</td>"
        f"<td class='n'>{p['ln_bayes_same']:.1f}</td><td>{esc(p['verdict'])}</td></tr>"
        for p in c["pairs"]
    )
    v = c["variation"]
    spread = (
        f"Specimens of a group differ by {100 * v['between_specimens_sd_scaled']:.1f} % (SD), "
        f"sessions of a specimen by {100 * v['between_sessions_sd_scaled']:.1f} %."
        if c["scale"] == "log"
        else f"Specimens of a group differ by {v['between_specimens_sd_scaled']:.4g} {unit} "
        f"(SD), sessions of a specimen by {v['between_sessions_sd_scaled']:.4g} {unit}."
    )
    figure = figure_html(
        forest_figure(c),
        "forest",
        "Forest plot",
        "each session, specimen and group with its 95 % interval",
        "Grey: each session's own posterior; coloured squares: each specimen's mean, shrunk "
        "toward its group; black diamonds: each group's mean. Intervals are 95 %.",
    )
    notes = "".join(f"<li>{esc(n)}</li>" for n in c["notes"])
    body = [
        f"<h1>Tissue comparison by {esc(c['by'])}</h1>",
        f"<p>{esc(q['label'])} ({unit}), on the {esc(c['scale'])} scale; "
        f"{len(c['sessions'])} sessions, fit settings {esc(c['settings_id'])}.</p>",
        "<h2>Groups</h2><table><tr><th>group</th><th>specimens</th><th>sessions</th>"
        f"<th>mean ({unit})</th><th>95 % interval</th></tr>{group_rows}</table>",
        f"<p>{esc(spread)}</p>",
        f"<h2>Pairs</h2><table><tr><th>A</th><th>B</th><th>P(A &gt; B)</th><th>{kind}</th>"
        "<th>95 % interval</th><th>ln BF (same)</th><th>verdict</th></tr>"
        f"{pair_rows}</table>",
        "<p class='small'>P(A &gt; B): the posterior probability that group A's mean is "
        "above B's (for a force or a stiffness: A stiffer than B). ln BF (same) &gt; 0 "
        "favours one tissue mean for A and B over two.</p>",
        figure,
        f"<h2>Notes</h2><ul>{notes}</ul>" if notes else "",
        "<h2>Model</h2><p>Sessions within specimens within groups, normal at each level; "
        "each session's posterior is its likelihood; the group means have a normal prior "
        f"(mean {c['model']['prior_mean_scaled']:.4g}, SD {c['model']['prior_sd_scaled']:.4g} "
        "on the modelled scale), the between-specimen and between-session SDs uniform priors "
        "integrated on a grid (docs/estimators.md).</p>",
        provenance(),
    ]
    return (
        "<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'>"
        "<meta name='viewport' content='width=device-width, initial-scale=1'>"
        f"<title>Tissue comparison by {esc(c['by'])}</title><style>{CSS}</style></head><body>"
        + "\n".join(body)
        + "</body></html>\n"
    )
