"""A scripted forceps behind a real pseudo-terminal: it answers IDENTIFY with whatever
Info it is given and, after START, sends exactly the bytes it is told to, so a test can
put valid-CRC frames with absurd content (or garbage) on the line."""

from __future__ import annotations

import errno
import os
import threading
import time
from collections.abc import Sequence
from typing import Any

from tissuecli.core.calibration import Channel
from tissuecli.hw.protocol import (
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
from tissuecli.sim.port import VirtualPort

RATE_HZ = 1000.0
CLOCK_HZ = 1_000_000
TICKS = int(CLOCK_HZ / RATE_HZ)  # device ticks per sample


def good_info(**changes: Any) -> dict[str, Any]:
    """A valid forceps Info object, with ``changes`` applied (a value of ``...`` drops a key)."""
    force = Channel.spanning(-1.0, 5.0, 8, "N")
    position = Channel.spanning(-0.5e-3, 15e-3, 8, "m")
    info: dict[str, Any] = {
        "protocol": PROTOCOL_VERSION,
        "device": "forceps",
        "model": "scripted test forceps",
        "firmware": "test",
        "rate_hz": RATE_HZ,
        "clock_hz": CLOCK_HZ,
        "adc_bits": 8,
        "calibration": {"force": force.as_dict(), "position": position.as_dict()},
    }
    for key, value in changes.items():
        if value is ...:
            info.pop(key, None)
        else:
            info[key] = value
    return info


def sample_frames(seqs: Sequence[int], clocks: Sequence[int], force: int = 10) -> list[bytes]:
    """Sample frames of the given sequence numbers and clock stamps (both wrapped to u32)."""
    return [
        encode(Sample(int(s) & 0xFFFFFFFF, int(c) & 0xFFFFFFFF, force, (i % 200) - 100))
        for i, (s, c) in enumerate(zip(seqs, clocks, strict=True))
    ]


class FakeForceps:
    """A forceps in a thread behind a pty that replays a script.

    Parameters
    ----------
    info : dict or bytes or None
        The Info reply: a dict (sent as an Info frame), raw bytes (sent as they are,
        e.g. a hand-made frame), or None (IDENTIFY is never answered).
    stream : sequence of bytes
        What to send after START, one item per sample period (a frame, garbage, or
        nothing for a frame lost on the way).
    period_s : float
        Nominal sample period: items go out in real time, as a device sampling at
        this rate would send them (never ahead of it).
    per_chunk : int
        Items written at once (a USB packet's worth).
    """

    def __init__(
        self,
        info: dict[str, Any] | bytes | None,
        stream: Sequence[bytes] = (),
        *,
        period_s: float = 1.0 / RATE_HZ,
        per_chunk: int = 4,
    ) -> None:
        self.info = info
        self.stream = list(stream)
        self.period_s = period_s
        self.per_chunk = per_chunk
        self.port = VirtualPort()
        self.started = threading.Event()
        self.finished = threading.Event()
        self._quit = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    @property
    def path(self) -> str:
        return self.port.path

    def __enter__(self) -> FakeForceps:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._quit.set()
        self._thread.join(timeout=5)
        self.port.close()

    def _write(self, data: bytes) -> None:
        """Write all of ``data``, waiting while the pty is full (nothing is dropped)."""
        view = memoryview(data)
        while view and not self._quit.is_set():
            try:
                n = os.write(self.port.master, view)
            except BlockingIOError:
                time.sleep(1e-4)
                continue
            except OSError as exc:
                if exc.errno == errno.EIO:  # nobody has the port open (yet, or any more)
                    time.sleep(1e-3)
                    continue
                raise
            view = view[n:]

    def _run(self) -> None:
        decoder = FrameDecoder()
        streaming = False
        i = 0
        t0 = 0.0
        while not self._quit.is_set():
            for msg in decoder.feed(self.port.read()):
                if not isinstance(msg, Command):
                    continue
                if msg.code == IDENTIFY and self.info is not None:
                    data = self.info if isinstance(self.info, bytes) else encode(Info(self.info))
                    self._write(data)
                elif msg.code == START and not streaming:
                    streaming = True
                    t0 = time.monotonic()
                    self.started.set()
                elif msg.code == STOP:
                    streaming = False
            # items i .. i + per_chunk - 1 are all "sampled" once the last one is due
            due = t0 + (i + self.per_chunk) * self.period_s
            if streaming and i < len(self.stream) and time.monotonic() >= due:
                self._write(b"".join(self.stream[i : i + self.per_chunk]))
                i += self.per_chunk
                if i >= len(self.stream):
                    self.finished.set()
            time.sleep(min(self.period_s, 1e-3))
