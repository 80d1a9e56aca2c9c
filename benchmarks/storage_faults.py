"""Storage faults: a writer running out of room, then a check of what it left.

Usage::

    python benchmarks/storage_faults.py [--trials 100] [--seed 0]
    sudo python benchmarks/storage_faults.py --tmpfs --trials 20   # also a real full disk

Part 1 (no root needed): the test suite's writer child (tests/formats/_writer_child.py) runs
under a random file-size limit (RLIMIT_FSIZE, SIGXFSZ ignored: writes past it fail
with EFBIG), either as shipped ("guarded": room is checked before every flush) or
with the checks turned off ("unguarded": HDF5 itself runs into the limit, which
tests the careful way out). After each run the limit is lifted and the file is
checked: exit code (1, or a signal), the one-line message, rows committed (the last
"flushed N" the child printed) against rows readable with exactly the values
written, whether a new session can still be added, and whether a file without a
committed row was removed.

Part 2 (``--tmpfs``, root only): a real tmpfs of a few MiB, partly filled first, then
``tissuecli record`` from a simulated forceps until the disk is full, half of the
time with another process filling the disk during the recording; then
``tissuecli play --log`` the same way; and the writer child unguarded on the
full tmpfs (HDF5 meeting ENOSPC itself).
"""

from __future__ import annotations

import argparse
import collections
import os
import random
import re
import resource
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "formats"))

from _writer_child import expected_rows  # noqa: E402

from tissuecli.core.errors import TissueError  # noqa: E402
from tissuecli.core.session import Session  # noqa: E402
from tissuecli.formats.sessions import read_session, write_session  # noqa: E402

CHILD = ROOT / "tests" / "formats" / "_writer_child.py"


def one_line(stderr: str) -> str | None:
    """The "Error: ..." line if stderr is exactly that, else None."""
    lines = [line for line in stderr.splitlines() if line.strip()]
    if len(lines) == 1 and lines[0].startswith("Error: ") and "Traceback" not in stderr:
        return lines[0]
    return None


def check_file(path: Path, name: str, committed: int, exact: bool) -> tuple[int, str]:
    """Rows readable in session `name` and the verdict on the file afterwards."""
    if not path.exists():
        return 0, "no file (nothing committed)" if committed == 0 else "LOST FILE"
    try:
        s = read_session(path, name, raw=exact)
    except TissueError as exc:
        return 0, f"DAMAGED: {exc}"
    n = len(s)
    if n < committed:
        return n, "LOST ROWS"
    if exact:
        want = expected_rows(0, n)
        if not all(
            np.array_equal(s.meta["raw"][key] if key.startswith("raw/") else getattr(s, key), v)
            for key, v in want.items()
        ):
            return n, "WRONG VALUES"
    # the file must take another session once there is room: tried on a copy on the
    # system's temporary drive, since the file itself may fill the small disk
    with tempfile.TemporaryDirectory() as scratch:
        copy = Path(scratch) / path.name
        shutil.copyfile(path, copy)
        try:
            t = np.arange(2000) * 1e-3
            write_session(copy, Session(t, np.ones_like(t), t * 1e-3, name="after"))
            if len(read_session(copy, name)) != n or len(read_session(copy, "after")) != 2000:
                return n, "CHANGED BY A LATER SESSION"
        except TissueError as exc:
            return n, f"NOT WRITABLE: {exc}"
    return n, "ok"


def child_trial(
    path: Path, limit: int | None, unguarded: bool, rng: random.Random, room: Any = None
) -> dict:
    """One run of the writer child, then :func:`check_file` (after `room()` frees space)."""
    cmd = [
        sys.executable,
        str(CHILD),
        str(path),
        "--interval",
        "0",
        "--sleep",
        "0",
        "--block",
        str(rng.choice([20, 137, 500, 4096, 6000])),
    ]
    if rng.random() < 0.5:
        cmd.append("--no-fsync")
    if limit is not None:
        cmd += ["--fsize-limit", str(limit)]
    if unguarded:
        cmd.append("--unguarded")
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    flushed = [int(x.split()[1]) for x in r.stdout.splitlines() if x.startswith("flushed")]
    committed = flushed[-1] if flushed else 0
    if room is not None:
        room()
    readable, verdict = check_file(path, "crash", committed, exact=True)
    return {
        "code": r.returncode,
        "line": one_line(r.stderr),
        "committed": committed,
        "readable": readable,
        "verdict": verdict,
        "stderr": r.stderr,
    }


def table(title: str, rows: list[dict]) -> None:
    print(f"\n{title}")
    codes = collections.Counter(r["code"] for r in rows)
    lines = sum(r["line"] is not None for r in rows)
    verdicts = collections.Counter(r["verdict"].split(":")[0] for r in rows)
    committed = sum(r["committed"] for r in rows)
    readable = sum(r["readable"] for r in rows)
    short = sum(r["readable"] < r["committed"] for r in rows)
    print(
        f"  trials {len(rows)}; exit codes {dict(sorted(codes.items()))}; "
        f"one-line error {lines}/{len(rows)}"
    )
    print(
        f"  rows committed {committed}, readable afterwards {readable}; "
        f"trials with fewer readable than committed: {short}"
    )
    print(f"  files afterwards: {dict(sorted(verdicts.items()))}")
    causes = collections.Counter(_cause(r["line"]) for r in rows if r["line"])
    print(f"  causes named: {dict(causes)}")
    for r in rows:
        if (
            r["verdict"] not in ("ok", "no file (nothing committed)")
            or r["code"] != 1
            or not r["line"]
        ):
            print("  PROBLEM:", r["code"], r["verdict"], r["stderr"][-300:])


CAUSES = (
    "not enough free space",
    "leaves no room",
    "file size limit reached",
    "disk full",
    "disk quota exceeded",
    "input/output error",
)


def _cause(line: str) -> str:
    """What the message names: refused at the start, or the fault that stopped writing."""
    for cause in CAUSES:
        if cause in line:
            return {"leaves no room": "file size limit: refused at start"}.get(cause, cause)
    return line[:60]


def part1(args: argparse.Namespace, rng: random.Random) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        for unguarded in (False, True):
            rows = []
            for k in range(args.trials):
                limit = int(10 ** rng.uniform(5.0, 7.0))  # 100 kB to 10 MB
                rows.append(child_trial(Path(tmp) / f"t{unguarded}{k}.h5", limit, unguarded, rng))
            table(
                f"file-size limit 0.1-10 MB, writer {'unguarded' if unguarded else 'guarded'} "
                f"(python benchmarks/storage_faults.py --trials {args.trials} --seed {args.seed})",
                rows,
            )


# -------------------------------------------------------------------------- tmpfs


class Tmpfs:
    def __init__(self, path: Path, size: str) -> None:
        self.path = path
        path.mkdir(parents=True, exist_ok=True)
        subprocess.run(
            ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], check=True
        )

    def clear(self) -> None:
        for p in self.path.iterdir():
            p.unlink()

    def fill(self, nbytes: int) -> None:
        with open(self.path / "fill", "wb") as f:
            try:
                f.write(b"\0" * nbytes)
            except OSError:
                pass

    def unfill(self) -> None:
        (self.path / "fill").unlink(missing_ok=True)

    def close(self) -> None:
        subprocess.run(["umount", str(self.path)], check=False)


def filler(directory: Path, delay: float) -> subprocess.Popen:
    """Another program that fills the disk after `delay` s."""
    return subprocess.Popen(
        ["sh", "-c", f"sleep {delay}; dd if=/dev/zero of={directory}/other bs=64k 2>/dev/null"]
    )


def start_sim(kind: str, link: Path, rate: int) -> subprocess.Popen:
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "tissuecli",
            "simulate",
            kind,
            "--link",
            str(link),
            "--rate",
            str(rate),
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    for _ in range(100):
        if link.exists():
            break
        time.sleep(0.05)
    return proc


def part2(args: argparse.Namespace, rng: random.Random) -> None:
    work = Path(tempfile.mkdtemp())
    fs = Tmpfs(work / "disk", "8m")
    try:
        forceps = start_sim("forceps", work / "forceps", 10000)
        rows = []
        for k in range(args.trials):
            fs.clear()
            fs.fill(rng.randint(0, 2 << 20))
            racing = k % 2 == 1
            other = filler(fs.path, rng.uniform(0.5, 3.0)) if racing else None
            out = fs.path / "r.h5"
            r = subprocess.run(
                [
                    sys.executable,
                    "-m",
                    "tissuecli",
                    "record",
                    "--port",
                    str(work / "forceps"),
                    "--out",
                    str(out),
                    "--session",
                    "s",
                    "--duration",
                    "600",
                    "--quiet",
                ],
                capture_output=True,
                text=True,
                timeout=600,
            )
            if other is not None:
                other.wait()
            line = one_line(r.stderr)
            saved = re.search(r"the (\d+) rows committed", line or "")
            committed = int(saved.group(1)) if saved else 0
            for p in fs.path.iterdir():  # room again: only the recording stays
                if p.name != "r.h5":
                    p.unlink()
            readable, verdict = check_file(out, "s", committed, exact=False)
            rows.append(
                {
                    "code": r.returncode,
                    "line": line,
                    "committed": committed,
                    "readable": readable,
                    "verdict": verdict,
                    "stderr": r.stderr,
                }
            )
        forceps.terminate()
        table(
            f"tissuecli record at 10 kHz onto an 8 MiB tmpfs, pre-filled 0-2 MiB, another "
            f"program filling it during every second trial (--tmpfs --trials {args.trials})",
            rows,
        )

        display = start_sim("display", work / "display", 1000)
        params = work / "liver.json"
        t = np.arange(3000) * 1e-3
        x = 2e-3 * (1 - np.cos(2 * np.pi * 3 * t))
        write_session(work / "fit.h5", Session(t, 350 * x + 0.01 * np.sin(t), x, name="s"))
        subprocess.run(
            [sys.executable, "-m", "tissuecli", "fit", str(work / "fit.h5"), "--out", str(params)],
            capture_output=True,
            check=True,
        )
        rows = []
        for k in range(max(2, args.trials // 4)):
            fs.clear()
            fs.fill(6 << 20)
            other = filler(fs.path, rng.uniform(0.5, 2.0)) if k % 2 else None
            out = fs.path / "plays.h5"
            r = subprocess.run(
                [
                    sys.executable,
                    "-m",
                    "tissuecli",
                    "play",
                    str(params),
                    "--port",
                    str(work / "display"),
                    "--duration",
                    "600",
                    "--log",
                    str(out),
                ],
                capture_output=True,
                text=True,
                timeout=900,
            )
            if other is not None:
                other.wait()
            line = one_line(
                r.stderr.split("\r")[-1]
                if "\r" in r.stderr
                else "\n".join(x for x in r.stderr.splitlines() if not x.startswith("playing"))
            )
            saved = re.search(r"the (\d+) rows committed", line or "")
            ok = out.exists() and saved is not None
            rows.append(
                {
                    "code": r.returncode,
                    "line": line,
                    "committed": int(saved.group(1)) if saved else 0,
                    "readable": _play_rows(out) if ok else 0,
                    "verdict": "ok" if ok or not out.exists() else "DAMAGED",
                    "stderr": r.stderr[-400:],
                }
            )
        display.terminate()
        table("tissuecli play --log onto the same tmpfs with 2 MiB free", rows)

        for unguarded in (False, True):
            rows = []
            for _ in range(args.trials):
                fs.clear()
                fs.fill(rng.randint(0, 7 << 20))
                out = fs.path / "c.h5"
                rows.append(child_trial(out, None, unguarded, rng, room=fs.unfill))
            table(
                f"writer child {'unguarded' if unguarded else 'guarded'} on the 8 MiB tmpfs "
                "pre-filled 0-7 MiB (HDF5 itself meets ENOSPC when unguarded)",
                rows,
            )
    finally:
        fs.close()
        shutil.rmtree(work, ignore_errors=True)


def _play_rows(path: Path) -> int:
    from tissuecli.formats.hdf5 import group_names, read_group
    from tissuecli.formats.playlog import PLAYS

    total = 0
    for name in group_names(path, PLAYS):
        columns, _ = read_group(path, f"{PLAYS}/{name}")
        total += len(columns["time"])
    return total


def metadata_growth() -> None:
    """Largest growth of the file per flush beyond the data chunks, bytes."""
    from tissuecli.formats.hdf5 import file_size
    from tissuecli.formats.sessions import session_writer

    worst = 0
    with tempfile.TemporaryDirectory() as tmp:
        for block in (1, 100, 999, 4096, 20000):
            w = session_writer(
                Path(tmp) / f"m{block}.h5",
                "s",
                meta={},
                calibration=None,
                flush_interval_s=0,
                fsync=False,
            )
            for i in range(300 if block < 5000 else 40):
                before, n_old = file_size(w._file), w.rows_flushed
                w.set_attrs(frames_lost=i, note="x" * (i % 7))
                w.append(expected_rows(w.rows, w.rows + block))
                chunks = w._chunk_bytes(n_old, w.rows_flushed)
                worst = max(worst, file_size(w._file) - before - chunks)
            w.close()
    print(
        f"largest HDF5 metadata growth in one flush (beyond data chunks): {worst} bytes; "
        "headroom kept: 1048576 bytes"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--tmpfs", action="store_true", help="also a real tmpfs (root only)")
    args = ap.parse_args()
    rng = random.Random(args.seed)
    signal.signal(signal.SIGXFSZ, signal.SIG_DFL)
    assert resource.getrlimit(resource.RLIMIT_FSIZE)[0] == resource.RLIM_INFINITY
    metadata_growth()
    part1(args, rng)
    if args.tmpfs:
        if os.geteuid() != 0:
            sys.exit("--tmpfs needs root (mount)")
        part2(args, rng)


if __name__ == "__main__":
    main()
