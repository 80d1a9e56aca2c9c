"""A simulated plain-text logger: a microcontroller that prints its forceps' samples as
lines (``t_us,force_N,closure_mm``, Serial Plotter ``force_N:0.12 closure_mm:1.5`` or
Teleplot ``>force_N:0.12``), from the moment it runs, whether anyone listens or not.

Its loop wakes with jitter, as a sketch's ``loop()`` does, so its own stamps wander
about the sample clock; now and then a line is broken on the way (cut short, a field
garbled, a byte that is not text) and the sample in it is lost as a sample but arrives
as a malformed line. Which lines break is a pure function of the seed and the line's
index (:meth:`TextLogger.broken`), so a test knows exactly which ones did.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..core.errors import InputError
from ..hw.realtime import Deadlines, StopFlag
from .port import VirtualPort
from .synth import CLOCK_HZ, ForcepsModel

#: the ways a text logger writes a line
FORMATS = ("csv", "plotter", "teleplot")
#: the stamps it may print: microseconds, milliseconds (both 32-bit, wrapping) or none
STAMPS = ("us", "ms", "none")
MAX_BURST_S = 0.5  # after a stall, print at most this much backlog at once


@dataclass
class TextLogger:
    """What the logger prints for each sample.

    Parameters
    ----------
    model : ForcepsModel
        The forceps it reads (its rate is the sample rate).
    format : {"csv", "plotter", "teleplot"}
        How a line is written.
    stamps : {"us", "ms", "none"}
        The device stamp printed: ``micros()`` or ``millis()`` as a 32-bit counter, or none.
    header_every_s : float
        A header line (csv) is printed first and again this often, s; 0 for none.
    jitter : float
        The loop wakes up to this fraction of a period late (uniform), 0 to 0.4.
    broken : float
        Probability that a line is broken on the way, 0 to 1.
    clock_start : int
        The device counter at sample 0, in its unit (set near 2**32 to see a wrap).
    """

    model: ForcepsModel
    format: str = "csv"
    stamps: str = "us"
    header_every_s: float = 1.0
    jitter: float = 0.2
    broken: float = 0.0
    clock_start: int = 0

    def __post_init__(self) -> None:
        if self.format not in FORMATS:
            raise InputError(f"--format {self.format!r}: give one of {', '.join(FORMATS)}")
        if self.stamps not in STAMPS:
            raise InputError(f"--stamps {self.stamps!r}: give one of {', '.join(STAMPS)}")
        if not 0.0 <= self.jitter <= 0.4:
            raise InputError("--jitter is a fraction of a period; give a value in [0, 0.4]")
        if not 0.0 <= self.broken <= 1.0:
            raise InputError("--broken is a probability per line; give a value in [0, 1]")
        self._cal = self.model.sensors.calibration
        self._unit = {"us": 1e6, "ms": 1e3, "none": 0.0}[self.stamps]

    @property
    def names(self) -> list[str]:
        """The columns (csv header, labels, variables)."""
        time_name = [f"t_{self.stamps}"] if self.stamps != "none" else []
        return [*time_name, "force_N", "closure_mm"]

    def header(self) -> bytes:
        """The header line (csv only; empty otherwise)."""
        if self.format != "csv" or self.header_every_s <= 0:
            return b""
        return (",".join(self.names) + "\n").encode()

    def broken_at(self, k: np.ndarray) -> np.ndarray:
        """Which of samples ``k`` are printed broken (a pure function of seed and ``k``)."""
        if not self.broken:
            return np.zeros(np.shape(k), dtype=bool)
        return _uniform(k, self.model.seed, 1) < self.broken

    def lines(self, k0: int, k1: int) -> list[bytes]:
        """The lines of samples ``k0 .. k1-1`` as printed, broken ones included."""
        k = np.arange(k0, k1)
        _, counts = self.model.samples(k0, k1)
        force = self._cal.force.to_si(counts[:, 0])
        closure_mm = self._cal.position.to_si(counts[:, 1]) * 1e3
        # the loop samples late by up to `jitter` periods; the stamp is read then
        late = self._late(k)
        t = (k + late) / (self.model.rate_hz * (1.0 + self.model.drift_ppm * 1e-6))
        ticks = (self.clock_start + np.floor(t * self._unit).astype(np.int64)) & 0xFFFFFFFF
        broken = self.broken_at(k)
        out = []
        for i in range(k.size):
            line = self._line(int(ticks[i]), float(force[i]), float(closure_mm[i]))
            out.append(self._break(line, int(k[i])) if broken[i] else line)
        return out

    def _late(self, k: np.ndarray) -> np.ndarray:
        """How late each sample is taken, in periods (a pure function of seed and ``k``)."""
        return _uniform(k, self.model.seed, 2) * self.jitter

    def _line(self, tick: int, force: float, closure_mm: float) -> bytes:
        stamp = self.stamps != "none"
        if self.format == "csv":
            fields = ([str(tick)] if stamp else []) + [f"{force:.5f}", f"{closure_mm:.5f}"]
            return (",".join(fields) + "\n").encode()
        if self.format == "plotter":
            parts = ([f"t_{self.stamps}:{tick}"] if stamp else []) + [
                f"force_N:{force:.5f}",
                f"closure_mm:{closure_mm:.5f}",
            ]
            return (" ".join(parts) + "\n").encode()
        # teleplot: its timestamps are milliseconds
        ts = ""
        if stamp:
            ms = tick / self._unit * 1e3
            ts = f"{ms:.3f}:" if self.stamps == "us" else f"{tick}:"
        return (f">force_N:{ts}{force:.5f}§N\n>closure_mm:{ts}{closure_mm:.5f}§mm\n").encode()

    def _break(self, line: bytes, k: int) -> bytes:
        """``line`` broken so that no dialect can read it: cut before its last field, a
        field garbled, or a byte that is not text."""
        how = k % 3
        if self.format == "teleplot":
            first, rest = line.split(b"\n", 1)
            # the first variable's value garbled: its row is dropped with it
            return first[:-6] + b"?" + first[-6:] + b"\n" + rest
        if how == 0:
            sep = b"," if self.format == "csv" else b" "
            return line[: line.rindex(sep)] + b"\n"
        if how == 1:
            return line[:-4] + b"?" + line[-4:]
        return line[:-3] + b"\xff" + line[-3:]


def _uniform(k: np.ndarray, seed: int, salt: int) -> np.ndarray:
    """A uniform number in [0, 1) for each index ``k``: a counter-based hash (splitmix64)
    of seed, salt and index, so any sample's draw is known without the ones before it."""
    with np.errstate(over="ignore"):
        z = np.asarray(k, dtype=np.uint64) + np.uint64(0x9E3779B97F4A7C15) * np.uint64(
            (seed * 8 + salt) & 0xFFFFFFFF
        )
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        z = z ^ (z >> np.uint64(31))
    return (z >> np.uint64(11)).astype(np.float64) / float(1 << 53)


def run_text_logger(
    logger: TextLogger,
    port: VirtualPort,
    *,
    stop: StopFlag | None = None,
    duration_s: float | None = None,
    period_s: float = 1e-3,
    on_ready: Callable[[VirtualPort], None] | None = None,
) -> dict[str, int]:
    """Print lines to ``port`` at the logger's rate until ``stop`` (or ``duration_s``).

    Lines are due at the device's rate; every ``period_s`` the due ones are written in
    one burst, as a UART driver with a FIFO would. The logger takes no commands: what
    the host sends is read and dropped.

    Returns
    -------
    dict
        ``sent`` lines, ``broken`` among them, ``skipped`` samples never printed (the
        process was starved of CPU for more than :data:`MAX_BURST_S`), ``overrun_bytes``
        the port could not take (nobody read them).
    """
    stop = stop if stop is not None else StopFlag()
    model = logger.model
    rate = model.rate_hz * (1.0 + model.drift_ppm * 1e-6)
    clock = Deadlines(period_s)
    k_next = sent = broken = skipped = 0
    next_header = clock.t0
    if on_ready is not None:
        on_ready(port)
    while not stop:
        now = time.monotonic()
        if duration_s is not None and now - clock.t0 >= duration_s:
            break
        port.read()
        k_due = int((now - clock.t0) * rate) + 1
        if k_due > k_next:
            behind = k_due - int(MAX_BURST_S * rate)
            if behind > k_next:  # starved: those samples are never printed
                skipped += behind - k_next
                k_next = behind
            out = b""
            if logger.header_every_s > 0 and now >= next_header:
                out += logger.header()
                next_header = now + logger.header_every_s
            out += b"".join(logger.lines(k_next, k_due))
            port.write(out)
            broken += int(logger.broken_at(np.arange(k_next, k_due)).sum())
            sent += k_due - k_next
            k_next = k_due
        delay = clock.next() - time.monotonic()
        if delay > 0:
            time.sleep(delay)
    return {"sent": sent, "broken": broken, "skipped": skipped, "overrun_bytes": port.overruns}


__all__ = ["CLOCK_HZ", "FORMATS", "STAMPS", "TextLogger", "run_text_logger"]
