"""``tissuecli demo``: the whole pipeline on simulated devices."""

from __future__ import annotations

import click

from .base import cli


@cli.command()
@click.option(
    "--duration",
    type=click.FloatRange(min=1),
    default=5.0,
    show_default=True,
    help="Seconds to record from the simulated forceps.",
)
@click.option(
    "--dir",
    "workdir",
    type=click.Path(file_okay=False),
    default=None,
    help="Keep the files here instead of a temporary directory.",
)
@click.option(
    "--force",
    is_flag=True,
    help="Replace demo.csv, tissue.json and report.html in --dir if they exist.",
)
def demo(duration: float, workdir: str | None, force: bool) -> None:
    """Everything on simulated devices: simulate, record, list, export, fit, report, play.

    A recording that lost frames or a faulty play ends the demo with "Error: the
    demo ran with faults: ..." and the exit status of the worst fault (3 data lost,
    4 watchdog, 5 loop off rate, 6 not rendered as checked, 7 a device lost;
    docs/usage.md).

    \b
    Example:
        tissuecli demo --dir demo-files
    """
    from ..app.demo import run_demo

    run_demo(duration_s=duration, workdir=workdir, say=click.echo, force=force)
