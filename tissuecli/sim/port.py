"""The pseudo-terminal behind which a simulated device lives, so hosts open it with
pyserial exactly like hardware. The device side needs no pyserial: plain ``os`` calls."""

from __future__ import annotations

import errno
import os
import pty
import select
import time
import tty
from pathlib import Path

from ..core.errors import DeviceError


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
            try:
                self._make_link(self.link)
            except BaseException:
                self.link = None  # not ours: close() must leave it alone
                self.close()
                raise

    def _make_link(self, link: Path) -> None:
        """Point ``link`` at this pty; a stale link (its pty gone) is replaced, a live one
        (another simulator's) or any other file is refused."""
        if link.is_symlink():
            if link.exists():
                raise DeviceError(
                    f"{link} is the port of a running simulated device "
                    f"({os.readlink(link)}); stop it or choose another --link"
                )
            link.unlink()  # left by a simulator that was killed
        elif link.exists():
            raise DeviceError(f"{link} exists and is not a symlink; choose another --link")
        try:
            link.symlink_to(self.name)
        except FileNotFoundError:
            raise DeviceError(
                f"cannot create --link {link}: directory {link.parent} does not exist"
            ) from None
        except OSError as exc:
            raise DeviceError(f"cannot create --link {link}: {exc.strerror}") from None

    def publish(self, link: str | os.PathLike[str]) -> None:
        """Make the symlink ``link`` to this pty now (for a port made without one, so that
        no host finds it before :meth:`round_trips` has run)."""
        self._make_link(Path(link))
        self.link = Path(link)

    def round_trips(
        self, probes: int = 100, interval_s: float = 1e-3, budget_s: float = 0.5
    ) -> list[float]:
        """Time up to ``probes`` round trips of one byte through the pseudo-terminal, s:
        from the device side to the host side and back, ``interval_s`` apart, as a host
        answering each frame at once would see them (the transfer alone, no host code);
        none is started after ``budget_s``, so a starved machine delays start-up by
        about that much at most.

        Each direction goes through the kernel's tty buffer work, which runs in a
        kernel worker thread at ordinary priority (not in the writer's or the reader's
        context): on a busy machine it, not either loop, is what delays a frame. Run
        before a host can open the port (a port made without a link); a probe lost for
        ``budget_s`` counts as that long.
        """
        got: list[float] = []
        give_up = time.monotonic() + budget_s
        for _ in range(probes):
            t0 = time.monotonic()
            if t0 > give_up:
                break
            os.write(self.master, b"\x00")
            if self._await(self._slave, budget_s):
                os.read(self._slave, 64)
                os.write(self._slave, b"\x00")
                if self._await(self.master, budget_s):
                    os.read(self.master, 64)
            got.append(time.monotonic() - t0)
            time.sleep(max(0.0, t0 + interval_s - time.monotonic()))
        return got

    @staticmethod
    def _await(fd: int, timeout_s: float) -> bool:
        try:
            return bool(select.select([fd], [], [], timeout_s)[0])
        except InterruptedError:
            return False

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
