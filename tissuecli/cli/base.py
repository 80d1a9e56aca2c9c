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
        try:
            code = super().main(*args, standalone_mode=False, **kwargs)
        except click.exceptions.NoArgsIsHelpError as exc:
            click.echo(exc.ctx.get_help())  # no command given: the help is the answer
            sys.exit(0)
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
