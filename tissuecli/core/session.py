"""A recorded session in memory: time, force and jaw position in SI units, and the
names of the quantities every file format stores."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .calibration import Adc
from .errors import InputError
from .timebase import median

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Quantity:
    """One sampled quantity of a session, as every file stores it.

    Attributes
    ----------
    name : str
        Column or dataset name (``time``, ``force``, ``position``).
    unit : str
        SI unit of the stored values.
    dimension : str
        ``time``, ``force`` or ``length``: what ``--units`` may convert it from.
    description : str
        One line for file attributes and headers.
    """

    name: str
    unit: str
    dimension: str
    description: str


#: The quantities of a session, in file order: the one definition CSV headers, HDF5
#: datasets, unit conversion and validation all read.
QUANTITIES: tuple[Quantity, ...] = (
    Quantity("time", "s", "time", "sample time on the device clock since the first sample"),
    Quantity("force", "N", "force", "grasp force, positive squeezes the tissue"),
    Quantity("position", "m", "length", "jaw closure, positive compresses the tissue"),
)
COLUMNS: tuple[str, ...] = tuple(q.name for q in QUANTITIES)


def check_name(name: object, kind: str = "session") -> str:
    """Return ``name`` if it can name a session (or play log); raise otherwise.

    Names become HDF5 group names and rows of tables, so they must be non-empty, free
    of ``/`` and of control characters, and at most 200 characters long.

    Raises
    ------
    InputError
        For an empty name, ``.``/``..``, a name with ``/`` or a control character, or
        one longer than 200 characters.
    """
    if not isinstance(name, str) or not name.strip():
        raise InputError(f"{kind} name is empty; give one with --{kind} NAME")
    if "/" in name or name in (".", ".."):
        raise InputError(f'{kind} name "{name}" is not allowed; choose a name without "/"')
    if not name.isprintable() or len(name) > 200:
        shown = name[:60].encode("unicode_escape").decode()
        raise InputError(
            f'{kind} name "{shown}" is not allowed; use at most 200 printable characters'
        )
    return name


@dataclass
class Session:
    """Samples of one grasp session.

    Attributes
    ----------
    time : ndarray, shape (n,)
        Sample times in s, strictly increasing (first sample near 0).
    force : ndarray, shape (n,)
        Grasp force in N (positive squeezes the tissue).
    position : ndarray, shape (n,)
        Jaw closure in m (positive compresses the tissue).
    name : str
        Session name inside its file.
    meta : dict
        Attributes stored with the session (tissue label, note, counters, ...).
    adc : Adc or None
        The converter the samples came through, when known (recordings and
        synthetic sessions): its ends mark clipped samples and its step is the
        floor of the position noise.
    """

    time: Array
    force: Array
    position: Array
    name: str = ""
    meta: dict[str, Any] = field(default_factory=dict)
    adc: Adc | None = None

    def __post_init__(self) -> None:
        self.time = np.asarray(self.time, dtype=np.float64)
        self.force = np.asarray(self.force, dtype=np.float64)
        self.position = np.asarray(self.position, dtype=np.float64)

    def __len__(self) -> int:
        return int(self.time.shape[0])

    @property
    def duration_s(self) -> float:
        return float(self.time[-1] - self.time[0]) if len(self) > 1 else 0.0

    @property
    def rate_hz(self) -> float:
        """Sample rate from the median sample interval (robust to lost frames)."""
        if len(self) < 2:
            return 0.0
        return float(1.0 / median(np.diff(self.time)))

    def replace(self, time: Array, force: Array, position: Array) -> Session:
        """The same session (name, meta, ADC) with other samples: a part of it, or a grid."""
        return Session(time, force, position, name=self.name, meta=dict(self.meta), adc=self.adc)

    def window(self, start_s: float | None = None, end_s: float | None = None) -> Session:
        """The samples with ``start_s <= time <= end_s`` (s, on the session's clock).

        Raises
        ------
        InputError
            If the bounds are not finite, are reversed, or hold fewer than 2 samples.
        """
        lo = -np.inf if start_s is None else float(start_s)
        hi = np.inf if end_s is None else float(end_s)
        if np.isnan(lo) or np.isnan(hi) or lo >= hi:
            raise InputError(f"--start {start_s} and --end {end_s}: give start < end, in s")
        keep = (self.time >= lo) & (self.time <= hi)
        if np.count_nonzero(keep) < 2:
            raise InputError(
                f"no samples between {lo:g} s and {hi:g} s; the session runs from "
                f"{self.time[0]:.3f} s to {self.time[-1]:.3f} s"
            )
        return self.replace(self.time[keep], self.force[keep], self.position[keep])

    def validate(self, min_samples: int = 2) -> Session:
        """Check shapes, finiteness and monotonic time; raise :class:`InputError` if wrong."""
        n = len(self)
        for label in COLUMNS:
            arr = getattr(self, label)
            if arr.ndim != 1 or arr.shape[0] != n:
                raise InputError(f"{label} has shape {arr.shape}; expected ({n},) like time")
            bad = np.flatnonzero(~np.isfinite(arr))
            if bad.size:
                raise InputError(
                    f"{label} has {bad.size} non-finite value(s) (NaN or Inf), first at sample "
                    f"{bad[0]}; remove or repair those rows"
                )
        if n < min_samples:
            raise InputError(f"session has {n} sample(s); at least {min_samples} are needed")
        steps = np.diff(self.time)
        back = np.flatnonzero(steps <= 0)
        if back.size:
            i = int(back[0])
            raise InputError(
                f"time is not strictly increasing at sample {i + 1} "
                f"({self.time[i]:.9g} s then {self.time[i + 1]:.9g} s); "
                "sort or repair the time column"
            )
        return self
