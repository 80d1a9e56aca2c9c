"""The simulated forceps' firmware: it answers IDENTIFY with its identity and
calibration, streams Sample frames between START and STOP at its own (optionally
drifting) clock, and can inject line faults for tests."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from .._version import __version__
from ..core.errors import InputError
from ..hw.protocol import (
    IDENTIFY,
    PROTOCOL_VERSION,
    START,
    STOP,
    Command,
    FrameDecoder,
    Info,
    Sample,
    encode,
)
from ..hw.realtime import Deadlines, StopFlag, wait_readable
from .port import VirtualPort
from .synth import CLOCK_HZ, ForcepsModel

MAX_BURST_S = 0.5  # after a stall, send at most this much backlog at once


@dataclass(frozen=True)
class Faults:
    """Line faults a simulated device injects, each as a probability per frame."""

    corrupt: float = 0.0  # a bit flipped, or the frame cut short and followed by garbage
    drop: float = 0.0  # the frame is never sent (its sequence number is skipped)

    def __post_init__(self) -> None:
        for name in ("corrupt", "drop"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise InputError(f"--{name} is a probability per frame; give a value in [0, 1]")

    def apply(self, frames: list[bytes], rng: np.random.Generator) -> bytes:
        """The bytes actually put on the line for ``frames``."""
        if not (self.corrupt or self.drop):
            return b"".join(frames)
        out = bytearray()
        for frame in frames:
            u = rng.random()
            if u < self.drop:
                continue
            if u < self.drop + self.corrupt:
                frame = bytearray(frame)
                if rng.random() < 0.5:
                    i = int(rng.integers(0, len(frame) - 1))
                    frame[i] ^= 1 << int(rng.integers(0, 8))
                else:
                    frame = frame[: int(rng.integers(1, len(frame) - 1))]
                    frame += rng.integers(
                        0, 256, int(rng.integers(1, 20)), dtype=np.uint8
                    ).tobytes()
                    frame += b"\x00"
                frame = bytes(frame)
            out += frame
        return bytes(out)


def forceps_info(model: ForcepsModel) -> dict[str, Any]:
    """What the simulated forceps answers to IDENTIFY."""
    return {
        "protocol": PROTOCOL_VERSION,
        "device": "forceps",
        "model": "tissuecli simulated forceps",
        "firmware": __version__,
        "rate_hz": model.rate_hz,
        "clock_hz": CLOCK_HZ,
        "adc_bits": model.sensors.bits,
        "calibration": model.sensors.calibration.as_dict(),
    }


def run_forceps(
    model: ForcepsModel,
    port: VirtualPort,
    *,
    faults: Faults = Faults(),
    stop: StopFlag | None = None,
    duration_s: float | None = None,
    period_s: float = 1e-3,
    on_ready: Callable[[VirtualPort], None] | None = None,
) -> dict[str, int]:
    """Run the simulated forceps' firmware until ``stop`` is set (or ``duration_s``).

    Samples are due at the device's own rate; every ``period_s`` the due ones
    are framed and written in one burst, as a UART driver with a FIFO would.

    Returns
    -------
    dict
        Counters: ``sent`` frames, ``dropped`` by fault injection, ``overrun_bytes``
        the port could not take (nobody reading), ``missed_deadlines``.
    """
    stop = stop if stop is not None else StopFlag()
    rng = np.random.default_rng(model.seed + 1)  # faults draw apart from sensor noise
    decoder = FrameDecoder()
    info = encode(Info(forceps_info(model)))
    streaming = False
    sent = 0
    clock = Deadlines(period_s)
    rate = model.rate_hz * (1.0 + model.drift_ppm * 1e-6)  # samples per true second
    k_next = 0
    if on_ready is not None:
        on_ready(port)
    while not stop:
        now = time.monotonic()
        if duration_s is not None and now - clock.t0 >= duration_s:
            break
        for msg in decoder.feed(port.read()):
            if isinstance(msg, Command):
                if msg.code == IDENTIFY:
                    port.write(info)
                elif msg.code == START:
                    streaming = True
                elif msg.code == STOP:
                    streaming = False
        k_due = int((now - clock.t0) * rate) + 1
        if streaming and k_due > k_next:
            k_next = max(k_next, k_due - int(MAX_BURST_S * rate))
            ticks, counts = model.samples(k_next, k_due)
            frames = [
                encode(Sample(k & 0xFFFFFFFF, int(t) & 0xFFFFFFFF, int(c[0]), int(c[1])))
                for k, t, c in zip(range(k_next, k_due), ticks, counts, strict=True)
            ]
            port.write(faults.apply(frames, rng))
            sent += len(frames)
        k_next = max(k_next, k_due)
        wait_readable(port.fileno(), clock.next())
    return {"sent": sent, "overrun_bytes": port.overruns, "missed_deadlines": clock.missed}
