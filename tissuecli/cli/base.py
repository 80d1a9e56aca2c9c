"""The command group and the one place library errors become click errors."""

from __future__ import annotations

import functools
import sys
from collections.abc import Callable
from typing import Any, TypeVar

import click

from .._version import __version__
from ..core.errors import TissueError

F = TypeVar("F", bound=Callable[..., Any])


def fail_cleanly(fn: F) -> F:
    """Turn library errors into click errors: one line on stderr, exit 1."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except TissueError as exc:
            raise click.ClickException(str(exc)) from None

    return wrapper  # type: ignore[return-value]


class Group(click.Group):
    """A group whose every command reports :class:`TissueError` as a one-line message."""

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
        try:
            code = super().main(*args, standalone_mode=False, **kwargs)
        except click.ClickException as exc:
            exc.show()
            sys.exit(1)
        except click.exceptions.Abort:
            click.echo("aborted", err=True)
            sys.exit(1)
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


def live_line(text: str) -> None:
    """A status line on stderr: rewritten in place on a terminal, one line each in a log."""
    tty = sys.stderr.isatty()
    click.echo(("\r" + text) if tty else text, err=True, nl=not tty)


def end_live_line() -> None:
    """Finish a status line rewritten in place."""
    if sys.stderr.isatty():
        click.echo(err=True)
