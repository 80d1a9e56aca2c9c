"""The ``calibrate`` services: the forceps' channels against known loads and gaps, and
the display's constants by a voltage sweep and ring-downs over its own link.

Forceps: reference values (a weight, a gauge block between the jaws) against raw
readings, typed at prompts, read from a CSV file or averaged from the live forceps;
:class:`~tissuecli.identify.calibration.ChannelFit` per channel; written as the
calibration file ``record --calibration`` and ``import --calibration`` read.

Display (the paper's procedure, with a reference mass for the known force): a sweep
of held voltages sets the static equilibria, so ``Kp`` and ``alpha``; releases from
a held pull ring down freely, so the natural frequency and damping, and with ``Kp``
the moving mass ``Mp`` and the damping ``b``; every frame off the end stops is fitted
at once. Written as a display profile with intervals. Nothing here does arithmetic
beyond bookkeeping: the fits are in :mod:`tissuecli.identify.calibration`.
"""

from __future__ import annotations

import math
import os
import re
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .._version import __version__
from ..core.errors import DeviceError, InputError
from ..core.flags import FLAG_LIMIT, FLAG_WATCHDOG
from ..core.units import UNITS, parse_quantity, unit_in_header
from ..formats.jsonfile import write_json
from ..formats.outputs import Output, check_outputs
from ..hw.device import Device, Display, Forceps
from ..hw.link import DEFAULT_BAUD
from ..hw.protocol import Encoder, Sample, SetVoltage
from ..hw.realtime import StopFlag, elevate, realtime
from ..hw.stream import Stream
from ..identify.calibration import (
    ChannelFit,
    DisplayFit,
    Estimate,
    fit_display,
    held_rate,
    off_stops,
    slow_force_warning,
)
from ..render.profile import PAPER_DISPLAY, PROFILE_UNITS, DisplayProfile

Array = NDArray[np.float64]
StrPath = str | os.PathLike[str]

MASS_UNITS = {"kg": 1.0, "g": 1e-3, "mg": 1e-6}
#: Heaviest reference mass a hand-held display is calibrated with, kg.
MAX_MASS_KG = 5.0
#: Dimension of each forceps channel's reference.
CHANNEL_DIMENSION = {"force": "force", "position": "length"}
CHANNEL_WORDS = {"force": "load", "position": "gap"}


def parse_mass(text: str, option: str) -> float:
    """A mass with an optional unit (``200g``, ``0.2``, ``0.2 kg``) in kg.

    Raises
    ------
    InputError
        Not a positive finite number up to :data:`MAX_MASS_KG`, or an unknown unit.
    """
    match = re.fullmatch(r"\s*([-+0-9.eE]+)\s*([a-z]*)\s*", text or "")
    try:
        value = float(match.group(1)) if match else math.nan
    except ValueError:
        value = math.nan
    factor = MASS_UNITS.get(match.group(2) or "kg") if match else None
    if factor is None or not (math.isfinite(value) and 0 < value * factor <= MAX_MASS_KG):
        raise InputError(
            f"{option} {str(text)[:30]!r}: give a mass up to {MAX_MASS_KG:g} kg such as 200g "
            f"(units: {', '.join(MASS_UNITS)})"
        )
    return value * factor


def check_out(out: StrPath, inputs: list[StrPath | None]) -> None:
    """Refuse, before any prompt or device, an ``--out`` that exists or cannot be written
    (a calibration never replaces a file)."""
    if os.path.lexists(out):
        raise InputError(
            f"--out {os.fspath(out)} exists; a calibration never replaces a file: choose "
            "another path"
        )
    check_outputs([Output(out, "--out")], inputs)


# ---------------------------------------------------------------------------- forceps


@dataclass
class Points:
    """Reference values (SI) against raw readings (counts, maybe averaged) of one channel."""

    reference: list[float] = field(default_factory=list)
    raw: list[float] = field(default_factory=list)

    def add(self, reference: float, raw: float) -> None:
        self.reference.append(float(reference))
        self.raw.append(float(raw))

    def __len__(self) -> int:
        return len(self.reference)


def parse_reference(text: str, channel: str) -> float:
    """A reference value typed at a prompt: a load (``50g``, ``0.49N``, ``0``) or a gap
    (``2mm``, ``0``), in SI. Zero is allowed (no load, jaws closed)."""
    dimension, word = CHANNEL_DIMENSION[channel], CHANNEL_WORDS[channel]
    zero = re.fullmatch(r"\s*\+?0*\.?0+\s*([A-Za-zµ]*)\s*", text or "")
    try:
        if zero:  # no load, jaws closed: parse_quantity takes only positive values
            parse_quantity(f"1{zero.group(1)}", dimension, word)
            return 0.0
        return parse_quantity(text, dimension, word)
    except InputError:
        example = "50g or 0.5N" if channel == "force" else "2mm"
        raise InputError(
            f"{word} {str(text)[:30]!r}: give 0 or a positive {dimension} such as {example} "
            f"(units: {', '.join(UNITS[dimension])})"
        ) from None


def read_points(path: StrPath, channel: str) -> Points:
    """Reference values and raw readings of ``channel`` from a text table.

    The first two numeric columns are the reference and the raw reading; the
    reference's unit comes from its header (``load [g]``, ``gap_mm``), SI otherwise.

    Raises
    ------
    InputError
        A missing or unreadable file, fewer than two numeric columns, or a reference
        unit of another dimension.
    """
    from ..formats.tables import read_table

    table = read_table(path)
    numeric = [i for i, ok in enumerate(table.numeric) if ok]
    if len(numeric) < 2:
        raise InputError(
            f"{os.fspath(path)}: needs two numeric columns, the {CHANNEL_WORDS[channel]} and "
            f"the raw reading; found {', '.join(table.names) or 'none'}"
        )
    ref_col, raw_col = numeric[:2]
    name = table.names[ref_col]
    unit = unit_in_header(name, channel) if table.header else None
    if unit is None and table.units:
        unit = table.units[ref_col] or None
    if unit is None and table.header:
        stray = _stray_unit(name)
        if stray is not None:
            raise InputError(
                f"{os.fspath(path)} column {name!r}: {stray} is not a unit of "
                f"{CHANNEL_DIMENSION[channel]}; give the {CHANNEL_WORDS[channel]} in "
                + ("N, g (grams-force), kgf, ..." if channel == "force" else "m, mm, um, ...")
            )
    factor = 1.0
    if unit is not None:
        factor = parse_quantity(f"1{unit}", CHANNEL_DIMENSION[channel], f"{path} column {name!r}")
    data = table.data[:, [ref_col, raw_col]]
    keep = np.all(np.isfinite(data), axis=1)
    points = Points()
    for ref, raw in data[keep]:
        points.add(ref * factor, raw)
    return points


def _stray_unit(header: str) -> str | None:
    """A unit a header names that is none the channel may have: one in brackets, or a
    known unit (or a mass) after an underscore."""
    from ..core.units import dimension_of

    bracket = re.search(r"[\[(]\s*([^\])]+?)\s*[\])]\s*$", header)
    if bracket:
        return bracket.group(1)
    tail = re.search(r"[_\s/-]([A-Za-zµ]+)\s*$", header)
    if tail and (dimension_of(tail.group(1)) is not None or tail.group(1) in MASS_UNITS):
        return tail.group(1)
    return None


class ForcepsReader:
    """Readings from the live forceps: both channels' raw counts averaged over frames.

    Parameters
    ----------
    url : str
        The forceps' port.
    frames : int
        Samples averaged per reading.
    baudrate : int
        Line rate, bit/s.

    Attributes
    ----------
    info : dict or None
        What the forceps answered to IDENTIFY.
    rate_hz : float or None
        Its sample rate, Hz (from its Info).
    force_rate_hz : float or None
        How often the force really changed in the readings so far, when it repeats
        regularly on the line (a load cell board read more slowly than the samples).
    """

    def __init__(self, url: str, frames: int = 200, baudrate: int = DEFAULT_BAUD) -> None:
        if frames < 1:
            raise InputError(f"--frames {frames} must be at least 1")
        self.frames = frames
        self.link: Device = Forceps(url, baudrate=baudrate).open(
            require_info=False, uses_calibration=False
        )
        self.info = self.link.info
        rate = (self.info or {}).get("rate_hz")
        self.rate_hz = float(rate) if isinstance(rate, (int, float)) else None
        #: how often the force really changes, if it repeats on the line (see read)
        self.force_rate_hz: float | None = None

    def read(self) -> tuple[float, float]:
        """Mean raw force and position counts over :attr:`frames` samples."""
        force: list[int] = []
        position: list[int] = []
        with Stream(self.link, Sample, stop=StopFlag(), idle_timeout_s=2.0) as stream:
            while len(force) < self.frames and stream.running():
                frames = stream.poll()
                if not frames:
                    stream.check_idle(time.monotonic())
                for m in frames:
                    assert isinstance(m, Sample)
                    force.append(m.force)
                    position.append(m.position)
        if not force:
            raise DeviceError(f"no sample from {self.link.url}")
        if self.rate_hz is not None:
            held = held_rate(force, self.rate_hz)
            if held is not None:
                self.force_rate_hz = min(held, self.force_rate_hz or held)
        return float(np.mean(force[: self.frames])), float(np.mean(position[: self.frames]))

    def close(self) -> None:
        self.link.close()


@dataclass
class ForcepsCalibration:
    """What :func:`calibrate_forceps` fitted and wrote."""

    force: ChannelFit
    position: ChannelFit
    path: str
    warnings: list[str]


def calibrate_forceps(
    force: Points,
    position: Points,
    out: StrPath,
    *,
    force_rate_hz: float | None = None,
    inputs: tuple[StrPath | None, ...] = (),
    note: str | None = None,
) -> ForcepsCalibration:
    """Fit both channels and write the calibration file ``out`` (never replacing a file).

    Parameters
    ----------
    force, position : Points
        Loads (N) and gaps (m) against raw counts.
    out : path
        The calibration file to write; refused if it exists.
    force_rate_hz : float, optional
        How often the force is read, Hz: warned about below
        :data:`~tissuecli.identify.calibration.MIN_FORCE_RATE_HZ`.
    inputs : paths
        Files read (never written).
    note : str, optional
        Stored as the file's ``note``.

    Raises
    ------
    InputError
        ``out`` exists or cannot be written, or a channel's points cannot be fitted.
    """
    check_out(out, list(inputs))
    fits = {
        name: ChannelFit().fit(p.reference, p.raw, what=f"{name} calibration")
        for name, p in (("force", force), ("position", position))
    }
    warnings = []
    for name, fit in fits.items():
        si = "N" if name == "force" else "m"
        if fit.nonlinear:
            warnings.append(
                f"the {name} channel is not linear: a quadratic term is significant "
                f"(F-test p = {fit.quadratic_p_:.2g}), departing {_si(fit.nonlinearity_, si)} "
                f"({100 * fit.nonlinearity_ / fit.span_:.2g} % of the {_si(fit.span_, si)} "
                "range) from the line the file stores; calibrate over the range you use"
            )
    if force_rate_hz is not None:
        slow = slow_force_warning(force_rate_hz)
        if slow is not None:
            warnings.append(slow)
    doc: dict[str, Any] = {
        "format": "tissuecli-calibration",
        "version": 1,
        "software": f"tissuecli {__version__}",
        "note": note or "measured by tissuecli calibrate forceps",
    }
    for name, fit in fits.items():
        doc[name] = {
            "gain": fit.gain_,
            "offset": fit.offset_,
            "unit": "N" if name == "force" else "m",
        }
    doc["fit"] = {name: _fit_dict(fit) for name, fit in fits.items()}
    write_json(out, doc)
    return ForcepsCalibration(fits["force"], fits["position"], os.fspath(out), warnings)


def _fit_dict(fit: ChannelFit) -> dict[str, Any]:
    return {
        "points": fit.n_,
        "gain_ci95": list(fit.gain_ci_),
        "offset_ci95": list(fit.offset_ci_),
        "residual_sd": fit.residual_sd_,
        "quadratic_p": fit.quadratic_p_,
        "nonlinearity": fit.nonlinearity_,
        "span": fit.span_,
    }


def _si(value: float, unit: str) -> str:
    if unit == "m":
        return f"{value * 1e3:.3g} mm"
    return f"{value:.3g} N"


def forceps_lines(result: ForcepsCalibration) -> list[str]:
    """The calibration of :func:`calibrate_forceps` as lines for people."""
    lines = []
    for name, fit, unit in (("force", result.force, "N"), ("position", result.position, "m")):
        lo, hi = fit.gain_ci_
        olo, ohi = fit.offset_ci_
        lines.append(
            f"{name}: gain {fit.gain_:.6g} {unit}/count (95 % {lo:.6g} .. {hi:.6g}), "
            f"offset {fit.offset_:.6g} {unit} (95 % {olo:.6g} .. {ohi:.6g})"
        )
        lines.append(
            f"  {fit.n_} points, residual {_si(fit.residual_sd_, unit)}"
            + (
                ""
                if fit.quadratic_p_ is None
                else f", linear (quadratic term p = {fit.quadratic_p_:.2g})"
                if not fit.nonlinear
                else f", NOT linear (quadratic term p = {fit.quadratic_p_:.2g})"
            )
        )
    lines.extend(f"warning: {w}" for w in result.warnings)
    lines.append(f"wrote {result.path}")
    return lines


# ---------------------------------------------------------------------------- display


class DisplayBench:
    """The display on the bench: holds a voltage for a while, answering every frame,
    and keeps every frame (device time, position, the voltage it applied, flags).

    The display's watchdog cuts the solenoid after 5 periods without a SetVoltage, so
    each batch of Encoder frames is answered; a cut on a busy machine costs nothing,
    since every frame says which voltage the display applied.
    """

    def __init__(self, link: Device, rate_hz: float, clock_hz: float, resolution: float) -> None:
        self.link, self.rate_hz, self.clock_hz = link, rate_hz, clock_hz
        self.resolution = resolution
        self.seq = 0
        self.ticks = 0
        self.last_clock: int | None = None
        self.t: list[float] = []
        self.x: list[float] = []
        self.volts: list[float] = []
        self.flags: list[int] = []

    def send(self, volts: float) -> None:
        self.link.send(SetVoltage(self.seq, volts))  # numbered by the frame it answers

    def hold(self, stream: Stream, volts: float, seconds: float) -> slice:
        """Hold ``volts`` for ``seconds`` of frames; the slice of the frames it kept."""
        n = max(int(round(seconds * self.rate_hz)), 1)
        first = len(self.t)
        self.send(volts)
        while len(self.t) < first + n:
            if not stream.running():
                raise InputError("calibration interrupted; nothing was written")
            frames = stream.poll()
            if not frames:
                stream.check_idle(time.monotonic())
                continue
            for m in frames:
                assert isinstance(m, Encoder)
                if self.last_clock is not None:
                    self.ticks += (m.clock - self.last_clock) & 0xFFFFFFFF
                self.last_clock, self.seq = m.clock, m.seq
                self.t.append(self.ticks / self.clock_hz)
                self.x.append(m.position * self.resolution)
                self.volts.append(float(m.volts))
                self.flags.append(int(m.flags))
            self.send(volts)
        return slice(first, len(self.t))

    def rest(self, kept: slice) -> float:
        """Mean position over the second half of a hold, m."""
        x = np.asarray(self.x[kept])
        return float(np.mean(x[x.size // 2 :]))

    def at_stop(self, kept: slice) -> bool:
        """Whether the piston ended a hold pressed against an end stop."""
        fl = np.asarray(self.flags[kept])
        return bool(np.any(fl[fl.size // 2 :] & FLAG_LIMIT))


@dataclass
class DisplayCalibration:
    """What :func:`calibrate_display` measured and wrote."""

    profile: DisplayProfile
    fit: DisplayFit
    mass_kg: float
    path: str
    url: str
    rate_hz: float
    reported: DisplayProfile | None
    holds: list[tuple[float, float | None]]
    release_volts: float
    ringdowns: int
    cut_frames: int
    notes: list[str] = field(default_factory=list)


def calibrate_display(
    url: str,
    out: StrPath,
    mass_kg: float,
    *,
    points: int = 9,
    hold_s: float = 1.0,
    ringdowns: int = 3,
    ring_s: float = 2.0,
    baudrate: int = DEFAULT_BAUD,
    stop: StopFlag | None = None,
    on_step: Callable[[str], None] | None = None,
) -> DisplayCalibration:
    """Measure the display's ``Kp``, ``alpha``, ``Mp`` and ``b`` over its own link.

    With ``mass_kg`` resting on the piston: hold ``points`` voltages from 0 to the
    reported ``v_max`` (evenly spaced in ``V^2``, so in position) ``hold_s`` each;
    then ``ringdowns`` times hold the sweep's voltage that lifts the piston about
    half-way to the top and release it to 0 V for ``ring_s``. Every frame off the
    end stops is fitted at once
    (:func:`~tissuecli.identify.calibration.fit_display`): the equilibria give
    ``Kp`` and ``alpha``, the ring-downs the natural frequency and damping, so ``Mp``
    and ``b``. The profile keeps the ``v_max``, ``stroke`` and encoder resolution the
    display reports (the paper's when it reports none). ``out`` is never replaced.

    Raises
    ------
    InputError
        ``out`` exists or cannot be written, bad arguments, or the fit fails (a mass
        that leaves too few frames off the end stops).
    DeviceError
        The device is not a display, or refuses the handshake.
    DeviceLost
        The display went silent; 0 V was sent.
    """
    check_out(out, [])
    if not (0 < mass_kg <= MAX_MASS_KG):
        raise InputError(f"--mass {mass_kg:g} kg must be in (0, {MAX_MASS_KG:g}] kg")
    if points < 4:
        raise InputError(f"--points {points} must be at least 4")
    if ringdowns < 1:
        raise InputError(f"--ringdowns {ringdowns} must be at least 1")
    if not (hold_s >= 0.2 and ring_s >= 0.2):
        raise InputError("--hold and --ring must be at least 0.2 s")
    say = on_step or (lambda line: None)
    link = Display(url, baudrate=baudrate, timeout=0.01).open()
    info = link.info or {}
    try:
        # what it reports, else the paper's
        reported = link.profile if isinstance(info.get("profile"), dict) else None
        limits = link.profile
        rate, clock = info.get("rate_hz"), info.get("clock_hz")
        rate_hz = float(rate) if isinstance(rate, (int, float)) else 1000.0
        clock_hz = float(clock) if isinstance(clock, (int, float)) else 1e6
        bench = DisplayBench(link, rate_hz, clock_hz, limits.resolution)
        with realtime():
            _, restore = elevate()
            try:
                holds, v1 = _procedure(bench, limits, points, hold_s, ringdowns, ring_s, stop, say)
            finally:
                restore()
    finally:
        link.close()
    x, volts, segment, zero, cut = _frames(bench, limits)
    say(f"fitting {x.size} frames")
    fit = fit_display(x - zero, volts, segment, 1.0 / rate_hz, mass_kg)
    notes = []
    v_max = limits.v_max
    if reported is not None and fit.alpha.value * v_max**2 > reported.max_pull:
        # the display's limits rule: its reported pull bounds the profile too
        v_max = math.sqrt(reported.max_pull / fit.alpha.value)
        notes.append(
            f"v_max lowered to {v_max:.4g} V so that the pull stays within the "
            f"{reported.max_pull:.4g} N the display reports (its alpha {reported.alpha:.5g} "
            "is too low); store the measured constants in the display to use its full range"
        )
    profile = DisplayProfile(
        Mp=fit.Mp.value,
        Kp=fit.Kp.value,
        alpha=fit.alpha.value,
        v_max=v_max,
        stroke=limits.stroke,
        resolution=limits.resolution,
        b=max(fit.b.value, 0.0),
    ).validate()
    if reported is None:
        notes.append(f"{url} reports no profile: v_max, stroke and resolution are the paper's")
    doc = profile.as_dict()
    doc["name"] = "calibrated " + time.strftime("%Y-%m-%d", time.gmtime())
    doc["note"] = (
        f"measured by tissuecli calibrate display at {url} with a {mass_kg:g} kg mass on the "
        f"piston: {len(holds)} held voltages, {ringdowns} ring-downs, {fit.frames} frames "
        "fitted; ci95 are 95 % intervals; v_max, stroke and resolution within what the "
        "display reports"
    )
    for key, est in (("Mp", fit.Mp), ("Kp", fit.Kp), ("alpha", fit.alpha), ("b", fit.b)):
        doc[key]["ci95"] = [est.lo, est.hi]
    write_json(out, doc)
    return DisplayCalibration(
        profile=profile,
        fit=fit,
        mass_kg=mass_kg,
        path=os.fspath(out),
        url=url,
        rate_hz=rate_hz,
        reported=reported,
        holds=[(v, None if r is None else r - zero) for v, r in holds],
        release_volts=v1,
        ringdowns=ringdowns,
        cut_frames=cut,
        notes=notes,
    )


def _procedure(
    bench: DisplayBench,
    limits: DisplayProfile,
    points: int,
    hold_s: float,
    ringdowns: int,
    ring_s: float,
    stop: StopFlag | None,
    say: Callable[[str], None],
) -> tuple[list[tuple[float, float | None]], float]:
    """The sweep and the releases; the held voltages with where the piston rested (None
    at an end stop), and the release voltage."""
    with Stream(
        bench.link,
        Encoder,
        stop=stop if stop is not None else StopFlag(),
        idle_timeout_s=0.5,
        before_stop=lambda: bench.send(0.0),
    ) as stream:
        bench.hold(stream, 0.0, hold_s)  # settle under the mass
        holds: list[tuple[float, float | None]] = []
        for i in range(points):
            v = limits.v_max * math.sqrt(i / (points - 1))
            kept = bench.hold(stream, v, hold_s)
            rest = None if bench.at_stop(kept) else bench.rest(kept)
            holds.append((v, rest))
            say(
                f"  held {v:.3f} V: "
                + ("at an end stop" if rest is None else f"near {rest * 1e3:.3f} mm")
            )
        free = [(v, r) for v, r in holds if r is not None]
        if len(free) < 3 or free[0][0] != 0.0:
            raise InputError(
                f"{len(free)} of {points} held voltages left the piston off its end stops: "
                "use a mass that holds it near mid-stroke at 0 V"
            )
        # release from the held voltage nearest half-way up from the rest under the mass
        target = 0.5 * free[0][1]
        v1 = min(free[1:], key=lambda vr: abs(vr[1] - target))[0]
        for i in range(ringdowns):
            bench.hold(stream, v1, hold_s)
            bench.hold(stream, 0.0, ring_s)
            say(f"  ring-down {i + 1} of {ringdowns}: released from {v1:.3f} V")
        bench.send(0.0)
    return holds, v1


def _frames(
    bench: DisplayBench, limits: DisplayProfile
) -> tuple[Array, Array, NDArray[np.int64], float, int]:
    """Positions, voltages and stretch labels of the frames off the end stops, the top
    stop's encoder reading (0 if the piston never reached it) and the frames the
    watchdog cut."""
    x = np.asarray(bench.x)
    volts = np.asarray(bench.volts)
    flags = np.asarray(bench.flags)
    t = np.asarray(bench.t)
    limit = (flags & FLAG_LIMIT) != 0
    top = limit & (x < x.min() + 0.5 * limits.stroke)
    zero = float(np.median(x[top])) if top.any() else 0.0
    inside = ~limit & off_stops(x, zero, zero + limits.stroke, 2 * limits.resolution)
    period = 1.0 / bench.rate_hz
    step = np.diff(t, prepend=t[0] - period)
    contiguous = np.abs(step - period) < 0.5 * period
    # a new stretch at every frame that is not the continuation of an inside one
    starts = inside & ~(np.roll(inside, 1) & contiguous)
    starts[0] = inside[0]
    segment = np.cumsum(starts)
    cut = int(np.sum((flags & FLAG_WATCHDOG) != 0))
    return x[inside], volts[inside], segment[inside], zero, cut


def display_lines(result: DisplayCalibration) -> list[str]:
    """The calibration of :func:`calibrate_display` as lines for people."""
    f = result.fit
    rep = result.reported

    def row(name: str, est: Estimate, fmt: str) -> str:
        unit = PROFILE_UNITS[name]
        was = f"; reported {getattr(rep, name):{fmt}}" if rep is not None else ""
        half = 0.5 * (est.hi - est.lo)
        return f"{name:5s} = {est.value:{fmt}} {unit} +- {half:.2g} (95 %{was})"

    free = sum(r is not None for _, r in result.holds)
    shown = rep or PAPER_DISPLAY
    lines = [
        f"display at {result.url}: {result.rate_hz:g} Hz, "
        f"{'reports' if rep is not None else 'assumed'} v_max {shown.v_max:g} V, stroke "
        f"{shown.stroke * 1e3:g} mm; {result.mass_kg:g} kg on the piston",
        f"sweep: {len(result.holds)} voltages held, {free} off the end stops; rest at 0 V "
        f"{f.x0 * 1e3:.3f} mm; {result.ringdowns} ring-downs released from "
        f"{result.release_volts:.3f} V",
        f"fit: {f.frames} frames in {f.segments} stretches, encoder residual "
        f"{f.residual_sd * 1e6:.2g} um; natural frequency {f.frequency_hz.value:.4g} Hz with "
        f"the mass, damping ratio {f.zeta.value:.3g}",
        row("Kp", f.Kp, ".5g"),
        row("alpha", f.alpha, ".5g"),
        row("Mp", f.Mp, ".4g"),
        row("b", f.b, ".3g"),
    ]
    lines.extend(f"note: {n}" for n in result.notes)
    if result.cut_frames:
        lines.append(
            f"note: the watchdog cut the solenoid on {result.cut_frames} frame(s) (a busy "
            "machine); those frames were fitted with the 0 V they had"
        )
    lines.append(f"wrote {result.path}")
    return lines
