"""``tissuecli live``: record the forceps, identify online and render it on the display."""

from __future__ import annotations

from typing import Any

import click

from .base import cli, end_by_signal, end_live_line, live_line
from .options import duration_option, rate_option, realtime_option, say_once, session_option


def _status_line(s: dict[str, Any]) -> None:
    live_line(
        f"live: {s['elapsed_s']:7.1f} s  {s['samples']} samples  "
        f"{'RENDERING' if s['rendering'] else '0 V      '}  {s['estimate']}"
    )


@cli.command()
@click.option("--forceps", required=True, help="The forceps' port (device path or URL).")
@click.option("--display", required=True, help="The display's port (device path or URL).")
@click.option(
    "--out",
    required=True,
    type=click.Path(dir_okay=False),
    help="HDF5 file to record to (created if missing; existing sessions untouched).",
)
@session_option("Session name (default live-<UTC time>).")
@duration_option("Seconds to record; default until Ctrl-C or SIGTERM.")
@rate_option("The display's loop rate in Hz.")
@realtime_option()
def live(
    forceps: str,
    display: str,
    out: str,
    session: str | None,
    duration: float | None,
    rate: float,
    no_realtime: bool,
) -> None:
    """Feel the tissue while it is grasped: record the forceps, identify the tissue
    online and render the estimate on the solenoid display.

    The recording is the one `record` makes. The display stays at 0 V until the
    online estimate is confident, and goes back to 0 V when confidence is lost, the
    forceps falls silent or either device goes. Updates are blended in without
    creating energy, and a passivity controller dissipates any the loop creates. At
    the end: the rendered force against the law fitted offline to the same
    recording, the delay to the first rendering and the energy figures.

    Exit status (docs/usage.md): 3 the recording lost frames, 4 the display's
    watchdog fired, 5 the display loop ran off its rate, 7 either device was lost
    (the recording is kept), 128 + the signal after Ctrl-C (130), SIGTERM or SIGHUP.

    \b
    Examples:
        tissuecli simulate forceps --link /tmp/forceps &
        tissuecli simulate display --link /tmp/display &
        tissuecli live --forceps /tmp/forceps --display /tmp/display --out live.h5 --duration 20
    """
    from ..app.live import live as run_live
    from ..app.summaries import live_lines
    from ..hw.realtime import StopFlag

    stop = StopFlag().install()
    try:
        summary = run_live(
            forceps,
            display,
            out,
            session,
            duration,
            rate_hz=rate,
            stop=stop,
            realtime=not no_realtime,
            on_status=_status_line,
            on_message=say_once,
        )
    finally:
        end_live_line()
    for line in live_lines(summary):
        click.echo(line)
    if summary.get("faults"):
        from ..core.errors import RunFault

        rec = summary["recording"]
        raise RunFault(
            "the live run was faulty: " + "; ".join(summary["faults"]) + f" (the recording "
            f"is saved in {rec['path']}, session {rec['session']!r})",
            summary["exit_code"],
        )
    end_by_signal(stop)
