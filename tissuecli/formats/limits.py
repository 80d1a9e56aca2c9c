"""What a reader may allocate: a file's declared sizes are checked against what it holds
and against the memory the process may use, before anything is allocated.

A file states its own sizes (an HDF5 dataset's shape, a .npy header's shape, a zip
member's inflated size). Trusting them lets a 2 kB file ask for terabytes, so every
reader checks them first:

* a compressed store may inflate at most :data:`MAX_INFLATION` times beyond the whole
  file's size (sensor data compresses 1.1-3 times; a run of zeros 1000 times);
* whatever is read whole must fit in :func:`memory_room`, the memory this process may
  still take (available RAM, and the address-space limit ``ulimit -v`` if set).
"""

from __future__ import annotations

import os
import resource

from ..core.errors import InputError

#: a dataset may hold at most this many times more bytes than the whole file (compressed
#: data); beyond that its size is damage or a decompression bomb
MAX_INFLATION = 64
#: slack for small files: headers, one chunk
SLACK_BYTES = 1 << 20
#: rows read and written at a time by the streaming readers (24 MB of float64 triples)
BLOCK_ROWS = 1 << 20


def memory_room() -> int:
    """Bytes this process may still allocate: 80 % of the available memory, and no more
    than the address-space limit leaves (``ulimit -v``)."""
    room = 8 << 30
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    room = int(line.split()[1]) * 1024 * 8 // 10
                    break
    except (OSError, ValueError, IndexError):
        pass
    for limit in (resource.RLIMIT_AS, getattr(resource, "RLIMIT_DATA", resource.RLIMIT_AS)):
        soft, _ = resource.getrlimit(limit)
        if soft != resource.RLIM_INFINITY:
            room = min(room, max(0, soft - _mapped_bytes()))
    return room


def _mapped_bytes() -> int:
    """This process's virtual size, bytes (0 if unknown)."""
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return 0


def gigabytes(n: float) -> str:
    return f"{n / 1e9:.3g} GB" if n >= 1e8 else f"{n / 1e6:.3g} MB"


def check_declared(declared: int, file_bytes: int, what: str) -> None:
    """Refuse `what` if the `declared` bytes it would inflate to are more than its file
    of `file_bytes` can hold, or more than this process may allocate.

    Raises
    ------
    InputError
        One line with both figures.
    """
    if declared > MAX_INFLATION * file_bytes + SLACK_BYTES:
        raise InputError(
            f"{what} declares {gigabytes(declared)} of values but its file holds "
            f"{gigabytes(file_bytes)} (more than {MAX_INFLATION} times as much: damaged, or a "
            "decompression bomb); give the original file"
        )
    room = memory_room()
    if declared > room:
        raise InputError(
            f"{what} needs {gigabytes(declared)} of memory to read and this process may take "
            f"{gigabytes(room)}; free memory, or split the recording"
        )
