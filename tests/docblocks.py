"""The fenced blocks of the documentation, how they are marked, run and compared.

The convention (docs/architecture.md, "Docs that match the code"):

- A ```` ```console ```` block is run: each ``$ `` line is a shell command (a line ending
  in ``\\`` continues it), and the lines up to the next ``$ `` line are what it prints
  on stdout (and on stderr too with ``stderr`` in the block's ``output`` mark, or when
  the command fails: an ``Error:`` line). A line ``...`` alone stands for any number of
  lines.
- A ```` ```text ```` block right after a ```` ```python ```` block is what that Python
  block prints (docs/api.md runs its blocks in order in one namespace).
- HTML comments right above a fence mark it:
  ``<!-- output: tol=5% vary=REGEX slow stderr -->`` numbers within 5 % (default 2 %),
  numbers on lines matching REGEX not compared (timings), run only with ``-m slow``,
  stderr quoted too;
  ``<!-- not-run: REASON -->`` shown, never run (a device, a long run, a file that is
  not in the repository), counted and listed by the test;
  ``<!-- file: NAME read=KIND -->`` the block is an example file: written as NAME into
  the page's working folder (for the commands after it) and read by its reader;
  ``<!-- text -->`` neither a command's output nor a file (a diagram, a formula).
- A bare ```` ``` ```` block holds commands only (each line a command, its continuation or
  a comment), which are not run; any other bare block must carry one of the marks.

``TISSUECLI_UPDATE_DOCS=1`` rewrites every quoted output with what the code prints now.
"""

from __future__ import annotations

import math
import os
import re
import shlex
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
UPDATE = os.environ.get("TISSUECLI_UPDATE_DOCS", "") not in ("", "0")
#: relative tolerance of numbers, unless a block says otherwise
DEFAULT_TOL = 0.02

FENCE = re.compile(r"^( *)(`{3,})([\w+-]*)\s*$")
MARK = re.compile(r"^\s*<!--\s*([\w-]+)\s*:?\s*(.*?)\s*-->\s*$")
NUMBER = re.compile(r"[-+]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?")
#: lines of a bare block that are commands: a program, a continuation, a comment
COMMAND = re.compile(
    r"^\s*(tissuecli|python3?|pip|sqlite3|git|apt-get|sudo|export|cd|TISSUECLI_\w+=|"
    r"PYTHONPATH=|taskset|curl|arduino-cli|cc |gcc |make|\./|ulimit|chrt|#|\.{3}$|\[)"
)


@dataclass
class Block:
    """A fenced block: where it is, its language, contents and marks."""

    doc: Path
    line: int  # 1-based line of the opening fence
    lang: str
    body: list[str]
    marks: dict[str, str] = field(default_factory=dict)
    indent: str = ""  # a fence inside a list item is indented; its lines too

    def indented(self, lines: list[str]) -> list[str]:
        """Lines as written back into the page, at the block's indent."""
        return [self.indent + line if line else line for line in lines]

    @property
    def where(self) -> str:
        return f"{rel(self.doc)}:{self.line}"

    @property
    def first(self) -> int:
        """Line number of the first line of the contents."""
        return self.line + 1


def rel(doc: Path) -> str:
    """A page's path as the messages give it: from the repository's root."""
    return str(doc.relative_to(ROOT)) if doc.is_relative_to(ROOT) else str(doc)


def blocks(doc: Path) -> list[Block]:
    """Every fenced block of a markdown file, with the marks in the comments above it."""
    out: list[Block] = []
    lines = doc.read_text(encoding="utf-8").split("\n")
    i = 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        marks: dict[str, str] = {}
        j = i - 1
        while j >= 0 and (mark := MARK.match(lines[j])):
            marks.setdefault(mark.group(1), mark.group(2))
            j -= 1
        indent, fence = m.group(1), m.group(2)
        end = i + 1
        while end < len(lines) and lines[end].rstrip() != indent + fence:
            end += 1
        body = [line[len(indent) :] if line.startswith(indent) else line
                for line in lines[i + 1 : end]]  # fmt: skip
        out.append(Block(doc, i + 1, m.group(3), body, marks, indent))
        i = end + 1
    return out


def options(block: Block) -> dict[str, object]:
    """The ``output`` mark read: ``tol`` (relative), ``vary`` (a regex) and ``slow``."""
    spec = block.marks.get("output", "")
    out: dict[str, object] = {"tol": DEFAULT_TOL, "vary": None, "slow": False, "stderr": False}
    for token in shlex.split(spec):
        key, _, value = token.partition("=")
        if key == "tol":
            out["tol"] = float(value.rstrip("%")) / (100.0 if value.endswith("%") else 1.0)
        elif key == "vary":
            out["vary"] = re.compile(value)
        elif key in ("slow", "stderr"):
            out[key] = True
        else:
            raise ValueError(f"{block.where}: unknown output option {key!r}")
    return out


def kind(block: Block) -> str:
    """What a block is: ``console``, ``output`` (a Python block's), ``python``, ``file``,
    ``not-run``, ``text``, ``commands``, ``code`` (another language), or ``unmarked``."""
    if "not-run" in block.marks:
        return "not-run"
    if "file" in block.marks:
        return "file"
    if "text" in block.marks:
        return "text"
    if block.lang == "console":
        return "console"
    if block.lang == "python":
        return "python"
    if block.lang == "text":
        return "output"
    if block.lang:
        return "code"
    if all(not line.strip() or COMMAND.match(line) or _continued(block.body, k)
           for k, line in enumerate(block.body)):  # fmt: skip
        return "commands"
    return "unmarked"


def _continued(body: list[str], k: int) -> bool:
    """Whether line k continues a command (the line before ends with a backslash, or it
    is indented under a command)."""
    return k > 0 and (body[k - 1].rstrip().endswith("\\") or body[k].startswith("    "))


@dataclass
class Step:
    """One command of a console block and the output quoted under it."""

    command: str
    line: int  # line of the first output line in the doc
    expected: list[str]


def steps(block: Block) -> list[Step]:
    """The commands of a console block with their quoted outputs."""
    out: list[Step] = []
    k = 0
    body = block.body
    while k < len(body):
        line = body[k]
        if not line.startswith("$ "):
            raise ValueError(f"{rel(block.doc)}:{block.first + k}: output before a command")
        command = line[2:]
        while command.rstrip().endswith("\\") and k + 1 < len(body):
            k += 1
            command = command.rstrip()[:-1] + " " + body[k].strip()
        k += 1
        start = k
        while k < len(body) and not body[k].startswith("$ "):
            k += 1
        out.append(Step(command, block.first + start, body[start:k]))
    return out


# -- running


def environment(work: Path) -> dict[str, str]:
    """The environment of documented commands: ``tissuecli`` this checkout's, a fixed
    terminal width, the repository's data/ beside the working folder."""
    bin_dir = work / ".bin"
    bin_dir.mkdir(exist_ok=True)
    wrapper = bin_dir / "tissuecli"
    wrapper.write_text(f'#!/bin/sh\nexec "{sys.executable}" -m tissuecli "$@"\n')
    wrapper.chmod(0o755)
    data = work / "data"
    if not data.exists():
        data.symlink_to(ROOT / "data")
    env = dict(os.environ)
    env.update(
        PATH=f"{bin_dir}{os.pathsep}{env.get('PATH', '')}",
        COLUMNS="100",
        PYTHONPATH=f"{ROOT}{os.pathsep}{env.get('PYTHONPATH', '')}",
        PYTHONHASHSEED="0",
        TZ="UTC",
    )
    env.pop("TISSUECLI_UPDATE_DOCS", None)
    return env


def run(
    command: str, work: Path, env: dict[str, str], stderr: bool = False, timeout: float = 900.0
) -> list[str]:
    """What a documented command prints on stdout; with ``stderr``, or if it fails, on
    stderr as well (stderr after stdout: progress lines are left out otherwise)."""
    done = subprocess.run(
        ["bash", "-c", command],
        cwd=work,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
        stdin=subprocess.DEVNULL,
    )
    if stderr:
        return lines_of(done.stdout + done.stderr)
    if done.returncode:
        errors = [line for line in lines_of(done.stderr) if line.startswith(("Error", "error"))]
        return lines_of(done.stdout) + errors
    return lines_of(done.stdout)


def lines_of(text: str) -> list[str]:
    lines = [line.rstrip() for line in text.replace("\r\n", "\n").split("\n")]
    while lines and not lines[-1]:
        lines.pop()
    return lines


# -- comparing


def _ulp(token: str) -> float:
    """One unit in the last digit a number is written with (0 for an integer)."""
    mantissa, _, exponent = token.lower().partition("e")
    if "." not in mantissa:
        return 0.0 if not exponent else 10.0 ** int(exponent)
    decimals = len(mantissa.split(".")[1])
    return 10.0 ** (-decimals + (int(exponent) if exponent else 0))


def same_line(expected: str, actual: str, tol: float, vary: re.Pattern[str] | None) -> bool:
    """Whether an output line matches its quote: the same words (runs of spaces count as
    one), and the same numbers within ``tol`` relative or one unit of the last digit
    quoted; on a line that ``vary`` matches, any numbers."""
    words_e = [w.split() for w in NUMBER.split(expected)]
    words_a = [w.split() for w in NUMBER.split(actual)]
    if words_e != words_a:
        return False
    if vary is not None and vary.search(expected):
        return True
    for e, a in zip(NUMBER.findall(expected), NUMBER.findall(actual), strict=False):
        if e == a:
            continue
        x, y = float(e), float(a)
        if not (math.isfinite(x) and math.isfinite(y)):
            return False
        if abs(x - y) > max(tol * max(abs(x), abs(y)), _ulp(e) * 1.0001):
            return False
    return True


def compare(
    expected: list[str], actual: list[str], tol: float, vary: re.Pattern[str] | None
) -> tuple[int, str] | None:
    """None if the output matches its quote, else the index of the first quoted line
    that does not and why. ``...`` in the quote stands for any lines."""
    segments: list[list[tuple[int, str]]] = [[]]
    for i, line in enumerate(expected):
        if line.strip() == "...":
            segments.append([])
        else:
            segments[-1].append((i, line))
    if len(segments) == 1:
        for (i, e), a in zip(segments[0], actual, strict=False):
            if not same_line(e, a, tol, vary):
                return i, f"expected {e!r}\n     got {a!r}"
        if len(actual) != len(expected):
            i = min(len(actual), len(expected))
            what = actual[i] if len(actual) > i else "(end of output)"
            return min(i, max(len(expected) - 1, 0)), (
                f"{len(expected)} line(s) quoted, {len(actual)} printed; first differing: {what!r}"
            )
        return None
    head, tail = segments[0], segments[-1]
    if len(head) + len(tail) > len(actual):
        return 0, f"{len(actual)} line(s) printed, fewer than quoted: {actual!r}"
    for (i, e), a in zip(head, actual, strict=False):
        if not same_line(e, a, tol, vary):
            return i, f"expected {e!r}\n     got {a!r}"
    for (i, e), a in zip(tail, actual[len(actual) - len(tail) :], strict=False):
        if not same_line(e, a, tol, vary):
            return i, f"expected {e!r}\n     got {a!r}"
    k = len(head)
    for segment in segments[1:-1]:  # found in order between the head and the tail
        while k + len(segment) <= len(actual) - len(tail):
            if all(
                same_line(e, a, tol, vary) for (_, e), a in zip(segment, actual[k:], strict=False)
            ):
                break
            k += 1
        else:
            return segment[0][0], f"no lines like {segment[0][1]!r} in the output"
        k += len(segment)
    return None


def elide(expected: list[str], actual: list[str]) -> list[str]:
    """The new quote of an output: as printed, with the quote's ``...`` kept (as many
    lines before and after it as the quote had)."""
    marks = [i for i, line in enumerate(expected) if line.strip() == "..."]
    if not marks:
        return actual
    head, tail = marks[0], len(expected) - marks[-1] - 1
    if head + tail >= len(actual):
        return actual
    return actual[:head] + ["..."] + (actual[len(actual) - tail :] if tail else [])


class Rewrites:
    """New contents for line ranges of the docs, written at the end."""

    def __init__(self) -> None:
        self.edits: dict[Path, list[tuple[int, int, list[str]]]] = {}

    def replace(self, doc: Path, first: int, count: int, lines: list[str]) -> None:
        """Lines ``first`` (1-based) to ``first + count - 1`` of ``doc`` become ``lines``."""
        self.edits.setdefault(doc, []).append((first, count, lines))

    def write(self) -> None:
        for doc, edits in self.edits.items():
            text = doc.read_text(encoding="utf-8").split("\n")
            for first, count, lines in sorted(edits, reverse=True):
                text[first - 1 : first - 1 + count] = lines
            doc.write_text("\n".join(text), encoding="utf-8")
        self.edits.clear()
