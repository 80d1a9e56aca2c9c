"""``tissuecli record``: a session from the forceps into an HDF5 file."""

from __future__ import annotations

import sys
from typing import Any

import click

from .base import cli, end_by_signal, end_live_line, live_line
from .options import duration_option, h5_out_option, label_options, reading, recording_options


def _status_line(session: str, identify: bool) -> Any:
    def show(s: Any) -> None:
        faults = s.faults
        clock = (
            f"  clock jumps {faults.clock_jumps}  steps {faults.clock_steps}  "
            f"restarts {faults.sequence_restarts}  rejected {faults.frames_rejected}"
            if faults.any
            else ""
        )
        tissue = f"  {_estimate_line(s.estimate)}" if identify else ""
        live_line(
            f"recording {session}: {s.elapsed_s:7.1f} s  {s.samples:>9,d} samples  "
            f"{s.rate_hz:7.1f} Hz  bad {s.bad_frames}  lost {s.lost_frames}  "
            f"{s.file_bytes / 1e6:6.2f} MB{clock}{tissue}"
        )

    return show


def _estimate_line(est: Any) -> str:
    """The online estimate in a few words: the law and its coefficients with +- (half
    the 95 % interval) once confident, ``identifying...`` before."""
    if est is None or not est.confident:
        return "identifying..."
    return est.describe()


def _plural(n: int, word: str) -> str:
    return f"{n} {word}" + ("" if n == 1 else "s")


def _summary(result: Any) -> str:
    """The line printed after a recording: what was saved, every fault count, the clock."""
    f = result.faults
    clock = ""
    if result.clock_map is not None:
        m = result.clock_map
        drift = f"clock drift {m.drift_ppm:+.1f} +- {m.drift_uncertainty_ppm:.1f} ppm"
        clock = (
            f"; {drift}, time rescaled to host seconds"
            if result.time_rescaled
            else f"; {drift} (not resolved: time kept on the device clock)"
        )
    return (
        f"saved {result.samples} samples ({result.duration_s:.3f} s at {result.rate_hz:.1f} Hz) "
        f"to {result.path} session {result.session!r}: {result.bad_frames} bad, "
        f"{result.lost_frames} lost, {f.frames_rejected} rejected frames, "
        f"{_plural(f.clock_jumps, 'clock jump')}, {_plural(f.clock_steps, 'clock step')}, "
        f"{_plural(f.sequence_restarts, 'sequence restart')}{clock}; {result.stop_reason}"
    )


def _text_options(
    protocol: str, columns: str | None, units: str | None, jaw_length: str | None
) -> dict[str, Any]:
    """The text logger's reading options; refused beside the binary protocol."""
    if protocol != "text":
        given = [
            n for n, v in (("columns", columns), ("units", units), ("jaw-length", jaw_length)) if v
        ]
        if given:
            raise click.UsageError(f"--{given[0]} is for --protocol text")
        return {}
    options = reading(columns, units, jaw_length, None)
    del options["rate_hz"]
    return options


def _text_summary(result: Any) -> str:
    """The line printed after a recording from a text logger."""
    m = result.meta
    return (
        f"saved {result.samples} samples ({result.duration_s:.3f} s at {result.rate_hz:.1f} Hz) "
        f"to {result.path} session {result.session!r}: "
        f"{_plural(m.get('lines_received', 0), 'line')} received, "
        f"{m.get('lines_malformed', 0)} malformed, {result.lost_frames} lost, "
        f"{m.get('lines_ignored', 0)} ignored, "
        f"{_plural(m.get('stamps_rejected', 0), 'stamp')} rejected, "
        f"{_plural(m.get('clock_wraps', 0), 'clock wrap')}; time: {m.get('time_base', '')}; "
        f"{result.stop_reason}"
    )


def _show_url(url: str) -> None:
    from ..live.server import exposure_warning

    click.echo(f"live view: {url}")
    warning = exposure_warning(url)
    if warning:
        click.echo(warning, err=True)


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
@click.option(
    "--baud",
    type=int,
    default=None,
    help="Line rate in bit/s [default: 921600 binary, 115200 text].",
)
@click.option(
    "--protocol",
    type=click.Choice(["binary", "text"]),
    default="binary",
    show_default=True,
    help="binary: tissuecli's framed protocol (docs/protocol.md); text: a logger printing "
    "lines (t,force,pos with or without a header, Serial Plotter force:1.2 pos:3.4, "
    "Teleplot >force:1.2), read with --columns, --units, --jaw-length and --calibration "
    "as import reads files (docs/recording.md).",
)
@recording_options(rate=False)
@click.option(
    "--identify/--no-identify",
    default=True,
    show_default=True,
    help="Identify the tissue online while recording: the status line shows the most "
    "probable law with K, S, M +- half their 95 % intervals once they are confident "
    "(docs/estimators.md, Online identification).",
)
@click.option(
    "--forgetting",
    type=click.FloatRange(min=0, min_open=True),
    default=5.0,
    show_default=True,
    help="Online identification forgets with this time constant, s: a new tissue "
    "replaces the old one in a few of them.",
)
@click.option("--quiet", is_flag=True, help="No live status line.")
@click.option(
    "--live",
    is_flag=False,
    flag_value="127.0.0.1:0",
    default=None,
    metavar="[HOST:PORT]",
    help="Serve a live view (traces, loop, estimate, status) on a local web page; "
    "alone: 127.0.0.1 and a free port. The URL is printed.",
)
def record(
    port: str,
    out: str,
    session: str | None,
    duration: float | None,
    tissue: str,
    note: str,
    calibration: str | None,
    baud: int | None,
    protocol: str,
    columns: str | None,
    units: str | None,
    jaw_length: str | None,
    identify: bool,
    forgetting: float,
    quiet: bool,
    live: str | None,
) -> None:
    """Record a session from the forceps into an HDF5 file.

    Everything received is flushed to disk at least every 0.25 s, so a crash
    or power cut loses at most that; Ctrl-C, SIGTERM and SIGHUP (the terminal
    closed) stop cleanly and lose nothing, then exit 128 + the signal (130 for
    Ctrl-C). A device that vanishes ends the recording with the data saved and
    exit code 7; a recording that lost, corrupt or rejected frames prints its
    summary, then exits 3; one stopped before any sample arrived writes nothing.
    Frames whose clock or sequence number is absurd are repaired or rejected and
    counted (docs/recording.md; exit codes in docs/usage.md).

    While recording, the tissue is identified online (the paper's four laws, exact
    posteriors, forgetting older samples): the status line shows the current
    estimate, and the last one is printed at the end. The stored session is the
    same with or without it; `tissuecli fit` gives the full offline fit.

    \b
    Examples:
        tissuecli record --port /tmp/forceps --out grasp.h5 --duration 10 --session liver-1
        tissuecli record --port /tmp/forceps --out grasp.h5 --no-identify
        tissuecli record --port /tmp/forceps --out grasp.h5 --live
        tissuecli record --port /tmp/forceps --out grasp.h5 --live 127.0.0.1:8050
        tissuecli record --port /dev/ttyACM0 --protocol text --out grasp.h5 --units mm
    """
    from ..hw.realtime import StopFlag

    # first, so that Ctrl-C while the rest loads stops cleanly instead of raising
    stop = StopFlag().install()

    from datetime import datetime, timezone
    from functools import partial

    from ..app.record import record as run
    from ..formats.params import read_calibration

    name = session or "session-" + datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S")
    status = None if quiet else _status_line(name, identify)
    text = _text_options(protocol, columns, units, jaw_length)
    if live is not None:
        from ..app.record import record_live

        run = partial(record_live, live, on_url=_show_url)
    try:
        result = run(
            port,
            out,
            name,
            protocol=protocol,
            status_interval_s=0.5 if sys.stderr.isatty() else 5.0,  # logs get a line every 5 s
            duration_s=duration,
            tissue=tissue,
            note=note,
            calibration=read_calibration(calibration) if calibration else None,
            baudrate=baud,
            stop=stop,
            **text,
            on_status=status,
            identify=identify,
            forgetting_s=forgetting,
        )
    finally:
        if status is not None:
            end_live_line()
    click.echo(_text_summary(result) if protocol == "text" else _summary(result))
    if identify:
        est = result.estimate
        last = "no estimate (too few samples in contact)" if est is None else est.describe()
        click.echo(f"online estimate: {result.identify_note or last}")
    lost = lost_data(result)
    if lost:
        from ..core.errors import EXIT_LOST_DATA, RunFault

        raise RunFault(
            f"the recording lost data: {lost}; the {result.samples} samples received are "
            f"saved in {result.path}, session {result.session!r}",
            EXIT_LOST_DATA,
        )
    end_by_signal(stop)


def lost_data(result: Any) -> str:
    """What a recording lost, in words (``3 frames lost on the line, 2 corrupt``), or ''."""
    said = [
        f"{n} {what}"
        for n, what in (
            (result.lost_frames, "frame(s) lost"),
            (result.bad_frames, "corrupt"),
            (result.faults.frames_rejected, "rejected (absurd clock or sequence)"),
        )
        if n
    ]
    return ", ".join(said)
