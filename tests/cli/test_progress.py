"""Progress of a fit: the library reports each stage through the object it is given,
the command line draws it on a terminal only."""

from __future__ import annotations

import io
from pathlib import Path

import pytest

from tissuecli.app.fit import fit_file
from tissuecli.cli import progress as terminal
from tissuecli.core.progress import Progress
from tissuecli.formats.sessions import write_session
from tissuecli.sim.synth import ForcepsModel, synthesize

from ..conftest import tissuecli


class Recorder(Progress):
    def __init__(self) -> None:
        self.events: list[tuple] = []

    def stage(self, name: str, total: int | None = None) -> None:
        self.events.append(("stage", name, total))

    def advance(self, done: int, total: int | None = None, note: str = "") -> None:
        self.events.append(("advance", done, total, note))

    def sampling(self, form: str, steps: int, need: int) -> None:
        self.events.append(("sampling", form, steps, need))

    def close(self) -> None:
        self.events.append(("close",))


@pytest.fixture(scope="module")
def grasp(tmp_path_factory: pytest.TempPathFactory) -> Path:
    s, _ = synthesize(ForcepsModel(seed=4), 4.0)
    s.name = "s"
    path = tmp_path_factory.mktemp("p") / "g.h5"
    write_session(path, s)
    return path


def test_every_stage_of_a_fit_is_reported_in_order(grasp: Path, tmp_path: Path) -> None:
    seen = Recorder()
    outcome = fit_file(grasp, report=tmp_path / "r.html", hold_out=0.3, progress=seen)
    stages = [e[1] for e in seen.events if e[0] == "stage"]
    assert stages[0] == f"reading {grasp}"
    order = ["filtering and finding grasps", "structure search", "sampling",
             "scoring the held-out part", "writing the report"]  # fmt: skip
    assert [s for s in stages if s in order] == order
    assert seen.events[-1] == ("close",)
    # the search counts every law it scores, by name, against the laws known so far
    counts = [e for e in seen.events if e[0] == "advance"]
    names = {e[3] for e in counts}
    assert {r.name for r in outcome.bayes.results_} <= names | {
        r.model.name for r in outcome.bayes.results_
    }
    assert all(done <= total for _, done, total, _ in counts)
    assert len(counts) >= len(outcome.bayes.results_)


def test_the_terminal_line_waits_two_seconds_then_redraws_in_place(monkeypatch) -> None:
    clock = [100.0]
    monkeypatch.setattr(terminal.time, "monotonic", lambda: clock[0])
    out = io.StringIO()
    bar = terminal.TerminalProgress(out)
    bar._stop.set()  # no ticker: the test moves the clock
    bar.stage("structure search", 24)
    bar.advance(1, 24, "x+xdot")
    assert out.getvalue() == ""  # a short stage draws nothing
    clock[0] += 2.5
    bar.advance(2, 24, "x+xdot+offset")
    bar.advance(3, 24, "x")
    bar.stage("sampling")
    bar.close()
    text = out.getvalue()
    assert text.count("\r") == 3 and text.endswith("\n")
    assert "structure search (2 s): 3 done, 21 left: x" in text.split("\r")[-1]
    # a narrower line blanks what the wider one left
    assert text.split("\r")[2].rstrip("\n").endswith(" ")


def test_a_fit_into_a_pipe_prints_no_progress(grasp: Path) -> None:
    result = tissuecli("fit", str(grasp))
    assert result.returncode == 0, result.stderr
    assert "\r" not in result.stderr and "structure search" not in result.stderr
