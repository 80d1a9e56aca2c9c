"""The command line fits a session longer than memory allows from streamed sums."""

from __future__ import annotations

from click.testing import CliRunner

from tissuecli.app import fit as fit_app
from tissuecli.cli import cli
from tissuecli.formats.sessions import write_session
from tissuecli.sim.synth import ForcepsModel, synthesize


def test_the_command_line_streams_a_long_session(tmp_path, monkeypatch) -> None:
    session, _ = synthesize(ForcepsModel(seed=7), 30.0)
    session.name = "long"
    path = tmp_path / "long.h5"
    write_session(path, session)
    monkeypatch.setattr(fit_app, "STREAM_ABOVE", 20_000)
    monkeypatch.setattr(fit_app, "STREAM_PILOT", 12_000)
    monkeypatch.setattr(fit_app, "STREAM_BLOCK", 10_000)
    done = CliRunner().invoke(cli, ["fit", str(path), "--forms", "paper"])
    assert done.exit_code == 0, done.output
    assert "30,000 samples at 1000 Hz, fitted from sums streamed block by block" in done.output
