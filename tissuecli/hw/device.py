"""One vocabulary for every device: open, read frames, command, limits, close.

A :class:`Device` subclass says what its kind is for (:attr:`~Device.role`), which
frames it streams (:attr:`~Device.frame_type`), which Info fields a host relies on
(:meth:`~Device.check_info`) and what limits it reports (:meth:`~Device.limits`);
:func:`register` adds it to :data:`DEVICES`, and from then on
:func:`~tissuecli.hw.link.open_device` opens, identifies and checks it by its kind
name. Adding a device is one class and that registry entry (docs/architecture.md,
"A new device"); the forceps, the display and the plain-text logger are built in.

A device is also what the host loops run over: :class:`~tissuecli.hw.stream.Stream`
and the haptic loop (:class:`~tissuecli.app.play.HostLoop`) use only :meth:`Device.command`,
:meth:`Device.poll`, :meth:`Device.send`, :meth:`Device.fileno`, :meth:`Device.nonblocking`
and :attr:`Device.bad_frames`, so a device that is not on a serial line (a simulated one
in the same process) overrides :meth:`Device.connect` and those, and runs in the same
loops.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, ClassVar, TypeVar

from ..core.errors import DeviceError
from ..render.profile import PAPER_DISPLAY, DisplayProfile, exceeded_limits, profile_from_dict
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
from .text import Line, TextLink

__all__ = [
    "DEVICES",
    "Device",
    "Display",
    "Forceps",
    "TextLogger",
    "device_class",
    "register",
]

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
        """Open the line, stop and drain the device, identify and check it (``options``
        go to :func:`~tissuecli.hw.link.open_device`)."""
        self.connect(**options)
        return self

    def connect(self, **options: Any) -> None:
        """Set :attr:`link` and :attr:`info`: the handshake of
        :func:`~tissuecli.hw.link.open_device` for a device on a framed serial line."""
        self.link, self.info = open_device(
            self.url, self.kind, baudrate=self.baudrate, timeout=self.timeout, **options
        )

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
        return [m for m in self.poll() if isinstance(m, self.frame_type)]

    def send(self, message: Message) -> None:
        """Send one command frame."""
        self._line().send(message)

    # ------------------------------------------------------------------ what loops use

    def command(self, name: str) -> None:
        """Send a command by name (``identify``, ``start``, ``stop``)."""
        self._line().command(name)

    def poll(self) -> list[Any]:
        """Everything that has arrived, decoded (frames of any type)."""
        return self._line().poll()

    def fileno(self) -> int | None:
        """A file descriptor a loop may wait on with ``select``; None if there is none
        (the loop then sleeps briefly between polls)."""
        return self._line().fileno()

    def nonblocking(self) -> None:
        """Make :meth:`poll` return at once (a loop that keeps its own deadlines)."""
        self._line().nonblocking()

    @property
    def bad_frames(self) -> int:
        """Frames that arrived corrupt so far."""
        return self.link.bad_frames if self.link is not None else 0

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

    #: The constants the host renders with (set by :meth:`open`).
    profile: DisplayProfile = PAPER_DISPLAY

    def open(  # type: ignore[override]
        self,
        *,
        rate_hz: float | None = None,
        profile: DisplayProfile | None = None,
        **options: Any,
    ) -> Display:
        """Open and identify the display, then check it against the host.

        Parameters
        ----------
        rate_hz : float, optional
            The host loop's rate, Hz: a display reporting another is refused.
        profile : DisplayProfile, optional
            Constants to render with; never beyond the limits the display reports
            (refused then). By default what it reports, else the paper's.
        """
        self.connect(**options)
        try:
            self.profile = self._checked_profile(rate_hz, profile)
        except BaseException:
            self.close()
            raise
        return self

    def _checked_profile(
        self, rate_hz: float | None, profile: DisplayProfile | None
    ) -> DisplayProfile:
        info = self.info or {}
        device_rate = info.get("rate_hz")
        if (
            rate_hz is not None
            and isinstance(device_rate, (int, float))
            and abs(device_rate - rate_hz) > 1e-6 * rate_hz
        ):
            raise DeviceError(
                f"the display at {self.url} runs its loop at {device_rate:g} Hz; "
                f"pass --rate {device_rate:g}"
            )
        reported = info.get("profile")
        limits = (
            profile_from_dict(reported, source=f"profile reported by {self.url}")
            if isinstance(reported, Mapping)
            else None
        )
        if profile is None:
            return limits if limits is not None else PAPER_DISPLAY
        if limits is not None:
            # the display's own limits rule: a file may ask less, never more
            over = exceeded_limits(profile, limits)
            if over:
                raise DeviceError(
                    f"--profile asks more than the display at {self.url} reports: "
                    + "; ".join(over)
                    + "; lower them to the display's, or give no --profile"
                )
        return profile

    def limits(self) -> dict[str, Any]:
        return dict((self.info or {}).get("profile") or {})


@register
class TextLogger(Device):
    """A plain-text logger (an Arduino or Teensy printing lines): it takes no commands
    and does not identify, so opening it opens the port and drops what arrived before;
    :meth:`read` returns :class:`~tissuecli.hw.text.Line` objects stamped on arrival.

    Attributes
    ----------
    link : TextLink or None
        The open port, line by line.
    """

    kind = "text-logger"
    role = "record --protocol text reads a logger that prints lines"
    frame_type = Line  # type: ignore[assignment]  (lines, not framed messages)

    def __init__(self, url: str, *, baudrate: int | None = None, timeout: float = 0.05) -> None:
        super().__init__(url, baudrate=115200 if baudrate is None else baudrate, timeout=timeout)
        self.link: TextLink | None = None  # type: ignore[assignment]
        self.info = {}

    def connect(self, **options: Any) -> None:
        self.link = TextLink(self.url, baudrate=self.baudrate, timeout=self.timeout)
        try:
            self.link.discard_input()
        except BaseException:
            self.close()
            raise

    def _line(self) -> TextLink:  # type: ignore[override]
        if self.link is None:
            raise DeviceError(f"the text logger at {self.url} is not open")
        return self.link

    def read(self) -> list[Line]:  # type: ignore[override]
        return self._line().poll()

    def send(self, message: Message) -> None:
        raise DeviceError(f"the text logger at {self.url} takes no commands")

    def nonblocking(self) -> None:
        self._line().link.nonblocking()

    def discard_input(self) -> None:
        """Drop whatever arrived before now (and the partial line it ends in)."""
        self._line().discard_input()

    @property
    def lines(self) -> int:
        """Lines received so far."""
        return self.link.lines if self.link is not None else 0
