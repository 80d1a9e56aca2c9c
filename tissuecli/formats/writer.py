"""The crash-safe, append-only writer of one HDF5 group of equal-length columns: what
``record`` streams a session through and ``play`` its log (see :mod:`.hdf5` for the
commit protocol and :mod:`.space` for storage faults)."""

from __future__ import annotations

import math
import os
import time as _time
from collections.abc import Iterable, Mapping, Sequence
from types import TracebackType
from typing import Any, NoReturn

import h5py
import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._version import __version__
from ..core.errors import Interrupted, SessionExists, StorageError
from .hdf5 import (
    CHUNK_ROWS,
    H5_ERRORS,
    MANAGED_ATTRS,
    SCHEMA_VERSION,
    Column,
    FileAppeared,
    StrPath,
    check_schema,
    clip,
    damaged,
    exists_message,
    file_size,
    first_line,
    foreign_message,
    fsync_dir,
    fsync_file,
    fsync_path,
    group_path,
    is_own_file,
    open_file,
    opened,
    set_attr,
    to_attr,
    truncated_at,
    utc_now,
)
from .space import (
    HEADROOM_BYTES,
    check_free_space,
    detach_descriptor,
    fault_cause,
    lifted_file_size_limit,
    make_room,
    release,
)

#: errors h5py raises when a write or flush fails: RuntimeError for most HDF5 write
#: failures (ENOSPC, EFBIG, EIO), OSError for the rest and for fsync
WRITE_ERRORS = (OSError, RuntimeError)


def row_bytes(columns: Sequence[Column]) -> int:
    """Bytes one row of `columns` takes on disk (48 for a session with raw data)."""
    return sum(np.dtype(c.dtype).itemsize * math.prod(c.shape) for c in columns)


def _attr_bytes(values: Mapping[str, Any]) -> int:
    """Generous size of encoded attributes on disk (heap and header space included)."""
    total = 0
    for value in values.values():
        if isinstance(value, str):
            total += len(value.encode("utf-8", "replace"))
        elif isinstance(value, np.ndarray):
            total += value.nbytes if value.dtype.kind != "O" else 64 * value.size
        total += 256
    return 2 * total


def _advice(cause: str) -> str:
    if cause.startswith("file size limit"):
        return "raise the limit ('ulimit -f') or start a new file"
    if cause.startswith(("disk full", "disk quota")):
        return "free some space or write to another drive"
    return "check the drive and its connection"


class SeriesWriter:
    """Append-only, crash-safe writer of one group of equal-length columns.

    Rows are buffered in memory and written whenever `flush_interval_s` has passed
    since the last flush, so a crash loses at most that much data. Use as a context
    manager: leaving the block closes the file, marking the group complete unless
    an exception other than ``KeyboardInterrupt``, ``Interrupted`` (a signal) or
    ``SystemExit`` is propagating.

    Storage faults (disk full, quota, file-size limit, I/O errors) stop the writer at
    once: the rows committed so far stay in the file, the group is marked incomplete
    with ``stop_reason`` saying why, the file is closed, and a one-line
    :class:`StorageError` is raised (again by any later :meth:`append`). Room for each
    flush is made before HDF5 writes anything (see :mod:`.space`), so a full disk never
    leaves a damaged file. A file this writer created is removed if it ends up holding
    no committed row.

    Parameters
    ----------
    path : str or os.PathLike
        HDF5 file, opened in append mode (created if missing). An existing file must be
        empty or written by tissuecli.
    group : str
        Group to create, e.g. ``'sessions/liver-1'``; it must not exist yet.
    columns : sequence of Column
        Datasets of the group; each gets shape ``(n, *column.shape)``.
    attrs : mapping
        Group attributes (dicts are stored as JSON strings).
    flush_interval_s : float, optional
        Longest time in s that appended rows stay only in memory (default 0.25 s).
    fsync : bool, optional
        Call ``os.fsync`` after every flush so data survive a power cut (default True).
    kind : str, optional
        Word used in error messages, and the option hint ``--<kind>`` (default 'session').
    option : str, optional
        The option that names the file, for messages (default '--out').
    min_free_bytes : int, optional
        Free space (and file-size limit) needed before the file is created or opened,
        bytes; default :data:`~.space.HEADROOM_BYTES`.
    chunk_rows : int, optional
        Rows per HDF5 chunk (default :data:`~.hdf5.CHUNK_ROWS`); larger chunks suit a
        file written in large blocks and read back whole (an import).

    Raises
    ------
    SessionExists
        If `group` already exists in the file (nothing is overwritten).
    StorageError
        If the file cannot be opened or created, is not a tissuecli file, or the drive
        lacks `min_free_bytes`.
    """

    def __init__(
        self,
        path: StrPath,
        group: str,
        columns: Sequence[Column],
        attrs: Mapping[str, Any],
        *,
        flush_interval_s: float = 0.25,
        fsync: bool = True,
        kind: str = "session",
        option: str = "--out",
        min_free_bytes: int | None = None,
        chunk_rows: int = CHUNK_ROWS,
    ) -> None:
        self.path = os.fspath(path)
        self.chunk_rows = int(chunk_rows)
        self.group_path = group_path(group)
        self.columns = list(columns)
        self.flush_interval_s = float(flush_interval_s)
        self.fsync = bool(fsync)
        self.kind = kind
        self._check_columns()
        encoded = {key: to_attr(value) for key, value in attrs.items() if key not in MANAGED_ATTRS}
        # buffered blocks and the count of rows on disk; see flush() for the update order
        self._buffer: list[tuple[int, dict[str, NDArray[Any]]]] = []
        self._written = 0
        self._committed = 0
        self._pending_attrs: dict[str, Any] = {}
        self._closed = False
        self._fault: StorageError | None = None
        self._group: h5py.Group | None = None
        self._fd = -1

        # refuse a drive without room before anything is created
        floor = HEADROOM_BYTES if min_free_bytes is None else int(min_free_bytes)
        what = "the play log" if kind == "play" else f"the {kind}"
        check_free_space(self.path, floor + _attr_bytes(encoded), what=what)
        existed = os.path.exists(self.path)
        if existed:
            # read-only first: a foreign file is refused without ever being opened for writing
            with opened(self.path, "r") as f:
                self._check_target(f, option)
        try:
            # a new file is created exclusively: one that appears meanwhile is never ours
            self._file = open_file(self.path, "a" if existed else "w-")
        except FileAppeared:
            raise
        except StorageError:
            if not existed:
                self._remove()  # HDF5 created the file, then failed (disk full)
            raise
        self._created = not existed
        try:
            self._check_target(self._file, option)
            try:
                handle = self._file.id.get_vfd_handle()
                self._fd = handle if isinstance(handle, int) else -1
            except H5_ERRORS:
                self._fd = -1
            self._make_room(HEADROOM_BYTES + _attr_bytes(encoded))
            self._create(encoded)
        except BaseException:
            if not self._closed:
                self._shutdown(broken=False, fault=True)
            raise
        if self.fsync and self._created:
            fsync_dir(self.path)
        self._last_flush = _time.monotonic()

    def _check_columns(self) -> None:
        names = [c.name.strip("/") for c in self.columns]
        if len(set(names)) != len(names) or not names:
            raise ValueError(f"column names must be unique and non-empty: {names}")
        for a in names:
            for b in names:
                if b.startswith(a + "/"):
                    raise ValueError(f"column {a!r} cannot also be the group of {b!r}")

    def _check_target(self, f: h5py.File, option: str) -> None:
        """Refuse a file tissuecli did not write, a newer schema, and a taken name."""
        try:
            own = is_own_file(f)
            version = f.attrs.get("schema_version") if own else None
            taken = own and self.group_path in f
        except H5_ERRORS as exc:
            raise damaged(self.path, "the root group", exc) from None
        if not own:
            raise StorageError(foreign_message(self.path, option))
        check_schema(version, self.path)
        if taken:
            leaf = self.group_path.rsplit("/", 1)[-1]
            raise SessionExists(exists_message(self.kind, leaf, self.path))

    def _create(self, encoded: Mapping[str, Any]) -> None:
        f = self._file
        try:
            if "schema_version" not in f.attrs:
                f.attrs["schema_version"] = SCHEMA_VERSION
                f.attrs["software"] = f"tissuecli {__version__}"
            g = f.create_group(self.group_path)
            for key, value in encoded.items():
                g.attrs[key] = value
            g.attrs["schema_version"] = SCHEMA_VERSION
            g.attrs["software_version"] = __version__
            g.attrs["created_utc"] = utc_now()
            g.attrs["complete"] = False
            g.attrs["rows_committed"] = np.int64(0)
            self._datasets: dict[str, h5py.Dataset] = {}
            for col in self.columns:
                dtype = np.dtype(col.dtype)
                # NaN fill makes rows that never reached the disk visible as such
                fill = np.nan if dtype.kind == "f" else None
                # no compression: compressed chunks move on every rewrite and freed space is
                # reused, so a kill -9 mid-flush left up to 42 % of test files unreadable
                ds = g.create_dataset(
                    col.name.strip("/"),
                    shape=(0, *col.shape),
                    maxshape=(None, *col.shape),
                    chunks=(self.chunk_rows, *col.shape),
                    dtype=dtype,
                    fillvalue=fill,
                )
                for key, value in col.attrs.items():
                    ds.attrs[key] = to_attr(value)
                self._datasets[col.name.strip("/")] = ds
            self._group = g
            f.flush()
            if self.fsync:
                fsync_file(f, self.path)
        except WRITE_ERRORS as exc:
            self._broke(exc)

    # -- appending

    @property
    def rows(self) -> int:
        """Rows appended so far (written to the file plus buffered in memory)."""
        return self._written + sum(n for n, _ in self._buffer)

    @property
    def rows_flushed(self) -> int:
        """Rows committed to disk by the last completed flush (what survives a kill -9)."""
        return self._committed

    @property
    def closed(self) -> bool:
        """True once :meth:`close` has run or a storage fault stopped the writer."""
        return self._closed

    @property
    def fault(self) -> StorageError | None:
        """The storage fault that stopped the writer, if one did."""
        return self._fault

    def append(self, block: Mapping[str, ArrayLike]) -> None:
        """Buffer a block of rows; flush if `flush_interval_s` has passed since the last flush.

        Parameters
        ----------
        block : mapping of str to array_like
            One array per column name, each of shape ``(k, *column.shape)`` with the
            same `k` for every column, in the column's unit.

        Raises
        ------
        ValueError
            If a column is missing or unknown, shapes disagree, or floats are given
            for an integer column.
        StorageError
            If a storage fault stopped the writer (now or at an earlier flush).
        """
        if self._fault is not None:
            raise self._fault from None
        if self._closed:
            raise ValueError("writer is closed")
        missing = [c.name for c in self.columns if c.name not in block]
        extra = sorted(set(block) - {c.name for c in self.columns})
        if missing or extra:
            raise ValueError(f"block columns wrong: missing {missing}, unknown {extra}")
        arrays: dict[str, NDArray[Any]] = {}
        n: int | None = None
        for col in self.columns:
            arr = np.asarray(block[col.name])
            dtype = np.dtype(col.dtype)
            if dtype.kind in "iu" and arr.dtype.kind not in "biu":
                raise ValueError(f"column {col.name!r} takes integers, got {arr.dtype}")
            if arr.ndim != 1 + len(col.shape) or arr.shape[1:] != col.shape:
                raise ValueError(
                    f"column {col.name!r} needs shape (k, {', '.join(map(str, col.shape))})"
                    f" but got {arr.shape}"
                    if col.shape
                    else f"column {col.name!r} needs shape (k,) but got {arr.shape}"
                )
            if n is None:
                n = arr.shape[0]
            elif arr.shape[0] != n:
                raise ValueError(f"column {col.name!r} has {arr.shape[0]} rows, others {n}")
            arrays[col.name] = np.array(arr, dtype=dtype, copy=True)
        if n:
            # one list.append: an interrupt cannot leave half a block buffered
            self._buffer.append((n, arrays))
        self.maybe_flush()

    def maybe_flush(self) -> bool:
        """Flush if `flush_interval_s` has passed since the last flush; return True if it did.

        Call this periodically when no rows arrive, so buffered rows still reach the disk.
        """
        if self._closed:
            return False
        if _time.monotonic() - self._last_flush >= self.flush_interval_s:
            self.flush()
            return True
        return False

    def set_attrs(self, **attrs: Any) -> None:
        """Update group attributes (counters, stop reason, ...) at the next flush."""
        for key, value in attrs.items():
            if key in MANAGED_ATTRS:
                raise ValueError(f"attribute {key!r} is managed by the writer")
            self._pending_attrs[key] = to_attr(value)

    def rewrite(self, name: str, values: ArrayLike, **attrs: Any) -> None:
        """Flush, then replace every row of column `name` (e.g. drift-corrected time).

        Done on the open file before :meth:`close`, so a session marked complete
        always holds the final values. Does nothing once a storage fault has stopped
        the writer: the committed rows stay as they were written.
        """
        if self._fault is not None:
            return
        if self._closed:
            raise ValueError("writer is closed")
        self.flush()
        values = np.asarray(values)
        ds = self._datasets[name.strip("/")]
        if values.shape != (self._written, *ds.shape[1:]):
            raise ValueError(f"{name}: {values.shape} values for {self._written} rows")
        # in place: the chunks exist already; the attributes fit in the headroom kept
        try:
            ds[:] = values
            for key, value in attrs.items():
                ds.attrs[key] = to_attr(value)
            self._file.flush()
            if self.fsync:
                fsync_file(self._file, self.path)
        except WRITE_ERRORS as exc:
            self._broke(exc)

    def column(self, name: str) -> StoredRows:
        """Flush, then the rows of column `name` written so far, read a block at a time
        (a slice of it reads those rows from the file)."""
        self.flush()
        if self._closed:
            raise ValueError("writer is closed")
        return StoredRows(self._datasets[name.strip("/")], self._written)

    def rewrite_blocks(self, name: str, blocks: Iterable[ArrayLike]) -> None:
        """Flush, then replace the rows of column `name` with `blocks`, in order from the
        first row, each written as it comes (so a block may be made from the rows it
        replaces, read just before); as :meth:`rewrite` otherwise."""
        if self._fault is not None:
            return
        if self._closed:
            raise ValueError("writer is closed")
        self.flush()
        ds = self._datasets[name.strip("/")]
        row = 0
        try:
            for block in blocks:
                values = np.asarray(block)
                if row + values.shape[0] > self._written:
                    raise ValueError(f"{name}: more values than the {self._written} rows")
                ds[row : row + values.shape[0]] = values
                row += values.shape[0]
            if row != self._written:
                raise ValueError(f"{name}: {row} values for {self._written} rows")
            self._file.flush()
            if self.fsync:
                fsync_file(self._file, self.path)
        except WRITE_ERRORS as exc:
            self._broke(exc)

    def flush(self) -> None:
        """Write buffered rows and pending attributes, then commit them to disk.

        Order matters for crash safety: (0) make room on the drive for everything this
        flush can allocate, or stop cleanly; (1) resize and fill the datasets, write
        attributes, ``H5Fflush`` and fsync; (2) overwrite ``rows_committed`` in place,
        ``H5Fflush`` and fsync. A reader of an incomplete group trusts only
        ``rows_committed`` rows, so a kill during (1) loses the new rows but never
        exposes half-written ones.

        Raises
        ------
        StorageError
            If writing fails or would fail (disk full, quota, file-size limit, drive
            removed, ...); the writer is then closed (see the class docstring).
        """
        if self._closed:
            return
        blocks = list(self._buffer)
        k = len(blocks)
        n_old = self._written
        n_new = n_old + sum(n for n, _ in blocks)
        pending = dict(self._pending_attrs)
        if n_new > n_old or pending:
            self._make_room(self._chunk_bytes(n_old, n_new) + _attr_bytes(pending) + HEADROOM_BYTES)
        try:
            if n_new > n_old:
                for col in self.columns:
                    data = np.concatenate([arrays[col.name] for _, arrays in blocks])
                    ds = self._datasets[col.name.strip("/")]
                    # n_old comes from our counter, not ds.shape, so a flush interrupted
                    # here is simply redone by the next one
                    ds.resize(n_new, axis=0)
                    ds[n_old:n_new] = data
            for key, value in pending.items():
                set_attr(self._group.attrs, key, value)
            if n_new > n_old or pending:
                self._file.flush()
                if self.fsync:
                    fsync_file(self._file, self.path)
            # both counters in one statement: no interrupt can fall between them
            self._written, self._buffer = n_new, self._buffer[k:]
            for key in pending:
                if self._pending_attrs.get(key) is pending[key]:
                    del self._pending_attrs[key]
            if n_new != self._committed:
                set_attr(self._group.attrs, "rows_committed", np.int64(n_new))
                self._file.flush()
                if self.fsync:
                    fsync_file(self._file, self.path)
                self._committed = n_new
        except WRITE_ERRORS as exc:
            self._broke(exc)
        self._last_flush = _time.monotonic()

    def close(self, *, complete: bool = True, **final_attrs: Any) -> None:
        """Flush, store `final_attrs` and ``complete``, and close the file.

        Does nothing if the writer is closed already, or was stopped by a storage
        fault (which closed it, marked the group incomplete and raised).

        Parameters
        ----------
        complete : bool, optional
            Whether the series ended as intended (default True).
        **final_attrs
            Last group attributes, e.g. ``stop_reason='user'`` or final counters.

        Raises
        ------
        StorageError
            If the last writes fail (the writer is then stopped as for any fault).
        """
        if self._closed:
            return
        try:
            self.set_attrs(**final_attrs)
        except ValueError:
            self._shutdown(broken=False, fault=False)
            raise
        self.flush()
        try:
            set_attr(self._group.attrs, "complete", bool(complete))
            self._file.flush()
            if self.fsync:
                fsync_file(self._file, self.path)
        except WRITE_ERRORS as exc:
            self._broke(exc)
        if not self._shutdown(broken=False, fault=False):
            raise StorageError(
                f"closing {self.path} failed; the file may be damaged; check the drive"
            )
        if self.fsync:
            try:
                fsync_path(self.path)
            except OSError as exc:
                raise StorageError(
                    f"writing {self.path} failed: {fault_cause(exc)}; {_advice(fault_cause(exc))}"
                ) from None

    # -- storage faults

    def _chunk_bytes(self, n_old: int, n_new: int) -> int:
        """Bytes of the chunks HDF5 allocates to grow every column from n_old to n_new rows."""
        size = self.chunk_rows
        chunks = -(-n_new // size) - -(-n_old // size)
        return chunks * size * row_bytes(self.columns)

    def _make_room(self, need: int) -> None:
        """Stop cleanly (before HDF5 writes a byte) unless `need` bytes fit past the file's end."""
        end = file_size(self._file)
        cause = make_room(self._fd if self._fd >= 0 else None, self.path, end, need)
        if cause is not None:
            self._stop(cause, broken=False)

    def _broke(self, exc: BaseException) -> NoReturn:
        """HDF5 failed to write: stop without writing to the file again."""
        self._stop(fault_cause(exc), broken=True)

    def _stop(self, cause: str, *, broken: bool) -> NoReturn:
        """Close the writer after a storage fault and raise its one-line StorageError.

        A clean stop (`broken` False: the fault was found before HDF5 wrote anything)
        still marks the group incomplete with the reason, in the room kept in reserve.
        After a failed HDF5 write nothing more is written to the file.
        """
        self._buffer = []
        if not broken and self._group is not None:
            try:
                for key, value in self._pending_attrs.items():
                    set_attr(self._group.attrs, key, value)
                self._group.attrs["stop_reason"] = f"storage fault: {cause}"
                set_attr(self._group.attrs, "complete", False)
                self._file.flush()
                if self.fsync:
                    fsync_file(self._file, self.path)
            except WRITE_ERRORS:
                broken = True
        self._pending_attrs = {}
        intact = self._shutdown(broken=broken, fault=True)
        self._fault = StorageError(self._fault_message(cause, intact))
        raise self._fault from None

    def _shutdown(self, *, broken: bool, fault: bool) -> bool:
        """Close the file; after a fault, remove it if this writer created it and no row
        was committed.

        Parameters
        ----------
        broken : bool
            HDF5 failed a write: move its descriptor away first (see
            :func:`~.space.detach_descriptor`) so that closing writes nothing more.
        fault : bool
            The writer stops on a fault or a failed start, not a normal close.

        Returns
        -------
        bool
            True if the file is gone or opens normally afterwards.
        """
        self._closed = True
        f = self._file
        end = 0
        if broken:
            end = file_size(f)
            if self._fd >= 0 and os.name == "posix":
                detach_descriptor(self._fd)
            # HDF5 rewrites its dirty metadata into the detached descriptor, at offsets a
            # file-size limit would refuse although nothing of it reaches the disk
            with lifted_file_size_limit():
                try:
                    f.close()
                except H5_ERRORS:
                    pass
        else:
            try:
                f.close()
            except H5_ERRORS:
                broken = True
        if fault and self._created and self._committed == 0:
            self._remove()
            return True
        release(self.path)
        if not (fault or broken):
            return True
        return _opens(self.path) or (broken and _repair(self.path, end))

    def _remove(self) -> None:
        try:
            os.remove(self.path)
        except OSError:
            pass

    def _fault_message(self, cause: str, intact: bool) -> str:
        advice = _advice(cause)
        if not os.path.exists(self.path):
            return f"cannot write {self.path}: {cause}; nothing was saved; {advice}"
        if not intact:
            return (
                f"writing {self.path} failed: {cause}; the file could not be closed cleanly "
                f"and may be damaged; {advice}"
            )
        if self._group is None:
            return f"cannot write {self.path}: {cause}; the file was left as it was; {advice}"
        leaf = self.group_path.rsplit("/", 1)[-1]
        return (
            f"writing {self.path} stopped: {cause}; the {self._committed} rows committed "
            f'before are saved in {self.kind} "{clip(leaf)}" (marked incomplete); {advice}'
        )

    def __enter__(self) -> SeriesWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if self._closed:
            return
        if exc_type is None:
            self.close(complete=True)
        elif issubclass(exc_type, (KeyboardInterrupt, Interrupted, SystemExit)):
            # Ctrl-C, SIGTERM and SIGHUP (turned into one of these) are normal ways to stop
            if "stop_reason" not in self._pending_attrs:
                self.set_attrs(stop_reason="interrupted")
            self.close(complete=True)
        else:
            if "stop_reason" not in self._pending_attrs:
                self.set_attrs(
                    stop_reason=f"error: {exc_type.__name__}: {first_line(exc)}"
                    if exc is not None
                    else f"error: {exc_type.__name__}"
                )
            self.close(complete=False)


class StoredRows:
    """Rows ``0 .. n - 1`` of a dataset, read a slice at a time (what :meth:`SeriesWriter.
    column` gives)."""

    def __init__(self, dataset: h5py.Dataset, rows: int) -> None:
        self._dataset, self._rows = dataset, rows

    def __len__(self) -> int:
        return self._rows

    def __getitem__(self, rows: slice) -> NDArray[Any]:
        start, stop, step = rows.indices(self._rows)
        if step != 1:
            raise ValueError("rows are read in runs, step 1")
        if stop <= start:
            return np.empty((0, *self._dataset.shape[1:]), self._dataset.dtype)
        out = np.empty((stop - start, *self._dataset.shape[1:]), self._dataset.dtype)
        self._dataset.read_direct(out, np.s_[start:stop])
        return out


def _opens(path: str) -> bool:
    """True if `path` is missing or HDF5 opens it."""
    if not os.path.exists(path):
        return True
    try:
        h5py.File(path, "r", locking=False).close()
    except H5_ERRORS:
        return False
    return True


def _repair(path: str, end: int) -> bool:
    """Undo the one damage a failed flush leaves: a superblock that claims more bytes
    than reached the disk ("truncated file").

    The file is extended with zeros (a sparse tail, no blocks needed) to the length
    the superblock states, which HDF5 had allocated (at most `end`); every committed
    row lies before the old end and reads as before, and readers ignore the rows
    past ``rows_committed``.
    """
    try:
        h5py.File(path, "r", locking=False).close()
        return True
    except H5_ERRORS as exc:
        lengths = truncated_at(exc)
    if lengths is None:
        return False
    size, stored = lengths
    if not size < stored <= max(end, size):
        return False
    try:
        with lifted_file_size_limit():
            os.truncate(path, stored)
    except OSError:
        return False
    return _opens(path)
