"""Counts-to-SI calibration of the forceps' ADC channels."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import InputError

Array = NDArray[np.float64]
CHANNELS = ("force", "position")
SI_UNITS = {"force": "N", "position": "m"}


@dataclass(frozen=True)
class Channel:
    """Calibration of one ADC channel: ``value = gain * counts + offset`` (SI)."""

    gain: float
    offset: float
    unit: str

    def to_si(self, counts: ArrayLike) -> Array:
        return self.gain * np.asarray(counts, dtype=np.float64) + self.offset

    def to_counts(self, values: ArrayLike, bits: int) -> NDArray[np.int16]:
        """Quantise to a signed ``bits``-bit ADC, saturating at its ends."""
        lo, hi = -(1 << (bits - 1)), (1 << (bits - 1)) - 1
        counts = np.rint((np.asarray(values, dtype=float) - self.offset) / self.gain)
        return np.clip(counts, lo, hi).astype(np.int16)

    @classmethod
    def spanning(cls, lo: float, hi: float, bits: int, unit: str) -> Channel:
        """The channel whose full ``bits``-bit range maps onto [lo, hi]."""
        gain = (hi - lo) / ((1 << bits) - 1)
        return cls(gain=gain, offset=lo + (1 << (bits - 1)) * gain, unit=unit)

    def as_dict(self) -> dict[str, float | str]:
        return {"gain": self.gain, "offset": self.offset, "unit": self.unit}


@dataclass(frozen=True)
class Calibration:
    """Counts-to-SI conversion of both forceps channels."""

    force: Channel
    position: Channel

    def as_dict(self) -> dict[str, dict[str, float | str]]:
        return {"force": self.force.as_dict(), "position": self.position.as_dict()}

    def channel(self, name: str) -> Channel:
        """The channel called ``name`` (``force`` or ``position``)."""
        return self.force if name == "force" else self.position


@dataclass(frozen=True)
class Adc:
    """The forceps' analogue-to-digital converter: signed ``bits`` bits and its calibration.

    A session that knows its ADC knows which samples are clipped (at either end of
    the range) and the position step, the floor of the position noise.
    """

    bits: int
    calibration: Calibration

    def ends(self, channel: str) -> tuple[float, float]:
        """SI values of the lowest and highest count of ``channel``."""
        ch = self.calibration.channel(channel)
        lo, hi = -(1 << (self.bits - 1)), (1 << (self.bits - 1)) - 1
        return ch.offset + ch.gain * lo, ch.offset + ch.gain * hi

    def step(self, channel: str) -> float:
        """One count of ``channel`` in SI (m or N)."""
        return abs(self.calibration.channel(channel).gain)


def calibration_from_dict(data: Mapping[str, Any]) -> Calibration:
    """Parse ``{"force": {"gain", "offset"}, "position": {...}}`` (SI per count, SI).

    Raises
    ------
    InputError
        If a channel or number is missing, not finite, or the gain is zero.
    """
    channels = {}
    for name in CHANNELS:
        entry = data.get(name) if isinstance(data, Mapping) else None
        if not isinstance(entry, Mapping):
            raise InputError(
                f'calibration has no "{name}" channel; expected '
                '{"force": {"gain": N_per_count, "offset": N}, "position": {"gain": m_per_count, '
                '"offset": m}}'
            )
        try:
            gain, offset = float(entry["gain"]), float(entry.get("offset", 0.0))
        except (KeyError, TypeError, ValueError):
            raise InputError(f'calibration channel "{name}" needs a numeric "gain"') from None
        if not (np.isfinite(gain) and np.isfinite(offset)) or gain == 0:
            raise InputError(f'calibration channel "{name}": gain must be finite and non-zero')
        unit = str(entry.get("unit", SI_UNITS[name]))
        if unit != SI_UNITS[name]:
            raise InputError(
                f'calibration channel "{name}" is in {unit}; '
                f"give gain and offset in {SI_UNITS[name]}"
            )
        channels[name] = Channel(gain=gain, offset=offset, unit=unit)
    return Calibration(**channels)
