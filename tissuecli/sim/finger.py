"""A simulated finger on the display's piston: smooth presses, a force source in N."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np


@dataclass(frozen=True)
class Press:
    """One press: raised-cosine rise, hold, raised-cosine release (smooth in force and
    its rate, so the piston is not kicked)."""

    start: float  # s
    rise: float  # s
    hold: float  # s
    fall: float  # s
    force: float  # N, peak

    def __call__(self, t: float) -> float:
        u = t - self.start
        if u <= 0.0:
            return 0.0
        if u < self.rise:
            return 0.5 * self.force * (1.0 - math.cos(math.pi * u / self.rise))
        u -= self.rise
        if u <= self.hold:
            return self.force
        u -= self.hold
        if u < self.fall:
            return 0.5 * self.force * (1.0 + math.cos(math.pi * u / self.fall))
        return 0.0


@dataclass(frozen=True)
class OperatorForce:
    """A simulated finger on the piston: smooth presses, a force source (N, positive down).

    Presses come one per ``slot`` seconds (3.3 per 10 s by default), the first
    starting at ``first`` s. Press ``i`` starts up to 0.3 s into its slot, peaks at
    a force drawn uniformly from ``force_range`` (1..2.5 N: firm grasps, below the
    3.4 N maximum on liver), rises and releases in 0.25..0.5 s and holds for
    0.2..0.8 s, all drawn from ``seed`` and ``i`` alone, so any time can be
    evaluated without the past and a run of any length is reproducible.
    A 2.5 s run therefore always contains one whole press.

    A force source is the hardest operator for tracking (nothing in the finger
    damps the piston) and the easiest to reproduce; a real finger adds its own
    mass and damping.
    """

    seed: int = 0
    first: float = 0.1
    slot: float = 3.0
    force_range: tuple[float, float] = (1.0, 2.5)

    def press(self, i: int) -> Press:
        """The ``i``-th press (``i >= 0``)."""
        return _press(self.seed, i, self.first, self.slot, self.force_range)

    def __call__(self, t: float) -> float:
        if t < self.first:
            return 0.0
        return self.press(int((t - self.first) // self.slot))(t)


@lru_cache(maxsize=64)
def _press(seed: int, i: int, first: float, slot: float, force_range: tuple[float, float]) -> Press:
    rng = np.random.default_rng([seed % 2**32, i])  # any int seed, negative ones too
    jitter, rise, hold, fall, force = rng.uniform(
        [0.0, 0.25, 0.2, 0.25, force_range[0]], [0.3, 0.5, 0.8, 0.5, force_range[1]]
    )
    return Press(
        first + i * slot + float(jitter), float(rise), float(hold), float(fall), float(force)
    )
