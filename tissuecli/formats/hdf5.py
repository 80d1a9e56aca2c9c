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

Storage faults (disk full, quota, file-size limit) are caught before HDF5 writes
anything (see :mod:`.space`). Every read is checked against the documented layout:
datasets must be numeric with one row per sample, counters must be numbers, and
anything else is reported as damage in one line instead of a traceback.
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import date, datetime, timezone
from typing import Any

import h5py
import numpy as np
from numpy.typing import NDArray

from .._version import __version__
from ..core.errors import StorageError
from .space import fault_cause, is_storage_fault

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


#: exceptions h5py raises for a file or object it cannot read or write: OSError for most,
#: RuntimeError for failed writes and flushes, KeyError/ValueError/TypeError for objects
#: and types it cannot make sense of
H5_ERRORS = (OSError, RuntimeError, KeyError, ValueError, TypeError)

#: dtype kinds of numeric datasets: signed and unsigned integers and floats (never bool,
#: text, compound, complex or opaque)
NUMBERS = "iuf"
INTEGERS = "iu"
#: a dataset may hold at most this many times more bytes than the whole file (compressed
#: data); beyond that its size is damage, and reading it would only exhaust memory
MAX_INFLATION = 64


def decode_attrs(attrs: h5py.AttributeManager, problems: list[str] | None = None) -> dict[str, Any]:
    """Every attribute, decoded with :func:`from_attr`.

    An attribute that cannot be read (a type h5py does not know, a damaged heap) is
    left out and, if `problems` is given, named there.
    """
    out: dict[str, Any] = {}
    for key in list(attrs):
        try:
            out[key] = from_attr(attrs[key])
        except H5_ERRORS as exc:
            if problems is not None:
                problems.append(
                    f"attribute {clip(key)} could not be read ({clip(first_line(exc))})"
                )
    return out


def utc_now() -> str:
    # microseconds: sessions written in quick succession still sort in creation order
    return datetime.now(timezone.utc).isoformat(timespec="microseconds")


def first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return clip(text[0], 200) if text else type(exc).__name__


def clip(text: object, limit: int = 60) -> str:
    """`text` cut to `limit` characters (messages never echo unbounded data)."""
    s = str(text)
    return s if len(s) <= limit else s[: limit - 3] + "..."


class FileAppeared(StorageError):
    """A file to be created exists already: another program made it meanwhile."""


def open_file(path: StrPath, mode: str) -> h5py.File:
    """Open an HDF5 file, turning every OS/HDF5 failure into a one-line StorageError.

    Readers ignore HDF5's file lock so that a session can be listed or read while it
    is being recorded; they trust only ``rows_committed`` rows of an unfinished group,
    which the writer updates only after the rows themselves are on disk.

    Raises
    ------
    FileAppeared
        In mode ``'w-'`` (create), if the file exists.
    StorageError
        For every other failure, in words.
    """
    name = os.fspath(path)
    try:
        if mode == "r":
            return h5py.File(name, mode, locking=False)
        return h5py.File(name, mode)
    except FileExistsError:
        raise FileAppeared(
            f"{name} was created by another program meanwhile; try again or choose another file"
        ) from None
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
    except (OSError, RuntimeError) as exc:
        raise StorageError(open_failure(name, mode, exc)) from None


_TRUNCATED = re.compile(r"truncated file: eof = (\d+).*stored_eof = (\d+)")


def truncated_at(exc: BaseException) -> tuple[int, int] | None:
    """``(size, stated size)`` in bytes if HDF5 refused a file as truncated, else None."""
    match = _TRUNCATED.search(str(exc))
    return (int(match.group(1)), int(match.group(2))) if match else None


def open_failure(name: str, mode: str, exc: BaseException) -> str:
    """One line saying why HDF5 could not open `name`, from the error h5py raised."""
    msg = str(exc)
    if "signature" in msg:
        return f"{name} is not an HDF5 file; give an .h5 file written by tissuecli"
    # HDF5: "unable to lock file, errno = 11" (EAGAIN); never a substring test on "lock",
    # which "sblock->base_addr" in the message of a truncated file also contains
    if isinstance(exc, BlockingIOError) or "unable to lock file" in msg:
        return (
            f"{name} is being written by another program (a recording still running?); "
            "wait until it ends or write to another file"
        )
    truncated = truncated_at(exc)
    if truncated:
        return (
            f"{name} is damaged or truncated: it ends at byte {truncated[0]} but its HDF5 "
            f"header says {truncated[1]} (a copy or download cut short?); restore it from a "
            "complete copy"
        )
    if mode != "r" and is_storage_fault(exc):
        return f"cannot write {name}: {fault_cause(exc)}; free some space or choose another drive"
    return f"{name} is damaged and cannot be opened ({first_line(exc)}); restore it from a copy"


@contextmanager
def opened(path: StrPath, mode: str = "r") -> Iterator[h5py.File]:
    f = open_file(path, mode)
    try:
        yield f
    finally:
        try:
            f.close()
        except H5_ERRORS:  # a reader has nothing to lose; the error that matters came first
            pass


def damaged(path: str, what: str, exc: BaseException) -> StorageError:
    """The error for an object of an opened file that HDF5 cannot read."""
    return StorageError(
        f"{what} in {path} is damaged ({first_line(exc)}); the file cannot be read as it is"
    )


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


def is_own_file(f: h5py.File) -> bool:
    """True if `f` is empty or carries tissuecli's root attributes.

    Raises
    ------
    OSError, RuntimeError, ...
        If the root cannot be read (the caller reports the file as damaged).
    """
    if len(f) == 0 and len(f.attrs) == 0:
        return True
    software = from_attr(f.attrs["software"]) if "software" in f.attrs else None
    return isinstance(software, str) and software.startswith("tissuecli")


def foreign_message(path: str, option: str) -> str:
    return (
        f"{path} was not written by tissuecli (it holds other HDF5 data and no tissuecli "
        f"root attributes); tissuecli adds only to its own files: give a new file with {option}"
    )


def group_path(group: str) -> str:
    path = "/".join(part for part in group.split("/") if part)
    if not path:
        raise ValueError("group path is empty")
    return path


def exists_message(kind: str, name: str, path: str) -> str:
    return f'{kind} "{name}" already exists in {path}; choose another --{kind} name'


def describe_dtype(dtype: np.dtype[Any]) -> str:
    """What a dataset holds, in words: 'text', 'booleans', 'compound records', ..."""
    if h5py.check_string_dtype(dtype) is not None or dtype.kind in "SU":
        return "text"
    if dtype.fields is not None:
        return "compound records"
    if dtype.subdtype is not None:
        return "an array per element"
    return {
        "b": "booleans",
        "c": "complex numbers",
        "O": "references or variable-length data",
        "V": "opaque bytes",
        "M": "dates",
        "m": "time spans",
        "f": "floating-point numbers",
        "i": "integers",
        "u": "integers",
    }.get(dtype.kind, f"values of type {dtype}")


def shape_text(trailing: tuple[int, ...]) -> str:
    return "(n, " + ", ".join(map(str, trailing)) + ")" if trailing else "(n,)"


def dataset_problem(obj: Any, kinds: str = NUMBERS, trailing: tuple[int, ...] = ()) -> str | None:
    """Why `obj` is not a dataset of shape ``(n, *trailing)`` with a dtype of `kinds`.

    Parameters
    ----------
    obj : h5py object or None
        What the group holds under the dataset's name (None if nothing).
    kinds : str
        Allowed dtype kinds, :data:`NUMBERS` or :data:`INTEGERS`.
    trailing : tuple of int
        Shape of one row, ``()`` for one value per row.

    Returns
    -------
    str or None
        The problem in words ('holds text; expected numbers'), or None if it fits.
    """
    if obj is None:
        return "is missing"
    if not isinstance(obj, h5py.Dataset):
        return "is not a dataset"
    pointer = elsewhere(obj)
    if pointer:
        return pointer
    dtype = obj.dtype
    wanted = "integers" if kinds == INTEGERS else "numbers"
    if dtype.fields is not None or dtype.subdtype is not None or dtype.kind not in kinds:
        return f"holds {describe_dtype(dtype)}; expected {wanted}"
    shape = obj.shape
    if shape is None:
        return "holds no dataspace (an empty attribute-like dataset); expected one row per sample"
    if len(shape) == 0:
        return f"is a single value; expected shape {shape_text(trailing)}, one row per sample"
    if tuple(shape[1:]) != tuple(trailing):
        return f"has shape {tuple(shape)}; expected {shape_text(trailing)}"
    return None


def elsewhere(ds: h5py.Dataset) -> str | None:
    """Why `ds` would read bytes from outside its own file, or None.

    An input file is data, never a pointer: a dataset with external raw storage (its
    bytes in another file, any file the user can read) or a virtual dataset (mapped
    from other datasets, in other files or this one) is refused before a byte of it
    is read. Only the dataset's creation properties are looked at.
    """
    try:
        plist = ds.id.get_create_plist()
        if plist.get_layout() == h5py.h5d.VIRTUAL:
            return (
                "is a virtual dataset (its values are mapped from other datasets or files); "
                "tissuecli reads only data stored in the file given"
            )
        if plist.get_external_count() > 0:
            return (
                "keeps its values in another file (HDF5 external storage); tissuecli reads "
                "only data stored in the file given"
            )
    except H5_ERRORS as exc:
        return f"has creation properties that cannot be read ({first_line(exc)})"
    return None


def columns_of(g: h5py.Group) -> dict[str, h5py.Dataset]:
    found: dict[str, h5py.Dataset] = {}

    def visit(name: str, obj: Any) -> None:
        if isinstance(obj, h5py.Dataset):
            found[name] = obj

    g.visititems(visit)
    return found


def count_value(value: Any) -> int | None:
    """`value` as a count (an integer >= 0), or None if it is not one.

    Accepts integers, integral floats (MATLAB writes doubles) and one-element arrays;
    never booleans or text.
    """
    value = scalar(value)
    if isinstance(value, (bool, np.bool_)):
        return None
    if isinstance(value, (int, np.integer)):
        return int(value) if value >= 0 else None
    if isinstance(value, (float, np.floating)) and math.isfinite(value) and value >= 0:
        return int(value) if float(value).is_integer() else None
    return None


def flag_value(value: Any) -> bool | None:
    """`value` as a boolean (bool, or the integers 0 and 1), or None if it is not one."""
    value = scalar(value)
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)) and int(value) in (0, 1):
        return bool(value)
    return None


def number_value(value: Any) -> float | None:
    """`value` as a float (NaN allowed), or None if it is not a number."""
    value = scalar(value)
    if isinstance(value, (bool, np.bool_)):
        return None
    if isinstance(value, (int, float, np.integer, np.floating)):
        return float(value)
    return None


def scalar(value: Any) -> Any:
    """The element of a one-element array (MATLAB stores attributes as 1x1 arrays)."""
    if isinstance(value, np.ndarray) and value.size == 1 and value.dtype.kind in "biuf":
        return value.reshape(()).item()
    return value


def committed_rows(attrs: Mapping[str, Any]) -> tuple[bool | None, int | None]:
    """``complete`` and ``rows_committed`` of a group's decoded attributes (None if unusable)."""
    return flag_value(attrs.get("complete")), count_value(attrs.get("rows_committed"))


def usable_rows(lengths: Sequence[int], complete: bool | None, committed: int | None) -> int:
    """Rows every column holds; unless the group is complete, no more than were committed.

    A group whose ``complete`` flag is missing or unreadable is trusted no further than
    its ``rows_committed`` counter, like an unfinished one.
    """
    lengths = list(lengths)
    n = min(lengths) if lengths else 0
    if complete is not True and committed is not None:
        n = min(n, committed)
    return n


def check_size(ds: h5py.Dataset, n: int, file_bytes: int) -> str | None:
    """A problem if reading `n` rows of `ds` needs far more memory than the file holds."""
    row = ds.dtype.itemsize * int(np.prod(ds.shape[1:], dtype=np.int64))
    if n * row > MAX_INFLATION * file_bytes + (1 << 20):
        return f"claims {n} rows, more than the file can hold"
    return None


def file_size(f: h5py.File) -> int:
    try:
        return int(f.id.get_filesize())
    except H5_ERRORS:
        return 0


def require_group(f: h5py.File, group: str, path: str) -> h5py.Group:
    try:
        g = f.get(group)
    except H5_ERRORS as exc:
        raise damaged(path, f"/{group}", exc) from None
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
        Group path, e.g. ``'plays/play-1'``.

    Returns
    -------
    columns : dict of str to ndarray
        Arrays of shape ``(n, ...)`` keyed by dataset path relative to the group.
    attrs : dict
        Decoded group attributes.

    Raises
    ------
    StorageError
        If the file or group is missing, unreadable or damaged, or a dataset is not
        numeric with one row per sample.
    """
    name = os.fspath(path)
    where = f"/{group_path(group)}"
    with opened(name, "r") as f:
        g = require_group(f, group_path(group), name)
        try:
            attrs = decode_attrs(g.attrs)
            check_schema(attrs.get("schema_version"), f"{where} in {name}")
            datasets = columns_of(g)
            for key, ds in datasets.items():
                problem = dataset_problem(ds, NUMBERS, tuple(ds.shape[1:]) if ds.shape else ())
                if problem:
                    raise StorageError(
                        f"{where} in {name} is damaged: dataset {clip(key)} {problem}"
                    )
            n = usable_rows([ds.shape[0] for ds in datasets.values()], *committed_rows(attrs))
            size = file_size(f)
            for key, ds in datasets.items():
                problem = check_size(ds, n, size)
                if problem:
                    raise StorageError(
                        f"{where} in {name} is damaged: dataset {clip(key)} {problem}"
                    )
            columns = {key: ds[:n] for key, ds in datasets.items()}
        except H5_ERRORS as exc:
            raise StorageError(unreadable(f"{where} in {name}", exc)) from None
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
        If the file is missing, not HDF5, or its list of groups is damaged.
    """
    name = os.fspath(path)
    with opened(name, "r") as f:
        try:
            root = f.get(group_path(parent))
            if not isinstance(root, h5py.Group):
                return []
            groups = [(start_key(g), key) for key, g in root.items() if isinstance(g, h5py.Group)]
        except H5_ERRORS as exc:
            raise damaged(name, f"/{parent}", exc) from None
    return [key for _, key in sorted(groups)]


def has_group(path: StrPath, parent: str, key: str) -> bool:
    """Whether a group named `key` lies under `parent`: one lookup, where
    :func:`group_names` reads every group's start to sort them.

    Raises
    ------
    StorageError
        If the file is missing, not HDF5, or its list of groups is damaged.
    """
    name = os.fspath(path)
    with opened(name, "r") as f:
        try:
            root = f.get(group_path(parent))
            return (
                isinstance(root, h5py.Group)
                and isinstance(root.get(key, getlink=True), h5py.HardLink)
                and isinstance(root.get(key), h5py.Group)
            )
        except H5_ERRORS as exc:
            raise damaged(name, f"/{parent}", exc) from None


def start_key(g: h5py.Group) -> str:
    """When a group started (``start_utc``, else ``created_utc``), to sort by; '' if unknown."""
    for key in ("start_utc", "created_utc"):
        try:
            value = from_attr(g.attrs[key]) if key in g.attrs else None
        except H5_ERRORS:
            value = None
        if isinstance(value, str) and value:
            return value
    return ""
