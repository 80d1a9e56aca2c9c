"""Named arrays as labs save them: MATLAB .mat files (v4-v7 through ``scipy.io``, v7.3
through the HDF5 layer) and NumPy .npz archives. Every numeric vector of the record's
length becomes a column; a matrix becomes one column per row or column
(``name:1``, ``name:2``, ...); struct fields are ``struct.field``. Scalars (a sampling
rate, say) are kept apart."""

from __future__ import annotations

import os
import zipfile
from collections import Counter
from pathlib import Path

import h5py
import numpy as np
from numpy.typing import NDArray

from ..core.errors import InputError
from .tables import Table

#: a matrix with at most this many rows (or columns) is a set of signals, not an image
MAX_SIGNALS = 16


def read_arrays(path: str | os.PathLike[str]) -> Table:
    """The numeric signals of a .mat or .npz file as a :class:`Table`.

    Raises
    ------
    InputError
        The file cannot be read, or holds no numeric vector.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path} does not exist; check the path")
    if path.suffix.lower() == ".npz" or zipfile.is_zipfile(path):
        found, kind = _npz(path), "NumPy .npz"
    elif h5py.is_hdf5(path):
        found, kind = _mat73(path), "MATLAB v7.3 (HDF5)"
    else:
        found, kind = _mat5(path), "MATLAB .mat"
    vectors: dict[str, NDArray[np.float64]] = {}
    scalars: list[str] = []
    for name, value in found.items():
        arr = np.asarray(value)
        if arr.dtype.kind not in "biuf" or arr.dtype.kind == "b":
            continue
        arr = np.squeeze(arr).astype(float)
        if arr.ndim == 0 or arr.size == 1:
            scalars.append(f"{name} = {float(arr.ravel()[0]):.6g}")
        elif arr.ndim == 1:
            vectors[name] = arr
        elif arr.ndim == 2 and min(arr.shape) <= MAX_SIGNALS:
            columns = arr if arr.shape[0] >= arr.shape[1] else arr.T
            for j in range(columns.shape[1]):
                vectors[f"{name}:{j + 1}"] = columns[:, j]
    if not vectors:
        raise InputError(f"{path} holds no numeric vector; save the signals as 1-D arrays")
    length, _ = Counter(v.size for v in vectors.values()).most_common(1)[0]
    longest = max(v.size for v in vectors.values())
    length = longest if sum(v.size == longest for v in vectors.values()) >= 2 else length
    names = [n for n, v in vectors.items() if v.size == length]
    others = [n for n in vectors if n not in names]
    notes = [f"{kind}, {len(names)} signal(s) of {length} samples"]
    if others:
        notes.append(f"ignored: {', '.join(others[:8])} (other lengths)")
    if scalars:
        notes.append("scalars: " + ", ".join(scalars[:8]))
    return Table(
        names=names,
        data=np.column_stack([vectors[n] for n in names]),
        lines=np.arange(1, length + 1, dtype=np.int64),
        source=kind,
        notes=notes,
        header=True,
    )


def _npz(path: Path) -> dict[str, object]:
    try:
        with np.load(path, allow_pickle=False) as archive:
            return {name: archive[name] for name in archive.files}
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise InputError(f"cannot read {path} as a NumPy .npz archive: {exc}") from None


def _mat5(path: Path) -> dict[str, object]:
    from scipy import io  # only for MATLAB files

    try:
        contents = io.loadmat(path, squeeze_me=True, struct_as_record=False)
    except (ValueError, TypeError, OSError, NotImplementedError) as exc:
        raise InputError(
            f"cannot read {path} as a MATLAB .mat file ({str(exc)[:80]}); give a .mat, .npz "
            "or text table"
        ) from None
    out: dict[str, object] = {}
    for name, value in contents.items():
        if name.startswith("__"):
            continue
        fields = getattr(value, "_fieldnames", None)
        if fields:  # a struct: one level of fields
            out.update({f"{name}.{f}": getattr(value, f) for f in fields})
        else:
            out[name] = value
    return out


def _mat73(path: Path) -> dict[str, object]:
    """MATLAB v7.3 files are HDF5; MATLAB writes arrays column-major, so they are
    transposed back."""
    out: dict[str, object] = {}
    try:
        with h5py.File(path, "r") as f:

            def visit(name: str, obj: object) -> None:
                if isinstance(obj, h5py.Dataset) and not name.startswith("#"):
                    if obj.dtype.kind in "iuf" and obj.size <= 50_000_000:
                        out[name.replace("/", ".")] = np.asarray(obj[()]).T

            f.visititems(visit)
    except (OSError, RuntimeError) as exc:
        raise InputError(f"cannot read {path} as a MATLAB v7.3 file: {exc}") from None
    return out
