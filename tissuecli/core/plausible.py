"""What a forceps session looks like, to catch unit mistakes: a closure of metres, a
force of a thousand newtons, or a sample rate of a third of a hertz are numbers in the
wrong unit far more often than they are measurements."""

from __future__ import annotations

import numpy as np

from .session import Session
from .units import dimension_of

#: beyond these a forceps session is implausible (jaws open at most a few cm; liver
#: grasps reach 3.4 N, and no laparoscopic grasp 200 N; loggers sample 10 Hz to 100 kHz)
MAX_CLOSURE_SPAN_M = 0.05
MAX_FORCE_N = 200.0
RATE_RANGE_HZ = (5.0, 1e6)


def unit_warnings(session: Session, *, position_given: bool | None = None) -> list[str]:
    """Warnings that name the likely unit mistake when a session is implausible for a
    forceps; empty when it is plausible. ``position_given`` False says the closure was
    converted from an angle (so its span is not a unit question); by default it is
    read from the units the session was imported with."""
    out: list[str] = []
    if position_given is None:
        units = session.meta.get("import_units")
        unit = str(units.get("position", "m")) if isinstance(units, dict) else "m"
        position_given = dimension_of(unit.split(" ")[0]) != "angle"
    if len(session) < 2:
        return out
    span = float(np.ptp(session.position))
    if position_given and span > MAX_CLOSURE_SPAN_M:
        out.append(
            f"the jaw closure spans {span:.4g} m, more than forceps jaws open "
            f"({MAX_CLOSURE_SPAN_M * 1e3:g} mm): "
            + _guess(span, MAX_CLOSURE_SPAN_M, (("mm", 1e-3), ("um", 1e-6)), "position")
        )
    peak = float(np.max(np.abs(session.force)))
    if peak > MAX_FORCE_N:
        out.append(
            f"the force reaches {peak:.4g} N, more than a grasp ({MAX_FORCE_N:g} N): "
            + _guess(peak, MAX_FORCE_N, (("gf", 9.80665e-3), ("mN", 1e-3)), "force")
        )
    rate = session.rate_hz
    lo, hi = RATE_RANGE_HZ
    if rate and not lo <= rate <= hi:
        options = (("ms", 1e-3), ("us", 1e-6)) if rate < lo else (("s", 1.0),)
        fix = next(
            (f"is time in {u}? pass --units time={u}" for u, f in options if lo <= rate / f <= hi),
            "check the time column and its unit",
        )
        out.append(f"the samples come {rate:.4g} times a second: {fix}")
    return out


def _guess(value: float, limit: float, units: tuple[tuple[str, float], ...], column: str) -> str:
    for unit, factor in units:
        if value * factor <= limit:
            return f"is {column} in {unit}? pass --units {column}={unit}"
    return f"check the {column} column and its unit"
