"""Reliability: every way tissuecli once destroyed data, crashed or hid a fault, rerun.

Usage::

    python benchmarks/reliability.py                 # every case, a markdown table
    python benchmarks/reliability.py --only json     # the cases whose name holds "json"
    python benchmarks/reliability.py --list          # names and what each tries

Each case runs the command line as a user would (``python -m tissuecli ...`` in its own
process), in a fresh temporary directory, against simulated devices where one is
needed: ``tissuecli simulate forceps|display`` in their own processes, or the test
suite's scripted forceps (``tests/app/fakedevice.py``: valid-CRC frames with absurd
content behind a real pty). For every case the script records

* the exit code of each command that matters (joined by ``/``);
* whether "Traceback" appeared anywhere in any output;
* whether a file the case started with changed (sha256 before and after; a file the
  user asked to replace with ``--force``, or a recording file a session is added to,
  is named and allowed, and then checked in its own way);
* whether a file written during the case is damaged (an HDF5 file that does not list,
  a session listed as damaged, JSON that does not parse, a CSV row without three
  values, a report without its end) or a leftover (``*.tmp``, ``*.part``, an empty
  file, a dangling symlink);
* the one-line message, and what the case checks beyond it (each check named).

A case holds when nothing above went wrong and every check passed. Storage faults use
a real tmpfs when run as root (``mount -t tmpfs``), else the file-size resource limit
(RLIMIT_FSIZE with SIGXFSZ ignored: writes past it fail with EFBIG, as on a full
disk). The long statistical trials have scripts of their own (``kill9.py``,
``storage_faults.py``, ``malformed_files.py``, ``clock_faults.py``, ``play_loop.py``);
docs/reliability.md quotes both.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import os
import re
import resource
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests" / "formats"))
sys.path.insert(0, str(ROOT / "benchmarks"))

from _busy import busy  # noqa: E402
from storage_faults import Tmpfs  # noqa: E402

from tests.app.fakedevice import TICKS, FakeForceps, good_info, sample_frames  # noqa: E402
from tests.formats.test_inputs import REPRODUCED, _params  # noqa: E402
from tests.formats.test_malformed_files import _replace, _session_file  # noqa: E402
from tissuecli.app.faults import play_faults  # noqa: E402
from tissuecli.core.errors import TissueError  # noqa: E402
from tissuecli.core.tissue import DEFAULT_TISSUE  # noqa: E402
from tissuecli.formats.jsonfile import write_json  # noqa: E402
from tissuecli.formats.params import tissue_to_dict  # noqa: E402
from tissuecli.formats.sessions import list_sessions, read_session, write_session  # noqa: E402
from tissuecli.sim.process import SimulatorProcess  # noqa: E402
from tissuecli.sim.synth import ForcepsModel, synthesize  # noqa: E402

#: characters of a message shown in the table
SHOWN = 150


# --------------------------------------------------------------------------- the record


@dataclass
class Step:
    """One command run: its arguments, exit code, output and wall time."""

    argv: list[str]
    code: int | None
    out: str
    err: str
    seconds: float
    expect: tuple[int, ...] | None
    key: bool
    #: a traceback the case accepts and reports as a partial result (not a failure)
    tolerated: bool = False

    @property
    def traceback(self) -> bool:
        return "Traceback" in self.out or "Traceback" in self.err

    @property
    def message(self) -> str:
        """The last non-empty line on stderr (else stdout): what the user reads last."""
        for text in (self.err, self.out):
            lines = [ln.strip() for ln in text.replace("\r", "\n").splitlines() if ln.strip()]
            if lines:
                return lines[-1]
        return ""

    @property
    def exit_ok(self) -> bool:
        return self.expect is None or self.code in self.expect


@dataclass
class Result:
    """What one case did, and whether it holds."""

    name: str
    tried: str
    steps: list[Step] = field(default_factory=list)
    checks: list[tuple[str, bool]] = field(default_factory=list)
    destroyed: list[str] = field(default_factory=list)
    damaged: list[str] = field(default_factory=list)
    leftovers: list[str] = field(default_factory=list)
    said: list[str] = field(default_factory=list)
    partial: list[str] = field(default_factory=list)
    error: str = ""
    seconds: float = 0.0

    @property
    def tracebacks(self) -> int:
        return sum(s.traceback for s in self.steps)

    @property
    def failures(self) -> list[str]:
        out = [
            f"traceback in `{' '.join(s.argv[:2])}`"
            for s in self.steps
            if s.traceback and not s.tolerated
        ]
        out += [
            f"`{' '.join(s.argv[:2])}` exit {s.code}, expected {'/'.join(map(str, s.expect or ()))}"
            for s in self.steps
            if not s.exit_ok
        ]
        out += [f"changed: {d}" for d in self.destroyed]
        out += [f"damaged: {d}" for d in self.damaged]
        out += [f"leftover: {d}" for d in self.leftovers]
        out += [f"check failed: {name}" for name, ok in self.checks if not ok]
        if self.error:
            out.append(f"the case itself failed: {self.error}")
        return out

    @property
    def verdict(self) -> str:
        if self.failures:
            return "no"
        return "partly" if self.partial else "yes"


class Ctx:
    """What a case works with: its directory, and ways to run and to record."""

    def __init__(
        self, result: Result, root: Path, tmpfs: bool, options: dict[str, Any] | None = None
    ) -> None:
        self.result = result
        self.options = options or {}
        self.root = root
        self.use_tmpfs = tmpfs
        self.before: dict[str, tuple[str, str]] = {}
        self.allowed: set[str] = set()
        self.cleanups: list[Callable[[], None]] = []

    # -- running commands

    def run(
        self,
        *args: object,
        expect: int | Sequence[int] | None = None,
        key: bool = True,
        timeout: float = 120.0,
        preexec: Callable[[], None] | None = None,
    ) -> Step:
        """Run ``python -m tissuecli ARGS`` in the case's directory and record it."""
        argv = [str(a) for a in args]
        t0 = time.monotonic()
        try:
            r = subprocess.run(
                [sys.executable, "-m", "tissuecli", *argv],
                cwd=self.root,
                capture_output=True,
                text=True,
                timeout=timeout,
                preexec_fn=preexec,
            )
            code, out, err = r.returncode, r.stdout, r.stderr
        except subprocess.TimeoutExpired as exc:
            code = None
            out = _text(exc.stdout)
            err = _text(exc.stderr) + f"\n(timed out after {timeout:g} s)"
        return self.record(argv, code, out, err, time.monotonic() - t0, expect, key)

    def popen(self, *args: object, script: bool = False) -> subprocess.Popen[str]:
        """Start ``python -m tissuecli ARGS`` (with ``script``, what the installed
        ``tissuecli`` command runs) without waiting (finish it with :meth:`finish`)."""
        head = console_script() if script else [sys.executable, "-m", "tissuecli"]
        return subprocess.Popen(
            [*head, *[str(a) for a in args]],
            cwd=self.root,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )

    def finish(
        self,
        proc: subprocess.Popen[str],
        t0: float,
        expect: int | Sequence[int] | None = None,
        key: bool = True,
    ) -> Step:
        code: int | None
        try:
            out, err = proc.communicate(timeout=60)
            code = proc.returncode
        except subprocess.TimeoutExpired:  # hung: shown as exit "-", never left running
            proc.kill()
            out, err = proc.communicate()
            err, code = err + "\n(timed out after 60 s)", None
        argv = [str(a) for a in proc.args[3:]]  # type: ignore[index]  (after python -m/-c X)
        return self.record(argv, code, out, err, time.monotonic() - t0, expect, key)

    def record(
        self,
        argv: list[str],
        code: int | None,
        out: str,
        err: str,
        seconds: float,
        expect: int | Sequence[int] | None,
        key: bool,
    ) -> Step:
        exp = (expect,) if isinstance(expect, int) else tuple(expect) if expect else None
        # paths as the user typed them: relative to the case's directory
        out, err = (x.replace(f"{self.root}/", "") for x in (out, err))
        step = Step(argv, code, out, err, seconds, exp, key)
        self.result.steps.append(step)
        return step

    # -- recording what was seen

    def check(self, what: str, ok: bool) -> bool:
        """A named check of the behaviour; a failed one fails the case."""
        self.result.checks.append((what, bool(ok)))
        return bool(ok)

    def say(self, text: str) -> None:
        """What the table says the program did (instead of, or besides, its message)."""
        self.result.said.append(text)

    def partly(self, text: str) -> None:
        """Holds, except for this (recorded as 'partly', said in the table)."""
        self.result.partial.append(text)

    def allow(self, *names: str) -> None:
        """Files the case asked to change (``--force``, or a session added to a file)."""
        self.allowed.update(names)

    def sim(self, kind: str, name: str | None = None, *args: str) -> SimulatorProcess:
        """A simulated device at ``name`` in the case's directory (enter it to start it); its
        link, removed when it stops, is not one of the user's files."""
        name = name or kind
        self.allow(name)
        return SimulatorProcess(kind, self.root / name, list(args))

    def begin(self) -> None:
        """The inputs are ready: remember every file the case starts with."""
        self.before = snapshot(self.root)

    # -- small disks

    def small_disk(self, size: int, free: int) -> tuple[Path, Callable[[], None] | None]:
        """A directory with about ``free`` bytes of room: a tmpfs of ``size`` bytes filled up
        to that when root (and allowed), else a plain directory and a preexec function
        that sets the file-size limit to ``free``."""
        disk = self.root / "disk"
        if self.use_tmpfs:
            try:
                fs = Tmpfs(disk, str(size))
            except subprocess.CalledProcessError:  # root without the right to mount
                self.use_tmpfs = False
            else:
                self.cleanups.append(fs.close)
                fs.fill(max(size - free, 0))
                return disk, None
        disk.mkdir(exist_ok=True)
        return disk, file_size_limit(free)


def console_script() -> list[str]:
    """What the installed ``tissuecli`` command runs: pip's console script for the entry
    point in pyproject.toml, ``from MODULE import FUNC; sys.exit(FUNC())``."""
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    module, func = project["scripts"]["tissuecli"].split(":")
    return [
        sys.executable,
        "-c",
        f"import re, sys; from {module} import {func}; sys.exit({func}())",
    ]


def _text(data: str | bytes | None) -> str:
    if data is None:
        return ""
    return data.decode(errors="replace") if isinstance(data, bytes) else data


def file_size_limit(limit: int) -> Callable[[], None]:
    """A preexec function: RLIMIT_FSIZE at ``limit`` bytes, SIGXFSZ ignored (EFBIG instead)."""

    def apply() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, resource.RLIM_INFINITY))

    return apply


def _sha(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def snapshot(root: Path) -> dict[str, tuple[str, str]]:
    """Every file under ``root`` (symlinks not followed, mounts included): kind and digest."""
    out: dict[str, tuple[str, str]] = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in filenames + [d for d in dirnames if Path(dirpath, d).is_symlink()]:
            p = Path(dirpath, name)
            rel = str(p.relative_to(root))
            if p.is_symlink():
                out[rel] = ("link", os.readlink(p))
            elif p.is_file():
                out[rel] = ("file", _sha(p))
            else:
                out[rel] = ("other", "")
    return out


def damage(path: Path) -> str | None:
    """Why a file written during a case is damaged, or None if it reads as its kind."""
    try:
        if path.stat().st_size == 0:
            return "empty"
        suffix = path.suffix.lower()
        if suffix == ".h5":
            rows = list_sessions(path)
            bad = [r["name"] for r in rows if r["status"].startswith("damaged")]
            return f"sessions listed as damaged: {bad}" if bad else None
        if suffix == ".json":
            json.loads(path.read_text(encoding="utf-8"))
        elif suffix == ".csv":
            lines = path.read_text(encoding="utf-8").splitlines()
            if not lines or any(ln.count(",") != 2 for ln in lines):
                return "a CSV row without three values"
        elif suffix == ".html":
            if b"</html>" not in path.read_bytes()[-200:]:
                return "report cut short"
    except (TissueError, OSError, ValueError) as exc:
        return str(exc).splitlines()[0][:120]
    return None


def leftover(path: Path) -> bool:
    """A temporary file, an empty file or a dangling symlink left behind."""
    name = path.name
    if path.is_symlink():
        return not path.exists()
    return (
        name.endswith((".tmp", ".part"))
        or (name.startswith(".") and ".tmp" in name)
        or (path.is_file() and path.stat().st_size == 0)
    )


def audit(ctx: Ctx) -> None:
    """After a case: inputs changed, files written damaged, leftovers."""
    res, root = ctx.result, ctx.root
    after = snapshot(root)
    for rel, what in ctx.before.items():
        if after.get(rel) != what and rel not in ctx.allowed:
            res.destroyed.append(rel + (" (removed)" if rel not in after else ""))
    for rel, what in after.items():
        path = root / rel
        if (rel not in ctx.before or rel in ctx.allowed) and leftover(path):
            res.leftovers.append(rel)
        elif what[0] == "file" and ctx.before.get(rel) != what:
            why = damage(path)
            if why is not None:
                res.damaged.append(f"{rel}: {why}")


# --------------------------------------------------------------------------- the cases


@dataclass
class Case:
    name: str
    tried: str
    fn: Callable[[Ctx], None]
    fast: bool


CASES: list[Case] = []


def case(name: str, tried: str, fast: bool = False) -> Callable[[Callable[[Ctx], None]], Any]:
    """Register a case: ``name`` (for --only), what a user tried, and whether it is quick
    enough for the test suite's subset."""

    def register(fn: Callable[[Ctx], None]) -> Callable[[Ctx], None]:
        CASES.append(Case(name, tried, fn, fast))
        return fn

    return register


def grasp_file(path: Path, seconds: float = 2.0, name: str = "liver-1") -> Path:
    """A recorded-looking session (the simulated forceps' model, its 8-bit ADC)."""
    s, _ = synthesize(ForcepsModel(seed=2), seconds)
    s.name = name
    write_session(path, s)
    return path


def params_file(path: Path) -> Path:
    """The default (liver-like) tissue's parameter file, as `fit --out` writes one."""
    write_json(path, tissue_to_dict(DEFAULT_TISSUE))
    return path


def session_digest(path: Path, name: str) -> str:
    """A digest of a session's samples and raw data, to tell it is untouched."""
    s = read_session(path, name, raw=True)
    h = hashlib.sha256()
    for a in (s.time, s.force, s.position, *[s.meta["raw"][k] for k in sorted(s.meta["raw"])]):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def one_line(step: Step, *needles: str, code: int = 1) -> bool:
    """Exit ``code`` (1 unless a fault's or a signal's) and a last line 'Error: ...'
    holding every needle, no line too long."""
    return (
        step.code == code
        and step.message.startswith("Error: ")
        and all(n in step.message for n in needles)
    )


# ---- outputs never destroy


def _same_file_case(ctx: Ctx, args: list[str]) -> None:
    for extra in ([], ["--force"]):
        s = ctx.run(*args, *extra, expect=1)
        ctx.check(f"refused {'with' if extra else 'without'} --force", one_line(s, "input file"))


@case(
    "out-export-same",
    "`export grasp.h5 --session liver-1 --csv grasp.h5` (and with `--force`)",
    fast=True,
)
def _(ctx: Ctx) -> None:
    grasp_file(ctx.root / "grasp.h5")
    ctx.begin()
    _same_file_case(ctx, ["export", "grasp.h5", "--session", "liver-1", "--csv", "grasp.h5"])


@case("out-fit-out-same", "`fit grasp.h5 --out grasp.h5` (and with `--force`)")
def _(ctx: Ctx) -> None:
    grasp_file(ctx.root / "grasp.h5")
    ctx.begin()
    _same_file_case(ctx, ["fit", "grasp.h5", "--out", "grasp.h5"])


@case("out-fit-report-same", "`fit grasp.h5 --report grasp.h5` (and with `--force`)")
def _(ctx: Ctx) -> None:
    grasp_file(ctx.root / "grasp.h5")
    ctx.begin()
    _same_file_case(ctx, ["fit", "grasp.h5", "--report", "grasp.h5"])


@case(
    "out-play-summary-same",
    "`play p.json --check --summary p.json` (and with `--force`)",
    fast=True,
)
def _(ctx: Ctx) -> None:
    params_file(ctx.root / "p.json")
    ctx.begin()
    _same_file_case(ctx, ["play", "p.json", "--check", "--summary", "p.json"])


@case(
    "out-input-via-links",
    "the output a symlink or a hard link to the input: `export grasp.h5 --csv alias --force`",
)
def _(ctx: Ctx) -> None:
    grasp_file(ctx.root / "grasp.h5")
    (ctx.root / "sym.csv").symlink_to("grasp.h5")
    os.link(ctx.root / "grasp.h5", ctx.root / "hard.csv")
    ctx.begin()
    for alias in ("sym.csv", "hard.csv"):
        s = ctx.run("export", "grasp.h5", "--csv", alias, "--force", expect=1)
        ctx.check(f"{alias} refused", one_line(s, "input file"))


@case(
    "out-existing-csv",
    "`import lab.csv --out lab.h5`, then `export lab.h5 --csv lab.csv` over the original CSV",
)
def _(ctx: Ctx) -> None:
    s, _ = synthesize(ForcepsModel(seed=3), 1.0)
    rows = np.c_[s.time, s.force, s.position]
    np.savetxt(ctx.root / "lab.csv", rows, delimiter=",", header="time,force,position", comments="")
    ctx.begin()
    ctx.run("import", "lab.csv", "--out", "lab.h5", "--session", "lab", expect=0, key=False)
    s = ctx.run("export", "lab.h5", "--csv", "lab.csv", expect=1)
    ctx.check("refused: exists, --force named", one_line(s, "exists", "--force"))


@case(
    "out-through-symlink",
    "`export --csv out.csv` where out.csv is a symlink to another file; then with `--force`",
)
def _(ctx: Ctx) -> None:
    grasp_file(ctx.root / "grasp.h5")
    (ctx.root / "victim.txt").write_text("someone else's file\n")
    (ctx.root / "out.csv").symlink_to("victim.txt")
    ctx.begin()
    s = ctx.run("export", "grasp.h5", "--csv", "out.csv", expect=1)
    ctx.check("refused without --force", one_line(s, "exists", "--force"))
    ctx.run("export", "grasp.h5", "--csv", "out.csv", "--force", expect=0)
    ctx.allow("out.csv")  # replaced as asked: the link, not its target
    link = ctx.root / "out.csv"
    ctx.check("--force replaced the link itself", not link.is_symlink() and link.is_file())
    ctx.say("with --force the link is replaced by the CSV; victim.txt unchanged")


@case(
    "out-planted-temp-names",
    "`ln -s victim p.json.tmp` (also `.p.json.tmp`, `r.html.part`); "
    "`fit grasp.h5 --out p.json --report r.html`",
    fast=True,
)
def _(ctx: Ctx) -> None:
    grasp_file(ctx.root / "grasp.h5")
    (ctx.root / "victim").write_text("victim\n")
    for planted in ("p.json.tmp", ".p.json.tmp", "r.html.part"):
        (ctx.root / planted).symlink_to("victim")
    ctx.begin()
    ctx.run("fit", "grasp.h5", "--out", "p.json", "--report", "r.html", expect=0)
    names = sorted(p.name for p in ctx.root.iterdir() if not p.is_symlink())
    ctx.check("only p.json and r.html new", names == ["grasp.h5", "p.json", "r.html", "victim"])
    ctx.say("victim untouched; p.json and r.html written through fresh exclusive names")


@case("out-permissions", "`chmod 600 p.json`; `fit grasp.h5 --out p.json --force`")
def _(ctx: Ctx) -> None:
    grasp_file(ctx.root / "grasp.h5")
    p = ctx.root / "p.json"
    p.write_text("{}\n")
    p.chmod(0o600)
    ctx.begin()
    ctx.run("fit", "grasp.h5", "--out", "p.json", "--force", expect=0)
    ctx.allow("p.json")
    mode = p.stat().st_mode & 0o777
    ctx.check("mode kept", mode == 0o600)
    ctx.say(f"replaced as asked; mode {mode:o} kept")


@case(
    "out-missing-dir-fit",
    "`fit grasp.h5 --out p.json --report missing/r.html`",
    fast=True,
)
def _(ctx: Ctx) -> None:
    grasp_file(ctx.root / "grasp.h5")
    ctx.begin()
    s = ctx.run("fit", "grasp.h5", "--out", "p.json", "--report", "missing/r.html", expect=1)
    ctx.check("refused, naming --report", one_line(s, "--report", "does not exist"))
    ctx.check("p.json not written", not (ctx.root / "p.json").exists())
    ctx.check("before the fit (< 3 s)", s.seconds < 3.0)
    ctx.say(f"refused in {s.seconds:.1f} s, before the fit; p.json not written")


@case(
    "out-missing-dir-play",
    "`play p.json --port DISPLAY --duration 20 --summary missing/s.json`",
)
def _(ctx: Ctx) -> None:
    params_file(ctx.root / "p.json")
    with ctx.sim("display"):
        ctx.begin()
        s = ctx.run(
            "play", "p.json", "--port", "display", "--duration", 20,
            "--summary", "missing/s.json", expect=1,
        )  # fmt: skip
    ctx.check("refused, naming --summary", one_line(s, "--summary", "does not exist"))
    ctx.check("before playing (< 3 s)", s.seconds < 3.0)
    ctx.say(f"refused in {s.seconds:.1f} s, before the display was opened")


# ---- storage faults


def _committed(step: Step) -> int:
    m = re.search(r"the (\d+) rows committed", step.message)
    return int(m.group(1)) if m else 0


@case(
    "disk-record-full",
    "`record` at 1 kHz onto a 2 MiB disk with 1.8 MB free until it is full; then `sessions`, "
    "and the file copied elsewhere takes a new `record`",
)
def _(ctx: Ctx) -> None:
    _record_until_full(ctx, 1_800_000)


@case(
    "disk-record-almost-none",
    "the same with 1.6 MB free, just over the room a new session needs (1.5 MB)",
)
def _(ctx: Ctx) -> None:
    _record_until_full(ctx, 1_600_000)


def _record_until_full(ctx: Ctx, free: int) -> None:
    disk, limit = ctx.small_disk(2 << 20, free)
    with ctx.sim("forceps"):
        ctx.begin()
        s = ctx.run(
            "record", "--port", "forceps", "--out", disk / "r.h5", "--session", "s",
            "--duration", 60, "--quiet", expect=1, preexec=limit, timeout=120,
        )  # fmt: skip
        cause = "disk full" if limit is None else "file size limit reached"
        ctx.check(f"one line naming '{cause}'", one_line(s, cause, "saved in session"))
        committed = _committed(s)
        ls = ctx.run("sessions", disk / "r.h5", expect=0, key=False)
        ctx.check("listed as incomplete", "incomplete" in ls.out)
        rows = len(read_session(disk / "r.h5", "s"))
        ctx.check("every committed row readable", rows >= committed > 0)
        shutil.copyfile(disk / "r.h5", ctx.root / "copy.h5")
        ctx.run(
            "record", "--port", "forceps", "--out", "copy.h5", "--session", "again",
            "--duration", 0.5, "--quiet", expect=0,
        )  # fmt: skip
        ctx.check("the copy lists both sessions", len(list_sessions(ctx.root / "copy.h5")) == 2)
    where = "2 MiB tmpfs" if limit is None else f"{free / 1e6:.1f} MB file-size limit"
    ctx.say(
        f"{where}: stopped after {s.seconds:.0f} s; {committed} rows committed, {rows} "
        f"readable; file takes new sessions"
    )


@case(
    "disk-record-no-room",
    "`record` onto a 2 MiB disk with 0.5 MB free",
)
def _(ctx: Ctx) -> None:
    disk, limit = ctx.small_disk(2 << 20, 500_000)
    with ctx.sim("forceps"):
        ctx.begin()
        s = ctx.run(
            "record", "--port", "forceps", "--out", disk / "r.h5", "--session", "s",
            "--duration", 5, "--quiet", expect=1, preexec=limit,
        )  # fmt: skip
    ctx.check("refused, no file", not (disk / "r.h5").exists())
    ctx.check("names the room", "free space" in s.message or "file size limit" in s.message)


@case(
    "disk-fit-report",
    "`fit grasp.h5 --out p.json --report r.html` onto a disk with 200 kB free (report 460 kB)",
)
def _(ctx: Ctx) -> None:
    grasp_file(ctx.root / "grasp.h5")
    disk, limit = ctx.small_disk(1 << 20, 200_000)
    ctx.begin()
    s = ctx.run(
        "fit", "grasp.h5", "--out", disk / "p.json", "--report", disk / "r.html",
        expect=1, preexec=limit,
    )  # fmt: skip
    cause = "no space left" if limit is None else "file size limit reached"
    ctx.check(f"one line naming '{cause}'", one_line(s, "r.html", cause))
    ctx.check("no report", not (disk / "r.html").exists())
    p = disk / "p.json"
    ctx.say(
        "p.json "
        + ("written whole (before the report)" if p.exists() else "not written")
        + "; no report, no temporary file"
    )


@case(
    "disk-play-log",
    "`play --log` at 1 kHz onto a disk with 1.85 MB free until it is full",
)
def _(ctx: Ctx) -> None:
    params_file(ctx.root / "p.json")
    disk, limit = ctx.small_disk(2 << 20, 1_850_000)
    with ctx.sim("display"):
        ctx.begin()
        s = ctx.run(
            "play", "p.json", "--port", "display", "--duration", 60, "--log", disk / "plays.h5",
            expect=1, preexec=limit, timeout=120,
        )  # fmt: skip
    cause = "disk full" if limit is None else "file size limit reached"
    ctx.check(f"one line naming '{cause}'", one_line(s, cause))
    committed = _committed(s)
    from tissuecli.formats.hdf5 import group_names, read_group

    names = group_names(disk / "plays.h5", "plays")
    rows = len(read_group(disk / "plays.h5", f"plays/{names[0]}")[0]["time"]) if names else 0
    ctx.check("every committed row readable", rows >= committed > 0)
    ctx.say(f"stopped after {s.seconds:.0f} s at 0 V; {committed} rows committed, {rows} readable")


@case(
    "disk-play-log-no-room",
    "`play --log` onto a disk with 0.5 MB free",
)
def _(ctx: Ctx) -> None:
    params_file(ctx.root / "p.json")
    disk, limit = ctx.small_disk(2 << 20, 500_000)
    with ctx.sim("display"):
        ctx.begin()
        s = ctx.run(
            "play", "p.json", "--port", "display", "--duration", 5, "--log", disk / "plays.h5",
            expect=1, preexec=limit,
        )  # fmt: skip
    ctx.check("refused before playing, no file", not (disk / "plays.h5").exists())
    ctx.check("names the room", "free space" in s.message or "file size limit" in s.message)


# ---- the device is not trusted


def _clean(n: int) -> tuple[np.ndarray, np.ndarray]:
    return np.arange(n) + 1000, np.arange(n) * TICKS + 123_456


def _record_fake(
    ctx: Ctx,
    stream: list[bytes],
    *extra: object,
    info: dict[str, Any] | None = None,
    expect: int | Sequence[int] | None = 0,
) -> Step:
    with FakeForceps(good_info() if info is None else info, stream) as dev:
        ctx.begin()
        return ctx.run(
            "record", "--port", dev.path, "--out", "grasp.h5", "--session", "s", "--quiet",
            *extra, expect=expect,
        )  # fmt: skip


_SAVED = re.compile(r"saved (\d+) samples \(([\d.]+) s at ([\d.]+) Hz\)")


def _summary_counts(step: Step) -> str:
    m = _SAVED.search(step.out + step.err)
    return f"{m.group(1)} samples, {m.group(2)} s at {m.group(3)} Hz" if m else "no summary"


def _rate_hz(step: Step) -> float:
    m = _SAVED.search(step.out + step.err)
    return float(m.group(3)) if m else float("nan")


@case(
    "dev-clock-2^31",
    "one valid-CRC frame with the device clock +2^31 ticks; `record --duration 1.2`",
    fast=True,
)
def _(ctx: Ctx) -> None:
    seq, clk = _clean(1500)
    clk[700] += 1 << 31
    s = _record_fake(ctx, sample_frames(seq, clk), "--duration", 1.2)
    session = read_session(ctx.root / "grasp.h5", "s")
    ctx.check("1200 samples", len(session) == 1200)
    ctx.check("time strictly increasing", bool(np.all(np.diff(session.time) > 0)))
    ctx.check("1 clock jump counted", "1 clock jump," in s.out + s.err)
    ctx.check("no wrap", session.meta.get("clock_wraps") == 0)
    ctx.check("the rate reported is 1000 Hz", abs(_rate_hz(s) - 1000.0) < 1.0)
    ctx.say(f"{_summary_counts(s)}; '1 clock jump' in the summary and the attributes")


@case(
    "dev-clock-jump-duration",
    "the device clock steps +4 s at 0.5 s; `record --duration 1.2`",
)
def _(ctx: Ctx) -> None:
    seq, clk = _clean(1500)
    clk[500:] += 4_000_000
    s = _record_fake(ctx, sample_frames(seq, clk), "--duration", 1.2)
    session = read_session(ctx.root / "grasp.h5", "s")
    ctx.check("1200 samples (the duration honoured)", len(session) == 1200)
    ctx.check("1 clock step counted", session.meta.get("clock_steps") == 1)
    ctx.say(f"{_summary_counts(s)}; 1 clock step counted; 'duration reached' at 1.2 s")


@case(
    "dev-clock-backwards",
    "the device clock steps back 0.3 s mid-stream; `record --duration 1.2`",
)
def _(ctx: Ctx) -> None:
    seq, clk = _clean(1500)
    clk[500:] -= 300_000
    s = _record_fake(ctx, sample_frames(seq, clk), "--duration", 1.2)
    session = read_session(ctx.root / "grasp.h5", "s")
    ctx.check("time strictly increasing", bool(np.all(np.diff(session.time) > 0)))
    ctx.check("1 clock step counted", session.meta.get("clock_steps") == 1)
    ctx.say(f"{_summary_counts(s)}; time increasing; 1 clock step counted")


@case(
    "dev-sequence-restart",
    "the device restarts its sequence and clock mid-stream (a reset); `record`, then `sessions`",
)
def _(ctx: Ctx) -> None:
    seq, clk = _clean(1500)
    seq[800:] = np.arange(700) + 7
    clk[800:] = np.arange(700) * TICKS + 55
    s = _record_fake(ctx, sample_frames(seq, clk), "--duration", 1.2)
    session = read_session(ctx.root / "grasp.h5", "s")
    ctx.check("time strictly increasing", bool(np.all(np.diff(session.time) > 0)))
    ctx.check("in the summary line", "1 sequence restart;" in s.out + s.err)
    ctx.check("in the attributes", session.meta.get("sequence_restarts") == 1)
    ls = ctx.run("sessions", "grasp.h5", expect=0, key=False)
    ctx.check("in the `sessions` table", "(1 sequence restart)" in ls.out)
    js = ctx.run("sessions", "grasp.h5", "--json", expect=0, key=False)
    faults = json.loads(js.out)[0].get("clock_faults", {}) if js.code == 0 else {}
    ctx.check("in `sessions --json`", faults.get("sequence_restarts") == 1)
    ctx.say(
        "counted: summary line, `sequence_restarts` attribute, `sessions` "
        "('(1 sequence restart)') and its --json (`clock_faults`)"
    )


def _drift(step: Step) -> tuple[float, float, bool] | None:
    m = re.search(r"clock drift ([-+][\d.]+) \+- ([\d.]+) ppm", step.out + step.err)
    if not m:
        return None
    return float(m.group(1)), float(m.group(2)), "time rescaled" in step.out + step.err


@case(
    "dev-clock-map-0ppm",
    "3 recordings of 3 s from the simulated forceps at 0 ppm: the drift reported",
)
def _(ctx: Ctx) -> None:
    ctx.begin()
    seen = []
    for run in range(3):
        with ctx.sim("forceps", f"forceps{run}", "--seed", str(run)):
            s = ctx.run(
                "record", "--port", f"forceps{run}", "--out", "grasp.h5",
                "--session", f"s{run}", "--duration", 3, "--quiet", expect=0,
            )  # fmt: skip
        d = _drift(s)
        ctx.check(f"run {run}: drift reported", d is not None)
        if d is not None:
            ctx.check(f"run {run}: 0 within 2 uncertainties", abs(d[0]) <= 2 * d[1])
            ctx.check(f"run {run}: time not rescaled", not d[2])
            seen.append(f"{d[0]:+.0f} +- {d[1]:.0f}")
    ctx.say(f"drift {', '.join(seen)} ppm (not resolved: time kept on the device clock)")


@case(
    "dev-clock-map-burst",
    "a 3 s recording with a 200 kB garbage burst mid-stream (a stall, then the backlog at once)",
)
def _(ctx: Ctx) -> None:
    seq, clk = _clean(3000)
    frames = sample_frames(seq, clk)
    rng = np.random.default_rng(1)
    burst = rng.integers(1, 256, 200_000, dtype=np.uint8).tobytes() + b"\0"
    s = _record_fake(ctx, frames[:1500] + [burst] + frames[1500:], "--duration", 2.9)
    d = _drift(s)
    ctx.check("drift reported", d is not None)
    if d is not None:
        ctx.check("0 within 2 uncertainties", abs(d[0]) <= 2 * d[1])
        ctx.check("time not rescaled", not d[2])
        ctx.say(f"drift {d[0]:+.0f} +- {d[1]:.0f} ppm, time kept on the device clock")


def _info_case(ctx: Ctx, changes: list[tuple[str, dict[str, Any], str]]) -> None:
    seq, clk = _clean(50)
    shown = []
    for label, change, needle in changes:
        s = _record_fake(ctx, sample_frames(seq, clk), info=good_info(**change), expect=1)
        ctx.check(f"{label}: one line naming {needle}", one_line(s, needle))
        ctx.check(f"{label}: no file", not (ctx.root / "grasp.h5").exists())
        shown.append(s.message.removeprefix("Error: "))
    ctx.say(shown[0])


@case("dev-info-rate", 'Info `rate_hz` of "1000", null, 10^300')
def _(ctx: Ctx) -> None:
    _info_case(
        ctx,
        [
            ("string", {"rate_hz": "1000"}, "rate_hz"),
            ("null", {"rate_hz": None}, "rate_hz"),
            ("huge", {"rate_hz": 10**300}, "rate_hz"),
        ],
    )


@case("dev-info-clock", 'Info `clock_hz` of "fast", null, 10^300, 0', fast=True)
def _(ctx: Ctx) -> None:
    _info_case(
        ctx,
        [
            ("string", {"clock_hz": "fast"}, "clock_hz"),
            ("null", {"clock_hz": None}, "clock_hz"),
            ("huge", {"clock_hz": 10**300}, "clock_hz"),
            ("zero", {"clock_hz": 0}, "clock_hz"),
        ],
    )


@case("dev-info-gain", "Info calibration with a force gain of 1e308 (infinite forces)")
def _(ctx: Ctx) -> None:
    cal = {"force": {"gain": 1e308}, "position": {"gain": 1e-5}}
    _info_case(ctx, [("gain", {"calibration": cal}, "calibration.force")])


@case(
    "dev-loss-count",
    "30 % of frames lost on the line; `record --duration 1`: frames lost counted",
)
def _(ctx: Ctx) -> None:
    seq, clk = _clean(1500)
    keep = np.random.default_rng(7).random(1500) > 0.3
    keep[0] = True
    kept = np.flatnonzero(keep)
    kept = kept[kept < 1000]
    want = int(kept[-1] + 1 - kept.size)
    # an empty item keeps the device's pace: it sampled, the line lost the frame
    line = [f if k else b"" for f, k in zip(sample_frames(seq, clk), keep, strict=True)]
    s = _record_fake(ctx, line, "--duration", 1, expect=3)  # data lost: exit 3
    m = re.search(r"(\d+) lost", s.out + s.err)
    got = int(m.group(1)) if m else -1
    ctx.check("lost = gaps among the samples kept", got == want)
    ctx.say(f"{_summary_counts(s)}; {got} lost, {want} missing among the kept")


# ---- files that are not what they seem


def _damaged_case(ctx: Ctx, mutate: Any, needle: str, listed: bool = True) -> None:
    _session_file(ctx.root, mutate)
    ctx.begin()
    ls = ctx.run("sessions", "s.h5", expect=0)
    if listed:
        ctx.check("`sessions` lists it as damaged, with the reason", "damaged" in ls.out)
    fit = ctx.run("fit", "s.h5", expect=1)
    ctx.check("`fit`: one line naming the dataset", one_line(fit, "is damaged", needle))
    exp = ctx.run("export", "s.h5", "--csv", "out.csv", expect=1)
    ctx.check("`export`: one line", one_line(exp, "is damaged", needle))
    ctx.check("no CSV written", not (ctx.root / "out.csv").exists())


@case("h5-text-dataset", "a session whose force dataset holds strings", fast=True)
def _(ctx: Ctx) -> None:
    _damaged_case(ctx, _replace("force", np.array([b"1.0"] * 300)), "force holds text")


@case("h5-compound-dataset", "a session whose time dataset is compound")
def _(ctx: Ctx) -> None:
    _damaged_case(ctx, _replace("time", np.zeros(300, dtype=[("a", "f8")])), "compound")


@case("h5-scalar-dataset", "a session whose force dataset is a single value")
def _(ctx: Ctx) -> None:
    _damaged_case(ctx, _replace("force", np.float64(1.0)), "single value")


@case("h5-2d-dataset", "a session whose force dataset has two columns; `export`")
def _(ctx: Ctx) -> None:
    _damaged_case(ctx, _replace("force", np.zeros((300, 2))), "shape (300, 2)")


@case("h5-missing-dataset", "a session without its time dataset; `sessions`, `fit`, `export`")
def _(ctx: Ctx) -> None:
    _damaged_case(ctx, lambda g: g.__delitem__("time"), "time is missing")
    ctx.check("not 'holds no sessions'", "holds no sessions" not in ctx.result.steps[0].out)


@case("h5-text-attributes", 'attributes of the wrong type (frames_lost "three", complete "yes")')
def _(ctx: Ctx) -> None:
    def mutate(g: h5py.Group) -> None:
        g.attrs["frames_lost"] = "three"
        g.attrs["complete"] = "yes"
        g.attrs["rows_committed"] = np.int64(120)

    _session_file(ctx.root, mutate)
    ctx.begin()
    ls = ctx.run("sessions", "s.h5", expect=0)
    ctx.check("the ignored attributes named", "attribute frames_lost is text" in ls.out)
    ctx.run("export", "s.h5", "--csv", "out.csv", expect=0)
    n = len((ctx.root / "out.csv").read_text().splitlines()) - 1
    ctx.check("trusted up to rows_committed", n == 120)
    ctx.say("listed as incomplete (complete unreadable), 120 rows (rows_committed), named")


@case("h5-truncated", "a session file cut to half its length; `sessions`, `fit`, `export`")
def _(ctx: Ctx) -> None:
    path = grasp_file(ctx.root / "grasp.h5", 5.0)
    os.truncate(path, path.stat().st_size // 2)
    ctx.begin()
    for args in (["sessions"], ["fit"], ["export", "--csv", "out.csv"]):
        s = ctx.run(args[0], "grasp.h5", *args[1:], expect=1)
        ctx.check(f"`{args[0]}`: 'truncated'", one_line(s, "truncated"))
        ctx.check(f"`{args[0]}`: not 'another program'", "another program" not in s.message)


def _json_case(ctx: Ctx, content: str | bytes | dict | None, needle: str) -> None:
    path = ctx.root / "p.json"
    if content is None:  # an HDF5 file given as the parameter file
        grasp_file(path)
    elif isinstance(content, dict):
        path.write_text(json.dumps(content))
    else:
        path.write_bytes(content if isinstance(content, bytes) else content.encode())
    ctx.begin()
    for args in (
        ["play", "p.json", "--check"],
        ["simulate", "forceps", "--params", "p.json", "--duration", "0.2", "--link", "f"],
    ):
        s = ctx.run(*args, expect=1)
        ctx.check(f"`{args[0]}`: one line naming it", one_line(s, needle))
        ctx.check(f"`{args[0]}`: short", max(map(len, s.err.splitlines() or [""])) < 400)


_JSON = {name: (content, needle) for name, content, needle in REPRODUCED}


@case("json-h5", "the .h5 file given as the parameter file (`play --check`, `simulate`)")
def _(ctx: Ctx) -> None:
    _json_case(ctx, *_JSON["hdf5"])


@case("json-utf8", "a parameter file that is not UTF-8", fast=True)
def _(ctx: Ctx) -> None:
    _json_case(ctx, *_JSON["bad_utf8"])


@case("json-deep", "a parameter file of 100,000 nested brackets", fast=True)
def _(ctx: Ctx) -> None:
    _json_case(ctx, *_JSON["deep"])


@case("json-400-digits", "K written as a 400-digit integer")
def _(ctx: Ctx) -> None:
    _json_case(ctx, *_JSON["digits"])


@case("json-k-1e300", "K = 1e300 (`play --check`, `simulate forceps --params`)")
def _(ctx: Ctx) -> None:
    _json_case(ctx, *_JSON["k1e300"])


@case("json-10mb-string", "a 10 MB string in the parameter file")
def _(ctx: Ctx) -> None:
    _json_case(ctx, *_JSON["bigstr"])


@case("json-halfmb-string", "a 500 kB string as the stiffness form (under the 1 MiB cap)")
def _(ctx: Ctx) -> None:
    _json_case(ctx, *_JSON["halfmb"])
    ctx.say(ctx.result.steps[-1].message + f" ({len(ctx.result.steps[-1].err)} characters)")


@case("json-version-99", "a parameter file of version 99", fast=True)
def _(ctx: Ctx) -> None:
    _json_case(ctx, _params(version=99), "written by a newer tissuecli")


# ---- other surprises


@case("csv-gap-fit", "a CSV with a 0.5 s gap in its time column: `import`, then `fit`")
def _(ctx: Ctx) -> None:
    s, _ = synthesize(ForcepsModel(seed=4), 4.0)
    t = s.time.copy()
    t[2000:] += 0.5
    rows = np.c_[t, s.force, s.position]
    np.savetxt(ctx.root / "gap.csv", rows, delimiter=",", header="time,force,position", comments="")
    ctx.begin()
    imp = ctx.run("import", "gap.csv", "--out", "gap.h5", "--session", "g", expect=0)
    ctx.check("the gap reported as lost samples", "500 lost" in imp.out + imp.err)
    fit = ctx.run("fit", "gap.h5", "--out", "p.json", expect=0)
    best = [ln for ln in fit.out.splitlines() if ln.startswith("best:")]
    ctx.say("imported, the gap named as 500 lost samples; fitted, " + (best[0] if best else ""))


@case("link-missing-dir", "`simulate forceps --link nodir/forceps`", fast=True)
def _(ctx: Ctx) -> None:
    ctx.begin()
    s = ctx.run("simulate", "forceps", "--link", "nodir/forceps", "--duration", 1, expect=1)
    ctx.check("one line", one_line(s, "does not exist"))


#: Ctrl-C trials of the sigint-early case, spread evenly over its first 60 ms
SIGINT_RUNS = 40
#: a record still running this long after its Ctrl-C ignored it, s
SIGINT_GRACE_S = 4.0


@case(
    "sigint-early",
    "Ctrl-C (SIGINT) 0-60 ms after `tissuecli record` (no --duration; the console script) "
    "starts, evenly spread "
    f"(--sigint-runs, default {SIGINT_RUNS})",
)
def _(ctx: Ctx) -> None:
    sigint_runs = ctx.options.get("sigint_runs", SIGINT_RUNS)
    outcomes: dict[str, list[float]] = {}
    in_package = ignored = 0
    with ctx.sim("forceps"):
        ctx.begin()
        for k, delay in enumerate(np.linspace(0.0, 0.06, sigint_runs)):
            out = f"r{k}.h5"
            t0 = time.monotonic()
            proc = ctx.popen("record", "--port", "forceps", "--out", out, "--quiet", script=True)
            time.sleep(float(delay))
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=SIGINT_GRACE_S)
            except subprocess.TimeoutExpired:
                # still recording: the Ctrl-C was lost; a second one, as a user would
                ignored += 1
                proc.send_signal(signal.SIGINT)
            step = ctx.finish(proc, t0, key=False)
            if step.seconds > SIGINT_GRACE_S:
                what = f"Ctrl-C ignored, recorded on until a second one (exit {step.code})"
                step.tolerated, step.expect = True, None
            elif step.traceback:
                what = "KeyboardInterrupt traceback while Python starts"
                in_package += "/tissuecli/" in step.err
                step.tolerated, step.expect = True, None
            elif step.code == -signal.SIGINT:
                what = "ended by the signal, no output"
            elif step.code == 1:
                what = f"one line: {step.message[:60]}"
            elif step.code == 0:
                what = "recorded (signal after the first sample)"
            else:
                what = f"exit {step.code}"
            ok = _no_file_or_listed(ctx.root / out, step.code)
            ctx.check(f"{delay * 1e3:.1f} ms: no file, or a listed session", ok)
            outcomes.setdefault(what, []).append(float(delay) * 1e3)
    tracebacks = sum(s.traceback for s in ctx.result.steps)
    ctx.check(f"every Ctrl-C stops the recorder ({ignored} ignored)", ignored == 0)
    if tracebacks:
        ctx.partly(
            f"{tracebacks} of {len(ctx.result.steps)} runs print a KeyboardInterrupt "
            f"traceback while the interpreter starts ({in_package} inside tissuecli's imports)"
        )
    ctx.say(
        "; ".join(
            f"{len(ms)}x {what} ({min(ms):.0f}-{max(ms):.0f} ms)"
            for what, ms in sorted(outcomes.items(), key=lambda kv: min(kv[1]))
        )
    )


def _no_file_or_listed(path: Path, code: int | None) -> bool:
    if not path.exists():
        return True
    try:
        rows = list_sessions(path)
    except TissueError:
        return False
    # a recording the Ctrl-C stopped exits 130 with its session complete and kept
    return code in (0, 130) and len(rows) == 1 and rows[0]["samples"] > 0


@case(
    "signal-before-streaming",
    "SIGINT once the device has been told START but before it sends a sample",
)
def _(ctx: Ctx) -> None:
    with FakeForceps(good_info(), []) as dev:
        ctx.begin()
        t0 = time.monotonic()
        proc = ctx.popen("record", "--port", dev.path, "--out", "grasp.h5", "--session", "s")
        ctx.check("the device was started", dev.started.wait(20))
        time.sleep(0.05)
        proc.send_signal(signal.SIGINT)
        s = ctx.finish(proc, t0, expect=130)
    ctx.check("one line: nothing was recorded", one_line(s, "nothing was recorded", code=130))
    ctx.check("no file, no empty session", not (ctx.root / "grasp.h5").exists())


@case("tissue-newline", "`import --tissue` with a newline and a forged row; `sessions`", fast=True)
def _(ctx: Ctx) -> None:
    t = np.arange(300) * 1e-3
    rows = np.c_[t, np.ones(300), np.ones(300) * 1e-3]
    np.savetxt(ctx.root / "a.csv", rows, delimiter=",", header="time,force,position", comments="")
    ctx.begin()
    label = "liver\nforged                 999      1.000   1000.0     0     0  complete    fake"
    ctx.run("import", "a.csv", "--out", "t.h5", "--session", "x", "--tissue", label, expect=0)
    ls = ctx.run("sessions", "t.h5", expect=0)
    ctx.check("one row per session", len(ls.out.strip().splitlines()) == 2)
    ctx.check("the label kept exactly", list_sessions(ctx.root / "t.h5")[0]["tissue"] == label)
    ctx.say("the newline shown as \\n in the table; --json keeps the label exactly")


@case(
    "fit-incomplete",
    "`fit --out` of a session whose recorder was killed with kill -9",
)
def _(ctx: Ctx) -> None:
    with ctx.sim("forceps"):
        ctx.begin()
        proc = ctx.popen("record", "--port", "forceps", "--out", "grasp.h5", "--session", "s")
        time.sleep(3.0)  # start-up, then about 2 s of grasps
        proc.kill()
        proc.communicate()
    fit = ctx.run("fit", "grasp.h5", "--out", "p.json", expect=0)
    ctx.check("a warning says it is incomplete", "is incomplete" in fit.out + fit.err)
    doc = json.loads((ctx.root / "p.json").read_text())
    ctx.check("the parameter file records it", doc.get("data", {}).get("complete") is False)
    ctx.say("'session 's' is incomplete: its recording never closed' warned; data.complete false")


@case(
    "display-takeover",
    "a second `simulate display --link L` while one runs on L",
)
def _(ctx: Ctx) -> None:
    with ctx.sim("display") as first:
        target = os.readlink(ctx.root / "display")
        ctx.begin()
        s = ctx.run("simulate", "display", "--link", "display", "--duration", 1, expect=1)
        ctx.check("refused in one line", one_line(s, "running simulated device"))
        link = ctx.root / "display"
        ctx.check("the link kept", link.is_symlink() and os.readlink(link) == target)
        ctx.check(
            "the first still runs", first.process is not None and first.process.poll() is None
        )
    ctx.check("the first removed its link on exit", not (ctx.root / "display").is_symlink())


@case("import-foreign", "`import a.csv --out theirs.h5`, an HDF5 file of another program")
def _(ctx: Ctx) -> None:
    with h5py.File(ctx.root / "theirs.h5", "w") as f:
        f["data"] = np.arange(10.0)
    t = np.arange(300) * 1e-3
    rows = np.c_[t, np.ones(300), np.ones(300) * 1e-3]
    np.savetxt(ctx.root / "a.csv", rows, delimiter=",", header="time,force,position", comments="")
    ctx.begin()
    s = ctx.run("import", "a.csv", "--out", "theirs.h5", "--session", "a", expect=1)
    ctx.check("refused in one line", one_line(s, "was not written by tissuecli"))


@case("port-regular-file", "`record --port notaport` where notaport is a regular file", fast=True)
def _(ctx: Ctx) -> None:
    (ctx.root / "notaport").write_text("hello\n")
    ctx.begin()
    s = ctx.run("record", "--port", "notaport", "--out", "r.h5", expect=1)
    ctx.check("says what it is", one_line(s, "not a serial device"))
    ctx.check("no file", not (ctx.root / "r.h5").exists())


@case(
    "repeated-options",
    "`--session a --session b`, `--out a --out b`, `--duration 1 --duration=2`",
    fast=True,
)
def _(ctx: Ctx) -> None:
    grasp_file(ctx.root / "grasp.h5")
    ctx.begin()
    for args in (
        ["export", "grasp.h5", "--session", "a", "--session", "b", "--csv", "o.csv"],
        ["fit", "grasp.h5", "--out", "a.json", "--out", "b.json"],
        ["record", "--port", "x", "--out", "r.h5", "--duration", "1", "--duration=2"],
    ):
        s = ctx.run(*args, expect=1)
        ctx.check(f"`{args[0]}` refused", one_line(s, "given twice"))


@case("bare-command", "`tissuecli` with no command", fast=True)
def _(ctx: Ctx) -> None:
    ctx.begin()
    s = ctx.run(expect=0)
    ctx.check("prints the help", "Usage:" in s.out and "Commands:" in s.out)
    ctx.say("prints the help, exit 0")


# ---- play under load


@case(
    "play-under-load",
    "`play --duration 5 --summary --log` with two busy processes on the 2 cores",
)
def _(ctx: Ctx) -> None:
    params_file(ctx.root / "p.json")
    with busy(2), ctx.sim("display"):
        ctx.begin()
        s = ctx.run(
            "play", "p.json", "--port", "display", "--duration", 5,
            "--summary", "s.json", "--log", "plays.h5", expect=(0, 3, 4, 5, 6, 7),
        )  # fmt: skip
    summary_path = ctx.root / "s.json"
    summary = json.loads(summary_path.read_text()) if summary_path.exists() else None
    if s.code == 0:
        faults = play_faults(summary or {}, 1000.0)
        ctx.check("exit 0 only when no fault is in the summary", summary is not None and not faults)
        ctx.say(f"within bounds: {summary['loop_rate_hz']:.0f} Hz, exit 0" if summary else "")
    else:
        loud = "the play was faulty" in s.message or "no Encoder frame" in s.message
        ctx.check("a fault's exit status says why", loud)
        ctx.check("the summary was written", summary is not None)
        if summary is not None:
            ctx.say(
                f"{s.message} [summary: verdict '{summary.get('verdict')}', loop "
                f"{summary.get('loop_rate_hz') or 0:.0f} Hz, watchdog on "
                f"{summary.get('watchdog_frames', 0)} frames]"
            )


@case(
    "play-display-lost",
    "the display killed (kill -9) 2 s into `play --duration 20 --summary s.json --log plays.h5`",
)
def _(ctx: Ctx) -> None:
    params_file(ctx.root / "p.json")
    with ctx.sim("display") as display:
        ctx.begin()
        t0 = time.monotonic()
        proc = ctx.popen(
            "play", "p.json", "--port", "display", "--duration", 20,
            "--summary", "s.json", "--log", "plays.h5",
        )  # fmt: skip
        time.sleep(3.0)  # start-up, then about 2 s of play
        display.stop(signal.SIGKILL)
        s = ctx.finish(proc, t0, expect=7)
    (ctx.root / "display").unlink(missing_ok=True)  # a killed simulator cannot remove it
    ctx.check("one line: the display lost, 0 V sent", one_line(s, "0 V was sent", code=7))
    ctx.check(
        "the line names what was written", "summary s.json and log plays.h5 written" in s.message
    )
    from tissuecli.formats.hdf5 import group_names, read_group

    names = group_names(ctx.root / "plays.h5", "plays")
    columns, attrs = read_group(ctx.root / "plays.h5", f"plays/{names[0]}")
    ctx.check("the log kept, marked incomplete", len(columns["time"]) > 0 and not attrs["complete"])
    summary_path = ctx.root / "s.json"
    summary = json.loads(summary_path.read_text()) if summary_path.exists() else {}
    ctx.check("the summary written up to the loss", summary.get("verdict") == "display lost")
    ctx.say(
        f"log of {len(columns['time'])} frames kept (incomplete); summary of "
        f"{summary.get('frames', 0)} frames written (verdict 'display lost'); the line ends "
        "'(summary s.json and log plays.h5 written)'"
    )


@case("play-check-xdot2", "`play --check` of x,xdot^2 with S = 1e6 N s^2/m^2", fast=True)
def _(ctx: Ctx) -> None:
    doc = {"model": {"f0": "x", "f1": "xdot^2"}, "parameters": {"K": 350, "S": 1e6, "M": 0.05}}
    (ctx.root / "s.json").write_text(json.dumps(doc))
    ctx.begin()
    s = ctx.run("play", "s.json", "--check", expect=1)
    ctx.check("refused: damping too strong", one_line(s, "cannot render", "damping too strong"))


# ---- kill -9


@case(
    "kill9-record",
    "`kill -9` of `record` 0.5-2 s in (3 times), into a file holding an earlier session",
)
def _(ctx: Ctx) -> None:
    seq, clk = _clean(3000)
    frames = sample_frames(seq, clk)
    with FakeForceps(good_info(), frames[:600]) as dev:
        subprocess.run(
            [sys.executable, "-m", "tissuecli", "record", "--port", dev.path, "--out",
             "grasp.h5", "--session", "earlier", "--duration", "0.5", "--quiet"],
            cwd=ctx.root, capture_output=True, check=True, timeout=60,
        )  # fmt: skip
    earlier = session_digest(ctx.root / "grasp.h5", "earlier")
    ctx.begin()
    ctx.allow("grasp.h5")  # sessions are added to it; the earlier one is compared below
    lost = []
    rng = np.random.default_rng(0)
    for k in range(3):
        with FakeForceps(good_info(), frames) as dev:
            t0 = time.monotonic()
            proc = ctx.popen(
                "record", "--port", dev.path, "--out", "grasp.h5", "--session", f"k{k}"
            )
            dev.started.wait(20)
            t_start = time.monotonic()
            time.sleep(float(rng.uniform(0.5, 2.0)))
            sent = (time.monotonic() - t_start) * 1000.0  # frames the device had sent
            proc.kill()
            ctx.finish(proc, t0, expect=-signal.SIGKILL)
        s = read_session(ctx.root / "grasp.h5", f"k{k}")
        ctx.check(f"kill {k}: readable, incomplete", s.meta.get("complete") is False)
        lost.append(max(sent - len(s), 0.0) / 1000.0)
    ctx.check(
        "the earlier session untouched", session_digest(ctx.root / "grasp.h5", "earlier") == earlier
    )
    rows = {r["name"]: r["status"] for r in list_sessions(ctx.root / "grasp.h5")}
    ctx.check("listed: earlier complete, the killed incomplete", rows.get("earlier") == "complete")
    ctx.say(
        f"file opens; earlier session identical; killed sessions 'incomplete'; at most "
        f"{max(lost):.2f} s lost (sent before the kill, not stored)"
    )


# --------------------------------------------------------------------------- running


@contextlib.contextmanager
def _this_checkout() -> Iterator[None]:
    """Every command and simulator a case starts runs the tissuecli of this checkout
    (PYTHONPATH first), not whichever one an editable install points at."""
    before = os.environ.get("PYTHONPATH")
    os.environ["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), before) if p)
    try:
        yield
    finally:
        if before is None:
            del os.environ["PYTHONPATH"]
        else:
            os.environ["PYTHONPATH"] = before


def run_case(c: Case, tmpfs: bool, **options: Any) -> Result:
    """Run one case in a fresh temporary directory and audit what it left; ``options``
    tune a case (``sigint_runs``)."""
    res = Result(c.name, c.tried)
    t0 = time.monotonic()
    with _this_checkout(), tempfile.TemporaryDirectory(prefix="tissuecli-rel-") as tmp:
        ctx = Ctx(res, Path(tmp), tmpfs, options)
        try:
            c.fn(ctx)
            audit(ctx)
        except Exception as exc:  # the harness or a check broke: shown, never hidden
            res.error = f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
        finally:
            for cleanup in reversed(ctx.cleanups):
                with contextlib.suppress(Exception):
                    cleanup()
    res.seconds = time.monotonic() - t0
    return res


def run_cases(
    names: Sequence[str] | None = None, tmpfs: bool = True, **options: Any
) -> list[Result]:
    """Run the cases whose name holds one of ``names`` (all if None)."""
    chosen = [c for c in CASES if names is None or any(n in c.name for n in names)]
    return [run_case(c, tmpfs, **options) for c in chosen]


def _cell(text: str, width: int = SHOWN) -> str:
    text = " ".join(text.split()).replace("|", "\\|")
    return text if len(text) <= width else text[: width - 1] + "…"


def table(results: Sequence[Result]) -> str:
    """The markdown table of the results."""
    lines = [
        "| case | what was tried | exit | tracebacks | data destroyed | files damaged "
        "| message / behaviour | holds |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        keys = [s for s in r.steps if s.key] or r.steps
        codes = "/".join("-" if s.code is None else str(s.code) for s in keys) or "-"
        if len(keys) > 6:  # a sweep: how often each code came
            counts: dict[str, int] = {}
            for s in keys:
                counts[str(s.code)] = counts.get(str(s.code), 0) + 1
            codes = ", ".join(f"{c} ({n}x)" for c, n in counts.items())
        damaged = r.damaged + [f"leftover {x}" for x in r.leftovers]
        tbs = r.tracebacks
        message = "; ".join(x for x in r.said if x) or (keys[-1].message if keys else "")
        verdict = r.verdict
        if r.failures or r.partial:
            verdict += ": " + "; ".join(r.failures + r.partial)
        lines.append(
            f"| `{r.name}` | {_cell(r.tried)} | {codes} | {tbs} | "
            f"{_cell(', '.join(r.destroyed)) or 0} | {_cell(', '.join(damaged)) or 0} | "
            f"{_cell(message, 2 * SHOWN)} | {_cell(verdict, 2 * SHOWN)} |"
        )
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> list[Result]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", action="append", help="run the cases whose name holds this")
    ap.add_argument("--list", action="store_true", help="list the cases and exit")
    ap.add_argument(
        "--no-tmpfs", action="store_true", help="file-size limit even as root (no mount)"
    )
    ap.add_argument("--json", type=Path, help="also write the results here, as JSON")
    ap.add_argument(
        "--sigint-runs", type=int, default=SIGINT_RUNS, help="Ctrl-C trials of sigint-early"
    )
    args = ap.parse_args(argv)
    if args.list:
        for c in CASES:
            print(f"{c.name:<26} {c.tried}")
        return []
    tmpfs = os.geteuid() == 0 and not args.no_tmpfs and shutil.which("mount") is not None
    chosen = [c for c in CASES if not args.only or any(n in c.name for n in args.only)]
    if not chosen:
        ap.error(f"no case name holds {args.only}")
    print(
        f"{len(chosen)} cases; storage faults on "
        f"{'a tmpfs' if tmpfs else 'the file-size limit (RLIMIT_FSIZE)'}",
        file=sys.stderr,
    )
    results = []
    t0 = time.monotonic()
    for c in chosen:
        r = run_case(c, tmpfs, sigint_runs=args.sigint_runs)
        results.append(r)
        print(f"  {r.name:<26} {r.verdict:<7} {r.seconds:5.1f} s", file=sys.stderr)
    print(table(results))
    held = sum(r.verdict == "yes" for r in results)
    partly = sum(r.verdict == "partly" for r in results)
    print(
        f"\n{len(results)} cases: {held} hold, {partly} partly, {len(results) - held - partly} "
        f"do not; {sum(len(r.steps) for r in results)} commands run, "
        f"{sum(r.tracebacks for r in results)} with a traceback; "
        f"{time.monotonic() - t0:.0f} s"
    )
    if args.json:
        args.json.write_text(
            json.dumps(
                [
                    {
                        "case": r.name,
                        "tried": r.tried,
                        "verdict": r.verdict,
                        "failures": r.failures,
                        "partial": r.partial,
                        "said": r.said,
                        "steps": [
                            {"argv": s.argv, "exit": s.code, "message": s.message} for s in r.steps
                        ],
                    }
                    for r in results
                ],
                indent=1,
            )
        )
    return results


if __name__ == "__main__":
    main()
