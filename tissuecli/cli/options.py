"""Options several commands share, each defined once."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import click

Decorator = Callable[[Callable[..., Any]], Callable[..., Any]]


def link_option(kind: str) -> Decorator:
    return click.option(
        "--link",
        type=click.Path(dir_okay=False),
        default=None,
        help=f"Make a symlink to the port here (e.g. /tmp/{kind}), so its name is stable.",
    )


def rate_option(help: str) -> Decorator:
    return click.option(
        "--rate",
        type=click.FloatRange(min=1, max=20000),
        default=1000.0,
        show_default=True,
        help=help,
    )


def duration_option(help: str) -> Decorator:
    return click.option(
        "--duration",
        type=click.FloatRange(min=0, min_open=True),
        default=None,
        help=help,
    )


def seed_option(help: str) -> Decorator:
    return click.option("--seed", type=int, default=0, show_default=True, help=help)


def forceps_options() -> Decorator:
    """``--params``, ``--adc-bits``, ``--force-noise`` and ``--position-noise``: the
    simulated forceps' tissue and sensors, whatever it speaks (with ``--rate``, ``--seed``
    and :func:`drift_option`, a :class:`tissuecli.app.simulate.SimulatedForceps`, built
    by :func:`simulated_forceps`)."""

    def apply(fn: Callable[..., Any]) -> Callable[..., Any]:
        for option in reversed(
            [
                click.option(
                    "--params",
                    "params_file",
                    type=click.Path(dir_okay=False),
                    default=None,
                    help="Tissue parameter file (as written by `fit --out`); a liver-like "
                    "default otherwise.",
                ),
                click.option(
                    "--adc-bits",
                    type=click.IntRange(8, 16),
                    default=8,
                    show_default=True,
                    help="ADC resolution; the paper's microcontroller has 8 bits.",
                ),
                click.option(
                    "--force-noise",
                    type=click.FloatRange(min=0),
                    default=0.005,
                    show_default=True,
                    help="Force sensor noise SD in N, before quantisation.",
                ),
                click.option(
                    "--position-noise",
                    type=click.FloatRange(min=0),
                    default=5e-6,
                    show_default=True,
                    help="Jaw position sensor noise SD in m, before quantisation.",
                ),
            ]
        ):
            fn = option(fn)
        return fn

    return apply


def drift_option() -> Decorator:
    """``--drift-ppm``: the simulated device's clock error (part of :func:`forceps_options`'
    forceps, listed among the fault injections)."""
    return click.option(
        "--drift-ppm",
        type=float,
        default=0.0,
        show_default=True,
        help="Fault injection: the device clock runs this many ppm fast.",
    )


def simulated_forceps(
    rate: float,
    seed: int,
    params_file: str | None,
    adc_bits: int,
    force_noise: float,
    position_noise: float,
    drift_ppm: float,
) -> Any:
    """The :class:`tissuecli.app.simulate.SimulatedForceps` of :func:`forceps_options`',
    :func:`drift_option`'s, ``--rate``'s and ``--seed``'s values."""
    from ..app.simulate import SimulatedForceps

    return SimulatedForceps(
        params=params_file,
        rate_hz=rate,
        adc_bits=adc_bits,
        force_noise_n=force_noise,
        position_noise_m=position_noise,
        drift_ppm=drift_ppm,
        seed=seed,
    )


def session_option(help: str, required: bool = False) -> Decorator:
    return click.option("--session", default=None, required=required, help=help)


def h5_out_option() -> Decorator:
    return click.option(
        "--out",
        required=True,
        type=click.Path(dir_okay=False),
        help="HDF5 file (created if missing).",
    )


def label_options(note_help: str = "Note stored with the session.") -> Decorator:
    """``--tissue`` and ``--note``: labels stored with a new session."""

    def apply(fn: Callable[..., Any]) -> Callable[..., Any]:
        fn = click.option("--note", default="", help=note_help)(fn)
        return click.option("--tissue", default="", help="Tissue label stored with the session.")(
            fn
        )

    return apply


def units_option(help: str) -> Decorator:
    return click.option("--units", default=None, help=help)


def recording_options(rate: bool = True) -> Decorator:
    """``--columns``, ``--units``, ``--jaw-length``, and for files ``--rate`` and
    ``--sheet``: how to read another logger's recording (``import``, and ``fit`` of a
    recording directly; ``record --protocol text`` without the options for files)."""

    def apply(fn: Callable[..., Any]) -> Callable[..., Any]:
        for option in reversed(
            [
                click.option(
                    "--columns",
                    default=None,
                    help="Which column is which, by header name or 1-based index, e.g. "
                    "'time=t_ms,force=force_g,position=3' [default: found by header name].",
                ),
                units_option(
                    "Units per column, e.g. 'time=ms,force=gf,position=mm' or the short "
                    "'mm,gf' [default: from the header, e.g. t_ms, else s, N, m]. Counts take "
                    "a scale (0.00076699*rad), a sensor that grows the other way a sign "
                    "(-deg). An angle (deg, rad) for position is the angle between the "
                    "jaws: give --jaw-length."
                ),
                click.option(
                    "--jaw-length",
                    default=None,
                    help="Hinge-to-tip length of the jaws, e.g. 20mm: turns a jaw angle into "
                    "the closure at the tips, a hinge torque into the force there.",
                ),
                click.option(
                    "--rate",
                    type=click.FloatRange(min=0, min_open=True),
                    default=None,
                    help="Sample rate in Hz, for files without a time column.",
                ),
                click.option(
                    "--sheet",
                    default=None,
                    help="The sheet of a spreadsheet (.xlsx, .xls, .ods) to read [default: "
                    "the only sheet with data; import stores each sheet as a session].",
                ),
            ][: None if rate else -2]
        ):
            fn = option(fn)
        return fn

    return apply


def reading(
    columns: str | None,
    units: str | None,
    jaw_length: str | None,
    rate: float | None,
    sheet: str | None = None,
) -> dict[str, Any]:
    """The keywords of :func:`tissuecli.app.transfer.import_recording` from
    :func:`recording_options`' values (--jaw-length parsed to metres)."""
    from ..core.units import parse_quantity

    return {
        "columns": columns,
        "units": units,
        "jaw_length_m": parse_quantity(jaw_length, "length", "--jaw-length")
        if jaw_length
        else None,
        "rate_hz": rate,
        **({"sheet": sheet} if sheet is not None else {}),
    }


def reading_progress(source: str, after_s: float = 2.0) -> Callable[[float], None]:
    """A progress line on stderr while a recording is read, once reading has taken more
    than `after_s` seconds (short files print nothing); cleared at the end."""
    import time

    start = time.monotonic()
    shown = [0.0]

    def report(fraction: float) -> None:
        now = time.monotonic()
        if now - start < after_s or (now - shown[0] < 0.5 and fraction < 1.0):
            return
        shown[0] = now
        end = "\n" if fraction >= 1.0 else ""
        click.echo(
            f"\rreading {source}: {100 * fraction:3.0f} % ({now - start:.0f} s)" + end,
            err=True,
            nl=False,
        )

    return report


def profile_option(help: str) -> Decorator:
    return click.option(
        "--profile", "profile_file", type=click.Path(dir_okay=False), default=None, help=help
    )


def force_option() -> Decorator:
    return click.option(
        "--force",
        is_flag=True,
        help="Replace output files that exist (an input file is never replaced).",
    )


def file_argument(name: str = "file") -> Decorator:
    return click.argument(name, type=click.Path(dir_okay=False))


def realtime_option() -> Decorator:
    return click.option(
        "--no-realtime",
        is_flag=True,
        help="Run the haptic loop without elevated scheduling (SCHED_FIFO, locked memory, "
        "one CPU); by default it asks for them and says once if refused.",
    )


def say_once(message: str) -> None:
    """A library's one-time notice (e.g. real-time scheduling refused), on stderr."""
    click.echo(f"note: {message}", err=True)
