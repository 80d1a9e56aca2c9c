"""Busy processes beside a benchmark: ``n`` interpreters spinning ``while 1: pass``, the
load that a loop or a test suite must keep working under on a shared machine."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager


@contextmanager
def busy(n: int) -> Iterator[None]:
    """Run ``n`` CPU-bound processes while the block runs; killed and reaped on leaving,
    whatever ends the block."""
    hogs = [subprocess.Popen([sys.executable, "-c", "while 1: pass"]) for _ in range(n)]
    try:
        yield
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait()
