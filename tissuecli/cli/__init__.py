"""Command line: the only click importer. Each command parses its options, calls one
service of :mod:`tissuecli.app` and prints the result; :func:`~tissuecli.cli.base.fail_cleanly`
turns every library error into a one-line message and exit code 1. Services are
imported inside the commands, so ``--help`` and each command load only what they use."""

from . import batch, calibrate, demo, files, fit, live, play, predict, record, simulate  # noqa: F401  (each adds its commands)
from .base import cli, fail_cleanly

__all__ = ["cli", "fail_cleanly", "main"]


def main() -> None:
    """Console entry point."""
    cli()
