"""HDF5 storage of sessions: crash-safe appending, whole-session writes and reading.

This is the only module that imports h5py. A file holds any number of sessions
under ``/sessions/<name>``; each session is a group of equal-length, chunked,
resizable datasets (one row per sample) with a ``unit`` attribute on every
dataset. The layout is described for users in ``docs/formats.md``.

Crash safety comes from plain HDF5 (no SWMR) used carefully:

* rows are buffered in memory and touch the file only inside :meth:`SeriesWriter.flush`,
  so between flushes the file on disk is exactly the last flushed state;
* every flush is a two-phase commit: data and metadata are flushed (and fsynced),
  then the group attribute ``rows_committed`` is overwritten in place and flushed
  again. A reader of a crashed session trusts only ``rows_committed`` rows;
* nothing is compressed, so chunks never move and file space is never freed and
  reused while committed metadata may still point at it;
* the default (earliest) file format is used, whose superblock has no
  "file open for writing" flag, so a killed writer leaves a file that opens normally.
"""

from __future__ import annotations

import json
import os
import time as _time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import date, datetime, timezone
from types import TracebackType
from typing import Any

import h5py
import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import SCHEMA_VERSION, __version__
from .errors import InputError, SessionExists, StorageError
from .session import Session

StrPath = str | os.PathLike[str]

#: rows per chunk: 32 KiB for float64, few chunk-index entries even for hour-long sessions
CHUNK_ROWS = 4096
#: parent group of every recorded or imported session
SESSIONS = "sessions"
#: group attributes managed by :class:`SeriesWriter`; caller values for these are replaced
MANAGED_ATTRS = ("schema_version", "software_version", "created_utc", "complete", "rows_committed")
#: keys of ``Session.meta`` that exist only in memory and are never stored as attributes
READ_ONLY_META = ("file", "raw", "calibration")
CHANNELS = ("force", "position")


@dataclass(frozen=True)
class Column:
    """One appendable dataset of a :class:`SeriesWriter` group.

    Attributes
    ----------
    name : str
        Dataset path relative to the group; may contain '/' (e.g. ``'raw/counts'``).
    dtype : str
        NumPy dtype of the stored values (e.g. ``'float64'``, ``'int16'``).
    shape : tuple of int
        Trailing shape of one row; ``()`` for a scalar per sample, so the dataset
        has shape ``(n, *shape)``.
    attrs : dict
        Dataset attributes: ``unit`` (required by convention), ``description``,
        ``conversion``, ``offset``, ``resolution``, ...
    """

    name: str
    dtype: str
    shape: tuple[int, ...] = ()
    attrs: dict[str, Any] = field(default_factory=dict)


SESSION_COLUMNS: list[Column] = [
    Column(
        "time",
        "float64",
        (),
        {"unit": "s", "description": "sample time on the device clock since the first sample"},
    ),
    Column(
        "force",
        "float64",
        (),
        {"unit": "N", "description": "grasp force, positive squeezes the tissue"},
    ),
    Column(
        "position",
        "float64",
        (),
        {"unit": "m", "description": "jaw closure, positive compresses the tissue"},
    ),
    Column(
        "raw/counts",
        "int16",
        (2,),
        {
            "unit": "count",
            "channels": list(CHANNELS),
            "description": "raw ADC counts as sent by the device, one column per channel",
        },
    ),
    Column(
        "raw/sequence",
        "uint32",
        (),
        {"unit": "1", "description": "frame sequence number as sent by the device"},
    ),
    Column(
        "raw/device_clock",
        "int64",
        (),
        {"unit": "tick", "description": "device clock, unwrapped to 64 bits"},
    ),
    Column(
        "raw/host_time",
        "float64",
        (),
        {"unit": "s", "description": "host monotonic clock, s since the session started"},
    ),
]


# --------------------------------------------------------------------------- attributes


def _json_default(value: Any) -> Any:
    """Make NumPy scalars and arrays JSON-serialisable."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (datetime, date)):
        return value.isoformat()
    raise TypeError(f"cannot store {type(value).__name__} in an HDF5 attribute")


def _to_attr(value: Any) -> Any:
    """Encode a Python value as something h5py can store as an attribute.

    ``None`` becomes an empty attribute, dicts and non-string lists become JSON
    strings, lists of strings become HDF5 string arrays, NumPy arrays are stored
    as they are. :func:`_from_attr` undoes this.
    """
    if value is None:
        return h5py.Empty("f")
    if isinstance(value, (bool, int, float, str, np.generic)):
        return value
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if isinstance(value, (datetime, date)):
        return value.isoformat()
    if isinstance(value, np.ndarray):
        if value.dtype.kind in "US":
            return _to_attr(value.astype(str).tolist())
        return value
    if isinstance(value, (list, tuple)):
        if value and all(isinstance(v, str) for v in value):
            # a native string array stays readable by any HDF5 tool
            return np.array(value, dtype=h5py.string_dtype())
        return json.dumps(list(value), default=_json_default)
    if isinstance(value, Mapping):
        return json.dumps(dict(value), default=_json_default)
    raise TypeError(f"cannot store {type(value).__name__} in an HDF5 attribute")


def _from_attr(value: Any) -> Any:
    """Decode an attribute read by h5py into plain Python (inverse of :func:`_to_attr`)."""
    if isinstance(value, h5py.Empty):
        return None
    if isinstance(value, bytes):
        value = value.decode("utf-8", "replace")
    if isinstance(value, str):
        if value[:1] in "{[" and value[-1:] in "}]":
            try:
                decoded = json.loads(value)
            except ValueError:
                return value
            if isinstance(decoded, (dict, list)):
                return decoded
        return value
    if isinstance(value, np.ndarray):
        if value.dtype.kind in "OSU":
            return [
                v.decode("utf-8", "replace") if isinstance(v, bytes) else str(v)
                for v in value.ravel()
            ]
        return value
    if isinstance(value, np.generic):
        return value.item()
    return value


def _set_attr(attrs: h5py.AttributeManager, key: str, encoded: Any) -> None:
    """Set one attribute, overwriting a numeric one in place when type and shape match.

    In-place writes keep the object header the same size, so a counter updated at
    every flush never makes HDF5 move metadata around.
    """
    if (
        key in attrs
        and isinstance(encoded, (bool, int, float, np.generic))
        and not isinstance(encoded, (str, np.str_, np.bytes_))
    ):
        old = attrs.get_id(key)
        new = np.asarray(encoded)
        if old.shape == () and old.dtype == new.dtype:
            old.write(new)
            return
    attrs[key] = encoded


def _decode_attrs(attrs: h5py.AttributeManager) -> dict[str, Any]:
    return {key: _from_attr(attrs[key]) for key in attrs}


def _utc_now() -> str:
    # microseconds: sessions written in quick succession still sort in creation order
    return datetime.now(timezone.utc).isoformat(timespec="microseconds")


# --------------------------------------------------------------------------- opening


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


def _open_file(path: StrPath, mode: str) -> h5py.File:
    """Open an HDF5 file, turning every OS/HDF5 failure into a one-line StorageError.

    Readers ignore HDF5's file lock so that a session can be listed or read while it
    is being recorded; they trust only ``rows_committed`` rows of an unfinished group,
    which the writer updates only after the rows themselves are on disk.
    """
    name = os.fspath(path)
    try:
        if mode == "r":
            return h5py.File(name, mode, locking=False)
        return h5py.File(name, mode)
    except FileNotFoundError:
        if mode == "r":
            raise StorageError(f"{name} does not exist; check the path") from None
        raise StorageError(
            f"cannot create {name}: its directory does not exist; create it or choose another path"
        ) from None
    except IsADirectoryError:
        raise StorageError(f"{name} is a directory; give the path of an .h5 file") from None
    except PermissionError:
        what = "read" if mode == "r" else "write"
        raise StorageError(
            f"cannot {what} {name}: permission denied; check the file's permissions"
        ) from None
    except OSError as exc:
        msg = str(exc)
        if "signature" in msg:
            raise StorageError(
                f"{name} is not an HDF5 file; give an .h5 file written by tissuecli"
            ) from None
        if "lock" in msg:
            raise StorageError(
                f"{name} is being written by another program (a recording still running?); "
                "wait until it ends or write to another file"
            ) from None
        raise StorageError(f"cannot open {name}: {_first_line(exc)}") from None


@contextmanager
def _opened(path: StrPath, mode: str = "r") -> Iterator[h5py.File]:
    f = _open_file(path, mode)
    try:
        yield f
    finally:
        f.close()


def _fsync(f: h5py.File, path: str) -> None:
    """Push the file's pages to the storage device (survives a power cut)."""
    try:
        fd = f.id.get_vfd_handle()
    except Exception:  # drivers without a POSIX descriptor
        fd = None
    if isinstance(fd, int) and fd >= 0:
        os.fsync(fd)
        return
    _fsync_path(path)


def _fsync_path(path: str) -> None:
    # fsync acts on the inode, so a fresh descriptor flushes pages written through another
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_dir(path: str) -> None:
    """Make a newly created file's directory entry durable (POSIX only)."""
    try:
        fd = os.open(os.path.dirname(os.path.abspath(path)), os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass  # some platforms cannot fsync a directory
    finally:
        os.close(fd)


def _check_schema(version: Any, where: str) -> None:
    if isinstance(version, (int, np.integer)) and int(version) > SCHEMA_VERSION:
        raise StorageError(
            f"{where} uses storage schema {int(version)}, newer than this tissuecli "
            f"({__version__}, schema {SCHEMA_VERSION}); upgrade tissuecli"
        )


def _group_path(group: str) -> str:
    path = "/".join(part for part in group.split("/") if part)
    if not path:
        raise ValueError("group path is empty")
    return path


def session_group(name: str) -> str:
    """HDF5 group path of session `name`, e.g. ``'sessions/liver-1'``."""
    _check_name(name, "session")
    return f"{SESSIONS}/{name}"


def _check_name(name: str, kind: str) -> None:
    if not isinstance(name, str) or not name.strip():
        raise InputError(f"{kind} name is empty; give one with --{kind} NAME")
    if "/" in name or name in (".", ".."):
        raise InputError(f'{kind} name "{name}" is not allowed; choose a name without "/"')


# --------------------------------------------------------------------------- writer


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
        self.group_path = _group_path(group)
        self.columns = list(columns)
        self.flush_interval_s = float(flush_interval_s)
        self.fsync = bool(fsync)
        self._check_columns()
        encoded = {key: _to_attr(value) for key, value in attrs.items() if key not in MANAGED_ATTRS}
        # buffered blocks and the count of rows on disk; see flush() for the update order
        self._buffer: list[tuple[int, dict[str, NDArray[Any]]]] = []
        self._written = 0
        self._committed = 0
        self._pending_attrs: dict[str, Any] = {}
        self._closed = False

        existed = os.path.exists(self.path)
        self._file = _open_file(self.path, "a")
        try:
            _check_schema(self._file.attrs.get("schema_version"), self.path)
            if self.group_path in self._file:
                leaf = self.group_path.rsplit("/", 1)[-1]
                raise SessionExists(_exists_message(kind, leaf, self.path))
            self._create(encoded)
        except BaseException:
            self._file.close()
            raise
        if self.fsync and not existed:
            _fsync_dir(self.path)
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
            g.attrs["created_utc"] = _utc_now()
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
                    ds.attrs[key] = _to_attr(value)
                self._datasets[col.name.strip("/")] = ds
            self._group = g
            f.flush()
            if self.fsync:
                _fsync(f, self.path)
        except OSError as exc:
            raise StorageError(f"cannot write {self.path}: {_first_line(exc)}") from None

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
            self._pending_attrs[key] = _to_attr(value)

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
                ds.attrs[key] = _to_attr(value)
            self._file.flush()
            if self.fsync:
                _fsync(self._file, self.path)
        except OSError as exc:
            raise StorageError(f"writing {self.path} failed: {_first_line(exc)}") from None

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
                _set_attr(self._group.attrs, key, value)
            if n_new > n_old or pending:
                self._file.flush()
                if self.fsync:
                    _fsync(self._file, self.path)
            # both counters in one statement: no interrupt can fall between them
            self._written, self._buffer = n_new, self._buffer[k:]
            for key in pending:
                if self._pending_attrs.get(key) is pending[key]:
                    del self._pending_attrs[key]
            if n_new != self._committed:
                _set_attr(self._group.attrs, "rows_committed", np.int64(n_new))
                self._file.flush()
                if self.fsync:
                    _fsync(self._file, self.path)
                self._committed = n_new
        except OSError as exc:
            raise StorageError(
                f"writing {self.path} failed: {_first_line(exc)}; check free disk space and "
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
                    _fsync(self._file, self.path)
            except OSError as exc:
                raise StorageError(
                    f"writing {self.path} failed: {_first_line(exc)}; check free disk space "
                    "and that the drive is still connected"
                ) from None
        finally:
            self._closed = True
            self._file.close()
        if self.fsync:
            try:
                _fsync_path(self.path)
            except OSError as exc:
                raise StorageError(
                    f"writing {self.path} failed: {_first_line(exc)}; check that the drive is "
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
                    stop_reason=f"error: {exc_type.__name__}: {_first_line(exc)}"
                    if exc is not None
                    else f"error: {exc_type.__name__}"
                )
            self.close(complete=False)


# --------------------------------------------------------------------------- sessions


def session_columns(
    *, raw: bool = True, calibration: Mapping[str, Mapping[str, float]] | None = None
) -> list[Column]:
    """Columns of a session group, with calibration attributes filled in.

    Parameters
    ----------
    raw : bool, optional
        Include the ``raw/*`` columns (sessions recorded from a device).
    calibration : mapping, optional
        ``{'force': {'gain': N/count, 'offset': N}, 'position': {'gain': m/count,
        'offset': m}}``; SI value = count * gain + offset.

    Returns
    -------
    list of Column
    """
    gains: dict[str, float] = {}
    offsets: dict[str, float] = {}
    for channel in CHANNELS:
        cal = (calibration or {}).get(channel)
        if calibration is not None and (cal is None or "gain" not in cal):
            raise ValueError(f"calibration lacks {channel!r} gain: {calibration}")
        gains[channel] = float(cal["gain"]) if cal else float("nan")
        offsets[channel] = float(cal.get("offset", 0.0)) if cal else float("nan")
    out: list[Column] = []
    for col in SESSION_COLUMNS:
        if col.name.startswith("raw/") and not raw:
            continue
        attrs = dict(col.attrs)
        if col.name in CHANNELS:
            # NWB meaning: the stored values are SI already; resolution is one count
            attrs.update(conversion=1.0, offset=0.0, resolution=gains[col.name])
        elif col.name == "raw/counts":
            # NWB meaning per channel: SI = counts * conversion + offset
            attrs.update(
                conversion=np.array([gains[c] for c in CHANNELS]),
                offset=np.array([offsets[c] for c in CHANNELS]),
            )
        out.append(Column(col.name, col.dtype, col.shape, attrs))
    return out


def _exists_message(kind: str, name: str, path: str) -> str:
    return f'{kind} "{name}" already exists in {path}; choose another --{kind} name'


def check_new_session(path: StrPath, name: str) -> None:
    """Check, before any work, that session `name` can be created in `path`.

    Raises
    ------
    InputError
        If the name is empty or contains '/'.
    SessionExists
        If the file already holds a session of that name.
    StorageError
        If the file exists but is not a readable HDF5 file, or its directory is missing.
    """
    group = session_group(name)
    file = os.fspath(path)
    if not os.path.exists(file):
        parent = os.path.dirname(os.path.abspath(file))
        if not os.path.isdir(parent):
            raise StorageError(
                f"cannot create {file}: its directory does not exist; create it or choose "
                "another path"
            )
        return
    with _opened(file, "r") as f:
        if group in f:
            raise SessionExists(_exists_message("session", name, file))


def session_writer(
    path: StrPath,
    name: str,
    *,
    meta: Mapping[str, Any],
    calibration: Mapping[str, Mapping[str, float]] | None,
    raw: bool = True,
    flush_interval_s: float = 0.25,
    fsync: bool = True,
) -> SeriesWriter:
    """Start writing session `name` into `path` (see :class:`SeriesWriter`).

    Parameters
    ----------
    path : str or os.PathLike
        HDF5 file (created if missing).
    name : str
        Session name; the group is ``/sessions/<name>``.
    meta : mapping
        Session attributes (tissue, note, source, start_utc, counters, ...).
    calibration : mapping or None
        Device calibration, see :func:`session_columns`.
    raw : bool, optional
        Include the ``raw/*`` columns; blocks must then carry them too.
    flush_interval_s, fsync
        See :class:`SeriesWriter`.

    Returns
    -------
    SeriesWriter
        Takes blocks with keys ``time``, ``force``, ``position`` (+ ``raw/*``).

    Raises
    ------
    SessionExists
        If the file already holds a session of that name.
    """
    group = session_group(name)
    attrs = {k: v for k, v in meta.items() if k not in READ_ONLY_META}
    attrs.setdefault("source", "device" if raw else "import")
    return SeriesWriter(
        path,
        group,
        session_columns(raw=raw, calibration=calibration),
        attrs,
        flush_interval_s=flush_interval_s,
        fsync=fsync,
        kind="session",
    )


RAW_KEYS = ("counts", "sequence", "device_clock", "host_time")


def write_session(
    path: StrPath, session: Session, *, raw: Mapping[str, ArrayLike] | None = None
) -> None:
    """Write a whole session at once (import, demo); never overwrites.

    Parameters
    ----------
    path : str or os.PathLike
        HDF5 file (created if missing).
    session : Session
        Session to store under ``/sessions/<session.name>``; ``session.meta`` becomes
        the group attributes (``meta['calibration']``, if any, goes to ``raw/counts``).
    raw : mapping, optional
        Raw arrays ``counts`` (n, 2) int16, ``sequence`` (n,), ``device_clock`` (n,)
        in ticks, ``host_time`` (n,) in s; keys may also carry the ``raw/`` prefix.

    Raises
    ------
    SessionExists
        If the name is taken.
    InputError
        If the session has no name or its arrays differ in length.
    """
    _check_name(session.name, "session")
    n = len(session)
    for label in ("force", "position"):
        if getattr(session, label).shape != (n,):
            raise InputError(
                f"{label} has shape {getattr(session, label).shape}; expected ({n},) like time"
            )
    block: dict[str, ArrayLike] = {
        "time": session.time,
        "force": session.force,
        "position": session.position,
    }
    if raw is not None:
        for key, value in raw.items():
            short = key.removeprefix("raw/")
            if short not in RAW_KEYS:
                raise ValueError(f"unknown raw array {key!r}; expected {RAW_KEYS}")
            block[f"raw/{short}"] = value
        lengths = {k: np.shape(v)[0] if np.ndim(v) else 0 for k, v in block.items()}
        if len(set(lengths.values())) != 1:
            raise InputError(f"raw arrays and samples differ in length: {lengths}")
    calibration = session.meta.get("calibration")
    with session_writer(
        path,
        session.name,
        meta=session.meta,
        calibration=calibration,
        raw=raw is not None,
        flush_interval_s=float("inf"),
    ) as writer:
        writer.append(block)


# --------------------------------------------------------------------------- reading


def _columns_of(g: h5py.Group) -> dict[str, h5py.Dataset]:
    found: dict[str, h5py.Dataset] = {}

    def visit(name: str, obj: Any) -> None:
        if isinstance(obj, h5py.Dataset):
            found[name] = obj

    g.visititems(visit)
    return found


def _usable_rows(g: h5py.Group, datasets: Mapping[str, h5py.Dataset]) -> int:
    """Rows every column holds; for an unfinished group, no more than were committed."""
    lengths = [ds.shape[0] if ds.shape else 0 for ds in datasets.values()]
    n = min(lengths) if lengths else 0
    committed = g.attrs.get("rows_committed")
    if not bool(g.attrs.get("complete", True)) and committed is not None:
        n = min(n, int(committed))
    return n


def _require_group(f: h5py.File, group: str, path: str) -> h5py.Group:
    g = f.get(group)
    if not isinstance(g, h5py.Group):
        raise StorageError(f"{path} has no group /{group}; check the file and the name")
    return g


def read_group(path: StrPath, group: str) -> tuple[dict[str, NDArray[Any]], dict[str, Any]]:
    """Read every dataset of a group written by :class:`SeriesWriter`.

    Columns are cut to a common length: an unfinished group (``complete`` False,
    e.g. after a crash) keeps only its committed rows.

    Parameters
    ----------
    path : str or os.PathLike
        HDF5 file.
    group : str
        Group path, e.g. ``'sessions/liver-1'``.

    Returns
    -------
    columns : dict of str to ndarray
        Arrays of shape ``(n, ...)`` keyed by dataset path relative to the group.
    attrs : dict
        Decoded group attributes.

    Raises
    ------
    StorageError
        If the file or group is missing, unreadable or damaged.
    """
    name = os.fspath(path)
    with _opened(name, "r") as f:
        g = _require_group(f, _group_path(group), name)
        try:
            attrs = _decode_attrs(g.attrs)
            _check_schema(attrs.get("schema_version"), f"/{group} in {name}")
            datasets = _columns_of(g)
            n = _usable_rows(g, datasets)
            columns = {key: ds[:n] for key, ds in datasets.items()}
        except (OSError, RuntimeError, KeyError) as exc:
            raise StorageError(_unreadable(f"/{group} in {name}", exc)) from None
    return columns, attrs


def _unreadable(what: str, exc: BaseException) -> str:
    return (
        f"{what} could not be read ({_first_line(exc)}); if it is being recorded, try "
        "again in a moment, otherwise the file is damaged"
    )


def _sessions_root(f: h5py.File) -> h5py.Group | None:
    root = f.get(SESSIONS)
    return root if isinstance(root, h5py.Group) else None


def _start_key(g: h5py.Group) -> str:
    start = _from_attr(g.attrs.get("start_utc", g.attrs.get("created_utc", "")))
    return str(start) if start is not None else ""


def group_names(path: StrPath, parent: str = SESSIONS) -> list[str]:
    """Names of the groups under `parent` (e.g. 'sessions'), oldest first.

    Raises
    ------
    StorageError
        If the file is missing or not HDF5.
    """
    with _opened(path, "r") as f:
        root = f.get(_group_path(parent))
        if not isinstance(root, h5py.Group):
            return []
        groups = [(_start_key(g), key) for key, g in root.items() if isinstance(g, h5py.Group)]
    return [key for _, key in sorted(groups)]


def session_names(path: StrPath) -> list[str]:
    """Names of the sessions in `path`, oldest first."""
    return group_names(path, SESSIONS)


def _pick_session(path: str, name: str | None) -> str:
    names = session_names(path)
    if name is None:
        if len(names) == 1:
            return names[0]
        if not names:
            raise StorageError(f"{path} holds no sessions; record or import one first")
        raise StorageError(
            f"{path} holds {len(names)} sessions ({', '.join(names)}); pass --session NAME"
        )
    if name not in names:
        available = ", ".join(names) if names else "none"
        raise StorageError(
            f'no session "{name}" in {path}; available: {available}; pass one with --session'
        )
    return name


def read_session(path: StrPath, name: str | None = None, *, raw: bool = False) -> Session:
    """Read one session.

    Parameters
    ----------
    path : str or os.PathLike
        HDF5 file.
    name : str, optional
        Session name; may be omitted when the file holds exactly one session.
    raw : bool, optional
        Also return the raw arrays in ``meta['raw']``, keyed by dataset name as in
        :data:`SESSION_COLUMNS` (``'raw/counts'`` (n, 2), ``'raw/sequence'``,
        ``'raw/device_clock'``, ``'raw/host_time'``), and the calibration in
        ``meta['calibration']``; empty dicts if the session has no raw data.

    Returns
    -------
    Session
        time in s, force in N, position in m; ``meta`` holds the group attributes
        plus ``'file'``. A session cut short by a crash (``meta['complete']`` False)
        holds the rows committed before the crash.

    Raises
    ------
    StorageError
        Missing or non-HDF5 file, no or several sessions without a name, unknown name.
    """
    file = os.fspath(path)
    name = _pick_session(file, name)
    columns, meta = read_group(file, session_group(name))
    missing = [c for c in ("time", *CHANNELS) if c not in columns]
    if missing:
        raise StorageError(
            f'session "{name}" in {file} lacks dataset(s) {", ".join(missing)}; it was not '
            "written by tissuecli"
        )
    meta["file"] = file
    if raw:
        meta["raw"] = {key: value for key, value in columns.items() if key.startswith("raw/")}
        meta["calibration"] = _read_calibration(file, session_group(name))
    return Session(
        time=columns["time"],
        force=columns["force"],
        position=columns["position"],
        name=name,
        meta=meta,
    )


def _read_calibration(path: str, group: str) -> dict[str, dict[str, float]]:
    with _opened(path, "r") as f:
        ds = f.get(f"{group}/raw/counts")
        if not isinstance(ds, h5py.Dataset) or "conversion" not in ds.attrs:
            return {}
        gains = np.atleast_1d(ds.attrs["conversion"])
        offsets = np.atleast_1d(ds.attrs.get("offset", np.zeros_like(gains)))
        channels = _from_attr(ds.attrs.get("channels", np.array(CHANNELS, dtype=object)))
    return {
        str(c): {"gain": float(gains[i]), "offset": float(offsets[i])}
        for i, c in enumerate(channels)
        if i < gains.size
    }


def list_sessions(path: StrPath) -> list[dict[str, Any]]:
    """Summaries of every session in `path`, oldest first.

    Returns
    -------
    list of dict
        Keys ``name``, ``tissue``, ``samples``, ``duration_s`` (s), ``rate_hz`` (Hz,
        from the median sample interval), ``frames_lost``, ``frames_bad``,
        ``complete``, ``start_utc`` (ISO 8601), ``source``.
    """
    file = os.fspath(path)
    out: list[dict[str, Any]] = []
    with _opened(file, "r") as f:
        root = _sessions_root(f)
        if root is None:
            return []
        for key, g in root.items():
            if not isinstance(g, h5py.Group) or not isinstance(g.get("time"), h5py.Dataset):
                continue
            try:
                attrs = _decode_attrs(g.attrs)
                n = _usable_rows(g, _columns_of(g))
                t = g["time"][:n]
            except (OSError, RuntimeError, KeyError) as exc:
                raise StorageError(_unreadable(f'session "{key}" in {file}', exc)) from None
            steps = np.diff(t)
            out.append(
                {
                    "name": key,
                    "tissue": attrs.get("tissue", ""),
                    "samples": int(n),
                    "duration_s": float(t[-1] - t[0]) if n > 1 else 0.0,
                    "rate_hz": float(1.0 / np.median(steps))
                    if n > 1 and np.median(steps) > 0
                    else 0.0,
                    "frames_lost": int(attrs.get("frames_lost", 0) or 0),
                    "frames_bad": int(attrs.get("frames_bad", 0) or 0),
                    "complete": bool(attrs.get("complete", False)),
                    "start_utc": attrs.get("start_utc") or attrs.get("created_utc", ""),
                    "source": attrs.get("source", ""),
                }
            )
    out.sort(key=lambda s: (str(s["start_utc"]), s["name"]))
    return out
