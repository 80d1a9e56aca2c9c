"""Every command output quoted in README.md and docs/ is what the code prints.

The convention is in tests/docblocks.py and docs/architecture.md ("Docs that match the
code"): ```` ```console ```` blocks are run and their quoted output compared (numbers
within a stated tolerance), a ```` ```text ```` block after a ```` ```python ```` block is
that block's output, example files are read by their readers, and a block that is not
run says why. A failing comparison names the page and the line.

``TISSUECLI_UPDATE_DOCS=1 python -m pytest tests/test_docs.py`` rewrites every quoted
output (slow blocks included) with what the code prints now.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

import docblocks as db  # noqa: E402

PAGES = {doc.name: doc for doc in db.DOCS}
CONSOLE = [name for name, doc in PAGES.items() if any(b.lang == "console" for b in db.blocks(doc))]
PYTHON = [
    name
    for name, doc in PAGES.items()
    if any(
        a.lang == "python" and b.lang == "text" and db.kind(a) == "python"
        for a, b in zip(db.blocks(doc), db.blocks(doc)[1:], strict=False)
    )
]


def test_every_block_is_run_or_marked(capsys: pytest.CaptureFixture[str]) -> None:
    """No quoted output goes unchecked: every fenced block is commands, code, a checked
    output, an example file read by a test, or marked as not run with a reason."""
    unmarked, not_run, counts = [], [], {}
    for doc in db.DOCS:
        for block in db.blocks(doc):
            kind = db.kind(block)
            counts[kind] = counts.get(kind, 0) + 1
            if kind == "unmarked":
                unmarked.append(f"{block.where}: {block.body[0][:70] if block.body else ''!r}")
            elif kind == "not-run":
                assert block.marks["not-run"], f"{block.where}: not-run needs a reason"
                not_run.append(f"{block.where}: {block.marks['not-run']}")
            elif kind == "console":
                db.steps(block)  # parses
                db.options(block)
            elif kind == "output":
                db.options(block)
    assert not unmarked, (
        "output blocks neither checked nor marked (make them ```console, or mark them "
        "<!-- not-run: why -->, <!-- file: NAME -->, <!-- text -->):\n" + "\n".join(unmarked)
    )
    with capsys.disabled():
        print(f"\ndoc blocks: {counts}; {len(not_run)} not run:")
        for line in not_run:
            print("  " + line)


def _check_page(name: str, work: Path, slow: bool) -> None:
    """Run a page's console blocks in order in ``work``; compare or rewrite."""
    doc = PAGES[name]
    env = db.environment(work)
    failures: list[str] = []
    rewrites = db.Rewrites()
    for block in db.blocks(doc):
        kind = db.kind(block)
        if kind == "file":
            _write_example(block, work)
            continue
        if kind != "console":
            continue
        opts = db.options(block)
        if opts["slow"] and not (slow or db.UPDATE):
            continue
        for step in db.steps(block):
            actual = db.run(step.command, work, env, stderr=bool(opts["stderr"]))
            bad = db.compare(step.expected, actual, opts["tol"], opts["vary"])
            if db.UPDATE and bad is not None:  # a quote that still matches is kept
                new = db.elide(step.expected, actual)
                if new != step.expected:
                    rewrites.replace(doc, step.line, len(step.expected), block.indented(new))
                continue
            if bad is not None and not db.UPDATE:
                index, why = bad
                failures.append(f"{db.rel(doc)}:{step.line + index}: "
                                f"`{step.command[:80]}` {why}")  # fmt: skip
    rewrites.write()
    assert not failures, (
        "quoted output differs from what the code prints (TISSUECLI_UPDATE_DOCS=1 "
        "python -m pytest tests/test_docs.py rewrites it):\n" + "\n".join(failures)
    )


@pytest.mark.parametrize("name", CONSOLE)
def test_console_outputs_are_what_the_commands_print(name: str, tmp_path: Path) -> None:
    _check_page(name, tmp_path, slow=False)


@pytest.mark.slow
@pytest.mark.parametrize("name", CONSOLE)
def test_slow_console_outputs_are_what_the_commands_print(name: str, tmp_path: Path) -> None:
    if db.UPDATE:
        pytest.skip("rewritten by the default run")
    _check_page(name, tmp_path, slow=True)


#: runs a page's Python blocks in order in one namespace in a fresh process (so that
#: what `import tissuecli` loads is what a user's process loads), each block's stdout
#: kept apart
DRIVER = """
import contextlib, io, json, sys
blocks = json.load(open(sys.argv[1], encoding="utf-8"))
namespace, outputs = {"__name__": "__main__"}, []
for source, where in blocks:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(source, where, "exec"), namespace)
    outputs.append(out.getvalue())
json.dump(outputs, open(sys.argv[2], "w", encoding="utf-8"))
"""


@pytest.mark.parametrize("name", PYTHON)
def test_python_examples_print_what_is_quoted(name: str, tmp_path: Path) -> None:
    """The Python blocks of a page run in order in one namespace, and each prints the
    ```text block that follows it."""
    doc = PAGES[name]
    blocks = db.blocks(doc)
    runs = [
        (block, after)
        for block, after in zip(blocks, [*blocks[1:], None], strict=False)
        if db.kind(block) == "python"
    ]
    (tmp_path / "blocks.json").write_text(
        json.dumps([["\n".join(b.body), b.where] for b, _ in runs]), encoding="utf-8"
    )
    done = subprocess.run(
        [sys.executable, "-c", DRIVER, "blocks.json", "outputs.json"],
        cwd=tmp_path,
        env=db.environment(tmp_path),
        capture_output=True,
        text=True,
        timeout=1200,
    )
    assert done.returncode == 0, f"{db.rel(doc)}: an example failed:\n{done.stderr[-3000:]}"
    outputs = json.loads((tmp_path / "outputs.json").read_text(encoding="utf-8"))
    failures: list[str] = []
    rewrites = db.Rewrites()
    for (_, after), printed in zip(runs, outputs, strict=True):
        if after is None or db.kind(after) != "output":
            continue
        actual = db.lines_of(printed)
        opts = db.options(after)
        bad = db.compare(after.body, actual, opts["tol"], opts["vary"])
        if db.UPDATE and bad is not None:  # a quote that still matches is kept
            new = db.elide(after.body, actual)
            if new != after.body:
                rewrites.replace(doc, after.first, len(after.body), after.indented(new))
        elif bad is not None:
            failures.append(f"{db.rel(doc)}:{after.first + bad[0]}: {bad[1]}")
    rewrites.write()
    assert not failures, (
        "quoted output differs from what the code prints (TISSUECLI_UPDATE_DOCS=1 "
        "python -m pytest tests/test_docs.py rewrites it):\n" + "\n".join(failures)
    )


# -- example files


def _write_example(block: db.Block, work: Path) -> Path:
    name = block.marks["file"].split()[0]
    path = work / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(block.body) + "\n", encoding="utf-8")
    return path


def _read_example(kind: str, path: Path) -> object:
    """Read an example file with the reader the program uses for its kind."""
    if kind == "calibration":
        from tissuecli.formats.params import read_calibration

        return read_calibration(path)
    if kind == "profile":
        from tissuecli.formats.params import read_profile

        return read_profile(path)
    if kind == "params":
        from tissuecli.formats.params import read_tissue

        return read_tissue(path)
    if kind == "manifest":
        from tissuecli.app.batch import read_manifest

        return read_manifest(path)
    if kind == "table":
        from tissuecli.formats.recording import read_recording

        return read_recording(path)
    if kind == "json":
        return json.loads(path.read_text())
    raise AssertionError(f"no reader for {kind!r}")


EXAMPLES = [
    pytest.param(block, id=block.where)
    for doc in db.DOCS
    for block in db.blocks(doc)
    if db.kind(block) == "file"
]


@pytest.mark.parametrize("block", EXAMPLES)
def test_example_files_are_read_by_their_readers(block: db.Block, tmp_path: Path) -> None:
    """An example file in the docs is one the program accepts."""
    spec = dict(t.partition("=")[::2] for t in block.marks["file"].split()[1:])
    path = _write_example(block, tmp_path)
    if "read" in spec:
        cwd = os.getcwd()
        os.chdir(tmp_path)
        try:
            _read_example(spec["read"], path)
        finally:
            os.chdir(cwd)


# -- the checker itself


def test_the_comparison_allows_the_stated_tolerance_and_nothing_else() -> None:
    assert db.compare(["K = 350.0 N/m"], ["K = 356.0 N/m"], 0.02, None) is None
    assert db.compare(["K = 350.0 N/m"], ["K = 360.0 N/m"], 0.02, None) is not None
    assert db.compare(["K = 350.0 N/m"], ["K = 360.0 N/m"], 0.05, None) is None
    assert db.compare(["K  = 350 N/m"], ["K = 350 N/m"], 0.02, None) is None  # spacing
    assert db.compare(["K = 350 N/m"], ["S = 350 N/m"], 0.5, None) is not None  # words
    assert db.compare(["P 0.99"], ["P 1.00"], 0.0, None) is None  # the last digit
    assert db.compare(["18 sessions"], ["19 sessions"], 0.02, None) is not None
    assert db.compare(["a", "...", "z"], ["a", "b", "c", "z"], 0.02, None) is None
    assert db.compare(["a", "...", "z"], ["a", "b"], 0.02, None) is not None
    assert db.compare(["a", "b"], ["a", "b", "c"], 0.02, None) is not None
    vary = db.re.compile(r" in [\d.]+ s")
    assert db.compare(["done in 1.2 s"], ["done in 9.9 s"], 0.02, vary) is None
    assert db.elide(["a", "...", "z"], ["a", "b", "c", "y"]) == ["a", "...", "y"]


def test_a_failing_comparison_names_the_page_and_the_line(tmp_path: Path) -> None:
    page = tmp_path / "page.md"
    page.write_text("x\n\n```console\n$ echo 1.5 N\n2.5 N\n```\n")
    (block,) = db.blocks(page)
    (step,) = db.steps(block)
    assert step.command == "echo 1.5 N" and step.line == 5
    bad = db.compare(step.expected, db.run(step.command, tmp_path, dict(os.environ)), 0.02, None)
    assert bad is not None and bad[0] == 0 and "2.5 N" in bad[1]
