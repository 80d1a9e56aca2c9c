"""The tissuecli wire protocol, version 1: framing, checksums and messages.

Shared by the forceps and the display (docs/protocol.md is the reference).
Every frame on the line is::

    COBS( payload || CRC-16/CCITT-FALSE(payload), big-endian ) || 0x00

and every payload starts with a one-byte message type followed by
little-endian fields. COBS removes every 0x00 from the body, so a receiver
that meets garbage resynchronises at the next 0x00. This module is pure: bytes
in, messages out; it never touches a port.
"""

from __future__ import annotations

import binascii
import json
import struct
from dataclasses import astuple, dataclass, field
from typing import Any, ClassVar

# the display's flag bits travel in Encoder frames; their table lives with the controller's
from ..core.flags import FLAG_LIMIT as FLAG_LIMIT
from ..core.flags import FLAG_MODEL as FLAG_MODEL
from ..core.flags import FLAG_STALE as FLAG_STALE
from ..core.flags import FLAG_WATCHDOG as FLAG_WATCHDOG

PROTOCOL_VERSION = 1
DELIMITER = b"\x00"
#: a frame longer than this without a delimiter is garbage (largest message + slack)
MAX_FRAME = 1024


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF); check value 0x29B1 for b"123456789"."""
    return binascii.crc_hqx(data, 0xFFFF)


def cobs_encode(data: bytes) -> bytes:
    """Consistent Overhead Byte Stuffing: the result has no 0x00 byte."""
    out = bytearray()
    for block in data.split(b"\x00"):
        # each zero-delimited block is sent in runs of at most 254 bytes
        while len(block) >= 254:
            out.append(0xFF)
            out += block[:254]
            block = block[254:]
        out.append(len(block) + 1)
        out += block
    return bytes(out)


def cobs_decode(data: bytes) -> bytes:
    """Inverse of :func:`cobs_encode`.

    Raises
    ------
    ValueError
        If ``data`` is not valid COBS (a zero byte, or a code running past the end).
    """
    out = bytearray()
    i, n = 0, len(data)
    while i < n:
        code = data[i]
        i += 1
        if code == 0:
            raise ValueError("zero byte inside a COBS frame")
        end = i + code - 1
        if end > n:
            raise ValueError("COBS code runs past the end of the frame")
        chunk = data[i:end]
        if b"\x00" in chunk:
            raise ValueError("zero byte inside a COBS frame")
        out += chunk
        i = end
        if code != 0xFF and i < n:
            out.append(0)
    return bytes(out)


# --------------------------------------------------------------------------- messages


@dataclass(frozen=True)
class Message:
    """Base of all messages; subclasses set ``TYPE`` and ``FORMAT`` (struct, little-endian)."""

    TYPE: ClassVar[int] = -1
    FORMAT: ClassVar[str] = ""

    def pack(self) -> bytes:
        return bytes([self.TYPE]) + struct.pack("<" + self.FORMAT, *astuple(self))

    @classmethod
    def unpack(cls, body: bytes) -> Message:
        return cls(*struct.unpack("<" + cls.FORMAT, body))


@dataclass(frozen=True)
class Sample(Message):
    """Forceps -> host: one sample of both sensors.

    ``clock`` is the device's free-running clock in ticks (wraps at 2**32);
    ``force`` and ``position`` are raw signed ADC counts.
    """

    TYPE: ClassVar[int] = 0x01
    FORMAT: ClassVar[str] = "IIhh"
    seq: int
    clock: int
    force: int
    position: int


@dataclass(frozen=True)
class Encoder(Message):
    """Display -> host: piston encoder reading and the voltage being applied.

    ``position`` is in encoder counts (positive down), ``volts`` the solenoid
    voltage in use, ``flags`` a bit set (see :data:`FLAG_WATCHDOG`).
    """

    TYPE: ClassVar[int] = 0x02
    FORMAT: ClassVar[str] = "IIifB"
    seq: int
    clock: int
    position: int
    volts: float
    flags: int


@dataclass(frozen=True)
class SetVoltage(Message):
    """Host -> display: the solenoid voltage to apply now, in volts.

    ``seq`` is the ``seq`` of the Encoder frame the voltage answers (the last one the
    host had), so the display can tell whether each period runs on the answer to the
    frame before it (:data:`FLAG_STALE`).
    """

    TYPE: ClassVar[int] = 0x21
    FORMAT: ClassVar[str] = "If"
    seq: int
    volts: float


@dataclass(frozen=True)
class SetModel(Message):
    """Host -> display: a SetVoltage with the tissue's local linear model around it.

    ``seq`` and ``volts`` are a :class:`SetVoltage`'s: applied as they are while the
    answer is on time. The rest let a display that states ``"local_model": true`` keep
    rendering the tissue while the next answer is late: ``u`` is the pull the law asked
    for over ``alpha`` (V^2; negative where the solenoid would have to push), meant for
    the tick after frame ``seq``; ``du_dx`` (V^2/m) and ``du_dv`` (V^2 s/m) are its
    slopes against the piston's position and velocity with the tracking error held (the
    tissue's local stiffness less the display's spring, and its local damping less the
    piston's, over ``alpha``). A display running on the answer ``d`` periods late
    applies ``sqrt(u + du_dx dx + du_dv dv)``, clamped to [0, v_max], ``dx`` and ``dv``
    its encoder's change since the tick the answer was meant for (docs/protocol.md,
    section 7).
    """

    TYPE: ClassVar[int] = 0x22
    FORMAT: ClassVar[str] = "Iffff"
    seq: int
    volts: float
    u: float
    du_dx: float
    du_dv: float


@dataclass(frozen=True)
class Command(Message):
    """Host -> device: a command without arguments (see :data:`COMMANDS`)."""

    TYPE: ClassVar[int] = 0x10
    FORMAT: ClassVar[str] = "B"
    code: int


@dataclass(frozen=True)
class Info(Message):
    """Device -> host: identity and calibration, a UTF-8 JSON object."""

    TYPE: ClassVar[int] = 0x03
    data: dict[str, Any] = field(default_factory=dict)

    def pack(self) -> bytes:
        return bytes([self.TYPE]) + json.dumps(self.data, separators=(",", ":")).encode()

    @classmethod
    def unpack(cls, body: bytes) -> Info:
        data = json.loads(body.decode())
        if not isinstance(data, dict):
            raise ValueError("INFO body is not a JSON object")
        return cls(data)


IDENTIFY, START, STOP = 1, 2, 3
COMMANDS = {"identify": IDENTIFY, "start": START, "stop": STOP}

MESSAGES: dict[int, type[Message]] = {
    m.TYPE: m for m in (Sample, Encoder, SetVoltage, SetModel, Command, Info)
}


def encode(message: Message) -> bytes:
    """One message as a complete frame, delimiter included."""
    payload = message.pack()
    frame = cobs_encode(payload + crc16(payload).to_bytes(2, "big")) + DELIMITER
    if len(frame) > MAX_FRAME:
        raise ValueError(
            f"{type(message).__name__} frame of {len(frame)} bytes exceeds {MAX_FRAME}"
        )
    return frame


def decode_frame(frame: bytes) -> Message:
    """Decode one frame (without its delimiter).

    Raises
    ------
    ValueError
        For bad COBS, a CRC mismatch, an unknown type or a wrong length.
    """
    body = cobs_decode(frame)
    if len(body) < 3:
        raise ValueError("frame too short")
    payload, crc = body[:-2], int.from_bytes(body[-2:], "big")
    if crc16(payload) != crc:
        raise ValueError("CRC mismatch")
    kind = MESSAGES.get(payload[0])
    if kind is None:
        raise ValueError(f"unknown message type 0x{payload[0]:02x}")
    try:
        return kind.unpack(payload[1:])
    except (struct.error, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise ValueError(f"bad {kind.__name__} body: {exc}") from exc


class FrameDecoder:
    """Turns a byte stream into messages; corrupt frames are dropped and counted.

    Feed it whatever the port returns. After garbage it resynchronises at the
    next delimiter, so at most the frame the garbage touched is lost.

    Attributes
    ----------
    bad_frames : int
        Frames rejected (bad COBS, CRC, type or length, or overlong).
    good_frames : int
        Frames decoded.
    """

    def __init__(self) -> None:
        self._buffer = b""
        self._skipping = False  # inside an overlong run: drop bytes until the next delimiter
        self.bad_frames = 0
        self.good_frames = 0

    def feed(self, data: bytes) -> list[Message]:
        """Add bytes; return the messages completed by them, in order.

        The result does not depend on how the stream is cut into calls.
        """
        pieces = (self._buffer + data).split(DELIMITER)
        self._buffer = pieces.pop()
        if self._skipping and pieces:
            pieces[0] = b""  # the end of the overlong run, already counted
            self._skipping = False
        if self._skipping:
            self._buffer = b""
        elif len(self._buffer) > MAX_FRAME:
            # counted now, once, so memory stays bounded however long the run
            self._buffer = b""
            self._skipping = True
            self.bad_frames += 1
        out: list[Message] = []
        for piece in pieces:
            if not piece:
                continue  # back-to-back delimiters: an idle line, not an error
            if len(piece) > MAX_FRAME:
                self.bad_frames += 1
                continue
            try:
                out.append(decode_frame(piece))
            except ValueError:
                self.bad_frames += 1
        self.good_frames += len(out)
        return out


class SequenceTracker:
    """Counts frames lost from gaps in a 32-bit sequence number.

    A jump backwards (a device reset) or forwards by more than ``max_gap``
    is treated as a restart of the sequence, not as billions of lost frames.
    """

    def __init__(self, max_gap: int = 1 << 24) -> None:
        self.last: int | None = None
        self.lost = 0
        self.restarts = 0
        self._max_gap = max_gap

    def update(self, seq: int) -> int:
        """Record ``seq``; return how many frames were lost just before it."""
        lost = 0
        if self.last is not None:
            gap = (seq - self.last) & 0xFFFFFFFF
            if gap == 0 or gap > self._max_gap:
                self.restarts += 1
            else:
                lost = gap - 1
        self.last = seq
        self.lost += lost
        return lost
