"""Writer process for the crash tests: appends deterministic rows until killed.

Usage: ``python _writer_child.py FILE [--interval S] [--block N] [--sleep S] [--no-fsync]
[--fsize-limit BYTES [--unguarded]]``

Prints ``flushed N`` (line-buffered) every time N rows have been committed to disk,
so the parent knows what must survive a kill -9. SIGTERM is turned into
KeyboardInterrupt; the writer then closes cleanly and the child prints ``total N``.

``--fsize-limit`` sets RLIMIT_FSIZE (with SIGXFSZ ignored, so writes past it fail
with EFBIG, as on a full disk); a storage fault then ends the child like the command
line would: ``Error: ...`` on stderr and exit code 1. ``--unguarded`` turns off the
writer's room checks, so that HDF5 itself runs into the limit.
"""

from __future__ import annotations

import argparse
import resource
import signal
import sys
import time
from pathlib import Path
from types import FrameType

import numpy as np
from numpy.typing import NDArray

# run as a script from tests/: make the package importable without installing it
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from tissuecli.core.errors import StorageError  # noqa: E402
from tissuecli.formats import writer as _writer  # noqa: E402
from tissuecli.formats.sessions import session_writer  # noqa: E402

CALIBRATION = {"force": {"gain": 0.01, "offset": -0.5}, "position": {"gain": 1e-6, "offset": 0.0}}


def expected_rows(start: int, stop: int) -> dict[str, NDArray]:
    """Row values the child writes for row indices start..stop-1 (exact in float64)."""
    i = np.arange(start, stop, dtype=np.int64)
    return {
        "time": i * 1e-3,
        "force": (i % 1000) * 0.25,
        "position": i * 1e-6,
        "raw/counts": np.stack([i % 30000, -(i % 30000)], axis=1).astype(np.int16),
        "raw/sequence": i.astype(np.uint32),
        "raw/device_clock": i * 10,
        "raw/host_time": i * 1e-3 + 0.5,
    }


def _terminate(signum: int, frame: FrameType | None) -> None:
    raise KeyboardInterrupt


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("file")
    parser.add_argument("--interval", type=float, default=0.05)
    parser.add_argument("--block", type=int, default=20)
    parser.add_argument("--sleep", type=float, default=0.002)
    parser.add_argument("--no-fsync", action="store_true")
    parser.add_argument("--name", default="crash")
    parser.add_argument("--fsize-limit", type=int, default=None)
    parser.add_argument("--unguarded", action="store_true")
    args = parser.parse_args()
    signal.signal(signal.SIGTERM, _terminate)
    if args.fsize_limit is not None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (args.fsize_limit, resource.RLIM_INFINITY))
    if args.unguarded:
        _writer.check_free_space = lambda *a, **k: None
        _writer.make_room = lambda *a, **k: None

    try:
        writer = session_writer(
            args.file,
            args.name,
            meta={"tissue": "test"},
            calibration=CALIBRATION,
            flush_interval_s=args.interval,
            fsync=not args.no_fsync,
        )
    except StorageError as exc:
        print(f"Error: {exc}", file=sys.stderr)
        sys.exit(1)
    try:
        with writer:
            last = 0
            while True:
                writer.append(expected_rows(writer.rows, writer.rows + args.block))
                if writer.rows_flushed != last:
                    last = writer.rows_flushed
                    print(f"flushed {last}", flush=True)
                if args.sleep:
                    time.sleep(args.sleep)
    except KeyboardInterrupt:
        print(f"total {writer.rows}", flush=True)
    except StorageError as exc:
        print(f"Error: {exc}", file=sys.stderr)
        sys.exit(1)


if __name__ == "__main__":
    main()
