"""A recorded session in memory: time, force and jaw position in SI units."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .errors import InputError

Array = NDArray[np.float64]


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
    """

    time: Array
    force: Array
    position: Array
    name: str = ""
    meta: dict[str, Any] = field(default_factory=dict)

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
        return float(1.0 / np.median(np.diff(self.time)))

    def validate(self, min_samples: int = 2) -> Session:
        """Check shapes, finiteness and monotonic time; raise :class:`InputError` if wrong."""
        n = len(self)
        for label, arr in (("time", self.time), ("force", self.force), ("position", self.position)):
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
