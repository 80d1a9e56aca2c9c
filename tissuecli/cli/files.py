"""``tissuecli sessions|import|export``: what a file holds, and CSV in and out."""

from __future__ import annotations

import json

import click

from .base import cli, printable
from .options import (
    file_argument,
    force_option,
    h5_out_option,
    label_options,
    session_option,
    units_option,
)


@cli.command()
@file_argument()
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
def sessions(file: str, as_json: bool) -> None:
    """List the sessions in an HDF5 file.

    \b
    Example:
        tissuecli sessions grasp.h5 --json
    """
    from ..formats.sessions import list_sessions

    rows = list_sessions(file)
    if as_json:
        click.echo(json.dumps(rows, indent=2))
        return
    if not rows:
        click.echo(f"{file} holds no sessions")
        return
    click.echo(
        f"{'session':<20} {'samples':>9} {'duration s':>10} {'rate Hz':>8} "
        f"{'lost':>5} {'bad':>5}  tissue"
    )
    for r in rows:
        flag = "" if r.get("complete", True) else "  (incomplete)"
        click.echo(
            f"{printable(r['name']):<20} {r['samples']:>9d} {r['duration_s']:>10.3f} "
            f"{r['rate_hz']:>8.1f} {r['frames_lost']:>5d} {r['frames_bad']:>5d}  "
            f"{printable(r.get('tissue', ''), 60)}{flag}"
        )


@cli.command("import")
@file_argument("csv_file")
@h5_out_option()
@session_option("Name of the new session.", required=True)
@units_option("Units of the CSV columns, any order, e.g. 'mm,gf' or 'ms,mN,um' [default: s,N,m].")
@label_options()
def import_(
    csv_file: str, out: str, session: str, units: str | None, tissue: str, note: str
) -> None:
    """Import a CSV with header time,force,position as a new session.

    \b
    Example (position in mm, force in grams-force):
        tissuecli import lab.csv --out grasp.h5 --session bench-3 --units mm,gf
    """
    from ..app.transfer import import_csv

    s = import_csv(csv_file, out, session, units=units, tissue=tissue, note=note)
    click.echo(
        f"imported {len(s)} samples ({s.duration_s:.3f} s at {s.rate_hz:.1f} Hz) "
        f"into {out} session {session!r}"
    )


@cli.command()
@file_argument()
@session_option("Session to export [default: the only one].")
@click.option(
    "--csv", "csv_out", required=True, type=click.Path(dir_okay=False), help="CSV file to write."
)
@units_option("Units to write, e.g. 'mm,gf' [default: s,N,m].")
@force_option()
def export(file: str, session: str | None, csv_out: str, units: str | None, force: bool) -> None:
    """Export a session to CSV (header time,force,position).

    \b
    Example:
        tissuecli export grasp.h5 --session liver-1 --csv liver-1.csv --units mm,gf
    """
    from ..app.transfer import export_csv

    s = export_csv(file, session, csv_out, units=units, force=force)
    click.echo(f"wrote {len(s)} samples of session {s.name!r} to {csv_out}")
