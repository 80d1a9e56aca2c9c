"""`sessions` says why each session ended and what an import counted."""

from __future__ import annotations

from pathlib import Path

import pytest
from click.testing import CliRunner

from tissuecli.cli import cli
from tissuecli.formats.sessions import ended, list_sessions, write_session
from tissuecli.sim.synth import ForcepsModel, synthesize

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize(
    ("reason", "complete", "word"),
    [
        ("duration reached", True, "duration"),
        ("interrupted by signal", True, "signal"),
        ("interrupted", False, "signal"),
        ("device lost: no Sample frame from /tmp/forceps for 500 ms", True, "device lost"),
        ("storage fault: disk full (1.1 MB free; ...)", False, "disk full"),
        ("storage fault: file size limit reached (2.1 MB)", False, "file size limit"),
        ("error: ValueError: x", False, "error"),
        ("", False, "crashed"),
        ("", True, ""),
    ],
)
def test_why_a_session_ended_in_a_word(reason: str, complete: bool, word: str) -> None:
    assert ended({"stop_reason": reason}, complete) == word


def _table(*args: str) -> list[str]:
    result = CliRunner().invoke(cli, ["sessions", *args])
    assert result.exit_code == 0, result.output
    return result.output.splitlines()


def test_a_recording_that_lost_its_forceps_does_not_read_as_complete_alone(tmp_path) -> None:
    s, _ = synthesize(ForcepsModel(seed=1), 1.0)
    s.name = "cut"
    reason = "device lost: no Sample frame from /tmp/forceps for 500 ms"
    s.meta.update(stop_reason=reason, complete=True, frames_lost=2)
    write_session(tmp_path / "g.h5", s)
    (row,) = list_sessions(tmp_path / "g.h5")
    assert (row["ended"], row["stop_reason"]) == ("device lost", reason)
    header, line = _table(str(tmp_path / "g.h5"))
    assert "ended" in header
    assert "device lost" in line and f"stopped: {reason}" in line


def test_sessions_shows_what_import_counted(tmp_path) -> None:
    """The logger's file loses samples on its clock and has a junk line: `sessions`
    counts them as `import` reported them, where it showed 'lost 0' before."""
    out = tmp_path / "lab.h5"
    result = CliRunner().invoke(
        cli,
        ["import", str(ROOT / "data" / "sim_logger_grasps.tsv"), "--out", str(out),
         "--jaw-length", "20mm", "--units", "time=ms",
         "--columns", "time=millis,force=force_g,position=angle_deg"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    assert "303 lost sample(s)" in result.output and "1 junk line(s) skipped" in result.output
    (row,) = list_sessions(out)
    assert (row["import_samples_lost"], row["import_lines_skipped"]) == (303, 1)
    assert row["ended"] == "imported"
    header, line = _table(str(out))
    cells = line.split()
    names = header.split()
    # "duration s" and "rate Hz" are two words of the header, one cell of a row
    assert cells[names.index("lost") - 2] == "303"
    assert cells[names.index("bad") - 2] == "1"
    assert "import: 303 sample(s) missing from the clock, 1 line(s) skipped" in line
