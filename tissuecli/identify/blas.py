"""One BLAS thread while a fit runs.

A fit multiplies thousands of small matrices (a few columns by tens of thousands of
samples: each shape node of a law with time constants forms its own products). A
threaded BLAS wakes its threads for each one, and on a loaded machine each wake-up
waits for a core: a 20,000-sample ramp-and-hold took 17 s of CPU with two threads and
3 s with one. One thread also makes the fit's last bits the same on any number of
cores (a threaded dot product splits its sum where the cores say).
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

_lock = threading.Lock()
_depth = 0
_limits: Any = None


@contextmanager
def one_blas_thread() -> Iterator[None]:
    """BLAS limited to one thread inside; restored as the first of the fits running at
    once in this process found it when the last of them leaves (one ending never lets
    another's threads back). Each entrant sets the limit itself, in case its BLAS
    keeps it per calling thread."""
    global _depth, _limits
    # loaded here: importing the fit stays light
    from threadpoolctl import threadpool_limits

    with _lock:
        limits = threadpool_limits(limits=1, user_api="blas")
        if _depth == 0:
            _limits = limits
        _depth += 1
    try:
        yield
    finally:
        with _lock:
            _depth -= 1
            if _depth == 0:
                _limits.restore_original_limits()
                _limits = None
