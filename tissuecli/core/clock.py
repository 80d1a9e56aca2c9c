"""Device clocks: unwrapping 32-bit tick counters and mapping device time to host time."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray


class TickUnwrapper:
    """Turns a wrapping 32-bit tick counter into a monotonic int64 count."""

    def __init__(self) -> None:
        self._last: int | None = None
        self._high = 0

    def __call__(self, ticks: ArrayLike) -> NDArray[np.int64]:
        t = np.asarray(ticks, dtype=np.int64)
        if t.size == 0:
            return t
        prev = t[0] if self._last is None else self._last
        # a step back of more than half the range is a wrap, not disorder
        steps = np.diff(np.concatenate([[prev], t]))
        wraps = np.cumsum(steps < -(1 << 31))
        out = t + (self._high + wraps) * (1 << 32)
        self._high += int(wraps[-1])
        self._last = int(t[-1])
        return out


@dataclass(frozen=True)
class ClockMap:
    """``host_s = offset_s + slope * device_s``, fitted by least squares.

    ``drift_ppm`` is how fast the device clock runs relative to the host
    (positive: the device clock is fast). The offset includes the mean
    transport latency, which a one-way stream cannot separate.
    """

    slope: float
    offset_s: float
    residual_rms_s: float
    drift_ppm: float
    samples: int

    def as_dict(self) -> dict[str, float | int]:
        return asdict(self)


def fit_clock_map(device_s: ArrayLike, host_s: ArrayLike) -> ClockMap | None:
    """Regress host time on device time; ``None`` with fewer than 10 samples or no span.

    A regression over all samples uses every arrival, so latency jitter
    averages out; two end-points alone carry all of their jitter into the slope.
    """
    d = np.asarray(device_s, dtype=float)
    h = np.asarray(host_s, dtype=float)
    if d.size < 10 or np.ptp(d) <= 0:
        return None
    d0, h0 = d.mean(), h.mean()
    dd = d - d0
    slope = float(np.dot(dd, h - h0) / np.dot(dd, dd))
    offset = float(h0 - slope * d0)
    resid = h - (offset + slope * d)
    return ClockMap(
        slope=slope,
        offset_s=offset,
        residual_rms_s=float(np.sqrt(np.mean(resid**2))),
        drift_ppm=float((1.0 / slope - 1.0) * 1e6),
        samples=int(d.size),
    )
