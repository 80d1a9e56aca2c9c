"""``tissuecli calibrate``: the forceps' channels and the display's constants."""

from __future__ import annotations

from typing import Any

import click

from .base import cli


@cli.group()
def calibrate() -> None:
    """Measure a device's constants: the forceps' gains and offsets, the display's profile.

    \b
    Examples:
        tissuecli calibrate forceps --loads loads.csv --gaps gaps.csv --out cal.json
        tissuecli calibrate display --port /tmp/display --mass 200g --out display.json
    """


def _collect(channel: str, reader: Any, frames: int) -> Any:
    """Reference values typed at prompts, each with a raw reading typed or read live."""
    from ..app.calibrate import Points, parse_reference

    word, example = ("load", "0, 50g, 100g, 1N") if channel == "force" else ("gap", "0, 2mm, 5mm")
    what = "known loads on the jaws" if channel == "force" else "gauge blocks between the jaws"
    click.echo(
        f"{channel}: put {what} one at a time and type each {word} ({example}); "
        "an empty line ends (3 or more; 5 or more to test linearity)",
        err=True,
    )
    points = Points()
    while True:
        text = click.prompt(f"  {word}", default="", show_default=False, err=True)
        if not text.strip():
            if len(points) >= 3:
                return points
            click.echo(f"  {len(points)} so far; give at least 3", err=True)
            continue
        try:
            ref = parse_reference(text, channel)
        except Exception as exc:  # a typo is asked again, not fatal
            click.echo(f"  {exc}", err=True)
            continue
        if reader is not None:
            force, position = reader.read()
            raw = force if channel == "force" else position
            click.echo(f"    read {raw:.2f} counts (mean of {frames} samples)", err=True)
        else:
            raw = click.prompt(f"  raw {channel} reading (counts)", type=float, err=True)
        points.add(ref, raw)


@calibrate.command("forceps")
@click.option(
    "--out",
    required=True,
    type=click.Path(dir_okay=False),
    help="Calibration file to write (JSON; an existing file is never replaced).",
)
@click.option(
    "--loads",
    type=click.Path(dir_okay=False),
    default=None,
    help="Text table of known loads and raw force readings (load first; unit in its "
    "header, e.g. load_g; N otherwise). Prompted for if not given.",
)
@click.option(
    "--gaps",
    type=click.Path(dir_okay=False),
    default=None,
    help="Text table of known gaps and raw closure readings (gap first; unit in its "
    "header, e.g. gap_mm; m otherwise). Prompted for if not given.",
)
@click.option(
    "--port",
    default=None,
    help="Read the raw values at each prompt from the live forceps here (path or URL).",
)
@click.option(
    "--frames",
    type=click.IntRange(min=1, max=100000),
    default=200,
    show_default=True,
    help="Samples averaged per live reading.",
)
@click.option(
    "--force-rate",
    type=click.FloatRange(min=0, min_open=True),
    default=None,
    help="How often the load cell is read, Hz (default: the live forceps' rate); "
    "warned about when too slow to see the mass term.",
)
@click.option("--note", default=None, help="Note stored in the file.")
def calibrate_forceps(
    out: str,
    loads: str | None,
    gaps: str | None,
    port: str | None,
    frames: int,
    force_rate: float | None,
    note: str | None,
) -> None:
    """Fit each forceps channel's gain and offset to known loads and gaps.

    Each channel is a straight line from raw counts to SI, value = gain * counts +
    offset, fitted with 95 % intervals; a quadratic term is tested (F-test) and
    reported when the channel is not linear. The file is what `record --calibration`
    and `import --calibration` read.

    \b
    Examples:
        tissuecli calibrate forceps --loads loads.csv --gaps gaps.csv --out cal.json
        tissuecli calibrate forceps --port /dev/ttyUSB0 --out cal.json
    """
    from ..app.calibrate import (
        ForcepsReader,
        calibrate_forceps,
        check_out,
        forceps_lines,
        read_points,
    )

    check_out(out, [loads, gaps])
    reader = ForcepsReader(port, frames) if port is not None else None
    try:
        points = {}
        for channel, path in (("force", loads), ("position", gaps)):
            points[channel] = (
                read_points(path, channel)
                if path is not None
                else _collect(channel, reader, frames)
            )
        rate = force_rate
        if rate is None and reader is not None:  # the force's own rate, if slower
            rate = reader.force_rate_hz or reader.rate_hz
    finally:
        if reader is not None:
            reader.close()
    result = calibrate_forceps(
        points["force"],
        points["position"],
        out,
        force_rate_hz=rate,
        inputs=(loads, gaps),
        note=note,
    )
    for line in forceps_lines(result):
        click.echo(line)


@calibrate.command("display")
@click.option(
    "--port",
    required=True,
    help="Display path (e.g. /dev/ttyUSB1, /tmp/display) or pyserial URL.",
)
@click.option(
    "--mass",
    required=True,
    help="The reference mass resting on the piston (e.g. 200g): about Kp x half the "
    "stroke / g (200g for the paper's display).",
)
@click.option(
    "--out",
    required=True,
    type=click.Path(dir_okay=False),
    help="Display profile to write (JSON; an existing file is never replaced).",
)
@click.option(
    "--points",
    type=click.IntRange(min=4, max=100),
    default=9,
    show_default=True,
    help="Voltages held in the sweep, 0 to v_max.",
)
@click.option(
    "--hold",
    type=click.FloatRange(min=0.2, max=60),
    default=1.0,
    show_default=True,
    help="Seconds each voltage is held.",
)
@click.option(
    "--ringdowns",
    type=click.IntRange(min=1, max=50),
    default=3,
    show_default=True,
    help="Free ring-downs after the sweep.",
)
@click.option(
    "--ring",
    type=click.FloatRange(min=0.2, max=60),
    default=2.0,
    show_default=True,
    help="Seconds each ring-down is recorded.",
)
@click.option("--yes", is_flag=True, help="Do not wait for Enter: the mass is already on.")
def calibrate_display(
    port: str,
    mass: str,
    out: str,
    points: int,
    hold: float,
    ringdowns: int,
    ring: float,
    yes: bool,
) -> None:
    """Measure the display's Kp, alpha, Mp and damping over its own link.

    With a known mass resting on the piston, a sweep of held voltages from 0 to
    v_max gives the spring (Kp) and the solenoid (alpha) from where the piston
    rests, and releases from a held pull ring down freely, giving the natural
    frequency and damping, so the piston's mass Mp and damping b. Every frame off
    the end stops is fitted at once. The profile (with 95 % intervals) is what
    `play --profile` and `live --profile` read; v_max, stroke and encoder
    resolution are those the display reports. About 20 s with the defaults.

    \b
    Example:
        tissuecli calibrate display --port /tmp/display --mass 200g --out display.json
    """
    from ..app.calibrate import calibrate_display as run
    from ..app.calibrate import check_out, display_lines, parse_mass

    mass_kg = parse_mass(mass, "--mass")
    check_out(out, [])
    if not yes:
        click.prompt(
            f"place the {mass_kg:g} kg mass on the piston, nothing else touching it, then "
            "press Enter",
            default="",
            show_default=False,
            err=True,
        )
    from ..hw.realtime import StopFlag

    result = run(
        port,
        out,
        mass_kg,
        stop=StopFlag().install(),  # Ctrl-C, SIGTERM: 0 V, STOP, nothing written
        points=points,
        hold_s=hold,
        ringdowns=ringdowns,
        ring_s=ring,
        on_step=lambda line: click.echo(line, err=True),
    )
    for line in display_lines(result):
        click.echo(line)
