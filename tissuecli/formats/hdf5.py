"""HDF5 files: attributes, opening with one-line errors, fsync, and reading a group.

h5py is imported only in :mod:`tissuecli.formats`. A file holds any number of sessions
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
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import date, datetime, timezone
from typing import Any

import h5py
import numpy as np
from numpy.typing import NDArray

from .._version import __version__
from ..core.errors import StorageError

StrPath = str | os.PathLike[str]

#: version of the file layout; readers refuse newer ones
SCHEMA_VERSION = 1

#: rows per chunk: 32 KiB for float64, few chunk-index entries even for hour-long sessions
CHUNK_ROWS = 4096
#: group attributes managed by :class:`SeriesWriter`; caller values for these are replaced
MANAGED_ATTRS = ("schema_version", "software_version", "created_utc", "complete", "rows_committed")


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


def _json_default(value: Any) -> Any:
    """Make NumPy scalars and arrays JSON-serialisable."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (datetime, date)):
        return value.isoformat()
    raise TypeError(f"cannot store {type(value).__name__} in an HDF5 attribute")


def to_attr(value: Any) -> Any:
    """Encode a Python value as something h5py can store as an attribute.

    ``None`` becomes an empty attribute, dicts and non-string lists become JSON
    strings, lists of strings become HDF5 string arrays, NumPy arrays are stored
    as they are. :func:`from_attr` undoes this.
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
            return to_attr(value.astype(str).tolist())
        return value
    if isinstance(value, (list, tuple)):
        if value and all(isinstance(v, str) for v in value):
            # a native string array stays readable by any HDF5 tool
            return np.array(value, dtype=h5py.string_dtype())
        return json.dumps(list(value), default=_json_default)
    if isinstance(value, Mapping):
        return json.dumps(dict(value), default=_json_default)
    raise TypeError(f"cannot store {type(value).__name__} in an HDF5 attribute")


def from_attr(value: Any) -> Any:
    """Decode an attribute read by h5py into plain Python (inverse of :func:`to_attr`)."""
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


def set_attr(attrs: h5py.AttributeManager, key: str, encoded: Any) -> None:
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


def decode_attrs(attrs: h5py.AttributeManager) -> dict[str, Any]:
    return {key: from_attr(attrs[key]) for key in attrs}


def utc_now() -> str:
    # microseconds: sessions written in quick succession still sort in creation order
    return datetime.now(timezone.utc).isoformat(timespec="microseconds")


def first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


def open_file(path: StrPath, mode: str) -> h5py.File:
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
        raise StorageError(f"cannot open {name}: {first_line(exc)}") from None


@contextmanager
def opened(path: StrPath, mode: str = "r") -> Iterator[h5py.File]:
    f = open_file(path, mode)
    try:
        yield f
    finally:
        f.close()


def fsync_file(f: h5py.File, path: str) -> None:
    """Push the file's pages to the storage device (survives a power cut)."""
    try:
        fd = f.id.get_vfd_handle()
    except Exception:  # drivers without a POSIX descriptor
        fd = None
    if isinstance(fd, int) and fd >= 0:
        os.fsync(fd)
        return
    fsync_path(path)


def fsync_path(path: str) -> None:
    # fsync acts on the inode, so a fresh descriptor flushes pages written through another
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def fsync_dir(path: str) -> None:
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


def check_schema(version: Any, where: str) -> None:
    if isinstance(version, (int, np.integer)) and int(version) > SCHEMA_VERSION:
        raise StorageError(
            f"{where} uses storage schema {int(version)}, newer than this tissuecli "
            f"({__version__}, schema {SCHEMA_VERSION}); upgrade tissuecli"
        )


def group_path(group: str) -> str:
    path = "/".join(part for part in group.split("/") if part)
    if not path:
        raise ValueError("group path is empty")
    return path


def exists_message(kind: str, name: str, path: str) -> str:
    return f'{kind} "{name}" already exists in {path}; choose another --{kind} name'


def columns_of(g: h5py.Group) -> dict[str, h5py.Dataset]:
    found: dict[str, h5py.Dataset] = {}

    def visit(name: str, obj: Any) -> None:
        if isinstance(obj, h5py.Dataset):
            found[name] = obj

    g.visititems(visit)
    return found


def usable_rows(g: h5py.Group, datasets: Mapping[str, h5py.Dataset]) -> int:
    """Rows every column holds; for an unfinished group, no more than were committed."""
    lengths = [ds.shape[0] if ds.shape else 0 for ds in datasets.values()]
    n = min(lengths) if lengths else 0
    committed = g.attrs.get("rows_committed")
    if not bool(g.attrs.get("complete", True)) and committed is not None:
        n = min(n, int(committed))
    return n


def require_group(f: h5py.File, group: str, path: str) -> h5py.Group:
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
    with opened(name, "r") as f:
        g = require_group(f, group_path(group), name)
        try:
            attrs = decode_attrs(g.attrs)
            check_schema(attrs.get("schema_version"), f"/{group} in {name}")
            datasets = columns_of(g)
            n = usable_rows(g, datasets)
            columns = {key: ds[:n] for key, ds in datasets.items()}
        except (OSError, RuntimeError, KeyError) as exc:
            raise StorageError(unreadable(f"/{group} in {name}", exc)) from None
    return columns, attrs


def unreadable(what: str, exc: BaseException) -> str:
    return (
        f"{what} could not be read ({first_line(exc)}); if it is being recorded, try "
        "again in a moment, otherwise the file is damaged"
    )


def group_names(path: StrPath, parent: str) -> list[str]:
    """Names of the groups under `parent` (e.g. 'sessions'), oldest first.

    Raises
    ------
    StorageError
        If the file is missing or not HDF5.
    """
    with opened(path, "r") as f:
        root = f.get(group_path(parent))
        if not isinstance(root, h5py.Group):
            return []
        groups = [(start_key(g), key) for key, g in root.items() if isinstance(g, h5py.Group)]
    return [key for _, key in sorted(groups)]


def start_key(g: h5py.Group) -> str:
    start = from_attr(g.attrs.get("start_utc", g.attrs.get("created_utc", "")))
    return str(start) if start is not None else ""
