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
    reading,
    reading_progress,
    recording_options,
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
        f"{'lost':>5} {'bad':>5}  {'status':<10}  {'ended':<12}  tissue"
    )
    for r in rows:
        status, _, reason = r["status"].partition(": ")
        if reason:  # damaged: no figures, the reason where the tissue goes
            click.echo(
                f"{printable(r['name']):<20} {'-':>9} {'-':>10} {'-':>8} {'-':>5} {'-':>5}  "
                f"{status:<10}  {'-':<12}  {printable(reason, 120)}"
            )
            continue
        notes = [_fault(k, n) for k, n in (r.get("clock_faults") or {}).items()]
        notes += r.get("warnings") or []
        # an imported session's losses are what the import counted: samples missing
        # from its clock, lines that were not data
        lost, bad = r["frames_lost"], r["frames_bad"]
        if r.get("import_samples_lost") is not None:
            lost += r["import_samples_lost"]
            bad += r.get("import_lines_skipped") or 0
            notes.append(
                f"import: {r['import_samples_lost']} sample(s) missing from the clock, "
                f"{r.get('import_lines_skipped') or 0} line(s) skipped"
            )
        if r.get("ended") not in ("", "duration", "signal", "imported"):
            notes.append(f"stopped: {printable(r.get('stop_reason') or r['ended'], 80)}")
        note = f"  ({'; '.join(notes)})" if notes else ""
        click.echo(
            f"{printable(r['name']):<20} {r['samples']:>9d} {_num(r['duration_s'], 10, 3)} "
            f"{_num(r['rate_hz'], 8, 1)} {lost:>5d} {bad:>5d}  "
            f"{status:<10}  {printable(r.get('ended') or '-', 12):<12}  "
            f"{printable(r.get('tissue', ''), 60)}{note}"
        )


#: how the table names each clock fault of a session (``clock_faults`` of list_sessions)
_FAULT_WORDS = {
    "clock_jumps": ("clock jump", "clock jumps"),
    "clock_steps": ("clock step", "clock steps"),
    "sequence_restarts": ("sequence restart", "sequence restarts"),
    "frames_rejected": ("frame rejected", "frames rejected"),
}


def _fault(key: str, n: int) -> str:
    one, many = _FAULT_WORDS.get(key, (key, key))
    return f"{n} {one if n == 1 else many}"


def _num(value: float | None, width: int, digits: int) -> str:
    return f"{value:>{width}.{digits}f}" if value is not None else f"{'-':>{width}}"


@cli.command("import")
@file_argument("source")
@h5_out_option()
@session_option("Name of the new session [default: the name of SOURCE without its extension].")
@recording_options()
@click.option(
    "--calibration",
    type=click.Path(dir_okay=False),
    default=None,
    help="Counts-to-SI JSON, as record takes (docs/formats.md): force and position are "
    "ADC counts; --units then names the time unit only.",
)
@label_options()
def import_(
    source: str,
    out: str,
    session: str | None,
    columns: str | None,
    units: str | None,
    jaw_length: str | None,
    rate: float | None,
    sheet: str | None,
    calibration: str | None,
    tissue: str,
    note: str,
) -> None:
    """Import a recording from another logger as a new session.

    SOURCE is a text table (comma, tab, semicolon or space separated; header, a
    units row, comments and junk lines allowed; UTF-8, UTF-16, cp1252, GBK or
    Shift-JIS), a spreadsheet (.xlsx, .xls, .ods: each sheet with data becomes a
    session named after it, or --sheet NAME picks one), a MATLAB .mat (v5 to v7.3),
    a NumPy .npz, another program's HDF5 or a LabVIEW TDMS file. Columns are found
    by header name unless --columns says; time stamps from a coarse or jittery clock
    are put back on their regular clock.

    \b
    Examples:
        tissuecli import lab.csv --out grasp.h5 --session bench-3 --units mm,gf
        tissuecli import log.tsv --out grasp.h5 --session cadaver-1 \\
            --columns time=t_ms,force=force_g,position=angle_deg \\
            --units time=ms,force=gf,position=deg --jaw-length 20mm
        tissuecli import rig.mat --out grasp.h5 --session rig-1 --columns time=t,force=F,position=x
        tissuecli import specimens.xlsx --out grasp.h5      # a session per sheet
        tissuecli import counts.csv --out grasp.h5 --calibration forceps-cal.json
    """
    from ..app.transfer import import_recordings

    for s, report in import_recordings(
        source,
        out,
        session,
        **reading(columns, units, jaw_length, rate, sheet),
        calibration=calibration,
        tissue=tissue,
        note=note,
        progress=reading_progress(source),
    ):
        for line in report.lines():
            click.echo(line)
        click.echo(
            f"imported {len(s)} samples ({s.duration_s:.3f} s at {s.rate_hz:.1f} Hz) "
            f"into {out} session {s.name!r}"
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
