"""Serial links to devices: the only module that imports pyserial.

:class:`Link` opens a port (a device path or any pyserial URL such as ``loop://``
or ``socket://host:port``), sends framed messages and returns decoded ones.
:func:`open_device` is the one handshake every host program uses: stop a stream a
crashed host left running, drain the line, identify the device and check that it
speaks this protocol and is the kind of device expected.
"""

from __future__ import annotations

import importlib
import math
import os
import stat
import time
from pathlib import Path
from typing import Any

import serial

from ..core.errors import DeviceError, DeviceLost
from .protocol import COMMANDS, PROTOCOL_VERSION, Command, FrameDecoder, Info, Message, encode

#: Device classes by kind name (:class:`tissuecli.hw.device.Device` subclasses, added
#: with :func:`tissuecli.hw.device.register`); the built-in ones load on first lookup.
DEVICES: dict[str, Any] = {}


def device_class(kind: str) -> Any:
    """The registered device class of ``kind``; :class:`DeviceError` naming those known."""
    if "forceps" not in DEVICES:  # the built-in classes register as their module loads
        importlib.import_module(f"{__package__}.device")
    try:
        return DEVICES[kind]
    except KeyError:
        raise DeviceError(
            f"no device of kind {kind!r}; known kinds: {', '.join(sorted(DEVICES))}"
        ) from None


DEFAULT_BAUD = 921600  # ptys ignore it; real 1 kHz forceps need >= 460800 (docs/protocol.md)


class Link:
    """A host's connection to one framed device.

    Parameters
    ----------
    url : str
        Device path (``/dev/ttyUSB0``, a simulator's ``--link``) or pyserial URL.
    baudrate : int
        Line rate in bit/s (ignored by ptys).
    timeout : float
        Longest a single :meth:`poll` blocks waiting for the first byte, in s.
    kind : str
        The device expected there (``forceps`` or ``display``), for error hints.
    """

    def __init__(
        self,
        url: str,
        baudrate: int = DEFAULT_BAUD,
        timeout: float = 0.05,
        kind: str = "forceps",
    ) -> None:
        self.url = url
        if "://" not in url and os.path.exists(url) and not stat.S_ISCHR(os.stat(url).st_mode):
            raise DeviceError(
                f"{url} is not a serial device (a regular file or a directory); give the "
                "device's path, e.g. /dev/ttyUSB0, or a simulator's --link"
            )
        try:
            self._port = serial.serial_for_url(
                url, baudrate=baudrate, timeout=timeout, write_timeout=1.0, exclusive=True
            )
        except (serial.SerialException, ValueError, OSError) as exc:
            hint = ""
            if not Path(url).exists() and "://" not in url:
                hint = (
                    "; is the device plugged in? For a simulated one run "
                    f"`tissuecli simulate {kind} --link {url}` first"
                )
            raise DeviceError(f"cannot open {url}: {_reason(exc)}{hint}") from None
        self.decoder = FrameDecoder()

    def send(self, message: Message) -> None:
        """Write one framed message."""
        try:
            self._port.write(encode(message))
        except (serial.SerialException, OSError) as exc:
            raise DeviceLost(f"lost {self.url} while writing: {_reason(exc)}") from None

    def command(self, name: str) -> None:
        """Send a command by name (``identify``, ``start``, ``stop``)."""
        self.send(Command(COMMANDS[name]))

    def poll(self) -> list[Message]:
        """Read what has arrived (waiting up to ``timeout`` for the first byte) and decode it."""
        try:
            # read(in_waiting or 1) returns everything buffered in one call;
            # read_until would go byte by byte (30x slower)
            data = self._port.read(self._port.in_waiting or 1)
        except (serial.SerialException, OSError) as exc:
            raise DeviceLost(f"lost {self.url}: {_reason(exc)}") from None
        return self.decoder.feed(data) if data else []

    def read_bytes(self) -> bytes:
        """The bytes that have arrived, undecoded (waiting up to ``timeout`` for the first):
        for devices that print lines rather than frames (:mod:`tissuecli.hw.text`)."""
        try:
            return bytes(self._port.read(self._port.in_waiting or 1))
        except (serial.SerialException, OSError) as exc:
            raise DeviceLost(f"lost {self.url}: {_reason(exc)}") from None

    def discard_input(self) -> None:
        """Drop whatever the device sent before now."""
        try:
            self._port.reset_input_buffer()
        except (serial.SerialException, OSError) as exc:
            raise DeviceLost(f"lost {self.url}: {_reason(exc)}") from None
        self.decoder = FrameDecoder()

    def identify(self, timeout_s: float = 2.0) -> dict[str, Any] | None:
        """Ask the device who it is; its Info dict, or ``None`` if it does not answer."""
        deadline = time.monotonic() + timeout_s
        self.command("identify")
        next_ask = time.monotonic() + 0.5
        while time.monotonic() < deadline:
            for msg in self.poll():
                if isinstance(msg, Info):
                    return msg.data
            if time.monotonic() > next_ask:  # a request lost in line noise is asked again
                self.command("identify")
                next_ask += 0.5
        return None

    @property
    def bad_frames(self) -> int:
        """Frames that arrived corrupt so far."""
        return self.decoder.bad_frames

    def fileno(self) -> int | None:
        """The port's file descriptor, to wait on with ``select``; None for URLs without
        one (``loop://``)."""
        try:
            return int(self._port.fileno())
        except (AttributeError, OSError, ValueError, TypeError):
            return None

    def nonblocking(self) -> None:
        """Make :meth:`poll` return at once: a loop that keeps its own deadlines waits instead."""
        self._port.timeout = 0

    def close(self) -> None:
        try:
            self._port.close()
        except (serial.SerialException, OSError):
            pass

    def __enter__(self) -> Link:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_device(
    url: str,
    kind: str,
    *,
    baudrate: int = DEFAULT_BAUD,
    timeout: float = 0.05,
    require_info: bool = True,
    no_info_hint: str = "",
    uses_calibration: bool = True,
) -> tuple[Link, dict[str, Any] | None]:
    """Open ``url``, stop and drain it, identify it and check what it reports.

    Parameters
    ----------
    url : str
        Device path or pyserial URL.
    kind : str
        The device expected: a kind registered in :data:`tissuecli.hw.device.DEVICES`
        (``forceps``, ``display``).
    baudrate, timeout
        See :class:`Link`.
    require_info : bool
        Refuse a device that does not answer IDENTIFY; otherwise return ``None``
        for its Info (a forceps that streams without identifying, given a calibration).
    no_info_hint : str
        Added to the refusal of a silent device (how else to proceed).
    uses_calibration : bool
        Whether the host will use the calibration in the Info (a forceps' is then
        checked; see :func:`check_info`).

    Returns
    -------
    link : Link
        Open, with the device stopped and its input drained.
    info : dict or None
        What the device answered to IDENTIFY, checked.

    Raises
    ------
    DeviceError
        If the port cannot be opened, the device is silent (and ``require_info``),
        speaks another protocol version, is another kind of device, or reports an
        Info field the host uses that is missing, of the wrong type or implausible.
    """
    link = Link(url, baudrate=baudrate, timeout=timeout, kind=kind)
    try:
        link.command("stop")  # a device left streaming by a crashed host
        time.sleep(0.05)
        link.discard_input()
        info = link.identify()
        if info is None:
            if require_info:
                raise DeviceError(
                    f"{url} did not answer IDENTIFY within 2 s; is it a {kind} and is it "
                    f"powered? For a simulated one run `tissuecli simulate {kind} --link {url}`"
                    + no_info_hint
                )
            return link, None
        check_identity(info, url, kind)
        check_info(info, url, kind, uses_calibration=uses_calibration)
        return link, info
    except BaseException:
        link.close()
        raise


def check_identity(info: dict[str, Any], url: str, kind: str) -> None:
    """Refuse a device of another protocol version or another kind than ``kind``."""
    version = info.get("protocol")
    if type(version) is not int or version != PROTOCOL_VERSION:
        raise DeviceError(
            f"{url} speaks protocol version {_show(version)}; this tissuecli speaks "
            f"{PROTOCOL_VERSION}. Update tissuecli or the {kind} firmware"
        )
    device = info.get("device", kind)
    if device != kind:
        raise DeviceError(f"{url} is a {_show(device)}, not a {kind}; {device_class(kind).role}")


#: Plausible values of the Info fields a host uses (docs/protocol.md, section 6).
RATE_HZ_RANGE = (1.0, 1e6)
CLOCK_HZ_RANGE = (1e3, 1e10)
#: device clock ticks per sample: enough to tell samples apart, far below the 2**32 wrap
TICKS_PER_SAMPLE_RANGE = (10.0, float(1 << 24))
ADC_BITS_RANGE = (8, 16)
#: largest magnitude at either ADC end (N, m) and smallest span of the ADC range
SI_END_LIMIT = {"force": 1e4, "position": 1.0}
SI_SPAN_MIN = {"force": 1e-6, "position": 1e-6}
SI_UNITS = {"force": "N", "position": "m"}


def check_info(info: dict[str, Any], url: str, kind: str, *, uses_calibration: bool = True) -> None:
    """Check every Info field the host uses: present, of the right type, plausible, as
    the device class of ``kind`` says (:meth:`~tissuecli.hw.device.Device.check_info`:
    a forceps must report ``rate_hz``, ``clock_hz`` and ``adc_bits`` and, if
    ``uses_calibration``, a plausible ``calibration``; a display's ``rate_hz`` and
    ``clock_hz`` are checked when present).

    Raises
    ------
    DeviceError
        One line naming the field, its value (shortened) and what it must be.
    """

    def refuse(name: str, value: object, must: str, hint: str = "") -> DeviceError:
        said = f"no Info {name}" if value is _MISSING else f"Info {name} = {_show(value)}"
        return DeviceError(
            f"{url} reports {said}; it must be {must}. Check the {kind} firmware{hint}"
        )

    device_class(kind).check_info(info, url, refuse, uses_calibration=uses_calibration)


def calibration_problem(calibration: object, bits: int) -> tuple[str, object, str] | None:
    """What is wrong with a forceps calibration object read through a ``bits``-bit ADC:
    ``(field, value, what it must be)``, or ``None`` if nothing is.

    Gains must be finite and non-zero, offsets finite (0 if absent), units SI, the SI
    values at both ADC ends within :data:`SI_END_LIMIT` and their span at least
    :data:`SI_SPAN_MIN`."""
    if not isinstance(calibration, dict):
        return "calibration", calibration, 'an object {"force": {...}, "position": {...}}'
    for channel in ("force", "position"):
        entry = calibration.get(channel, _MISSING)
        name = f"calibration.{channel}"
        if not isinstance(entry, dict):
            return name, entry, 'an object {"gain": ..., "offset": ..., "unit": ...}'
        gain, offset = _number(entry.get("gain")), _number(entry.get("offset", 0.0))
        if gain is None or gain == 0:
            return f"{name}.gain", entry.get("gain", _MISSING), "a finite non-zero number"
        if offset is None:
            return f"{name}.offset", entry.get("offset"), "a finite number"
        unit = entry.get("unit", SI_UNITS[channel])
        if unit != SI_UNITS[channel]:
            return f"{name}.unit", unit, f'"{SI_UNITS[channel]}"'
        lo, hi = -(1 << (bits - 1)), (1 << (bits - 1)) - 1
        ends = (offset + gain * lo, offset + gain * hi)
        limit, span = SI_END_LIMIT[channel], SI_SPAN_MIN[channel]
        unit = SI_UNITS[channel]
        if not all(math.isfinite(e) and abs(e) <= limit for e in ends):
            return (
                f"{name} (gain, offset)",
                (gain, offset),
                f"such that both ADC ends map within +-{limit:g} {unit} "
                f"(they map to {ends[0]:.3g} and {ends[1]:.3g} {unit})",
            )
        if abs(ends[1] - ends[0]) < span:
            return (
                f"{name}.gain",
                gain,
                f"large enough for the ADC range to span at least {span:g} {unit}",
            )
    return None


_MISSING = object()  # a field the device did not send
MISSING = _MISSING


def _number(value: object) -> float | None:
    """``value`` as a finite float if it is a JSON number (not a boolean), else None."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    try:
        out = float(value)
    except OverflowError:  # an integer beyond the range of a double
        return None
    return out if math.isfinite(out) else None


number = _number


def _show(value: object, limit: int = 60) -> str:
    """``repr(value)`` cut to ``limit`` characters: devices may send anything."""
    try:
        text = repr(value)
    except ValueError:  # an integer too long to print
        text = "a huge number"
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _reason(exc: BaseException) -> str:
    """The useful part of a pyserial/OS error message ("no such file or directory")."""
    text = str(exc)
    if "] " in text:  # "could not open port X: [Errno 2] No such file or directory: 'X'"
        return text.rsplit("] ", 1)[1].split(":", 1)[0].lower()
    if isinstance(exc, OSError) and exc.strerror:
        return str(exc.strerror).lower()
    return text
