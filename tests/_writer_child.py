"""Writer process for the crash tests: appends deterministic rows until killed.

Usage: ``python _writer_child.py FILE [--interval S] [--block N] [--sleep S] [--no-fsync]``

Prints ``flushed N`` (line-buffered) every time N rows have been committed to disk,
so the parent knows what must survive a kill -9. SIGTERM is turned into
KeyboardInterrupt; the writer then closes cleanly and the child prints ``total N``.
"""

from __future__ import annotations

import argparse
import signal
import sys
import time
from pathlib import Path
from types import FrameType

import numpy as np
from numpy.typing import NDArray

# run as a script from tests/: make the package importable without installing it
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

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
    args = parser.parse_args()
    signal.signal(signal.SIGTERM, _terminate)

    writer = session_writer(
        args.file,
        args.name,
        meta={"tissue": "test"},
        calibration=CALIBRATION,
        flush_interval_s=args.interval,
        fsync=not args.no_fsync,
    )
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


if __name__ == "__main__":
    main()
