"""Unit conversion at the edges. Everything inside tissuecli is SI (N, m, s, kg, V).

Units are given as a comma-separated list such as ``"mm,gf"``; each unit is
recognised by its dimension (length, force or time), so the order does not matter.
"""

from __future__ import annotations

from dataclasses import dataclass

from .errors import InputError
from .session import QUANTITIES

STANDARD_GRAVITY = 9.80665  # m/s^2, exact by definition

#: factor to SI for each known unit, by dimension
UNITS: dict[str, dict[str, float]] = {
    "length": {"m": 1.0, "cm": 1e-2, "mm": 1e-3, "um": 1e-6, "in": 0.0254},
    "force": {
        "N": 1.0,
        "mN": 1e-3,
        "kN": 1e3,
        "gf": 1e-3 * STANDARD_GRAVITY,
        "kgf": STANDARD_GRAVITY,
    },
    "time": {"s": 1.0, "ms": 1e-3, "us": 1e-6, "min": 60.0},
}

#: which column carries which dimension
COLUMN_DIMENSION = {q.name: q.dimension for q in QUANTITIES}


@dataclass(frozen=True)
class ColumnUnits:
    """Units of the time, force and position columns, with factors to SI."""

    time: str = "s"
    force: str = "N"
    position: str = "m"

    def factor(self, column: str) -> float:
        """Multiply a value in this column's unit by this to get SI."""
        return UNITS[COLUMN_DIMENSION[column]][getattr(self, column)]

    def __str__(self) -> str:
        return f"{self.time},{self.force},{self.position}"


def parse_units(spec: str | None) -> ColumnUnits:
    """Parse ``"mm,gf"`` (any order, any subset) into :class:`ColumnUnits`.

    Raises
    ------
    InputError
        For an unknown unit or two units of one dimension.
    """
    if not spec:
        return ColumnUnits()
    chosen: dict[str, str] = {}
    for token in (t.strip() for t in spec.split(",")):
        if not token:
            continue
        dims = [d for d, table in UNITS.items() if token in table]
        if not dims:
            known = ", ".join(u for table in UNITS.values() for u in table)
            raise InputError(f"unknown unit {token!r} in --units; use any of: {known}")
        dim = dims[0]
        if dim in chosen:
            raise InputError(f"--units gives two {dim} units ({chosen[dim]} and {token}); give one")
        chosen[dim] = token
    return ColumnUnits(
        time=chosen.get("time", "s"),
        force=chosen.get("force", "N"),
        position=chosen.get("length", "m"),
    )
