"""Named arrays as labs save them: MATLAB .mat files (v4-v7 through ``scipy.io``, v7.3
through the HDF5 layer) and NumPy .npz archives. Every numeric vector of the record's
length becomes a column; a matrix becomes one column per row or column
(``name:1``, ``name:2``, ...); struct fields are ``struct.field``. Scalars (a sampling
rate, say) are kept apart."""

from __future__ import annotations

import os
import zipfile
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from numpy.typing import NDArray

from ..core.errors import InputError
from .limits import check_declared
from .tables import Table

#: a matrix with at most this many rows (or columns) is a set of signals, not an image
MAX_SIGNALS = 16


@dataclass
class _Entry:
    """A stored array, known by its declared shape and type before it is read."""

    shape: tuple[int, ...]
    dtype: np.dtype[Any]
    load: Callable[[], Any]


def read_arrays(path: str | os.PathLike[str]) -> Table:
    """The numeric signals of a .mat or .npz file as a :class:`Table`.

    Every array's declared shape is checked against what the file holds and the memory
    this process may use (:mod:`.limits`) before it is read; only the vectors kept are
    read.

    Raises
    ------
    InputError
        The file cannot be read, holds no numeric vector, or declares more than it holds.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path} does not exist; check the path")
    file_bytes = path.stat().st_size
    if path.suffix.lower() == ".npz" or zipfile.is_zipfile(path):
        found, kind = _npz(path), "NumPy .npz"
    elif h5py.is_hdf5(path):
        found, kind = _mat73(path), "MATLAB v7.3 (HDF5)"
    else:
        found, kind = _mat5(path, file_bytes), "MATLAB .mat"
    shapes: dict[str, tuple[int, ...]] = {}
    scalars: list[str] = []
    for name, entry in found.items():
        if entry.dtype.kind not in "iuf":
            continue
        shape = tuple(d for d in entry.shape if d != 1)
        if len(shape) == 0:
            scalars.append(name)
        elif len(shape) == 1 or (len(shape) == 2 and min(shape) <= MAX_SIGNALS):
            shapes[name] = shape
    if not shapes:
        raise InputError(f"{path} holds no numeric vector; save the signals as 1-D arrays")
    signals = {name: max(shape) for name, shape in shapes.items()}
    counts = Counter(signals.values())
    length, _ = counts.most_common(1)[0]
    longest = max(signals.values())
    length = longest if counts[longest] >= 2 else length
    kept = [n for n, size in signals.items() if size == length]
    declared = sum(int(np.prod(found[n].shape)) * found[n].dtype.itemsize for n in kept)
    check_declared(max(declared, 8 * length * len(kept)), file_bytes, f"{path}")
    vectors: dict[str, NDArray[np.float64]] = {}
    for name in kept:
        arr = np.squeeze(np.asarray(found[name].load())).astype(float)
        if arr.ndim == 1:
            vectors[name] = arr
        else:
            columns = arr if arr.shape[0] >= arr.shape[1] else arr.T
            for j in range(columns.shape[1]):
                vectors[f"{name}:{j + 1}"] = columns[:, j]
    values = []
    for name in scalars[:8]:
        try:
            values.append(f"{name} = {float(np.ravel(found[name].load())[0]):.6g}")
        except (ValueError, IndexError, TypeError, OSError):
            continue
    others = [n for n in shapes if n not in kept]
    names = list(vectors)
    notes = [f"{kind}, {len(names)} signal(s) of {length} samples"]
    if others:
        notes.append(f"ignored: {', '.join(others[:8])} (other lengths)")
    if values:
        notes.append("scalars: " + ", ".join(values))
    return Table(
        names=names,
        data=np.column_stack([vectors[n] for n in names]),
        lines=np.arange(1, length + 1, dtype=np.int64),
        source=kind,
        notes=notes,
        header=True,
    )


_NPY_HEADERS = {
    (1, 0): np.lib.format.read_array_header_1_0,
    (2, 0): np.lib.format.read_array_header_2_0,
}


def _npz(path: Path) -> dict[str, _Entry]:
    """The arrays of a .npz archive, from their .npy headers (nothing is inflated yet).

    Each member's header declares its shape and type; the zip directory declares how
    many bytes it inflates to (and :mod:`zipfile` never inflates more). An array that
    declares more elements than its member holds is refused, as is a pickled one."""
    try:
        archive = zipfile.ZipFile(path)
    except (OSError, zipfile.BadZipFile, ValueError) as exc:
        raise InputError(f"cannot read {path} as a NumPy .npz archive: {exc}") from None
    out: dict[str, _Entry] = {}
    with archive:
        for info in archive.infolist():
            if not info.filename.endswith(".npy"):
                continue
            name = info.filename[: -len(".npy")]
            try:
                with archive.open(info) as fh:
                    version = np.lib.format.read_magic(fh)
                    reader = _NPY_HEADERS.get(version)
                    if reader is None:
                        raise ValueError(f"unsupported .npy version {version}")
                    shape, fortran, dtype = reader(fh)
                    offset = fh.tell()
            except (OSError, ValueError, zipfile.BadZipFile, RuntimeError, EOFError) as exc:
                raise InputError(
                    f"cannot read array {name!r} of {path} ({str(exc)[:80]}); give a .npz "
                    "written by numpy.savez"
                ) from None
            if dtype.hasobject:
                raise InputError(
                    f"array {name!r} of {path} holds Python objects (a pickle), which are "
                    "never loaded; save numeric arrays"
                )
            elements = int(np.prod(shape, dtype=object))
            if elements * dtype.itemsize > info.file_size - offset:
                raise InputError(
                    f"array {name!r} of {path} declares {elements} elements of "
                    f"{dtype.itemsize} bytes but holds {max(0, info.file_size - offset)} "
                    "bytes; the file is damaged"
                )
            out[name] = _Entry(
                tuple(int(d) for d in shape), dtype, partial(_npy, path, info.filename)
            )
    return out


def _npy(path: Path, member: str) -> NDArray[Any]:
    try:
        with zipfile.ZipFile(path) as archive, archive.open(member) as fh:
            return np.lib.format.read_array(fh, allow_pickle=False)
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise InputError(f"cannot read {member} of {path}: {str(exc)[:80]}") from None


def _mat5(path: Path, file_bytes: int) -> dict[str, _Entry]:
    from scipy import io  # only for MATLAB files

    fail = (ValueError, TypeError, OSError, NotImplementedError, EOFError, MemoryError)
    try:
        declared = io.whosmat(path)
    except fail as exc:
        raise InputError(
            f"cannot read {path} as a MATLAB .mat file ({str(exc)[:80]}); give a .mat, .npz "
            "or text table"
        ) from None
    sizes = {"double": 8, "single": 4, "int8": 1, "uint8": 1, "int16": 2, "uint16": 2,
             "int32": 4, "uint32": 4, "int64": 8, "uint64": 8}  # fmt: skip
    total = sum(int(np.prod(shape, dtype=object)) * sizes.get(cls, 8) for _, shape, cls in declared)
    check_declared(total, file_bytes, f"{path}")
    try:
        contents = io.loadmat(path, squeeze_me=True, struct_as_record=False)
    except fail as exc:
        raise InputError(
            f"cannot read {path} as a MATLAB .mat file ({str(exc)[:80]}); give a .mat, .npz "
            "or text table"
        ) from None
    out: dict[str, _Entry] = {}
    for name, value in contents.items():
        if name.startswith("__"):
            continue
        fields = getattr(value, "_fieldnames", None)
        items = {f"{name}.{f}": getattr(value, f) for f in fields} if fields else {name: value}
        for key, item in items.items():  # a struct: one level of fields
            arr = np.asarray(item)
            out[key] = _Entry(arr.shape, arr.dtype, partial(lambda a: a, arr))
    return out


def _mat73(path: Path) -> dict[str, _Entry]:
    """MATLAB v7.3 files are HDF5; MATLAB writes arrays column-major, so they are
    transposed back. A dataset stored outside the file is refused (:func:`.hdf5.elsewhere`)."""
    from .hdf5 import elsewhere

    out: dict[str, _Entry] = {}
    try:
        with h5py.File(path, "r") as f:

            def visit(name: str, obj: object) -> None:
                if isinstance(obj, h5py.Dataset) and not name.startswith("#"):
                    pointer = elsewhere(obj)
                    if pointer:
                        raise InputError(f"{path}: dataset /{name} {pointer}")
                    if obj.dtype.kind in "iuf" and obj.shape:
                        out[name.replace("/", ".")] = _Entry(
                            tuple(reversed(obj.shape)), obj.dtype, partial(_h5, path, name)
                        )

            f.visititems(visit)
    except (OSError, RuntimeError) as exc:
        raise InputError(f"cannot read {path} as a MATLAB v7.3 file: {exc}") from None
    return out


def _h5(path: Path, name: str) -> NDArray[Any]:
    try:
        with h5py.File(path, "r") as f:
            return np.asarray(f[name][()]).T
    except (OSError, RuntimeError, KeyError) as exc:
        raise InputError(f"cannot read /{name} of {path}: {str(exc)[:80]}") from None
