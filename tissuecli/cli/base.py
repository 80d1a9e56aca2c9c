"""The command group and the one place library errors become click errors."""

from __future__ import annotations

import functools
import signal
import sys
from collections.abc import Callable
from typing import Any, TypeVar

import click

from .._version import __version__
from ..core.errors import (
    EXIT_ERROR,
    Interrupted,
    TissueError,
    signal_exit_code,
    signal_name,
)

F = TypeVar("F", bound=Callable[..., Any])


class Failure(click.ClickException):
    """A library error as click shows it (``Error: ...``), with the exit status of its
    class (docs/usage.md, "Exit status")."""

    def __init__(self, message: str, exit_code: int = EXIT_ERROR) -> None:
        super().__init__(message)
        self.exit_code = exit_code


def fail_cleanly(fn: F) -> F:
    """Turn library errors into click errors: one line on stderr, the exit status of the
    error's class (1 for an error a user can fix; 3-7 for a run with faults)."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except TissueError as exc:
            raise Failure(str(exc), exc.exit_code) from None

    return wrapper  # type: ignore[return-value]


def _interrupt(signum: int, frame: Any) -> None:
    """Ctrl-C, SIGTERM or SIGHUP in a command without a loop of its own to stop: unwind,
    so that partial outputs are removed on the way out."""
    raise Interrupted(signum)


def interruptible() -> Callable[[], None]:
    """Ctrl-C, SIGTERM and SIGHUP end the command by :class:`Interrupted` (the long
    commands replace these handlers with a :class:`~tissuecli.hw.realtime.StopFlag` for a
    clean stop); returns what puts the handlers back as they were (for a command run
    in-process).

    Ctrl-C is handled here too rather than left to Python's ``KeyboardInterrupt``: one
    that passes through code compiled from a string (``exec``, as ``dataclasses`` and
    ``namedtuple`` do while a module loads) marks the interpreter as ended by an
    unhandled Ctrl-C, and CPython then kills the process with SIGINT after it exits 130.
    A Ctrl-C that the process started ignoring (a background job) stays ignored."""
    previous: dict[int, Any] = {}
    for name in ("SIGINT", "SIGTERM", "SIGHUP"):
        sig = getattr(signal, name, None)
        if sig is None or (name == "SIGINT" and signal.getsignal(sig) == signal.SIG_IGN):
            continue
        try:
            previous[sig] = signal.signal(sig, _interrupt)
        except ValueError:  # not the main thread (a test's runner): leave them
            break

    def restore() -> None:
        for sig, handler in previous.items():
            signal.signal(sig, handler)

    return restore


def _signal_behind(exc: BaseException) -> int | None:
    """The signal number of an :class:`Interrupted` or ``KeyboardInterrupt`` that caused
    ``exc`` (through ``__cause__`` or ``__context__``), or None."""
    seen: set[int] = set()
    cause: BaseException | None = exc
    while cause is not None and id(cause) not in seen:
        seen.add(id(cause))
        if isinstance(cause, Interrupted):
            return cause.signum
        if isinstance(cause, KeyboardInterrupt):
            return int(signal.SIGINT)
        cause = cause.__cause__ or cause.__context__
    return None


def end_by_signal(stop: Any) -> None:
    """After a long command's summary: exit ``128 + signum`` if a signal (``stop``, a
    :class:`~tissuecli.hw.realtime.StopFlag`) ended it, saying so on stderr."""
    if stop:
        said = signal_name(stop.signal)
        click.echo(f"stopped by {said}; everything up to then is saved", err=True)
        raise click.exceptions.Exit(signal_exit_code(stop.signal))


class Command(click.Command):
    """A command that refuses an option given twice instead of silently keeping the last."""

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        refuse_repeats(self, ctx, args)
        return super().parse_args(ctx, args)


def refuse_repeats(command: click.Command, ctx: click.Context, args: list[str]) -> None:
    """Raise a usage error if a single-valued option appears twice in ``args``."""
    options: dict[str, tuple[click.Option, bool]] = {}
    for param in command.params:
        if isinstance(param, click.Option) and not (param.multiple or param.count):
            for name in (*param.opts, *param.secondary_opts):
                options[name] = (param, not param.is_flag)
    seen: dict[str, str] = {}
    i = 0
    while i < len(args) and args[i] != "--":
        token = args[i]
        name = token.split("=", 1)[0] if token.startswith("--") else token
        if name in options:
            param, takes_value = options[name]
            if param.name in seen:
                also = "" if seen[param.name] == name else f" (also as {seen[param.name]})"
                raise click.UsageError(f"{name} is given twice{also}; give it once", ctx)
            seen[param.name or name] = name
            i += takes_value and "=" not in token  # skip the option's value
        i += 1


class Group(click.Group):
    """A group whose every command reports :class:`TissueError` as a one-line message and
    refuses repeated options."""

    command_class = Command

    def add_command(self, cmd: click.Command, name: str | None = None) -> None:
        if cmd.callback is not None:
            cmd.callback = fail_cleanly(cmd.callback)
        super().add_command(cmd, name)

    def group(self, *args: Any, **kwargs: Any) -> Any:
        kwargs.setdefault("cls", Group)
        return super().group(*args, **kwargs)

    def main(self, *args: Any, standalone_mode: bool = True, **kwargs: Any) -> Any:
        """As click's, but every bad input (usage errors too) exits with code 1."""
        if not standalone_mode:
            return super().main(*args, standalone_mode=False, **kwargs)
        restore = interruptible()
        try:
            code = super().main(*args, standalone_mode=False, **kwargs)
        except click.exceptions.NoArgsIsHelpError as exc:
            click.echo(exc.ctx.get_help())  # no command given: the help is the answer
            sys.exit(0)
        except Failure as exc:
            exc.show()
            sys.exit(exc.exit_code)
        except click.ClickException as exc:
            exc.show()
            sys.exit(EXIT_ERROR)
        except (click.exceptions.Abort, KeyboardInterrupt):
            # click turns a KeyboardInterrupt into Abort; both are Ctrl-C
            click.echo(f"aborted: interrupted by {signal_name(signal.SIGINT)}", err=True)
            sys.exit(signal_exit_code(signal.SIGINT))
        except Interrupted as exc:
            click.echo(f"aborted: {exc}", err=True)
            sys.exit(signal_exit_code(exc.signum))
        except Exception as exc:
            # a signal that landed inside an import or a class being made comes back
            # wrapped (RuntimeError from __set_name__, ...): still the signal's ending
            signum = _signal_behind(exc)
            if signum is None:
                raise
            click.echo(f"aborted: interrupted by {signal_name(signum)}", err=True)
            sys.exit(signal_exit_code(signum))
        finally:
            restore()
        sys.exit(code if isinstance(code, int) else 0)


@click.group(cls=Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="tissuecli")
def cli() -> None:
    """Give a surgeon's sense of touch back through a sensorised laparoscopic forceps.

    \b
    Record grasps from the forceps, identify the tissue law
        K f0(x) + S f1(xdot) + M xddot = F
    and render that tissue on a solenoid haptic display.

    \b
    Try it with no hardware:  tissuecli demo
    Typical session:
        tissuecli simulate forceps --link /tmp/forceps &
        tissuecli record --port /tmp/forceps --out grasp.h5 --duration 10 --session liver-1
        tissuecli sessions grasp.h5

    All quantities are SI (N, m, s, kg, V) inside and in every file.
    """


def printable(text: object, width: int | None = None) -> str:
    """``text`` for one line of a table: control characters escaped (a newline in a label
    cannot forge a row), cut to ``width`` characters with an ellipsis."""
    shown = "".join(
        c if c.isprintable() else c.encode("unicode_escape").decode() for c in str(text)
    )
    if width is not None and len(shown) > width:
        shown = shown[: width - 1] + "…"
    return shown


def live_line(text: str) -> None:
    """A status line on stderr: rewritten in place on a terminal, one line each in a log."""
    tty = sys.stderr.isatty()
    click.echo(("\r" + text) if tty else text, err=True, nl=not tty)


def end_live_line() -> None:
    """Finish a status line rewritten in place."""
    if sys.stderr.isatty():
        click.echo(err=True)
