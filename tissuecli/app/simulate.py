"""The ``simulate`` services: run a simulated forceps or display in this process, behind
a pseudo-terminal, until Ctrl-C, SIGTERM or a set duration."""

from __future__ import annotations

import os
import sys
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from ..core.tissue import DEFAULT_TISSUE, Tissue
from ..formats.params import read_profile, read_tissue
from ..hw.realtime import StopFlag, device_loop
from ..sim.display import run_simulated_display
from ..sim.forceps import Faults, run_forceps
from ..sim.port import VirtualPort
from ..sim.synth import ForcepsModel, Sensors
from ..sim.textlogger import TextLogger, run_text_logger

StrPath = str | os.PathLike[str]


@dataclass(frozen=True)
class SimulatedForceps:
    """The simulated forceps every ``simulate`` service runs, whatever it speaks: the
    tissue it squeezes, its sample rate, its sensors and ADC, its clock.

    Attributes
    ----------
    params : path, optional
        Tissue parameter file (as ``fit --out`` writes it); a liver-like default
        otherwise.
    rate_hz : float
        Sample rate, Hz.
    adc_bits : int
        ADC resolution, bits.
    force_noise_n, position_noise_m : float
        Sensor noise SDs before quantisation, N and m.
    drift_ppm : float
        The device clock runs this many ppm fast.
    seed : int
        Seed of noise and operator.
    """

    params: StrPath | None = None
    rate_hz: float = 1000.0
    adc_bits: int = 8
    force_noise_n: float = 0.005
    position_noise_m: float = 5e-6
    drift_ppm: float = 0.0
    seed: int = 0

    def model(self) -> ForcepsModel:
        """The forceps model these options describe (its tissue read from ``params``)."""
        return ForcepsModel(
            tissue=read_tissue(self.params) if self.params else DEFAULT_TISSUE,
            rate_hz=self.rate_hz,
            drift_ppm=self.drift_ppm,
            seed=self.seed,
            sensors=Sensors(
                bits=self.adc_bits,
                force_noise_n=self.force_noise_n,
                position_noise_m=self.position_noise_m,
            ),
        )


def simulate_forceps(
    link: StrPath | None = None,
    *,
    forceps: SimulatedForceps | None = None,
    corrupt: float = 0.0,
    drop: float = 0.0,
    duration_s: float | None = None,
    on_ready: Callable[[VirtualPort, Tissue], None] | None = None,
) -> dict[str, int]:
    """Run the simulated forceps until SIGINT/SIGTERM (or ``duration_s``).

    Parameters
    ----------
    link : path, optional
        Make a symlink to the pty here.
    forceps : SimulatedForceps, optional
        Tissue, rate, sensors and clock (the defaults of :class:`SimulatedForceps`).
    corrupt, drop : float
        Fault injection: probabilities per frame.
    duration_s : float, optional
        Exit after this many seconds.
    on_ready : callable, optional
        Called with the port and the tissue once the port exists.

    Returns
    -------
    dict
        The firmware's counters (``sent`` frames, ...).
    """
    model = (forceps or SimulatedForceps()).model()
    faults = Faults(corrupt=corrupt, drop=drop)
    stop = StopFlag().install()
    port = VirtualPort(link)
    try:
        with device_loop(_to_stderr):
            return run_forceps(
                model,
                port,
                faults=faults,
                stop=stop,
                duration_s=duration_s,
                on_ready=None if on_ready is None else lambda p: on_ready(p, model.tissue),
            )
    finally:
        port.close()


def _to_stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def simulate_display(
    link: StrPath | None = None,
    *,
    profile: StrPath | None = None,
    rate_hz: float = 1000.0,
    seed: int = 0,
    duration_s: float | None = None,
    on_ready: Callable[[VirtualPort], None] | None = None,
    say: Callable[[str], None] | None = None,
    load_kg: float = 0.0,
    reports: StrPath | None = None,
    watchdog_periods: int | None = None,
) -> dict[str, Any]:
    """Run the simulated display until SIGINT/SIGTERM (or ``duration_s``); see
    :func:`tissuecli.sim.display.run_simulated_display`. ``profile`` is a display
    profile file (the paper's prototype otherwise); ``reports`` the profile file it
    answers to IDENTIFY (``profile`` by default); ``load_kg`` a reference mass resting
    on the piston in place of the finger; ``watchdog_periods`` a fixed watchdog limit
    (by default judged against the port at start-up)."""
    return run_simulated_display(
        link,
        profile=read_profile(profile) if profile else None,
        reports=read_profile(reports) if reports else None,
        load_kg=load_kg,
        rate_hz=rate_hz,
        seed=seed,
        duration_s=duration_s,
        on_ready=on_ready,
        say=say,
        watchdog_periods=watchdog_periods,
    )


def simulate_text_logger(
    link: StrPath | None = None,
    *,
    forceps: SimulatedForceps | None = None,
    line_format: str = "csv",
    stamps: str = "us",
    header_every_s: float = 1.0,
    jitter: float = 0.2,
    broken: float = 0.001,
    clock_start: int = 0,
    duration_s: float | None = None,
    on_ready: Callable[[VirtualPort, Tissue], None] | None = None,
) -> dict[str, int]:
    """Run a simulated plain-text logger until SIGINT/SIGTERM (or ``duration_s``).

    Parameters
    ----------
    line_format : {"csv", "plotter", "teleplot"}
        How lines are written (:class:`~tissuecli.sim.textlogger.TextLogger`).
    stamps : {"us", "ms", "none"}
        The device stamp printed on each line.
    header_every_s : float
        Print the csv header first and again this often, s; 0 for none.
    jitter : float
        The loop samples up to this fraction of a period late.
    broken : float
        Probability that a line is broken on the way.
    clock_start : int
        The device counter at the first sample (near 2**32 to see it wrap).
    Others
        As :func:`simulate_forceps`.

    Returns
    -------
    dict
        ``sent`` lines, ``broken`` among them, ``overrun_bytes``.
    """
    model = (forceps or SimulatedForceps()).model()
    logger = TextLogger(
        model,
        format=line_format,
        stamps=stamps,
        header_every_s=header_every_s,
        jitter=jitter,
        broken=broken,
        clock_start=clock_start,
    )
    stop = StopFlag().install()
    port = VirtualPort(link)
    try:
        return run_text_logger(
            logger,
            port,
            stop=stop,
            duration_s=duration_s,
            on_ready=(lambda p: on_ready(p, model.tissue)) if on_ready is not None else None,
        )
    finally:
        port.close()
