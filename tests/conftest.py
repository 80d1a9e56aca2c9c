"""Shared fixtures: simulated devices on real pseudo-terminals, and device classes
registered for one test."""

from __future__ import annotations

import signal
import subprocess
import sys
import traceback
from collections.abc import Iterator
from pathlib import Path

import pytest

from tissuecli.hw.device import DEVICES, register
from tissuecli.sim.process import SimulatorProcess


@pytest.fixture(autouse=True)
def _signal_handlers_put_back() -> Iterator[None]:
    """A long command run in this process (CliRunner) installs its stop flag for Ctrl-C,
    SIGTERM and SIGHUP; put the handlers back, so that Ctrl-C still ends the test run."""
    sigs = [getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, n)]
    saved = {sig: signal.getsignal(sig) for sig in sigs}
    yield
    for sig, handler in saved.items():
        if handler is not None and signal.getsignal(sig) is not handler:
            signal.signal(sig, handler)


@pytest.fixture
def forceps(tmp_path: Path) -> Iterator[callable]:
    """Factory: ``forceps(*args)`` starts a simulated forceps, stopped at teardown."""
    started: list[SimulatorProcess] = []

    def start(*args: str, name: str = "forceps") -> SimulatorProcess:
        sim = SimulatorProcess("forceps", tmp_path / name, list(args)).__enter__()
        started.append(sim)
        return sim

    yield start
    for sim in started:
        sim.stop()


@pytest.fixture
def registered_device() -> Iterator[callable]:
    """Factory: ``registered_device(cls)`` puts a new kind of device in the registry for
    this test and returns it; at teardown the entry is removed (and a class's
    ``opened`` instance, if it keeps one, forgotten)."""
    added: list[type] = []

    def add(cls: type) -> type:
        register(cls)
        added.append(cls)
        return cls

    yield add
    for cls in added:
        DEVICES.pop(cls.kind, None)
        if hasattr(cls, "opened"):
            cls.opened = None


def tissuecli(*args: str, **kwargs: object) -> subprocess.CompletedProcess[str]:
    """Run the command line as a user would, in its own process."""
    return subprocess.run(
        [sys.executable, "-m", "tissuecli", *args],
        capture_output=True,
        text=True,
        timeout=kwargs.pop("timeout", 60),
        **kwargs,
    )  # type: ignore[arg-type]


def tissuecli_here(*args: str) -> subprocess.CompletedProcess[str]:
    """The command line run in this process (click's CliRunner), answered as
    :func:`tissuecli` answers: for tests of what a command computes and prints, without
    a new interpreter's start for each command. An exception that escapes the command
    comes back as the traceback an interpreter would print, with exit status 1."""
    from click.testing import CliRunner

    from tissuecli.cli import cli

    result = CliRunner().invoke(cli, list(args))
    stderr = result.stderr
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        stderr += "Traceback (most recent call last):\n" + "".join(
            traceback.format_exception(result.exception)
        )
    return subprocess.CompletedProcess(list(args), result.exit_code, result.stdout, stderr)


def popen(*args: str, default_sigint: bool = False) -> subprocess.Popen[str]:
    """``python -m tissuecli ARGS`` with pipes; ``default_sigint``: the child starts with
    SIGINT at its default, not ignored as a shell's background job inherits it (Python
    then leaves it ignored, as every program started under ``nohup`` or ``&`` does)."""

    def sigint_default() -> None:
        signal.signal(signal.SIGINT, signal.SIG_DFL)

    return subprocess.Popen(
        [sys.executable, "-m", "tissuecli", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=sigint_default if default_sigint else None,
    )


def assert_clean_error(result: subprocess.CompletedProcess[str] | object, *needles: str) -> None:
    """Exit code 1, a one-line 'Error: ...' message containing ``needles``, no traceback."""
    out = getattr(result, "stderr", None) or getattr(result, "output", "")
    code = getattr(result, "returncode", getattr(result, "exit_code", None))
    assert code == 1, out
    assert "Traceback" not in out, out
    lines = [line for line in out.strip().splitlines() if line.strip()]
    assert lines and lines[-1].startswith("Error: "), out
    for needle in needles:
        assert needle in lines[-1], out
