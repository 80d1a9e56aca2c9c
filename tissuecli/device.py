"""Serial devices: the only module that imports pyserial.

Host side: :class:`Link` opens a port (a device path or any pyserial URL such
as ``loop://`` or ``socket://host:port``), sends framed messages and returns
decoded ones. Device side: :class:`VirtualPort` is the pseudo-terminal behind
which a simulated device lives, so the host opens it exactly like hardware.
"""

from __future__ import annotations

import errno
import os
import pty
import time
import tty
from pathlib import Path

import serial

from .errors import DeviceError, DeviceLost
from .protocol import COMMANDS, Command, FrameDecoder, Info, Message, encode

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
    """

    def __init__(self, url: str, baudrate: int = DEFAULT_BAUD, timeout: float = 0.05) -> None:
        self.url = url
        try:
            self._port = serial.serial_for_url(
                url, baudrate=baudrate, timeout=timeout, write_timeout=1.0, exclusive=True
            )
        except (serial.SerialException, ValueError, OSError) as exc:
            hint = ""
            if not Path(url).exists() and "://" not in url:
                hint = (
                    "; is the device plugged in? For a simulated one run "
                    f"`tissuecli simulate forceps --link {url}` first"
                )
            raise DeviceError(f"cannot open {url}: {_reason(exc)}{hint}") from None
        self.decoder = FrameDecoder()
        self.bytes_read = 0

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
        self.bytes_read += len(data)
        return self.decoder.feed(data) if data else []

    def discard_input(self) -> None:
        """Drop whatever the device sent before now."""
        try:
            self._port.reset_input_buffer()
        except (serial.SerialException, OSError) as exc:
            raise DeviceLost(f"lost {self.url}: {_reason(exc)}") from None
        self.decoder = FrameDecoder()

    def identify(self, timeout_s: float = 2.0) -> dict | None:
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

    def close(self) -> None:
        try:
            self._port.close()
        except (serial.SerialException, OSError):
            pass

    def __enter__(self) -> Link:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _reason(exc: BaseException) -> str:
    """The useful part of a pyserial/OS error message ("no such file or directory")."""
    text = str(exc)
    if "] " in text:  # "could not open port X: [Errno 2] No such file or directory: 'X'"
        return text.rsplit("] ", 1)[1].split(":", 1)[0].lower()
    if isinstance(exc, OSError) and exc.strerror:
        return str(exc.strerror).lower()
    return text


class VirtualPort:
    """A pseudo-terminal for a simulated device, optionally behind a stable symlink.

    The device writes to and reads from the master side; hosts open
    :attr:`name` (or the link) with pyserial like any serial port. Writes
    never block: when nobody drains the port the bytes are dropped, as a UART
    would drop them, and counted in :attr:`overruns`.
    """

    def __init__(self, link: str | os.PathLike[str] | None = None) -> None:
        self.master, self._slave = pty.openpty()
        tty.setraw(self._slave)  # no echo, no line discipline: bytes pass untouched
        os.set_blocking(self.master, False)
        self.name = os.ttyname(self._slave)
        self.link = Path(link) if link else None
        self.overruns = 0
        if self.link is not None:
            if self.link.is_symlink() or self.link.exists():
                if not self.link.is_symlink():
                    self.close()
                    raise DeviceError(
                        f"{self.link} exists and is not a symlink; choose another --link"
                    )
                self.link.unlink()
            self.link.symlink_to(self.name)

    @property
    def path(self) -> str:
        """What a host should open: the link if there is one, else the pty itself."""
        return str(self.link) if self.link else self.name

    def write(self, data: bytes) -> int:
        """Write without blocking; return the number of bytes that did not fit."""
        try:
            sent = os.write(self.master, data)
        except BlockingIOError:
            sent = 0
        except OSError as exc:
            if exc.errno == errno.EIO:
                sent = 0
            else:
                raise
        dropped = len(data) - sent
        self.overruns += dropped
        return dropped

    def read(self) -> bytes:
        """Whatever the host has sent, without blocking."""
        try:
            return os.read(self.master, 4096)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError as exc:
            if exc.errno == errno.EIO:
                return b""
            raise

    def fileno(self) -> int:
        return self.master

    def close(self) -> None:
        if self.link is not None and self.link.is_symlink() and os.readlink(self.link) == self.name:
            self.link.unlink()
        for fd in (self.master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass
