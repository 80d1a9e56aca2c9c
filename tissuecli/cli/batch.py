"""Many sessions: ``fit``'s batch options and report, and ``catalogue``, ``compare`` and
``classify`` over the catalogue they fill."""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable
from typing import Any

import click

from .base import cli, printable
from .options import Decorator, force_option


def batch_options() -> Decorator:
    """``--catalogue``, ``--manifest``, ``--jobs``, ``--scheduler``, ``--on-error``, ``--refit``."""

    def apply(fn: Callable[..., Any]) -> Callable[..., Any]:
        for option in reversed(
            [
                click.option(
                    "--catalogue",
                    type=click.Path(dir_okay=False),
                    default=None,
                    help="SQLite catalogue to add the fits to (created if missing); a session "
                    "already there with the same settings is not fitted again.",
                ),
                click.option(
                    "--manifest",
                    type=click.Path(dir_okay=False, exists=True),
                    default=None,
                    help="CSV of labels: columns file[,session],tissue,specimen,operator,note "
                    "(more columns become labels too); files relative to the manifest.",
                ),
                click.option(
                    "--jobs",
                    type=click.IntRange(min=1),
                    default=None,
                    help="Worker processes [default: every core for several sessions].",
                ),
                click.option(
                    "--scheduler",
                    default=None,
                    metavar="tcp://HOST:PORT",
                    help="Run the fits on this Dask distributed cluster (pip install "
                    "'tissuecli[dask]').",
                ),
                click.option(
                    "--on-error",
                    type=click.Choice(["continue", "stop"]),
                    default=None,
                    help="For several sessions: go on after a failure and list the failures "
                    "at the end (the default), or stop at the first.",
                ),
                click.option(
                    "--refit",
                    is_flag=True,
                    help="Fit sessions already in the catalogue again.",
                ),
            ]
        ):
            fn = option(fn)
        return fn

    return apply


class ProgressBar:
    """``fitted 120/400 [#####-----] 2:31 left`` on stderr: rewritten in place on a
    terminal; in a log, a line every 10 s and at the end."""

    def __init__(self) -> None:
        self.tty = sys.stderr.isatty()
        self.last = 0.0
        self.shown = False

    def __call__(self, done: int, total: int, left_s: float | None) -> None:
        now = time.monotonic()
        end = done >= total
        if not self.tty and not end and now - self.last < 10.0:
            return
        self.last = now
        width = 24
        fill = int(width * done / total) if total else width
        eta = "" if left_s is None or end else f" {_clock(left_s)} left"
        line = f"fitted {done}/{total} [{'#' * fill}{'-' * (width - fill)}]{eta}"
        click.echo(("\r" + line + "\033[K") if self.tty else line, err=True, nl=end or not self.tty)
        self.shown = not end


def _clock(seconds: float) -> str:
    s = int(round(seconds))
    return (
        f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"
    )


def run_batch(items: Any, *, settings: dict[str, Any], **options: Any) -> None:
    """Fit many sessions (:func:`tissuecli.app.batch.fit_batch`), print what happened,
    and exit 1 if any failed (said in the last line)."""
    from ..app.batch import fit_batch

    bar = ProgressBar()
    result = fit_batch(items, progress=bar, **options, **settings)
    if bar.shown:
        click.echo(err=True)
    if result.fitted:
        width = min(max(len(f.session) for f in result.fitted), 40)
        click.echo(f"{'session':<{width}}  {'tissue':<10} {'specimen':<12} {'P':>5}  law")
        for f in result.fitted:
            p = "" if f.probability is None else f"{f.probability:.2f}"
            tissue = printable(f.labels.get("tissue", ""), 10)
            specimen = printable(f.labels.get("specimen", ""), 12)
            click.echo(
                f"{printable(f.session, width):<{width}}  {tissue:<10} {specimen:<12} {p:>5}  "
                f"{f.law or '-'}"
            )
    for item, why in result.failed:
        click.echo(f"failed: {printable(item, 120)}: {why}")
    skipped = (
        f", {len(result.skipped)} already in the catalogue with these settings (--refit "
        "fits them again)"
        if result.skipped
        else ""
    )
    relabelled = f", {result.relabelled} relabelled" if result.relabelled else ""
    click.echo(
        f"{len(result.fitted)} of {result.inputs} session(s) fitted on {result.executor} in "
        f"{result.seconds:.1f} s{skipped}{relabelled}"
    )
    where = options.get("catalogue")
    stored = (
        f"catalogue {where} holds {result.catalogue_fits} fit(s)"
        if where
        else "nothing stored: give --catalogue to keep the fits"
    )
    if result.failed:
        click.echo(
            f"{len(result.failed)} of {result.inputs} session(s) failed (listed above); {stored}"
        )
        click.get_current_context().exit(1)
    click.echo(f"no failures; {stored}")


@cli.command("catalogue")
@click.argument("catalogue_file", type=click.Path(dir_okay=False))
@click.option(
    "--where",
    multiple=True,
    help="Keep fits whose column equals a value, e.g. tissue=liver (repeatable).",
)
@click.option("--json", "as_json", is_flag=True, help="One JSON object per fit, for scripts.")
@click.option(
    "--export",
    type=click.Choice(["csv", "parquet"]),
    default=None,
    help="Write the fits as a table (one row per fit, each coefficient's mean and SD) "
    "for pandas, DuckDB or R; parquet needs pyarrow.",
)
@click.option(
    "--out",
    type=click.Path(dir_okay=False),
    default=None,
    help="File for --export (never replaced).",
)
def catalogue_command(
    catalogue_file: str, where: tuple[str, ...], as_json: bool, export: str | None, out: str | None
) -> None:
    """List the fits of a catalogue, filter them, export them.

    \b
    Examples:
        tissuecli catalogue tissues.db
        tissuecli catalogue tissues.db --where tissue=liver --json
        tissuecli catalogue tissues.db --export parquet --out tissues.parquet
    """
    from ..app.compare import list_catalogue

    if export and not out:
        raise click.UsageError("--export needs --out FILE")
    if out and not export:
        raise click.UsageError("--out goes with --export csv or --export parquet")
    header, rows = list_catalogue(catalogue_file, where, export=export, out=out)
    if export:
        click.echo(f"{len(rows)} fit(s) written to {out}")
        return
    if as_json:
        for r in rows:
            click.echo(json.dumps(dict(zip(header, r, strict=True))))
        return
    shown = ["id", "session", "tissue", "specimen", "law", "law_probability", "noise_sd_N"]
    idx = [header.index(c) for c in shown]
    coef = [i for i, h in enumerate(header) if h.endswith("]") and "_mean" in h]
    click.echo(
        f"{'id':>4} {'session':<20} {'tissue':<10} {'specimen':<12} {'law':<22} {'P':>5} "
        f"{'noise mN':>8}  " + "  ".join(header[i].replace("_mean", "") for i in coef)
    )
    for r in rows:
        i, s, t, sp, law, p, noise = (r[j] for j in idx)
        vals = "  ".join(
            f"{'-' if r[i] is None else format(r[i], '.4g'):>{len(header[i]) - 5}}" for i in coef
        )
        click.echo(
            f"{i:>4} {printable(s, 20):<20} {printable(t, 10):<10} {printable(sp, 12):<12} "
            f"{printable(law or '-', 22):<22} {'' if p is None else format(p, '.2f'):>5} "
            f"{'' if noise is None else format(noise * 1e3, '.2f'):>8}  {vals}"
        )
    click.echo(f"{len(rows)} fit(s)")


def quantity_option() -> Decorator:
    return click.option(
        "--quantity",
        default="force:x=3mm,v=20mm/s",
        show_default=True,
        help="What to compare: a coefficient by symbol (K, S, ...; only fits whose law has "
        "it), or 'force:x=CLOSURE,v=SPEED', the tissue's force at that closure while "
        "closing at that speed, from each fit's posterior (compares across laws).",
    )


def scale_option() -> Decorator:
    """``--scale`` and ``--prior-sd``: the modelled scale and the group means' prior."""

    def apply(fn: Callable[..., Any]) -> Callable[..., Any]:
        fn = click.option(
            "--prior-sd",
            type=click.FloatRange(min=0, min_open=True),
            default=None,
            help="SD of the prior of the group means, on the modelled scale: how far apart "
            "you expect tissues to be [default: 1 on the log scale, a factor e; on the "
            "linear scale twice the values' spread]. The Bayes factors depend on it.",
        )(fn)
        return click.option(
            "--scale",
            type=click.Choice(["log", "linear"]),
            default="log",
            show_default=True,
            help="Model the quantity's logarithm (tissues differ by factors) or the quantity.",
        )(fn)

    return apply


def selection_options() -> Decorator:
    def apply(fn: Callable[..., Any]) -> Callable[..., Any]:
        fn = click.option(
            "--settings",
            "settings_id",
            default=None,
            help="Use the fits made with these settings (an id from "
            "`catalogue --json`), where the catalogue holds several.",
        )(fn)
        fn = click.option(
            "--where",
            multiple=True,
            help="Use only fits whose column equals a value, e.g. operator=operator-1.",
        )(fn)
        fn = click.option(
            "--by", default="tissue", show_default=True, help="The label that names the groups."
        )(fn)
        return click.option(
            "--catalogue",
            "catalogue_file",
            required=True,
            type=click.Path(dir_okay=False, exists=True),
            help="Catalogue written by fit --catalogue.",
        )(fn)

    return apply


@cli.command()
@selection_options()
@quantity_option()
@scale_option()
@click.option(
    "--report",
    type=click.Path(dir_okay=False),
    default=None,
    help="Write an HTML report with a forest plot (sessions, specimens, groups).",
)
@click.option(
    "--json",
    "json_out",
    type=click.Path(dir_okay=False),
    default=None,
    help="Write the numbers behind the comparison as JSON.",
)
@force_option()
def compare(
    catalogue_file: str,
    by: str,
    where: tuple[str, ...],
    settings_id: str | None,
    quantity: str,
    scale: str,
    prior_sd: float | None,
    report: str | None,
    json_out: str | None,
    force: bool,
) -> None:
    """Compare tissue groups across specimens: for each pair, P(A stiffer than B) with a
    95 % interval of the difference, and the Bayes factor for one tissue.

    Sessions within specimens within groups, normal at each level, each session's
    posterior as its likelihood (docs/estimators.md).

    \b
    Examples:
        tissuecli compare --catalogue tissues.db --by tissue --report compare.html
        tissuecli compare --catalogue tissues.db --quantity K --json compare.json
    """
    from ..app.compare import compare_catalogue, compare_lines

    comparison = compare_catalogue(
        catalogue_file,
        by=by,
        where=where,
        settings_id=settings_id,
        quantity=quantity,
        scale=scale,
        prior_sd=prior_sd,
        report=report,
        json_out=json_out,
        force=force,
    )
    for line in compare_lines(comparison):
        click.echo(line)
    for path, what in ((report, "report"), (json_out, "JSON")):
        if path:
            click.echo(f"{what} written to {path}")


@cli.command()
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("--session", default=None, help="Session of FILE [default: every session].")
@selection_options()
@click.option(
    "--quantity",
    "quantities",
    multiple=True,
    help="Quantities to classify by, as compare's --quantity (repeatable; taken as "
    "independent given the tissue, so give ones that vary independently, e.g. K and S) "
    "[default: force:x=3mm,v=20mm/s].",
)
@scale_option()
def classify(
    file: str,
    session: str | None,
    catalogue_file: str,
    by: str,
    where: tuple[str, ...],
    settings_id: str | None,
    quantities: tuple[str, ...],
    scale: str,
    prior_sd: float | None,
) -> None:
    """The probability of each tissue group for a new grasp: FILE's sessions are fitted
    with the catalogue's settings and set against the hierarchical model of the
    catalogue's groups (equal prior odds; quantities taken as independent).

    \b
    Example:
        tissuecli classify grasp.h5 --catalogue tissues.db
    """
    from ..app.compare import classify_file

    header, rows = classify_file(
        file,
        session=session,
        catalogue=catalogue_file,
        by=by,
        where=where,
        settings_id=settings_id,
        quantities=quantities or ("force:x=3mm,v=20mm/s",),
        scale=scale,
        prior_sd=prior_sd,
    )
    width = max([len("session"), *(len(r[0]) for r in rows)])
    click.echo(
        f"{'session':<{width}}  "
        + "  ".join(f"{printable(h, 10):>10}" for h in header)
        + "  most probable"
    )
    for name, probs in rows:
        best = header[max(range(len(probs)), key=probs.__getitem__)]
        click.echo(
            f"{printable(name, width):<{width}}  "
            + "  ".join(f"{p:10.3f}" for p in probs)
            + f"  {best}"
        )
