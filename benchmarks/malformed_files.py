"""Malformed HDF5 session files: how `sessions`, `fit` and `export` answer them.

Usage::

    python benchmarks/malformed_files.py [--examples 2000] [--seed 0] [--cli 40]

Draws files from the test suite's generator (tests/formats/_malformed.py: datasets of text,
compound records, booleans, complex numbers, references, single values or two
columns; missing datasets, groups or dangling links in their place; counters stored
as text; files cut at a random byte or made of random bytes) and runs the library
functions behind the three commands on each, in process. Every call must return or
raise a one-line TissueError; anything else is counted as a traceback, by the
tissuecli subpackage that raised it (formats: reading the file; identify: the fit
of numbers read without fault). The first
``--cli`` files are also run through the command line in subprocesses, checking the
exit code (0, or 1 with one line "Error: ...") and that no traceback is printed.
"""

from __future__ import annotations

import argparse
import collections
import subprocess
import sys
import tempfile
import traceback
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "formats"))

from _malformed import clean, specs, write_spec  # noqa: E402
from hypothesis import HealthCheck, given, seed, settings  # noqa: E402

from tissuecli.app.fit import fit_file  # noqa: E402
from tissuecli.app.transfer import export_csv  # noqa: E402
from tissuecli.formats.sessions import list_sessions, read_session  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--examples", type=int, default=2000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cli", type=int, default=40, help="files also run through the CLI")
    ap.add_argument("--show", type=int, default=1, help="tracebacks to print in full")
    args = ap.parse_args()
    outcomes: collections.Counter[tuple[str, str]] = collections.Counter()
    kinds: collections.Counter[str] = collections.Counter()
    tracebacks: list[str] = []
    cli: collections.Counter[str] = collections.Counter()
    drawn = [0]

    @seed(args.seed)
    @settings(
        max_examples=args.examples,
        deadline=None,
        database=None,
        suppress_health_check=list(HealthCheck),
    )
    @given(spec=specs())
    def run(spec) -> None:  # noqa: ANN001
        drawn[0] += 1
        for kind in spec.columns.values():
            kinds[kind] += 1
        kinds[f"file: {spec.corruption}"] += 1
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "m.h5"
            write_spec(path, spec)
            calls = {
                "sessions": lambda: list_sessions(path),
                "read": lambda: read_session(path, spec.name, raw=True),
                "export": lambda: export_csv(path, spec.name, Path(tmp) / "o.csv"),
                "fit": lambda: fit_file(path, spec.name),
            }
            for label, call in calls.items():
                try:
                    outcomes[(label, clean(call))] += 1
                except BaseException as exc:  # a traceback a user would see
                    where = _origin(exc)
                    outcomes[(label, f"traceback in {where}")] += 1
                    tracebacks.append(f"{where}: {spec}\n{traceback.format_exc()}")
            if drawn[0] <= args.cli:
                for command in (["sessions"], ["fit"], ["export", "--csv", f"{tmp}/c.csv"]):
                    r = subprocess.run(
                        [sys.executable, "-m", "tissuecli", command[0], str(path), *command[1:]],
                        capture_output=True,
                        text=True,
                        timeout=120,
                    )
                    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
                    ok = "Traceback" not in r.stderr + r.stdout and (
                        r.returncode == 0
                        or (
                            r.returncode == 1 and len(lines) == 1 and lines[0].startswith("Error: ")
                        )
                    )
                    cli[f"{command[0]} {'clean' if ok else 'TRACEBACK'} exit {r.returncode}"] += 1

    run()
    print(f"{drawn[0]} malformed files drawn (seed {args.seed})")
    origins = sorted({key[1] for key in outcomes if key[1].startswith("traceback")})
    print(f"{'call':<10} {'result':>7} {'1-line error':>12} " + " ".join(origins))
    for label in ("sessions", "read", "export", "fit"):
        print(
            f"{label:<10} {outcomes[(label, 'ok')]:>7} {outcomes[(label, 'error')]:>12} "
            + " ".join(f"{outcomes[(label, o)]:>{len(o)}}" for o in origins)
        )
    if not origins:
        print("no traceback")
    print("command-line runs:", dict(sorted(cli.items())))
    print("dataset kinds and file corruptions drawn:")
    for kind, count in sorted(kinds.items()):
        print(f"  {kind:<28} {count}")
    for text in tracebacks[: args.show]:
        print(text)


def _origin(exc: BaseException) -> str:
    """The tissuecli subpackage whose code raised `exc` (its innermost tissuecli frame)."""
    where = "?"
    for frame, _ in traceback.walk_tb(exc.__traceback__):
        parts = Path(frame.f_code.co_filename).parts
        if "tissuecli" in parts[:-1]:
            i = len(parts) - 1 - parts[::-1].index("tissuecli")
            where = "tissuecli/" + (parts[i + 1] if i + 2 < len(parts) else parts[-1])
    return where


if __name__ == "__main__":
    main()
