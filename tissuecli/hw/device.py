"""One vocabulary for every device on a framed serial line: open, read frames, command,
limits, close.

A :class:`Device` subclass says what its kind is for (:attr:`~Device.role`), which
frames it streams (:attr:`~Device.frame_type`), which Info fields a host relies on
(:meth:`~Device.check_info`) and what limits it reports (:meth:`~Device.limits`);
:func:`register` adds it to :data:`DEVICES`, and from then on
:func:`~tissuecli.hw.link.open_device` opens, identifies and checks it by its kind
name. Adding a device is one class and that registry entry (docs/architecture.md,
"A new device"); the forceps and the display are the two built in.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar, TypeVar

from ..core.errors import DeviceError
from .link import (
    ADC_BITS_RANGE,
    CLOCK_HZ_RANGE,
    DEFAULT_BAUD,
    DEVICES,
    MISSING,
    RATE_HZ_RANGE,
    TICKS_PER_SAMPLE_RANGE,
    Link,
    calibration_problem,
    device_class,
    number,
    open_device,
)
from .protocol import Encoder, Message, Sample, SetVoltage

__all__ = ["DEVICES", "Device", "Display", "Forceps", "device_class", "register"]

D = TypeVar("D", bound="type[Device]")


def register(cls: D) -> D:
    """Class decorator: make ``cls`` known by its :attr:`Device.kind`."""
    if not cls.kind:
        raise TypeError(f"{cls.__name__} has no kind")
    DEVICES[cls.kind] = cls
    return cls


class Device:
    """A device a host opens over a serial line and streams frames from.

    Use it as the host loops do: open (handshake, identity and Info checked), START,
    read frames, send commands, STOP (always, however the loop ends), close::

        with device_class("display")(url).open() as dev:
            dev.start()
            frames = dev.read()
            dev.send(SetVoltage(0, 0.0))

    Parameters
    ----------
    url : str
        Device path or pyserial URL.
    baudrate : int
        Line rate, bit/s.
    timeout : float
        Longest a single read waits for its first byte, s.

    Attributes
    ----------
    link : Link or None
        The open line (None before :meth:`open` and after :meth:`close`).
    info : dict or None
        What the device answered to IDENTIFY, checked.
    """

    #: kind name, as devices report it in their Info ``device`` field
    kind: ClassVar[str] = ""
    #: what this kind of device is for, said when another kind answers
    role: ClassVar[str] = ""
    #: the frames it streams after START
    frame_type: ClassVar[type[Message]] = Message
    #: Info fields a host must have from it (``rate_hz``, ``clock_hz`` are checked when
    #: present whatever the kind)
    required_info: ClassVar[tuple[str, ...]] = ()

    def __init__(self, url: str, *, baudrate: int | None = None, timeout: float = 0.05) -> None:
        self.url = url
        self.baudrate = DEFAULT_BAUD if baudrate is None else baudrate
        self.timeout = timeout
        self.link: Link | None = None
        self.info: dict[str, Any] | None = None

    # ------------------------------------------------------------------ lifecycle

    def open(self, **options: Any) -> Device:
        """Open the line, stop and drain the device, identify and check it."""
        self.link, self.info = open_device(
            self.url, self.kind, baudrate=self.baudrate, timeout=self.timeout, **options
        )
        return self

    def _line(self) -> Link:
        if self.link is None:
            raise DeviceError(f"the {self.kind} at {self.url} is not open")
        return self.link

    def start(self) -> None:
        self._line().command("start")

    def stop(self) -> None:
        self._line().command("stop")

    def read(self) -> list[Message]:
        """The frames of :attr:`frame_type` that have arrived."""
        return [m for m in self._line().poll() if isinstance(m, self.frame_type)]

    def send(self, message: Message) -> None:
        """Send one command frame."""
        self._line().send(message)

    def close(self) -> None:
        if self.link is not None:
            self.link.close()
            self.link = None

    def __enter__(self) -> Device:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ what it reports

    def limits(self) -> dict[str, Any]:
        """What the device reports of its own limits (empty if nothing)."""
        return {}

    @classmethod
    def check_info(
        cls, info: dict[str, Any], url: str, refuse: Callable[..., DeviceError], **options: Any
    ) -> None:
        """Check the Info fields a host uses; raise ``refuse(name, value, must)``.

        The base checks ``rate_hz`` and ``clock_hz`` (required if in
        :attr:`required_info`, else when present) and their ratio."""
        for name, (lo, hi) in (("rate_hz", RATE_HZ_RANGE), ("clock_hz", CLOCK_HZ_RANGE)):
            if name not in info and name not in cls.required_info:
                continue
            value = number(info.get(name))
            if value is None or not lo <= value <= hi:
                raise refuse(name, info.get(name, MISSING), f"a number of Hz in [{lo:g}, {hi:g}]")
        rate, clock = number(info.get("rate_hz")), number(info.get("clock_hz"))
        if rate is not None and clock is not None:
            lo, hi = TICKS_PER_SAMPLE_RANGE
            if not lo <= clock / rate <= hi:
                raise refuse(
                    "clock_hz / rate_hz",
                    clock / rate,
                    f"between {lo:g} and {hi:g} clock ticks per sample",
                )


@register
class Forceps(Device):
    """The sensorised forceps: streams :class:`~tissuecli.hw.protocol.Sample` frames
    (force and closure counts) and reports its rate, clock, ADC and calibration."""

    kind = "forceps"
    role = "record reads the forceps (a display is driven by `tissuecli play`)"
    frame_type = Sample
    required_info = ("rate_hz", "clock_hz", "adc_bits")

    @classmethod
    def check_info(
        cls, info: dict[str, Any], url: str, refuse: Callable[..., DeviceError], **options: Any
    ) -> None:
        """Rate, clock and ADC bits required; the calibration checked when the host uses
        it (``uses_calibration``)."""
        super().check_info(info, url, refuse)
        bits = info.get("adc_bits", MISSING)
        lo_bits, hi_bits = ADC_BITS_RANGE
        if type(bits) is not int or not lo_bits <= bits <= hi_bits:
            raise refuse("adc_bits", bits, f"an integer in [{lo_bits}, {hi_bits}]")
        if options.get("uses_calibration", True):
            problem = calibration_problem(info.get("calibration", MISSING), bits)
            if problem is not None:
                name, value, must = problem
                raise refuse(name, value, must, ", or give --calibration FILE")

    def limits(self) -> dict[str, Any]:
        return dict((self.info or {}).get("calibration") or {})


@register
class Display(Device):
    """The solenoid haptic display: streams :class:`~tissuecli.hw.protocol.Encoder`
    frames, takes :class:`~tissuecli.hw.protocol.SetVoltage` commands and reports its
    profile (``v_max``, stroke, constants)."""

    kind = "display"
    role = "play drives the display (a forceps is read by `tissuecli record`)"
    frame_type = Encoder
    command_type = SetVoltage

    def limits(self) -> dict[str, Any]:
        return dict((self.info or {}).get("profile") or {})
