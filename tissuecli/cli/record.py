"""``tissuecli record``: a session from the forceps into an HDF5 file."""

from __future__ import annotations

import sys
from typing import Any

import click

from .base import cli, end_live_line, live_line
from .options import duration_option, h5_out_option, label_options


def _status_line(session: str) -> Any:
    def show(s: Any) -> None:
        live_line(
            f"recording {session}: {s.elapsed_s:7.1f} s  {s.samples:>9,d} samples  "
            f"{s.rate_hz:7.1f} Hz  bad {s.bad_frames}  lost {s.lost_frames}  "
            f"{s.file_bytes / 1e6:6.2f} MB"
        )

    return show


@cli.command()
@click.option(
    "--port", required=True, help="Device path (e.g. /dev/ttyUSB0, /tmp/forceps) or pyserial URL."
)
@h5_out_option()
@click.option(
    "--session", default=None, help="Session name [default: session-<UTC time>]. Never overwritten."
)
@duration_option("Seconds to record (device time); default until Ctrl-C or SIGTERM.")
@label_options(note_help="Operator note stored with the session.")
@click.option(
    "--calibration",
    type=click.Path(dir_okay=False),
    default=None,
    help="Counts-to-SI JSON for devices that do not report one (docs/formats.md).",
)
@click.option("--baud", type=int, default=921600, show_default=True, help="Line rate in bit/s.")
@click.option("--quiet", is_flag=True, help="No live status line.")
def record(
    port: str,
    out: str,
    session: str | None,
    duration: float | None,
    tissue: str,
    note: str,
    calibration: str | None,
    baud: int,
    quiet: bool,
) -> None:
    """Record a session from the forceps into an HDF5 file.

    Everything received is flushed to disk at least every 0.25 s, so a crash
    or power cut loses at most that; Ctrl-C and SIGTERM stop cleanly and lose
    nothing. A device that vanishes ends the recording with the data saved and
    exit code 1.

    \b
    Example:
        tissuecli record --port /tmp/forceps --out grasp.h5 --duration 10 --session liver-1
    """
    from datetime import datetime, timezone

    from ..app.record import record as run
    from ..formats.params import read_calibration
    from ..hw.realtime import StopFlag

    name = session or "session-" + datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S")
    status = None if quiet else _status_line(name)
    try:
        result = run(
            port,
            out,
            name,
            status_interval_s=0.5 if sys.stderr.isatty() else 5.0,  # logs get a line every 5 s
            duration_s=duration,
            tissue=tissue,
            note=note,
            calibration=read_calibration(calibration) if calibration else None,
            baudrate=baud,
            stop=StopFlag().install(),
            on_status=status,
        )
    finally:
        if status is not None:
            end_live_line()
    drift = f", clock drift {result.clock_map.drift_ppm:+.0f} ppm" if result.clock_map else ""
    click.echo(
        f"saved {result.samples} samples ({result.duration_s:.3f} s at {result.rate_hz:.1f} Hz) "
        f"to {result.path} session {result.session!r}: {result.bad_frames} bad, "
        f"{result.lost_frames} lost frames{drift}; {result.stop_reason}"
    )
