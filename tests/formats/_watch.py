"""Whether a file was opened or read while something ran: Linux inotify through ctypes.

Used to show that reading an untrusted input never touches another file: the kernel
reports every open and read of the watched file, whatever library (HDF5 in C, say)
does it.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import struct
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

IN_ACCESS = 0x001
IN_OPEN = 0x020
IN_NONBLOCK = 0o4000


class Touches:
    """Open and read events seen on the watched file."""

    def __init__(self) -> None:
        self.opens = 0
        self.reads = 0


@contextmanager
def watch(path: Path) -> Iterator[Touches]:
    """Count opens and reads of `path` during the block (raises OSError without inotify)."""
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    fd = libc.inotify_init1(IN_NONBLOCK)
    if fd < 0:
        raise OSError(ctypes.get_errno(), "inotify_init1 failed")
    touches = Touches()
    try:
        wd = libc.inotify_add_watch(fd, os.fsencode(path), IN_OPEN | IN_ACCESS)
        if wd < 0:
            raise OSError(ctypes.get_errno(), "inotify_add_watch failed")
        yield touches
        while True:
            try:
                data = os.read(fd, 65536)
            except BlockingIOError:
                break
            offset = 0
            while offset < len(data):
                _, mask, _, length = struct.unpack_from("iIII", data, offset)
                touches.opens += bool(mask & IN_OPEN)
                touches.reads += bool(mask & IN_ACCESS)
                offset += 16 + length
    finally:
        os.close(fd)
