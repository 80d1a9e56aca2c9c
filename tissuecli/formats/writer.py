"""The crash-safe, append-only writer of one HDF5 group of equal-length columns: what
``record`` streams a session through and ``play`` its log (see :mod:`.hdf5` for the
commit protocol)."""

from __future__ import annotations

import os
import time as _time
from collections.abc import Mapping, Sequence
from types import TracebackType
from typing import Any

import h5py
import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._version import __version__
from ..core.errors import SessionExists, StorageError
from .hdf5 import (
    CHUNK_ROWS,
    MANAGED_ATTRS,
    SCHEMA_VERSION,
    Column,
    StrPath,
    check_schema,
    exists_message,
    first_line,
    fsync_dir,
    fsync_file,
    fsync_path,
    group_path,
    open_file,
    set_attr,
    to_attr,
    utc_now,
)


class SeriesWriter:
    """Append-only, crash-safe writer of one group of equal-length columns.

    Rows are buffered in memory and written whenever `flush_interval_s` has passed
    since the last flush, so a crash loses at most that much data. Use as a context
    manager: leaving the block closes the file, marking the group complete unless
    an exception other than ``KeyboardInterrupt``/``SystemExit`` is propagating.

    Parameters
    ----------
    path : str or os.PathLike
        HDF5 file, opened in append mode (created if missing).
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

    Raises
    ------
    SessionExists
        If `group` already exists in the file (nothing is overwritten).
    StorageError
        If the file cannot be opened or created.
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
    ) -> None:
        self.path = os.fspath(path)
        self.group_path = group_path(group)
        self.columns = list(columns)
        self.flush_interval_s = float(flush_interval_s)
        self.fsync = bool(fsync)
        self._check_columns()
        encoded = {key: to_attr(value) for key, value in attrs.items() if key not in MANAGED_ATTRS}
        # buffered blocks and the count of rows on disk; see flush() for the update order
        self._buffer: list[tuple[int, dict[str, NDArray[Any]]]] = []
        self._written = 0
        self._committed = 0
        self._pending_attrs: dict[str, Any] = {}
        self._closed = False

        existed = os.path.exists(self.path)
        self._file = open_file(self.path, "a")
        try:
            check_schema(self._file.attrs.get("schema_version"), self.path)
            if self.group_path in self._file:
                leaf = self.group_path.rsplit("/", 1)[-1]
                raise SessionExists(exists_message(kind, leaf, self.path))
            self._create(encoded)
        except BaseException:
            self._file.close()
            raise
        if self.fsync and not existed:
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
                    chunks=(CHUNK_ROWS, *col.shape),
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
        except OSError as exc:
            raise StorageError(f"cannot write {self.path}: {first_line(exc)}") from None

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
        """True once :meth:`close` has run; later appends raise ValueError."""
        return self._closed

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
        """
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
        always holds the final values.
        """
        self.flush()
        values = np.asarray(values)
        ds = self._datasets[name.strip("/")]
        if values.shape != (self._written, *ds.shape[1:]):
            raise ValueError(f"{name}: {values.shape} values for {self._written} rows")
        try:
            ds[:] = values
            for key, value in attrs.items():
                ds.attrs[key] = to_attr(value)
            self._file.flush()
            if self.fsync:
                fsync_file(self._file, self.path)
        except OSError as exc:
            raise StorageError(f"writing {self.path} failed: {first_line(exc)}") from None

    def flush(self) -> None:
        """Write buffered rows and pending attributes, then commit them to disk.

        Order matters for crash safety: (1) resize and fill the datasets, write
        attributes, ``H5Fflush`` and fsync; (2) overwrite ``rows_committed`` in place,
        ``H5Fflush`` and fsync. A reader of an incomplete group trusts only
        ``rows_committed`` rows, so a kill during (1) loses the new rows but never
        exposes half-written ones.

        Raises
        ------
        StorageError
            If writing fails (disk full, drive removed, ...).
        """
        if self._closed:
            return
        blocks = list(self._buffer)
        k = len(blocks)
        n_old = self._written
        n_new = n_old + sum(n for n, _ in blocks)
        try:
            if n_new > n_old:
                for col in self.columns:
                    data = np.concatenate([arrays[col.name] for _, arrays in blocks])
                    ds = self._datasets[col.name.strip("/")]
                    # n_old comes from our counter, not ds.shape, so a flush interrupted
                    # here is simply redone by the next one
                    ds.resize(n_new, axis=0)
                    ds[n_old:n_new] = data
            pending = dict(self._pending_attrs)
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
        except OSError as exc:
            raise StorageError(
                f"writing {self.path} failed: {first_line(exc)}; check free disk space and "
                "that the drive is still connected"
            ) from None
        self._last_flush = _time.monotonic()

    def close(self, *, complete: bool = True, **final_attrs: Any) -> None:
        """Flush, store `final_attrs` and ``complete``, and close the file.

        Parameters
        ----------
        complete : bool, optional
            Whether the series ended as intended (default True).
        **final_attrs
            Last group attributes, e.g. ``stop_reason='user'`` or final counters.
        """
        if self._closed:
            return
        try:
            self.set_attrs(**final_attrs)
            self.flush()
            try:
                self._group.attrs["complete"] = bool(complete)
                self._file.flush()
                if self.fsync:
                    fsync_file(self._file, self.path)
            except OSError as exc:
                raise StorageError(
                    f"writing {self.path} failed: {first_line(exc)}; check free disk space "
                    "and that the drive is still connected"
                ) from None
        finally:
            self._closed = True
            self._file.close()
        if self.fsync:
            try:
                fsync_path(self.path)
            except OSError as exc:
                raise StorageError(
                    f"writing {self.path} failed: {first_line(exc)}; check that the drive is "
                    "still connected"
                ) from None

    def __enter__(self) -> SeriesWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc_type is None:
            self.close(complete=True)
        elif issubclass(exc_type, (KeyboardInterrupt, SystemExit)):
            # Ctrl-C and SIGTERM (turned into one of these) are normal ways to stop
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
