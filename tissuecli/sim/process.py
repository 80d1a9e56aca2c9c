"""A simulated device in its own process, as ``tissuecli simulate KIND --link PATH`` runs it:
what tests, benchmarks and ``demo`` start to get a real serial port with a device behind it."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from ..core.errors import DeviceError

#: How long a simulated device may take to open its port, s: its interpreter and imports
#: start at ordinary priority, 0.5 s on an idle machine, 5.7 s at a load average of 16.6
#: and over 10 s with two busy processes added on this 2-core machine; and it times its
#: port for up to 0.5 s (``VirtualPort.round_trips``).
READY_TIMEOUT_S = 30.0


class SimulatorProcess:
    """A simulated device in its own process, as ``tissuecli simulate KIND --link PATH``.

    Use as a context manager: entering waits until the port exists, leaving
    sends SIGTERM (the clean stop) and waits for the process to end.
    """

    def __init__(
        self,
        kind: str,
        link: str | os.PathLike[str],
        args: Sequence[str] = (),
        ready_timeout_s: float = READY_TIMEOUT_S,
    ) -> None:
        self.kind = kind
        self.link = Path(link)
        self.args = [
            sys.executable,
            "-m",
            "tissuecli",
            "simulate",
            kind,
            "--link",
            str(link),
            *args,
        ]
        self.ready_timeout_s = ready_timeout_s
        self.process: subprocess.Popen[str] | None = None

    def __enter__(self) -> SimulatorProcess:
        self.process = subprocess.Popen(
            self.args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        deadline = time.monotonic() + self.ready_timeout_s
        while not self.link.is_symlink():
            if self.process.poll() is not None:
                err = self.process.stderr.read().strip() if self.process.stderr else ""
                raise DeviceError(f"simulated {self.kind} failed to start: {err}")
            if time.monotonic() > deadline:
                self.stop()
                raise DeviceError(
                    f"simulated {self.kind} did not open {self.link} within "
                    f"{self.ready_timeout_s:g} s"
                )
            time.sleep(0.01)
        return self

    def stop(self, sig: int = signal.SIGTERM) -> int | None:
        """Signal the process and wait for it; its exit code."""
        if self.process is None:
            return None
        if self.process.poll() is None:
            self.process.send_signal(sig)
            try:
                self.process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        for stream in (self.process.stdout, self.process.stderr):
            if stream is not None:
                stream.close()
        return self.process.returncode

    def __exit__(self, *exc: object) -> None:
        self.stop()
