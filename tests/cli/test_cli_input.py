"""The command line itself: repeated options, no command, labels in tables, ports and
links that are not what they seem."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import click
import pytest
from click.testing import CliRunner

from tissuecli.cli import cli

from ..conftest import assert_clean_error, tissuecli


def _commands() -> list[tuple[list[str], click.Command]]:
    out = []
    for name, cmd in cli.commands.items():
        if isinstance(cmd, click.Group):
            out += [([name, sub], c) for sub, c in cmd.commands.items()]
        else:
            out.append(([name], cmd))
    return out


SINGLE_OPTIONS = [
    (path, opt)
    for path, cmd in _commands()
    for opt in cmd.params
    if isinstance(opt, click.Option)
    and not (opt.multiple or opt.count)
    and opt.name != "help"
    and "--version" not in opt.opts
]


@pytest.mark.parametrize(
    ("path", "option"),
    SINGLE_OPTIONS,
    ids=[f"{' '.join(p)} {o.opts[0]}" for p, o in SINGLE_OPTIONS],
)
def test_every_option_given_twice_is_refused(path: list[str], option: click.Option) -> None:
    flag = option.opts[-1]
    once = [flag] if option.is_flag else [flag, "1"]
    result = CliRunner().invoke(cli, [*path, *once, *once])
    assert result.exit_code == 1, result.output
    assert f"{flag} is given twice" in result.output


def test_no_command_shows_the_help_and_succeeds() -> None:
    for args in ([], ["simulate"]):
        result = tissuecli(*args)
        assert result.returncode == 0 and "Usage:" in result.stdout, result.stderr


def test_a_newline_in_a_label_cannot_forge_a_row(tmp_path: Path) -> None:
    csv = tmp_path / "a.csv"
    csv.write_text("time,force,position\n" + "".join(f"{i / 1e3},1,{i}e-6\n" for i in range(50)))
    h5 = tmp_path / "a.h5"
    forged = "liver\nforged    99999"
    assert (
        CliRunner()
        .invoke(cli, ["import", str(csv), "--out", str(h5), "--session", "s", "--tissue", forged])
        .exit_code
        == 0
    )
    listing = CliRunner().invoke(cli, ["sessions", str(h5)]).output.splitlines()
    assert len(listing) == 2 and "liver\\nforged" in listing[1]
    bad = CliRunner().invoke(cli, ["import", str(csv), "--out", str(h5), "--session", "a\nb"])
    assert_clean_error(bad, "not allowed")


def test_a_port_that_is_a_file_or_a_directory_is_named_as_such(tmp_path: Path) -> None:
    (tmp_path / "file").write_text("")
    for port in (tmp_path / "file", tmp_path):
        result = tissuecli("record", "--port", str(port), "--out", str(tmp_path / "x.h5"))
        assert_clean_error(result, "not a serial device")


def test_a_live_simulator_keeps_its_link(tmp_path: Path) -> None:
    link = tmp_path / "display"
    first = subprocess.Popen(
        [sys.executable, "-m", "tissuecli", "simulate", "display", "--link", str(link)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    try:
        deadline = time.monotonic() + 10
        while not link.is_symlink() and time.monotonic() < deadline:
            time.sleep(0.02)
        target = link.readlink()
        second = tissuecli("simulate", "display", "--link", str(link), "--duration", "1")
        assert_clean_error(second, "running simulated device")
        assert link.readlink() == target  # still the first simulator's port
    finally:
        first.terminate()
        first.wait(timeout=10)
    assert not link.exists() and not link.is_symlink()  # removed by its owner on exit
    missing = tissuecli("simulate", "forceps", "--link", str(tmp_path / "no" / "f"))
    assert_clean_error(missing, "does not exist")
