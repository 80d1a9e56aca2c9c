"""``tissuecli play``: render an identified tissue on the solenoid display."""

from __future__ import annotations

from typing import Any

import click

from ..core.errors import InputError, RenderError
from .base import cli, end_by_signal, end_live_line, live_line
from .options import (
    duration_option,
    file_argument,
    force_option,
    profile_option,
    rate_option,
    realtime_option,
    say_once,
)


def _status_line(s: dict[str, Any]) -> None:
    live_line(
        f"playing: {s['duration_s']:7.1f} s  error rms {s['tracking_rms_m'] * 1e6:6.1f} um  "
        f"saturated {s['saturated_fraction']:6.1%}  unrenderable "
        f"{s['unrenderable_fraction']:6.1%}  {s['loop_rate_hz']:7.1f} Hz  "
        f"lost {s['frames_lost']}"
    )


@cli.command()
@file_argument("params_file")
@click.option(
    "--port",
    default=None,
    help="Display path (e.g. /dev/ttyUSB1, /tmp/display) or pyserial URL; not needed with --check.",
)
@duration_option("Seconds to play; default until Ctrl-C or SIGTERM.")
@rate_option("Control-loop rate in Hz; must be the display's.")
@click.option(
    "--log",
    type=click.Path(dir_okay=False),
    default=None,
    help="HDF5 file to log every frame to, as group plays/<name> (never overwritten).",
)
@click.option(
    "--summary",
    "summary_file",
    type=click.Path(dir_okay=False),
    default=None,
    help="Write the summary (or with --check the verdict) as JSON here.",
)
@click.option(
    "--check",
    "check_only",
    is_flag=True,
    help="Only report the renderable band and the verdict; open no port, move nothing.",
)
@profile_option("Display profile JSON (SI); default: what the display reports, else the paper's.")
@realtime_option()
@force_option()
def play(
    params_file: str,
    port: str | None,
    duration: float | None,
    rate: float,
    log: str | None,
    summary_file: str | None,
    check_only: bool,
    profile_file: str | None,
    no_realtime: bool,
    force: bool,
) -> None:
    """Render an identified tissue on the solenoid haptic display.

    The tissue is checked first: a display that would saturate below a firm grasp
    (3.4 N), a tissue softer than the display's spring, or an unstable loop are
    refused with the reason. Ctrl-C, SIGTERM, a lost display or any error leave
    the solenoid at 0 V.

    After a faulty play the summary and log are written, then "Error: the play was
    faulty: ..." says why, with the exit status of its class (docs/usage.md): 4 the
    display's watchdog fired, 5 the loop rate more than 2 % off or over 5 % of
    periods missed, 3 frames lost, 6 the tracking error beyond its bound by over
    0.4 mm, over 5 % of frames saturated or 30 % unrenderable (docs/rendering.md).
    A display lost mid-play ends with exit 7 after the summary up to the loss and
    the log are written. A play ended by Ctrl-C, SIGTERM or SIGHUP (the terminal
    closed) sends 0 V, writes its summary and exits 128 + the signal (130 Ctrl-C).

    \b
    Examples:
        tissuecli simulate display --link /tmp/display &
        tissuecli play liver.json --port /tmp/display --duration 20 --log plays.h5
        tissuecli play liver.json --check        # the band and the verdict only
    """
    from ..app.play import PlayFaults, PlayLost, check_file, play_file
    from ..app.summaries import play_lines
    from ..hw.realtime import StopFlag

    if check_only:
        result = check_file(
            params_file, profile=profile_file, rate_hz=rate, summary=summary_file, force=force
        )
        for line in result.lines():
            click.echo(line)
        if not result.renderable:
            raise RenderError("the display cannot render this tissue: " + "; ".join(result.reasons))
        return
    if port is None:
        raise InputError("give the display's port with --port (or use --check)")
    faulty: PlayFaults | PlayLost | None = None
    stop = StopFlag().install()
    try:
        summary = play_file(
            params_file,
            port,
            duration,
            profile=profile_file,
            summary=summary_file,
            force=force,
            rate_hz=rate,
            log=log,
            stop=stop,
            on_status=_status_line,
            realtime=not no_realtime,
            on_message=say_once,
        )
    except (PlayFaults, PlayLost) as exc:  # the figures first, then the one-line error
        summary, faulty = exc.summary, exc
    finally:
        end_live_line()
    for line in play_lines(summary):
        click.echo(line)
    if faulty is not None:
        raise faulty
    end_by_signal(stop)
