"""Options several commands share, each defined once."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import click

Decorator = Callable[[Callable[..., Any]], Callable[..., Any]]


def link_option(kind: str) -> Decorator:
    return click.option(
        "--link",
        type=click.Path(dir_okay=False),
        default=None,
        help=f"Make a symlink to the port here (e.g. /tmp/{kind}), so its name is stable.",
    )


def rate_option(help: str) -> Decorator:
    return click.option(
        "--rate",
        type=click.FloatRange(min=1, max=20000),
        default=1000.0,
        show_default=True,
        help=help,
    )


def duration_option(help: str) -> Decorator:
    return click.option(
        "--duration",
        type=click.FloatRange(min=0, min_open=True),
        default=None,
        help=help,
    )


def seed_option(help: str) -> Decorator:
    return click.option("--seed", type=int, default=0, show_default=True, help=help)


def session_option(help: str, required: bool = False) -> Decorator:
    return click.option("--session", default=None, required=required, help=help)


def h5_out_option() -> Decorator:
    return click.option(
        "--out",
        required=True,
        type=click.Path(dir_okay=False),
        help="HDF5 file (created if missing).",
    )


def label_options(note_help: str = "Note stored with the session.") -> Decorator:
    """``--tissue`` and ``--note``: labels stored with a new session."""

    def apply(fn: Callable[..., Any]) -> Callable[..., Any]:
        fn = click.option("--note", default="", help=note_help)(fn)
        return click.option("--tissue", default="", help="Tissue label stored with the session.")(
            fn
        )

    return apply


def units_option(help: str) -> Decorator:
    return click.option("--units", default=None, help=help)


def profile_option(help: str) -> Decorator:
    return click.option(
        "--profile", "profile_file", type=click.Path(dir_okay=False), default=None, help=help
    )


def force_option() -> Decorator:
    return click.option(
        "--force",
        is_flag=True,
        help="Replace output files that exist (an input file is never replaced).",
    )


def file_argument(name: str = "file") -> Decorator:
    return click.argument(name, type=click.Path(dir_okay=False))
