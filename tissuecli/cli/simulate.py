"""``tissuecli simulate forceps|display|study``: simulated devices behind real serial ports,
and a simulated tissue study written as sessions."""

from __future__ import annotations

import sys
from typing import Any

import click

from .base import cli, end_live_line, live_line
from .options import (
    drift_option,
    duration_option,
    forceps_options,
    link_option,
    profile_option,
    rate_option,
    seed_option,
    simulated_forceps,
)


@cli.group()
def simulate() -> None:
    """Run a simulated device behind a real pseudo-terminal serial port."""


def _announce(port: Any, detail: str) -> None:
    """Print the port (for scripts, on stdout) and what runs behind it (stderr)."""
    click.echo(port.path if port.link is None else f"{port.link} -> {port.name}")
    click.echo(detail, err=True)
    sys.stdout.flush()


@simulate.command("forceps")
@link_option("forceps")
@rate_option("Sample rate in Hz.")
@forceps_options()
@click.option(
    "--corrupt",
    type=click.FloatRange(0, 1),
    default=0.0,
    show_default=True,
    help="Fault injection: probability that a frame is corrupted on the line.",
)
@click.option(
    "--drop",
    type=click.FloatRange(0, 1),
    default=0.0,
    show_default=True,
    help="Fault injection: probability that a frame is never sent.",
)
@drift_option()
@seed_option("Seed of noise and operator.")
@duration_option("Exit after this many seconds (default: run until Ctrl-C or SIGTERM).")
@click.option(
    "--protocol",
    type=click.Choice(["binary", "text"]),
    default="binary",
    show_default=True,
    help="binary: the framed protocol (docs/protocol.md); text: a plain-text logger "
    "printing lines from the start, whoever listens (docs/recording.md).",
)
@click.option(
    "--format",
    "line_format",
    type=click.Choice(["csv", "plotter", "teleplot"]),
    default="csv",
    show_default=True,
    help="Text only: t_us,force_N,closure_mm lines; Serial Plotter label:value pairs; "
    "or Teleplot >name:value lines.",
)
@click.option(
    "--stamps",
    type=click.Choice(["us", "ms", "none"]),
    default="us",
    show_default=True,
    help="Text only: the device stamp on each line, micros() or millis() (32-bit, "
    "wrapping), or none.",
)
@click.option(
    "--header-every",
    type=click.FloatRange(min=0),
    default=1.0,
    show_default=True,
    help="Text only: print the csv header first and again every this many s; 0 for none.",
)
@click.option(
    "--jitter",
    type=click.FloatRange(0, 0.4),
    default=0.2,
    show_default=True,
    help="Text only: the logger samples up to this fraction of a period late.",
)
@click.option(
    "--broken",
    type=click.FloatRange(0, 1),
    default=0.001,
    show_default=True,
    help="Text only: probability that a line is broken on the way.",
)
@click.option(
    "--clock-start",
    type=click.IntRange(0, 2**32 - 1),
    default=0,
    show_default=True,
    help="Text only: the device counter at the first sample (near 4294967295 to see it wrap).",
)
def simulate_forceps(
    link: str | None,
    rate: float,
    params_file: str | None,
    adc_bits: int,
    force_noise: float,
    position_noise: float,
    corrupt: float,
    drop: float,
    drift_ppm: float,
    seed: int,
    duration: float | None,
    protocol: str,
    line_format: str,
    stamps: str,
    header_every: float,
    jitter: float,
    broken: float,
    clock_start: int,
) -> None:
    """A simulated forceps: an operator squeezing tissue, sensors, an ADC, the wire protocol.

    It prints its port, then streams to whoever opens it and sends START.
    With --protocol text it is a plain-text logger instead, printing lines from the
    start. Stop it with Ctrl-C or SIGTERM.

    \b
    Examples:
        tissuecli simulate forceps --link /tmp/forceps --rate 1000 &
        tissuecli simulate forceps --link /tmp/logger --protocol text --rate 500 &
    """
    forceps = simulated_forceps(
        rate, seed, params_file, adc_bits, force_noise, position_noise, drift_ppm
    )
    if protocol == "text":
        from ..app.simulate import simulate_text_logger

        if corrupt or drop:
            raise click.UsageError(
                "--corrupt and --drop are for frames; a text logger breaks lines with --broken"
            )

        def announce(port: Any, tissue: Any) -> None:
            _announce(
                port,
                f"simulated text logger printing {line_format} lines of {tissue.law.name} "
                f"tissue at {rate:g} Hz, stamps {stamps}; Ctrl-C to stop",
            )

        counters = simulate_text_logger(
            link,
            forceps=forceps,
            line_format=line_format,
            stamps=stamps,
            header_every_s=header_every,
            jitter=jitter,
            broken=broken,
            clock_start=clock_start,
            duration_s=duration,
            on_ready=announce,
        )
        click.echo(
            f"stopped: {counters['sent']} lines printed, {counters['broken']} broken, "
            f"{counters['skipped']} skipped (starved), {counters['overrun_bytes']} bytes "
            "nobody read",
            err=True,
        )
        return
    from ..app.simulate import simulate_forceps as run

    def ready(port: Any, tissue: Any) -> None:
        _announce(
            port,
            f"simulated forceps streaming {tissue.law.name} tissue at {rate:g} Hz, "
            f"{adc_bits}-bit ADC; Ctrl-C to stop",
        )

    counters = run(
        link,
        forceps=forceps,
        corrupt=corrupt,
        drop=drop,
        duration_s=duration,
        on_ready=ready,
    )
    click.echo(f"stopped: {counters['sent']} frames sent", err=True)


@simulate.command("display")
@link_option("display")
@profile_option("Display profile JSON (SI); the paper's prototype otherwise.")
@rate_option("Control-loop rate in Hz.")
@seed_option("Seed of the operator's presses.")
@duration_option("Exit after this many seconds (default: run until Ctrl-C or SIGTERM).")
@click.option(
    "--load",
    "load",
    default=None,
    help="A reference mass resting on the piston instead of the finger (e.g. 200g), "
    "for `tissuecli calibrate display`.",
)
@click.option(
    "--reports",
    "reports_file",
    type=click.Path(dir_okay=False),
    default=None,
    help="Display profile JSON it answers to IDENTIFY (default: the one it runs): "
    "stored constants that are not its true ones.",
)
@click.option(
    "--watchdog-periods",
    "watchdog_periods",
    type=int,
    default=None,
    help="Cut the solenoid after this many periods without a SetVoltage (5 is the "
    "firmware's). Default: 5 plus 4 times the longest round trip through its port "
    "timed at start-up, at most 50 ms (50 ms on a machine with no CPU to spare), said "
    "on stderr when longer than 5.",
)
def simulate_display(
    link: str | None,
    profile_file: str | None,
    rate: float,
    seed: int,
    duration: float | None,
    load: str | None,
    reports_file: str | None,
    watchdog_periods: int | None,
) -> None:
    """A simulated solenoid display: piston, spring, solenoid, encoder and a pressing finger.

    It prints its port, then sends an Encoder frame every period to whoever opens
    it and sends START, and applies the SetVoltage frames it receives. With no
    SetVoltage for its watchdog's periods (stated in its IDENTIFY answer; see
    --watchdog-periods) it switches the solenoid off. The finger
    presses 1-2.5 N a few times per 10 s (with --load, a mass rests on the piston
    instead). Stop it with Ctrl-C or SIGTERM.

    \b
    Examples:
        tissuecli simulate display --link /tmp/display &
        tissuecli simulate display --link /tmp/display --profile true.json --load 200g &
    """
    from ..app.calibrate import parse_mass

    load_kg = parse_mass(load, "--load") if load is not None else 0.0
    from ..app.simulate import simulate_display as run

    counters = run(
        link,
        profile=profile_file,
        rate_hz=rate,
        seed=seed,
        duration_s=duration,
        on_ready=lambda port: _announce(
            port, f"simulated display at {rate:g} Hz, operator seed {seed}; Ctrl-C to stop"
        ),
        say=lambda line: click.echo(line, err=True),
        load_kg=load_kg,
        reports=reports_file,
        watchdog_periods=watchdog_periods,
    )
    click.echo(
        f"stopped: {counters['sent']} frames sent, {counters['commands']} SetVoltage received, "
        f"{counters['watchdog_trips']} watchdog trips; command age by tick "
        f"{_ages(counters['command_ages'])}, catching up {_ages(counters['command_ages_late'])}",
        err=True,
    )


def _ages(counts: list[int]) -> str:
    """Ticks by the age of the command in use: ``0:1990 1:10 2:0 3:0 4+:0``."""
    last = len(counts) - 1
    return " ".join(f"{a}{'+' if a == last else ''}:{n}" for a, n in enumerate(counts))


@simulate.command("study")
@click.option(
    "--out", required=True, type=click.Path(dir_okay=False), help="New HDF5 file to write."
)
@click.option(
    "--groups",
    type=click.IntRange(2, 4),
    default=4,
    show_default=True,
    help="Tissue groups (fat, liver, kidney, tumour: 250-520 N/m).",
)
@click.option(
    "--specimens",
    type=click.IntRange(1),
    default=10,
    show_default=True,
    help="Specimens per group.",
)
@click.option(
    "--sessions",
    type=click.IntRange(1),
    default=10,
    show_default=True,
    help="Sessions per specimen.",
)
@click.option(
    "--specimen-sd",
    type=click.FloatRange(0),
    default=0.1,
    show_default=True,
    help="SD of ln(coefficient) between specimens of a group.",
)
@click.option(
    "--session-sd",
    type=click.FloatRange(0),
    default=0.03,
    show_default=True,
    help="SD of ln(coefficient) between sessions of a specimen.",
)
@duration_option("Length of each session in s [default: 4].")
@seed_option("Seed of the study.")
def simulate_study(
    out: str,
    groups: int,
    specimens: int,
    sessions: int,
    specimen_sd: float,
    session_sd: float,
    duration: float | None,
    seed: int,
) -> None:
    """Write a simulated tissue study: tissue groups, specimens that differ, sessions of
    each, labelled with tissue, specimen and operator, for `fit`, `compare` and
    `classify` to work on.

    \b
    Example:
        tissuecli simulate study --out study.h5 --specimens 4 --sessions 3
        tissuecli fit study.h5 --catalogue tissues.db
    """
    from ..app.study import write_study
    from ..sim.study import GROUPS, StudyDesign

    design = StudyDesign(
        groups=dict(list(GROUPS.items())[:groups]),
        specimens=specimens,
        sessions=sessions,
        specimen_sd=specimen_sd,
        session_sd=session_sd,
        duration_s=duration or 4.0,
        seed=seed,
    )

    def show(i: int, total: int) -> None:
        if i == total or i % 10 == 0:
            live_line(f"simulated {i}/{total} sessions")

    n = write_study(out, design, progress=show)
    end_live_line()
    click.echo(f"{n} sessions of {groups} tissues x {specimens} specimens written to {out}")
