"""Disk space for the HDF5 writers: enough free space before a file is created, blocks
reserved ahead of every write, and storage faults named in words.

HDF5 has no way back from a failed write: a flush that runs out of space half way has
already rewritten the superblock and other metadata in place, and the file then claims
bytes that never reached the disk ("truncated file"). So the writers never let HDF5 be
the one to find out. Before each flush they make sure the bytes it can need exist:

* the file-size limit of the process (``ulimit -f``, ``RLIMIT_FSIZE``) is checked
  against the file's end plus what the flush may allocate;
* on Linux the blocks are reserved beyond the end of the file with
  ``fallocate(FALLOC_FL_KEEP_SIZE)``, which fails with ENOSPC or EDQUOT *before*
  anything is written (and also guards against other programs filling the disk);
* elsewhere, or on file systems without ``fallocate``, the free space is compared
  with the need (``os.fstatvfs``).

A writer that is refused stops cleanly: the file is exactly as after its last commit
plus a few attributes written into the room kept in reserve (:data:`HEADROOM_BYTES`).
"""

from __future__ import annotations

import contextlib
import errno
import math
import os
import re
import sys
from collections.abc import Iterator
from typing import Any

from ..core.errors import StorageError

#: Room kept beyond the end of a file being written, bytes: HDF5 metadata of a flush
#: (chunk-index nodes, object-header continuations, attribute heaps) and the closing
#: attributes. Measured growth beyond the data chunks: at most 30 KB per flush.
HEADROOM_BYTES = 1 << 20
#: Seconds of data that must fit on the disk before a recording or a play log starts.
PREFLIGHT_S = 10.0

_CAUSES = {
    errno.ENOSPC: "disk full",
    errno.EDQUOT: "disk quota exceeded",
    errno.EFBIG: "file size limit reached",
    errno.EIO: "input/output error (drive failing or removed?)",
    errno.EROFS: "the file system is read-only",
    errno.ENODEV: "the drive was removed",
    errno.ENXIO: "the drive was removed",
}
_HDF5_ERRNO = re.compile(r"errno = (\d+)")


def fault_errno(exc: BaseException) -> int | None:
    """The OS error number behind an OSError or an h5py/HDF5 error, if it names one."""
    number = getattr(exc, "errno", None)
    if isinstance(number, int) and number > 0:
        return number
    # h5py raises RuntimeError on write failures; HDF5's text carries "errno = N"
    match = _HDF5_ERRNO.search(str(exc))
    return int(match.group(1)) if match else None


def fault_cause(exc: BaseException) -> str:
    """A few words naming a storage fault: 'disk full', 'file size limit reached', ..."""
    number = fault_errno(exc)
    if number in _CAUSES:
        return _CAUSES[number]
    if number is not None:
        return os.strerror(number).lower()
    text = str(exc).strip().splitlines()
    return (text[0] if text else type(exc).__name__)[:120]


def is_storage_fault(exc: BaseException) -> bool:
    """True for errors a full, limited, read-only or failing drive causes."""
    return fault_errno(exc) in _CAUSES


def megabytes(n: float) -> str:
    return f"{n / 1e6:.1f} MB" if n >= 1e5 else f"{n / 1e3:.0f} kB"


def file_size_limit() -> int | None:
    """The process's file-size limit in bytes (``ulimit -f``), or None if unlimited."""
    try:
        import resource
    except ImportError:  # not POSIX
        return None
    soft, _ = resource.getrlimit(resource.RLIMIT_FSIZE)
    return None if soft == resource.RLIM_INFINITY or soft < 0 else int(soft)


@contextlib.contextmanager
def lifted_file_size_limit() -> Iterator[None]:
    """Raise the soft file-size limit to the hard one for the duration of the block.

    Used only while HDF5 closes a file whose descriptor was moved to an in-memory file
    (see :func:`detach_descriptor`): HDF5 rewrites its dirty metadata at the same
    offsets, which the limit would refuse even though nothing reaches the disk.
    """
    try:
        import resource
    except ImportError:
        yield
        return
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    lifted = False
    if soft != resource.RLIM_INFINITY and (hard == resource.RLIM_INFINITY or hard > soft):
        try:
            resource.setrlimit(resource.RLIMIT_FSIZE, (hard, hard))
            lifted = True
        except (OSError, ValueError):
            pass
    try:
        yield
    finally:
        if lifted:
            resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))


def free_bytes(where: str | int) -> int | None:
    """Bytes an unprivileged user may still write on the file system of a path or descriptor."""
    try:
        st = os.fstatvfs(where) if isinstance(where, int) else os.statvfs(where)
    except (OSError, AttributeError):
        return None
    return int(st.f_bavail) * int(st.f_frsize)


def preflight_bytes(bytes_per_s: float, seconds: float = PREFLIGHT_S) -> int:
    """Free space a writer needs to start: `seconds` of data plus :data:`HEADROOM_BYTES`.

    At 1 kHz with raw data (48 bytes per sample) that is 0.48 MB + 1 MiB.
    """
    rate = bytes_per_s if math.isfinite(bytes_per_s) and bytes_per_s > 0 else 0.0
    return int(seconds * rate) + HEADROOM_BYTES


def check_free_space(path: str | os.PathLike[str], need: int, *, what: str) -> None:
    """Refuse to start writing `path` when its drive or the file-size limit cannot hold `need`.

    Parameters
    ----------
    path : path
        File to be written (it may not exist yet).
    need : int
        Bytes that must fit, e.g. :func:`preflight_bytes`.
    what : str
        What is about to be written, for the message (e.g. 'the recording').

    Raises
    ------
    StorageError
        Naming the free space (or the limit) and the need.
    """
    name = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(name))
    if not os.path.isdir(directory):
        return  # the caller reports a missing directory in its own words
    free = free_bytes(directory)
    if free is not None and free < need:
        raise StorageError(
            f"not enough free space for {what} in {directory}: {megabytes(free)} free, "
            f"{megabytes(need)} needed (its first data plus {megabytes(HEADROOM_BYTES)} kept "
            "in reserve so that the file closes intact); free some space or write to "
            "another drive"
        )
    limit = file_size_limit()
    try:
        size = os.path.getsize(name)
    except OSError:
        size = 0
    if limit is not None and size + need > limit:
        raise StorageError(
            f"the file size limit of this process ({megabytes(limit)}, see 'ulimit -f') "
            f"leaves no room for {what} in {name} ({megabytes(need)} needed); raise the "
            "limit or write a smaller file"
        )


_FALLOC_FL_KEEP_SIZE = 0x01
_fallocate: Any = None
_fallocate_loaded = False


def _load_fallocate() -> Any:
    """libc's fallocate through ctypes (Linux only); None where it does not exist."""
    global _fallocate, _fallocate_loaded
    if not _fallocate_loaded:
        _fallocate_loaded = True
        if sys.platform.startswith("linux"):
            try:
                import ctypes

                libc = ctypes.CDLL(None, use_errno=True)
                fn = getattr(libc, "fallocate64", None) or libc.fallocate
                fn.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_int64, ctypes.c_int64]
                fn.restype = ctypes.c_int
                _fallocate = fn
            except (OSError, AttributeError):
                _fallocate = None
    return _fallocate


def reserve(fd: int, offset: int, length: int) -> bool:
    """Reserve disk blocks for bytes ``[offset, offset + length)`` of an open file.

    The file's size is left as it is (``FALLOC_FL_KEEP_SIZE``), so HDF5 and readers see
    no change; later writes into the range cannot fail for lack of space.

    Returns
    -------
    bool
        False if the system or file system cannot reserve (the caller then compares
        free space instead).

    Raises
    ------
    OSError
        ENOSPC, EDQUOT, EIO, ... if the blocks cannot be had.
    """
    fn = _load_fallocate()
    if fn is None or length <= 0:
        return False
    import ctypes

    while True:
        if fn(fd, _FALLOC_FL_KEEP_SIZE, offset, length) == 0:
            return True
        number = ctypes.get_errno()
        if number == errno.EINTR:
            continue
        if number in (errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL, errno.ENODEV):
            return False
        raise OSError(number, os.strerror(number))


def make_room(fd: int | None, path: str, end: int, need: int) -> str | None:
    """Make sure `need` bytes can be written past byte `end` of the open file `path`.

    Parameters
    ----------
    fd : int or None
        The file's descriptor, to reserve blocks through; None to compare free space only.
    path : str
        The file, for the free space of its drive.
    end : int
        Current end of the file (HDF5's allocated size), bytes.
    need : int
        Bytes the next writes may allocate, bytes.

    Returns
    -------
    str or None
        None if they can be written; otherwise the cause in words ('disk full',
        'file size limit reached (2.1 MB)').
    """
    limit = file_size_limit()
    if limit is not None and end + need > limit:
        return f"file size limit reached ({megabytes(limit)})"
    where: str | int = path if fd is None else fd
    if fd is not None:
        try:
            if reserve(fd, end, need):
                return None
        except OSError as exc:
            if fault_errno(exc) not in (errno.ENOSPC, errno.EDQUOT):
                return fault_cause(exc)
            return short_of_room(fault_cause(exc), free_bytes(where), need)
    free = free_bytes(where)
    if free is not None and free < need:
        return short_of_room("disk full", free, need)
    return None


def short_of_room(cause: str, free: int | None, need: int) -> str:
    """'disk full' with the figures behind it: the free space, what the next write
    needed, and the rule (its data plus :data:`HEADROOM_BYTES` kept in reserve, so
    that the file can always be closed intact)."""
    have = "free space unknown" if free is None else f"{megabytes(free)} free"
    return (
        f"{cause} ({have}; the next write needs {megabytes(need)}: its data plus "
        f"{megabytes(HEADROOM_BYTES)} kept in reserve so that the file closes intact)"
    )


def release(path: str) -> None:
    """Give back blocks reserved beyond the end of a closed file.

    Truncating a file to its own size frees blocks allocated past its end (ext4,
    XFS, tmpfs); the contents are unchanged.
    """
    try:
        fd = os.open(path, os.O_WRONLY)
    except OSError:
        return
    try:
        os.ftruncate(fd, os.fstat(fd).st_size)
    except OSError:
        pass
    finally:
        os.close(fd)


def detach_descriptor(fd: int) -> bool:
    """Point descriptor `fd` at an empty in-memory file, leaving the file it had alone.

    After a failed write HDF5 still holds dirty metadata, and closing the file retries
    the write; if that fails too, HDF5 keeps a half-destroyed file identifier that
    crashes the process (SIGSEGV) when h5py or the library's exit handler releases it
    later. Moving the descriptor first lets the close succeed, and nothing more is
    written to the real file.

    Returns
    -------
    bool
        False if no in-memory file could be made (the close is then attempted as is).
    """
    spare: int | None = None
    try:
        if hasattr(os, "memfd_create"):
            spare = os.memfd_create("tissuecli-detached")
        else:  # macOS and others: an unlinked temporary file
            import tempfile

            spare = os.dup(tempfile.TemporaryFile().fileno())
        os.dup2(spare, fd)
        return True
    except OSError:
        return False
    finally:
        if spare is not None:
            os.close(spare)
