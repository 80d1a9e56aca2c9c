"""Other programs' binary recordings: generic HDF5 (datasets named by their path), NWB
TimeSeries, and LabVIEW TDMS (through npTDMS, the ``tdms`` extra).

Each file becomes a :class:`Columns`: named signals of one length, known by their
declared shapes, whose values are read block by block only when chosen. Columns are
matched by name (``/data/force``), or by their last word (``force``) against the
synonyms of :mod:`.recording`. Nothing outside the file is ever read: an HDF5 dataset
with external storage or virtual sources is refused before a byte of it is read (see
:func:`.hdf5.elsewhere`; external links are never followed), and npTDMS is handed the
open file, so that it never opens a ``.tdms_index`` beside it.
"""

from __future__ import annotations

import os
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..core.errors import InputError
from .limits import BLOCK_ROWS, check_declared
from .tables import Block

#: a matrix with at most this many columns is a set of signals, not an image
MAX_SIGNALS = 16
#: unit words other programs write (NWB, LabVIEW) and the units tissuecli reads
UNIT_WORDS = {
    "second": "s", "seconds": "s", "sec": "s", "millisecond": "ms", "milliseconds": "ms",
    "meter": "m", "meters": "m", "metre": "m", "metres": "m", "millimeter": "mm",
    "millimeters": "mm", "millimetre": "mm", "millimetres": "mm", "micrometer": "um",
    "micrometers": "um", "newton": "N", "newtons": "N", "millinewton": "mN",
    "millinewtons": "mN", "gram": "g", "grams": "g", "degree": "deg", "degrees": "deg",
    "radian": "rad", "radians": "rad",
}  # fmt: skip

#: reads rows ``start:stop`` of a column, in its unit
Reader = Callable[[int, int], NDArray[np.float64]]


@dataclass
class Columns:
    """Named signals of one length from a binary file, read only when chosen.

    Attributes
    ----------
    names : list of str
        Full names (``/acquisition/force``, ``group/channel``).
    keys : list of str
        The word each is matched by (its last path element).
    units : list of str
        The unit each declares (``""`` if none), as a units row.
    """

    path: Path
    source: str
    names: list[str]
    keys: list[str]
    units: list[str]
    readers: list[Reader]
    length: int
    notes: list[str] = field(default_factory=list)
    elsewhere: dict[int, str] = field(default_factory=dict)
    header: bool = True
    rows: int = 0

    @property
    def numeric(self) -> list[bool]:
        return [True] * len(self.names)

    def head_text(self, index: int) -> list[str]:
        return []

    def blocks(self, columns: list[int]) -> Iterator[Block]:
        """The chosen columns, :data:`~.limits.BLOCK_ROWS` rows at a time (row numbers,
        from 1, stand for line numbers)."""
        for c in columns:
            if c in self.elsewhere:
                raise InputError(f"{self.path}: dataset {self.names[c]} {self.elsewhere[c]}")
        size = self.path.stat().st_size
        check_declared(8 * self.length * len(columns), size, f"{self.path}")
        for start in range(0, self.length, BLOCK_ROWS):
            stop = min(self.length, start + BLOCK_ROWS)
            values = np.empty((stop - start, len(columns)))
            for j, c in enumerate(columns):
                values[:, j] = self.readers[c](start, stop)
            self.rows = stop
            yield Block(values, np.arange(start + 1, stop + 1, dtype=np.int64))

    def fraction(self) -> float:
        return self.rows / self.length if self.length else 1.0

    def finish(self) -> list[str]:
        return list(self.notes)


def unit_word(text: Any) -> str:
    """A unit as another program wrote it (``meters``, ``N``), as tissuecli names it."""
    if isinstance(text, bytes):
        text = text.decode("utf-8", "replace")
    if not isinstance(text, str):
        return ""
    word = text.strip()
    return UNIT_WORDS.get(word.lower(), word)


def _one_length(
    path: Path, found: list[tuple[str, str, str, int, Reader]], kind: str
) -> tuple[list[tuple[str, str, str, int, Reader]], int, list[str]]:
    """The signals of the most common length (the record), and notes on the others."""
    if not found:
        return [], 0, []
    lengths = Counter(n for _, _, _, n, _ in found)
    length = max(lengths, key=lambda n: (lengths[n], n))
    kept = [f for f in found if f[3] == length]
    others = [f[0] for f in found if f[3] != length]
    notes = [f"{kind}, {len(kept)} signal(s) of {length} samples"]
    if others:
        notes.append(f"ignored: {', '.join(others[:8])} (other lengths)")
    return kept, length, notes


# -- HDF5 and NWB


def read_hdf5(path: str | os.PathLike[str]) -> Columns:
    """The numeric signals of another program's HDF5 file (NWB included).

    Every 1-D numeric dataset is a column named by its path; a 2-D one with at most
    :data:`MAX_SIGNALS` columns gives ``path:1``, ``path:2``, ...; a ``unit`` or
    ``units`` attribute names its unit. An NWB TimeSeries (a group with ``data`` and
    ``timestamps``, or ``starting_time`` with its ``rate``) is one column named by the
    group, in its ``unit`` after ``conversion`` and ``offset``, and its time stamps one
    more (``.../timestamps``).

    Raises
    ------
    InputError
        The file cannot be read, or holds no numeric signal (the message lists what it
        holds).
    """
    import h5py

    from .hdf5 import elsewhere

    path = Path(path)
    found: list[tuple[str, str, str, int, Reader]] = []
    pointers: dict[str, str] = {}
    seen: list[str] = []
    series: list[str] = []
    try:
        with h5py.File(path, "r", locking=False) as f:
            nwb = "nwb_version" in f.attrs

            def visit(name: str, obj: Any) -> None:
                seen.append("/" + name)
                if (
                    isinstance(obj, h5py.Group)
                    and "data" in obj
                    and ("timestamps" in obj or "starting_time" in obj)
                ):
                    _series(path, obj, "/" + name, found, pointers)
                    series.append("/" + name)
                    return
                if not isinstance(obj, h5py.Dataset) or any(
                    ("/" + name).startswith(s + "/") for s in series
                ):
                    return
                _dataset(path, obj, "/" + name, found, pointers, elsewhere)

            f.visititems(visit)
    except (OSError, RuntimeError, ValueError, KeyError, TypeError) as exc:
        raise InputError(f"cannot read {path} as an HDF5 file: {str(exc)[:100]}") from None
    kept, length, notes = _one_length(path, found, "NWB file" if nwb else "HDF5 file")
    # the series of one recording share their time: the first series' stamps stand for all
    clocks = [i for i, k in enumerate(kept) if k[0].endswith(("/timestamps", "/starting_time"))]
    kept = [k for i, k in enumerate(kept) if i not in clocks[1:]]
    if not kept:
        listed = ", ".join(seen[:12]) or "nothing"
        raise InputError(
            f"{path} holds no numeric signal (1-D datasets of numbers); it holds: {listed}"
        )
    names = [k[0] for k in kept]
    return Columns(
        path=path,
        source="NWB" if nwb else "HDF5",
        names=names,
        keys=[k[1] for k in kept],
        units=[k[2] for k in kept],
        readers=[k[4] for k in kept],
        length=length,
        notes=notes,
        elsewhere={i: pointers[n] for i, n in enumerate(names) if n in pointers},
    )


def _attr(obj: Any, *keys: str) -> Any:
    for key in keys:
        if key in obj.attrs:
            try:
                value = obj.attrs[key]
            except (OSError, TypeError, ValueError):
                continue
            if isinstance(value, np.ndarray) and value.size == 1:
                value = value.reshape(()).item()
            return value
    return None


def _number(value: Any, default: float) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        return default
    return out if np.isfinite(out) else default


def _h5_reader(path: Path, name: str, column: int | None, scale: float, shift: float) -> Reader:
    def read(start: int, stop: int) -> NDArray[np.float64]:
        import h5py

        with h5py.File(path, "r", locking=False) as f:
            ds = f[name]
            part = ds[start:stop] if column is None else ds[start:stop, column]
        return np.asarray(part, dtype=np.float64) * scale + shift

    return read


def _dataset(
    path: Path,
    ds: Any,
    name: str,
    found: list[tuple[str, str, str, int, Reader]],
    pointers: dict[str, str],
    elsewhere: Callable[[Any], str | None],
) -> None:
    if ds.dtype.kind not in "iuf" or ds.dtype.fields is not None or not ds.shape:
        return
    shape = ds.shape
    unit = unit_word(_attr(ds, "unit", "units", "Unit", "Units"))
    leaf = name.rsplit("/", 1)[-1]
    problem = elsewhere(ds)
    if len(shape) == 1 and shape[0] > 1:
        if problem:
            pointers[name] = problem
        found.append((name, leaf, unit, shape[0], _h5_reader(path, name, None, 1.0, 0.0)))
    elif len(shape) == 2 and min(shape) <= MAX_SIGNALS and max(shape) > 1 and shape[0] >= shape[1]:
        for j in range(shape[1]):
            column = f"{name}:{j + 1}"
            if problem:
                pointers[column] = problem
            found.append(
                (column, f"{leaf}:{j + 1}", unit, shape[0], _h5_reader(path, name, j, 1.0, 0.0))
            )


def _series(
    path: Path,
    g: Any,
    name: str,
    found: list[tuple[str, str, str, int, Reader]],
    pointers: dict[str, str],
) -> None:
    """An NWB TimeSeries: its data (after conversion and offset) and its time."""
    from .hdf5 import elsewhere

    data = g["data"]
    if not hasattr(data, "dtype") or data.dtype.kind not in "iuf" or len(data.shape or ()) != 1:
        return
    n = data.shape[0]
    leaf = name.rsplit("/", 1)[-1]
    conversion = _number(_attr(data, "conversion"), 1.0)
    offset = _number(_attr(data, "offset"), 0.0)
    unit = unit_word(_attr(data, "unit"))
    if elsewhere(data):
        pointers[name] = str(elsewhere(data))
    found.append((name, leaf, unit, n, _h5_reader(path, data.name, None, conversion, offset)))
    if "timestamps" in g:
        stamps = g["timestamps"]
        if hasattr(stamps, "dtype") and stamps.dtype.kind in "iuf" and stamps.shape == (n,):
            column = f"{name}/timestamps"
            if elsewhere(stamps):
                pointers[column] = str(elsewhere(stamps))
            found.append(
                (column, "timestamps", "s", n, _h5_reader(path, stamps.name, None, 1.0, 0.0))
            )
        return
    start = g["starting_time"]
    rate = _number(_attr(start, "rate"), float("nan"))
    if not (rate > 0):
        return
    t0 = _number(start[()] if hasattr(start, "shape") and start.shape == () else 0.0, 0.0)

    def clock(a: int, b: int) -> NDArray[np.float64]:
        return t0 + np.arange(a, b) / rate

    found.append((f"{name}/starting_time", "time", "s", n, clock))


# -- LabVIEW TDMS


def read_tdms(path: str | os.PathLike[str]) -> Columns:
    """The channels of a LabVIEW TDMS file, named ``group/channel``, in the unit their
    ``unit_string`` property gives; a channel with a waveform increment
    (``wf_increment``, s) gives its time too (``group/channel/time``).

    The file is handed to npTDMS open, so that it never reads a ``.tdms_index`` file
    beside it.

    Raises
    ------
    InputError
        npTDMS is missing, the file cannot be read, or it holds no numeric channel.
    """
    try:
        from nptdms import TdmsFile
    except ImportError:
        raise InputError(
            "reading LabVIEW TDMS files needs npTDMS: pip install 'tissuecli[tdms]'"
        ) from None
    path = Path(path)
    found: list[tuple[str, str, str, int, Reader]] = []
    seen: list[str] = []
    try:
        fh = open(path, "rb")
    except OSError as exc:
        raise InputError(f"cannot read {path}: {exc.strerror}") from None
    try:
        if fh.read(4) != b"TDSm":
            raise InputError(f"{path} is not a LabVIEW TDMS file (it does not start with TDSm)")
        fh.seek(0)
        with TdmsFile.open(fh) as tdms:
            size = path.stat().st_size
            for group in tdms.groups():
                for channel in group.channels():
                    name = f"{group.name}/{channel.name}"
                    seen.append(name)
                    dtype = getattr(channel, "dtype", None)
                    n = len(channel)
                    if dtype is None or np.dtype(dtype).kind not in "iuf" or n < 2:
                        continue
                    if n * np.dtype(dtype).itemsize > size:
                        raise InputError(
                            f"{path}: channel {name} declares {n} values, more than the file "
                            "holds; the file is damaged"
                        )
                    props = channel.properties
                    unit = unit_word(props.get("unit_string", ""))
                    found.append(
                        (name, channel.name, unit, n, _tdms_reader(path, group.name, channel.name))
                    )
                    step = _number(props.get("wf_increment"), float("nan"))
                    if step > 0:
                        t0 = _number(props.get("wf_start_offset"), 0.0)
                        found.append((f"{name}/time", "time", "s", n, _clock(t0, step)))
    except InputError:
        raise
    except Exception as exc:  # npTDMS raises plain ValueError, KeyError, struct.error, ...
        raise InputError(f"cannot read {path} as a TDMS file: {str(exc)[:100]}") from None
    finally:
        fh.close()
    kept, length, notes = _one_length(path, found, "LabVIEW TDMS file")
    if not kept:
        listed = ", ".join(seen[:12]) or "no channels"
        raise InputError(f"{path} holds no numeric channel; it holds: {listed}")
    # channels of one waveform share a time: keep the first
    times = [i for i, k in enumerate(kept) if k[1] == "time"]
    kept = [k for i, k in enumerate(kept) if i not in times[1:]]
    return Columns(
        path=path,
        source="TDMS",
        names=[k[0] for k in kept],
        keys=[k[1] for k in kept],
        units=[k[2] for k in kept],
        readers=[k[4] for k in kept],
        length=length,
        notes=notes,
    )


def _clock(t0: float, step: float) -> Reader:
    def read(a: int, b: int) -> NDArray[np.float64]:
        return t0 + np.arange(a, b) * step

    return read


def _tdms_reader(path: Path, group: str, channel: str) -> Reader:
    def read(start: int, stop: int) -> NDArray[np.float64]:
        from nptdms import TdmsFile

        with open(path, "rb") as fh, TdmsFile.open(fh) as tdms:
            return np.asarray(tdms[group][channel][start:stop], dtype=np.float64)

    return read
