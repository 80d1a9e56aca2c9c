"""The quick cases of benchmarks/reliability.py, so that the suite guards docs/reliability.md,
and the harness itself: it must see a destroyed file, a leftover and a traceback."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import reliability  # noqa: E402

FAST = [c for c in reliability.CASES if c.fast]


def test_the_fast_subset_is_a_real_one() -> None:
    assert 10 <= len(FAST) < len(reliability.CASES) / 2
    names = [c.name for c in reliability.CASES]
    assert len(set(names)) == len(names)


@pytest.mark.parametrize("case", FAST, ids=[c.name for c in FAST])
def test_fast_case_holds(case: reliability.Case) -> None:
    result = reliability.run_case(case, tmpfs=False)
    assert result.steps, "the case ran no command"
    assert result.verdict == "yes", result.failures or result.partial


def _harmful(ctx: reliability.Ctx) -> None:
    """What the page must never hide: an input rewritten, a temporary file left behind,
    a wrong exit code and a traceback."""
    (ctx.root / "input.csv").write_text("time,force,position\n0,1,2\n")
    ctx.begin()
    (ctx.root / "input.csv").write_text("gone\n")
    (ctx.root / ".out.json.x1y2.tmp").write_text("{")
    ctx.run("--version", expect=1)
    ctx.record(["fit"], 1, "", "Traceback (most recent call last):\n", 0.0, 1, True)


def test_the_harness_sees_destroyed_data_leftovers_and_tracebacks() -> None:
    result = reliability.run_case(reliability.Case("harm", "harm", _harmful, True), tmpfs=False)
    assert result.verdict == "no"
    assert result.destroyed == ["input.csv"]
    assert result.leftovers == [".out.json.x1y2.tmp"]
    assert result.tracebacks == 1
    assert any("expected 1" in f for f in result.failures)
    row = reliability.table([result]).splitlines()[-1]
    assert "| `harm` |" in row and "| 1 | input.csv |" in row and row.endswith("|")


_CTRL_C_WHILE_LOADING = """
import os, signal, sys

class CtrlC:
    def find_spec(self, name, path=None, target=None):
        if name == "tissuecli.cli":
            os.kill(os.getpid(), signal.SIGINT)  # as if the user pressed Ctrl-C now
        return None

sys.meta_path.insert(0, CtrlC())
from tissuecli.__main__ import run
run()
"""


def test_the_console_script_turns_a_ctrl_c_while_loading_into_one_line() -> None:
    """`tissuecli` (the installed command) runs the guarded entry point, and a Ctrl-C
    while the command line loads ends in 'aborted', exit 130, without a traceback."""
    assert reliability.console_script()[-1].endswith(
        "from tissuecli.__main__ import run; sys.exit(run())"
    )
    root = str(Path(__file__).resolve().parents[1])
    env = {**os.environ, "PYTHONPATH": root}
    done = subprocess.run(
        [sys.executable, "-c", _CTRL_C_WHILE_LOADING, "record", "--port", "x", "--out", "r.h5"],
        capture_output=True, text=True, timeout=60, env=env,
    )  # fmt: skip
    assert (done.returncode, done.stderr) == (
        130,
        "aborted: interrupted by SIGINT (Ctrl-C)\n",
    )


_CTRL_C_IN_GENERATED_CODE = """
import tissuecli.app.batch as batch

def expand_inputs(*args, **kwargs):
    # what a module loading mid-command does (a dataclass's __init__, a namedtuple):
    # run code compiled from a string; the Ctrl-C lands inside it
    exec("import os, signal\\nos.kill(os.getpid(), signal.SIGINT)\\nsum(range(99))")
    raise AssertionError("the Ctrl-C never arrived")

batch.expand_inputs = expand_inputs
from tissuecli.__main__ import run
run()
"""


def test_a_ctrl_c_inside_code_compiled_from_a_string_still_exits_130(tmp_path) -> None:
    """Run as ``python -m`` (as the suite runs every command), CPython kills a process
    with SIGINT after it has exited when a KeyboardInterrupt passed through code compiled
    from a string, even one that was caught: a command stopped there must still say
    'aborted' and exit 130, not die by the signal."""
    (tmp_path / "ctrl_c_in_exec.py").write_text(_CTRL_C_IN_GENERATED_CODE)
    root = str(Path(__file__).resolve().parents[1])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), root])}
    done = subprocess.run(
        [sys.executable, "-m", "ctrl_c_in_exec", "fit", "g.h5", "--out", "p.json"],
        capture_output=True, text=True, timeout=60, env=env, cwd=tmp_path,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),  # even in a job
    )  # fmt: skip
    assert (done.returncode, done.stderr) == (
        130,
        "aborted: interrupted by SIGINT (Ctrl-C)\n",
    )
