"""Command line: the only click importer. Each command parses options, calls one
library function and prints its result; library errors become one-line messages."""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from typing import Any, TypeVar

import click

from . import __version__
from .errors import TissueError

F = TypeVar("F", bound=Callable[..., Any])


def _fail_cleanly(fn: F) -> F:
    """Turn library errors into click errors: one line on stderr, exit 1."""
    import functools

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except TissueError as exc:
            raise click.ClickException(str(exc)) from None

    return wrapper  # type: ignore[return-value]


class Group(click.Group):
    """A group whose every command reports :class:`TissueError` as a one-line message."""

    def add_command(self, cmd: click.Command, name: str | None = None) -> None:
        if cmd.callback is not None:
            cmd.callback = _fail_cleanly(cmd.callback)
        super().add_command(cmd, name)

    def group(self, *args: Any, **kwargs: Any) -> Any:
        kwargs.setdefault("cls", Group)
        return super().group(*args, **kwargs)

    def main(self, *args: Any, standalone_mode: bool = True, **kwargs: Any) -> Any:
        """As click's, but every bad input (usage errors too) exits with code 1."""
        if not standalone_mode:
            return super().main(*args, standalone_mode=False, **kwargs)
        try:
            code = super().main(*args, standalone_mode=False, **kwargs)
        except click.ClickException as exc:
            exc.show()
            sys.exit(1)
        except click.exceptions.Abort:
            click.echo("aborted", err=True)
            sys.exit(1)
        sys.exit(code if isinstance(code, int) else 0)


@click.group(cls=Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="tissuecli")
def cli() -> None:
    """Give a surgeon's sense of touch back through a sensorised laparoscopic forceps.

    \b
    Record grasps from the forceps, identify the tissue law
        K f0(x) + S f1(xdot) + M xddot = F
    and render that tissue on a solenoid haptic display.

    \b
    Try it with no hardware:  tissuecli demo
    Typical session:
        tissuecli simulate forceps --link /tmp/forceps &
        tissuecli record --port /tmp/forceps --out grasp.h5 --duration 10 --session liver-1
        tissuecli sessions grasp.h5

    All quantities are SI (N, m, s, kg, V) inside and in every file.
    """


# --------------------------------------------------------------------------- simulate


@cli.group()
def simulate() -> None:
    """Run a simulated device behind a real pseudo-terminal serial port."""


@simulate.command("forceps")
@click.option(
    "--link",
    type=click.Path(dir_okay=False),
    default=None,
    help="Make a symlink to the port here (e.g. /tmp/forceps), so its name is stable.",
)
@click.option(
    "--rate",
    type=click.FloatRange(min=1, max=20000),
    default=1000.0,
    show_default=True,
    help="Sample rate in Hz.",
)
@click.option(
    "--params",
    "params_file",
    type=click.Path(dir_okay=False),
    default=None,
    help="Tissue parameter file (as written by `fit --out`); a liver-like default otherwise.",
)
@click.option(
    "--adc-bits",
    type=click.IntRange(8, 16),
    default=8,
    show_default=True,
    help="ADC resolution; the paper's microcontroller has 8 bits.",
)
@click.option(
    "--force-noise",
    type=click.FloatRange(min=0),
    default=0.005,
    show_default=True,
    help="Force sensor noise SD in N, before quantisation.",
)
@click.option(
    "--position-noise",
    type=click.FloatRange(min=0),
    default=5e-6,
    show_default=True,
    help="Jaw position sensor noise SD in m, before quantisation.",
)
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
@click.option(
    "--drift-ppm",
    type=float,
    default=0.0,
    show_default=True,
    help="Fault injection: the device clock runs this many ppm fast.",
)
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of noise and operator.")
@click.option(
    "--duration",
    type=click.FloatRange(min=0, min_open=True),
    default=None,
    help="Exit after this many seconds (default: run until Ctrl-C or SIGTERM).",
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
) -> None:
    """A simulated forceps: an operator squeezing tissue, sensors, an ADC, the wire protocol.

    It prints its port, then streams to whoever opens it and sends START.
    Stop it with Ctrl-C or SIGTERM.
    """
    from .device import VirtualPort
    from .models import DEFAULT_TISSUE
    from .params import read_tissue
    from .simulate import Faults, StopFlag, run_forceps
    from .synth import ForcepsModel, Sensors

    tissue = read_tissue(params_file) if params_file else DEFAULT_TISSUE
    model = ForcepsModel(
        tissue=tissue,
        rate_hz=rate,
        drift_ppm=drift_ppm,
        seed=seed,
        sensors=Sensors(bits=adc_bits, force_noise_n=force_noise, position_noise_m=position_noise),
    )
    faults = Faults(corrupt=corrupt, drop=drop)
    stop = StopFlag().install()
    port = VirtualPort(link)
    try:

        def ready(p: VirtualPort) -> None:
            click.echo(p.path if p.link is None else f"{p.link} -> {p.name}")
            click.echo(
                f"simulated forceps streaming {tissue.model.name} tissue at {rate:g} Hz, "
                f"{adc_bits}-bit ADC; Ctrl-C to stop",
                err=True,
            )
            sys.stdout.flush()

        counters = run_forceps(
            model, port, faults=faults, stop=stop, duration_s=duration, on_ready=ready
        )
    finally:
        port.close()
    click.echo(f"stopped: {counters['sent']} frames sent", err=True)


@simulate.command("display")
@click.option(
    "--link",
    type=click.Path(dir_okay=False),
    default=None,
    help="Make a symlink to the port here (e.g. /tmp/display), so its name is stable.",
)
@click.option(
    "--profile",
    "profile_file",
    type=click.Path(dir_okay=False),
    default=None,
    help="Display profile JSON (SI); the paper's prototype otherwise.",
)
@click.option(
    "--rate",
    type=click.FloatRange(min=1, max=20000),
    default=1000.0,
    show_default=True,
    help="Control-loop rate in Hz.",
)
@click.option(
    "--seed", type=int, default=0, show_default=True, help="Seed of the operator's presses."
)
@click.option(
    "--duration",
    type=click.FloatRange(min=0, min_open=True),
    default=None,
    help="Exit after this many seconds (default: run until Ctrl-C or SIGTERM).",
)
def simulate_display(
    link: str | None, profile_file: str | None, rate: float, seed: int, duration: float | None
) -> None:
    """A simulated solenoid display: piston, spring, solenoid, encoder and a pressing finger.

    It prints its port, then sends an Encoder frame every period to whoever opens
    it and sends START, and applies the SetVoltage frames it receives. With no
    SetVoltage for 5 periods it switches the solenoid off (watchdog). The finger
    presses 1-2.5 N a few times per 10 s. Stop it with Ctrl-C or SIGTERM.
    """
    from .play import read_profile, run_simulated_display

    profile = read_profile(profile_file) if profile_file else None

    def ready(p: Any) -> None:
        click.echo(p.path if p.link is None else f"{p.link} -> {p.name}")
        click.echo(
            f"simulated display at {rate:g} Hz, operator seed {seed}; Ctrl-C to stop", err=True
        )
        sys.stdout.flush()

    counters = run_simulated_display(
        link,
        profile=profile,
        rate_hz=rate,
        seed=seed,
        duration_s=duration,
        on_ready=ready,
        say=lambda line: click.echo(line, err=True),
    )
    click.echo(
        f"stopped: {counters['sent']} frames sent, {counters['commands']} SetVoltage received, "
        f"{counters['watchdog_trips']} watchdog trips",
        err=True,
    )


# --------------------------------------------------------------------------- record


def _status_printer(session: str) -> Callable[[Any], None]:
    """Live one-line status on stderr (rewritten in place on a terminal)."""
    tty = sys.stderr.isatty()

    def show(s: Any) -> None:
        line = (
            f"recording {session}: {s.elapsed_s:7.1f} s  {s.samples:>9,d} samples  "
            f"{s.rate_hz:7.1f} Hz  bad {s.bad_frames}  lost {s.lost_frames}  "
            f"{s.file_bytes / 1e6:6.2f} MB"
        )
        click.echo(("\r" + line) if tty else line, err=True, nl=not tty)

    return show


@cli.command()
@click.option(
    "--port", required=True, help="Device path (e.g. /dev/ttyUSB0, /tmp/forceps) or pyserial URL."
)
@click.option(
    "--out", required=True, type=click.Path(dir_okay=False), help="HDF5 file (created if missing)."
)
@click.option(
    "--session", default=None, help="Session name [default: session-<UTC time>]. Never overwritten."
)
@click.option(
    "--duration",
    type=click.FloatRange(min=0, min_open=True),
    default=None,
    help="Seconds to record (device time); default until Ctrl-C or SIGTERM.",
)
@click.option("--tissue", default="", help="Tissue label stored with the session.")
@click.option("--note", default="", help="Operator note stored with the session.")
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

    from .params import read_calibration
    from .record import record as run
    from .simulate import StopFlag

    name = session or "session-" + datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S")
    cal = read_calibration(calibration) if calibration else None
    stop = StopFlag().install()
    status = None if quiet else _status_printer(name)
    try:
        result = run(
            port,
            out,
            name,
            status_interval_s=0.5 if sys.stderr.isatty() else 5.0,  # logs get a line every 5 s
            duration_s=duration,
            tissue=tissue,
            note=note,
            calibration=cal,
            baudrate=baud,
            stop=stop,
            on_status=status,
        )
    finally:
        if status is not None and sys.stderr.isatty():
            click.echo(err=True)
    drift = f", clock drift {result.clock_map.drift_ppm:+.0f} ppm" if result.clock_map else ""
    click.echo(
        f"saved {result.samples} samples ({result.duration_s:.3f} s at {result.rate_hz:.1f} Hz) "
        f"to {result.path} session {result.session!r}: {result.bad_frames} bad, "
        f"{result.lost_frames} lost frames{drift}; {result.stop_reason}"
    )


# --------------------------------------------------------------------------- files


@cli.command()
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
def sessions(file: str, as_json: bool) -> None:
    """List the sessions in an HDF5 file."""
    from .storage import list_sessions

    rows = list_sessions(file)
    if as_json:
        click.echo(json.dumps(rows, indent=2))
        return
    if not rows:
        click.echo(f"{file} holds no sessions")
        return
    header = (
        f"{'session':<20} {'samples':>9} {'duration s':>10} {'rate Hz':>8} "
        f"{'lost':>5} {'bad':>5}  tissue"
    )
    click.echo(header)
    for r in rows:
        flag = "" if r.get("complete", True) else "  (incomplete)"
        click.echo(
            f"{r['name']:<20} {r['samples']:>9d} {r['duration_s']:>10.3f} {r['rate_hz']:>8.1f} "
            f"{r['frames_lost']:>5d} {r['frames_bad']:>5d}  {r.get('tissue', '')}{flag}"
        )


@cli.command("import")
@click.argument("csv_file", type=click.Path(dir_okay=False))
@click.option(
    "--out", required=True, type=click.Path(dir_okay=False), help="HDF5 file (created if missing)."
)
@click.option("--session", required=True, help="Name of the new session.")
@click.option(
    "--units",
    default=None,
    help="Units of the CSV columns, any order, e.g. 'mm,gf' or 'ms,mN,um' [default: s,N,m].",
)
@click.option("--tissue", default="", help="Tissue label stored with the session.")
@click.option("--note", default="", help="Note stored with the session.")
def import_(
    csv_file: str, out: str, session: str, units: str | None, tissue: str, note: str
) -> None:
    """Import a CSV with header time,force,position as a new session.

    \b
    Example (position in mm, force in grams-force):
        tissuecli import lab.csv --out grasp.h5 --session bench-3 --units mm,gf
    """
    from .transfer import import_csv

    s = import_csv(csv_file, out, session, units=units, tissue=tissue, note=note)
    click.echo(
        f"imported {len(s)} samples ({s.duration_s:.3f} s at {s.rate_hz:.1f} Hz) "
        f"into {out} session {session!r}"
    )


@cli.command()
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("--session", default=None, help="Session to export [default: the only one].")
@click.option(
    "--csv", "csv_out", required=True, type=click.Path(dir_okay=False), help="CSV file to write."
)
@click.option("--units", default=None, help="Units to write, e.g. 'mm,gf' [default: s,N,m].")
def export(file: str, session: str | None, csv_out: str, units: str | None) -> None:
    """Export a session to CSV (header time,force,position)."""
    from .transfer import export_csv

    s = export_csv(file, session, csv_out, units=units)
    click.echo(f"wrote {len(s)} samples of session {s.name!r} to {csv_out}")


# --------------------------------------------------------------------------- fit


def _sampling_progress() -> Callable[[str, int, float], None]:
    """A progress line while emcee runs: form, steps, and steps needed (50 tau)."""

    def show(form: str, steps: int, tau: float) -> None:
        need = max(1000, int(50 * tau))
        done = min(1.0, steps / need)
        bar = "#" * int(20 * done) + "-" * (20 - int(20 * done))
        click.echo(
            f"\rsampling {form:<11} [{bar}] {steps:>6} steps (need ~{need})",
            err=True,
            nl=done >= 1.0,
        )

    return show


@cli.command()
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("--session", default=None, help="Session to fit [default: the only one].")
@click.option(
    "--out",
    type=click.Path(dir_okay=False),
    default=None,
    help="Write the parameter file (JSON, SI) for `play` and `simulate forceps --params`.",
)
@click.option(
    "--report",
    type=click.Path(dir_okay=False),
    default=None,
    help="Write a self-contained HTML report with plots.",
)
@click.option(
    "--method",
    type=click.Choice(["bayes", "pinv", "both"]),
    default="bayes",
    show_default=True,
    help="bayes: every form with posteriors and model choice; pinv: the paper's "
    "windowed pseudoinverse alone; both.",
)
@click.option(
    "--forms",
    default="all",
    show_default=True,
    help="'all' to choose among x|x^3 and xdot|xdot^2, or one form such as x,xdot.",
)
@click.option(
    "--sampler",
    type=click.Choice(["auto", "emcee"]),
    default="auto",
    show_default=True,
    help="auto samples only where the exact posterior does not apply; emcee samples "
    "every form and checks its evidence by stepping-stone.",
)
@click.option(
    "--differentiator",
    type=click.Choice(["gaussian", "savgol", "gradient"]),
    default="gaussian",
    show_default=True,
    help="How velocity and acceleration are estimated.",
)
@click.option(
    "--window",
    type=click.FloatRange(min=0, min_open=True),
    default=1.0,
    show_default=True,
    help="pinv window length in s.",
)
@click.option(
    "--force-scale",
    type=click.FloatRange(min=0, min_open=True),
    default=20.0,
    show_default=True,
    help="Prior scale in N: the force each term may reach at jaw-scale motion (5 mm, "
    "50 mm/s, 10 m/s^2). Raise it for stiff materials.",
)
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the sampler.")
def fit(
    file: str,
    session: str | None,
    out: str | None,
    report: str | None,
    method: str,
    forms: str,
    sampler: str,
    differentiator: str,
    window: float,
    force_scale: float,
    seed: int,
) -> None:
    """Identify the tissue law K f0(x) + S f1(xdot) + M xddot = F from a session.

    \b
    Examples:
        tissuecli fit grasp.h5 --session liver-1 --out liver.json --report liver.html
        tissuecli fit grasp.h5 --method pinv          # the paper's method alone
        tissuecli fit grasp.h5 --forms x,xdot         # one form, no model choice
    """
    from .fit import fit_file, summary_lines

    outcome = fit_file(
        file,
        session,
        out=out,
        report=report,
        method=method,
        forms=forms,
        sampler=sampler,
        differentiator=differentiator,
        window_s=window,
        force_scale=force_scale,
        seed=seed,
        progress=_sampling_progress() if sys.stderr.isatty() else None,
    )
    for line in summary_lines(outcome):
        click.echo(line)
    for path, what in ((out, "parameters"), (report, "report")):
        if path:
            click.echo(f"{what} written to {path}")


# --------------------------------------------------------------------------- play


def _play_status() -> Callable[[dict[str, Any]], None]:
    """Live one-line status on stderr while playing (rewritten in place on a terminal)."""
    tty = sys.stderr.isatty()

    def show(s: dict[str, Any]) -> None:
        line = (
            f"playing: {s['duration_s']:7.1f} s  error rms {s['tracking_rms_m'] * 1e6:6.1f} um  "
            f"saturated {s['saturated_fraction']:6.1%}  unrenderable "
            f"{s['unrenderable_fraction']:6.1%}  {s['loop_rate_hz']:7.1f} Hz  "
            f"lost {s['frames_lost']}"
        )
        click.echo(("\r" + line) if tty else line, err=True, nl=not tty)

    return show


@cli.command()
@click.argument("params_file", type=click.Path(dir_okay=False))
@click.option(
    "--port",
    default=None,
    help="Display path (e.g. /dev/ttyUSB1, /tmp/display) or pyserial URL; not needed with --check.",
)
@click.option(
    "--duration",
    type=click.FloatRange(min=0, min_open=True),
    default=None,
    help="Seconds to play; default until Ctrl-C or SIGTERM.",
)
@click.option(
    "--rate",
    type=click.FloatRange(min=1, max=20000),
    default=1000.0,
    show_default=True,
    help="Control-loop rate in Hz; must be the display's.",
)
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
@click.option(
    "--profile",
    "profile_file",
    type=click.Path(dir_okay=False),
    default=None,
    help="Display profile JSON (SI); default: what the display reports, else the paper's.",
)
def play(
    params_file: str,
    port: str | None,
    duration: float | None,
    rate: float,
    log: str | None,
    summary_file: str | None,
    check_only: bool,
    profile_file: str | None,
) -> None:
    """Render an identified tissue on the solenoid haptic display.

    The tissue is checked first: a display that would saturate below a firm grasp
    (3.4 N), a tissue softer than the display's spring, or an unstable loop are
    refused with the reason. Ctrl-C, SIGTERM, a lost display or any error leave
    the solenoid at 0 V.

    \b
    Examples:
        tissuecli simulate display --link /tmp/display &
        tissuecli play liver.json --port /tmp/display --duration 20 --log plays.h5
        tissuecli play liver.json --check        # the band and the verdict only
    """
    from .display import PAPER_DISPLAY, check
    from .errors import InputError, RenderError
    from .params import read_tissue, write_json
    from .play import play as run
    from .play import read_profile, summary_lines
    from .simulate import StopFlag

    tissue = read_tissue(params_file)
    profile = read_profile(profile_file) if profile_file else None
    if check_only:
        result = check(tissue, profile or PAPER_DISPLAY, rate)
        for line in result.lines():
            click.echo(line)
        if summary_file:
            write_json(summary_file, {"check": result.as_dict()})
        if not result.renderable:
            raise RenderError("the display cannot render this tissue: " + "; ".join(result.reasons))
        return
    if port is None:
        raise InputError("give the display's port with --port (or use --check)")
    stop = StopFlag().install()
    status = _play_status()
    try:
        summary = run(
            tissue,
            port,
            duration,
            rate_hz=rate,
            log=log,
            stop=stop,
            profile=profile,
            on_status=status,
        )
    finally:
        if sys.stderr.isatty():
            click.echo(err=True)
    if summary_file:
        write_json(summary_file, summary)
    for line in summary_lines(summary):
        click.echo(line)


# --------------------------------------------------------------------------- demo


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
def demo(duration: float, workdir: str | None) -> None:
    """Everything on simulated devices: simulate, record, list, export, fit, report, play."""
    from .demo import run_demo

    run_demo(duration_s=duration, workdir=workdir, say=click.echo)


def main() -> None:
    """Console entry point."""
    cli()
