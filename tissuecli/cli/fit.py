"""``tissuecli fit``: identify the tissue law from a session."""

from __future__ import annotations

from typing import Any

import click

from .base import cli
from .batch import batch_options, run_batch
from .options import (
    force_option,
    reading,
    recording_options,
    seed_option,
    session_option,
)


def _grasps(text: str) -> str | list[int]:
    """``all``, ``none`` or a list of grasp numbers."""
    if text in ("all", "none"):
        return text
    try:
        return [int(p) for p in text.split(",") if p.strip()]
    except ValueError:
        raise click.BadParameter("give all, none or grasp numbers such as 1,3") from None


@cli.command()
@click.argument("files", nargs=-1, required=True, type=click.Path())
@session_option("Session to fit [default: every session of the file].")
@recording_options()
@click.option(
    "--out",
    type=click.Path(dir_okay=False),
    default=None,
    help="Write the parameter file (JSON, SI) for `play` and `simulate forceps --params`.",
)
@click.option(
    "--report",
    type=click.Path(dir_okay=False),
    default=None,
    help="Write a self-contained HTML report with plots.",
)
@click.option(
    "--draws",
    type=click.Path(dir_okay=False),
    default=None,
    help="Write the chosen law's posterior draws (CSV, one column per parameter with its "
    "unit; pandas and ArviZ read it) and the structure probabilities beside it "
    "(FILE's stem + .structures.csv).",
)
@click.option(
    "--plots",
    type=click.Path(file_okay=False),
    default=None,
    help="Write the report's plots as files into this directory (created if missing).",
)
@click.option(
    "--plot-format",
    type=click.Choice(["png", "svg", "pdf"]),
    default=None,
    help="Format of the plot files [default: png]; without --plots, they go beside "
    "--report, in REPORT's stem + _plots.",
)
@click.option(
    "--method",
    type=click.Choice(["bayes", "pinv", "both"]),
    default="bayes",
    show_default=True,
    help="bayes: every form with posteriors and model choice; pinv: the paper's "
    "windowed pseudoinverse alone; both.",
)
@click.option(
    "--forms",
    default="all",
    show_default=True,
    help="Candidate laws: 'all' (the 24 linear laws: x, x^3 or both, with xdot or "
    "xdot|xdot|, with or without dry friction and a force offset, all with xddot; then a "
    "search adding contact and relaxation branches: about 30 laws), 'linear' (the 24), "
    "'paper' (the paper's four), or one law: x,xdot or terms joined by +, "
    "e.g. x+x^3+xdot+sign(xdot)+offset.",
)
@click.option(
    "--sampler",
    type=click.Choice(["auto", "emcee"]),
    default="auto",
    show_default=True,
    help="auto samples only where the exact posterior does not apply; emcee samples "
    "every form and checks its evidence by stepping-stone.",
)
@click.option(
    "--differentiator",
    default="gaussian",
    show_default=True,
    help="How velocity and acceleration are estimated: gaussian, savgol or gradient "
    "(any registered differentiator).",
)
@click.option(
    "--window",
    type=click.FloatRange(min=0, min_open=True),
    default=1.0,
    show_default=True,
    help="pinv window length in s.",
)
@click.option(
    "--force-scale",
    type=click.FloatRange(min=0, min_open=True),
    default=None,
    help="Prior scale in N: the force each term may reach at the session's typical motion "
    "[default: five times the session's largest force].",
)
@click.option(
    "--grasps",
    default="all",
    show_default=True,
    help="Where grasps alternate with free jaw motion: fit every grasp (all), every sample "
    "(none), or the grasps numbered, e.g. 1,3.",
)
@click.option(
    "--hold-out",
    type=click.FloatRange(0.0, 1.0, max_open=True),
    default=0.0,
    help="Keep this fraction of the session, at its end, out of the fit and report how "
    "well the fit predicts it, e.g. 0.3.",
)
@click.option("--start", type=float, default=None, help="Fit from this time on, s.")
@click.option("--end", type=float, default=None, help="Fit up to this time, s.")
@seed_option("Seed of the sampler.")
@force_option()
@batch_options()
def fit(
    files: tuple[str, ...],
    session: str | None,
    columns: str | None,
    units: str | None,
    jaw_length: str | None,
    rate: float | None,
    sheet: str | None,
    out: str | None,
    report: str | None,
    draws: str | None,
    plots: str | None,
    plot_format: str | None,
    method: str,
    forms: str,
    sampler: str,
    differentiator: str,
    window: float,
    force_scale: float | None,
    grasps: str,
    hold_out: float,
    start: float | None,
    end: float | None,
    seed: int,
    force: bool,
    catalogue: str | None,
    manifest: str | None,
    jobs: int | None,
    scheduler: str | None,
    on_error: str | None,
    refit: bool,
) -> None:
    """Identify the tissue law K f0(x) + S f1(xdot) + M xddot = F (and laws beyond it:
    offset, friction) from a session, choosing among the candidate laws by evidence.

    FILES are tissuecli HDF5 files, or any recording `import` reads (text table,
    spreadsheet sheet, .mat, .npz, other programs' HDF5 and TDMS), read on the fly
    with --columns, --units, --jaw-length, --rate and --sheet;
    folders and patterns ('data/**/*.h5') name every file in them. Several
    sessions are fitted in parallel (--jobs, or --scheduler for a Dask cluster)
    into a catalogue (--catalogue); a session already there with the same
    settings is not fitted again.

    Where grasps alternate with free jaw motion, the grasps are found against the
    free-jaw force and fitted alone.

    \b
    Examples:
        tissuecli fit grasp.h5 --session liver-1 --out liver.json --report liver.html
        tissuecli fit grasp.h5 --method pinv          # the paper's method alone
        tissuecli fit grasp.h5 --forms x,xdot         # one law, no model choice
        tissuecli fit grasp.h5 --grasps 2,3 --hold-out 0.3
        tissuecli fit grasp.h5 --start 12.5 --end 40
        tissuecli fit grasp.h5 --draws draws.csv --report r.html --plot-format svg
        tissuecli fit data/phantom_EF30_0T_A1.csv --forms "x+x^3+offset" \\
            --columns "time=Time (s),force=Load (N),position=Compression (mm)"
        tissuecli fit study.h5 'more/*.h5' --catalogue tissues.db --jobs 2
    """
    from ..app.batch import expand_inputs

    settings: dict[str, Any] = dict(
        grasps=_grasps(grasps),
        start_s=start,
        end_s=end,
        hold_out=hold_out,
        method=method,
        forms=forms,
        sampler=sampler,
        differentiator=differentiator,
        window_s=window,
        force_scale=force_scale,
        seed=seed,
    )
    items = expand_inputs(files, session)
    if len(items) > 1 or catalogue or manifest or jobs or scheduler:
        if out or report or draws or plots:
            raise click.UsageError(
                "--out, --report, --draws and --plots write one fit: give one input "
                "without --catalogue, or keep many fits in a --catalogue"
            )
        run_batch(
            items,
            catalogue=catalogue,
            manifest=manifest,
            jobs=jobs,
            scheduler=scheduler,
            on_error=on_error or "continue",
            refit=refit,
            reading=reading(columns, units, jaw_length, rate, sheet),
            settings=settings,
        )
        return
    from ..app.fit import fit_file, plots_beside, summary_lines
    from .progress import TerminalProgress

    if plot_format is not None and plots is None:
        if report is None:
            raise click.UsageError("--plot-format needs --plots DIR or --report FILE")
        plots = plots_beside(report)
    outcome = fit_file(
        items[0].file,
        items[0].session,
        out=out,
        report=report,
        draws=draws,
        plots=plots,
        plot_format=plot_format or "png",
        force=force,
        reading=reading(columns, units, jaw_length, rate, sheet),
        **settings,
        progress=TerminalProgress.for_terminal(),
    )
    for line in summary_lines(outcome):
        click.echo(line)
    if draws:
        from ..formats.draws import structures_path

        click.echo(f"posterior draws written to {draws}, structure probabilities to "
                   f"{structures_path(draws)}")  # fmt: skip
    for path, what in ((out, "parameters"), (report, "report"), (plots, "plots")):
        if path:
            click.echo(f"{what} written to {path}")
