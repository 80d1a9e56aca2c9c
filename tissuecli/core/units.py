"""Unit conversion at the edges. Everything inside tissuecli is SI (N, m, s, kg, V).

``--units`` names the unit of each column, ``time=ms,force=gf,position=mm``; the short
form ``mm,gf`` (any order, any subset) recognises each unit by its dimension. Headers
such as ``t_ms``, ``force (N)`` or ``closure [mm]`` carry their unit too
(:func:`unit_in_header`). Jaw closure may be given as the angle between the jaws
(``deg``, ``rad``), which needs the jaw length to become a closure at the tips.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from .errors import InputError
from .session import QUANTITIES

STANDARD_GRAVITY = 9.80665  # m/s^2, exact by definition

#: factor to SI for each known unit, by dimension (angle: to radians)
UNITS: dict[str, dict[str, float]] = {
    "length": {"m": 1.0, "cm": 1e-2, "mm": 1e-3, "um": 1e-6, "µm": 1e-6, "nm": 1e-9, "in": 0.0254},
    "force": {
        "N": 1.0,
        "mN": 1e-3,
        "kN": 1e3,
        "gf": 1e-3 * STANDARD_GRAVITY,
        "g": 1e-3 * STANDARD_GRAVITY,  # a force logged "in grams" is grams-force
        "kgf": STANDARD_GRAVITY,
        "lbf": 0.45359237 * STANDARD_GRAVITY,
    },
    "time": {"s": 1.0, "ms": 1e-3, "us": 1e-6, "µs": 1e-6, "ns": 1e-9, "min": 60.0},
    "angle": {"rad": 1.0, "mrad": 1e-3, "deg": math.pi / 180},
    "torque": {"Nm": 1.0, "N*m": 1.0, "mNm": 1e-3, "Nmm": 1e-3, "N*mm": 1e-3},
}

#: which column carries which dimension, and the other dimensions it may be given in
COLUMN_DIMENSION = {q.name: q.dimension for q in QUANTITIES}
ALTERNATIVES = {"position": ("angle",), "force": ("torque",)}

#: a unit, optionally scaled: ``mm``, ``0.0007670*rad`` (one ADC count), ``3.98e-5Nm``,
#: or signed: ``-deg`` (a sensor that reads the other way)
_SCALED = re.compile(r"\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|[-+])?\s*\*?\s*(\S+?)\s*")


def unit_factor(unit: str) -> tuple[str, float] | None:
    """The dimension and SI factor of a unit, optionally scaled (``0.5*mm``) or signed
    (``-deg``: the column grows the other way); None if unknown or the scale is not a
    finite non-zero number."""
    match = _SCALED.fullmatch(unit or "")
    if match is None:
        return None
    dim = next((d for d, table in UNITS.items() if match.group(2) in table), None)
    if dim is None:
        return None
    sign = {"-": "-1", "+": "1", None: "1"}.get(match.group(1), match.group(1))
    scale = float(sign)
    if not (math.isfinite(scale) and scale != 0):
        return None
    return dim, scale * UNITS[dim][match.group(2)]


def dimension_of(unit: str) -> str | None:
    """The dimension of a (possibly scaled) unit, or None if unknown."""
    found = unit_factor(unit)
    return found[0] if found else None


@dataclass(frozen=True)
class ColumnUnits:
    """Units of the time, force and position columns, with factors to SI.

    ``given`` names the columns whose unit was stated (the others may be read from
    a header, else SI is assumed). A unit may carry a scale, ``0.000767*rad`` for a
    position logged in ADC counts. A position in an angle unit (``deg``, ``rad``) is
    the angle between the jaws; a force in a torque unit (``Nm``) is the torque about
    their hinge.
    """

    time: str = "s"
    force: str = "N"
    position: str = "m"
    given: frozenset[str] = field(default=frozenset(), compare=False)

    def factor(self, column: str) -> float:
        """Multiply a value in this column's unit by this to get SI (radians for angles,
        N m for torques)."""
        unit = getattr(self, column)
        found = unit_factor(unit)
        if found is None:
            raise InputError(f"unknown unit {unit!r} for {column}")
        return found[1]

    @property
    def position_is_angle(self) -> bool:
        return dimension_of(self.position) == "angle"

    @property
    def force_is_torque(self) -> bool:
        return dimension_of(self.force) == "torque"

    def __str__(self) -> str:
        return f"time={self.time},force={self.force},position={self.position}"


def parse_units(spec: str | None) -> ColumnUnits:
    """Parse ``--units``: ``time=ms,force=gf,position=mm`` or the short ``mm,gf``.

    In the short form each unit is recognised by its dimension, so the order does
    not matter; an angle unit is taken for position. The two forms may be mixed.

    Raises
    ------
    InputError
        For an unknown column or unit, a unit of the wrong dimension for its column,
        or a column given twice.
    """
    chosen: dict[str, str] = {}
    for token in (t.strip() for t in (spec or "").split(",")):
        if not token:
            continue
        if "=" in token:
            column, unit = (part.strip() for part in token.split("=", 1))
            if column not in COLUMN_DIMENSION:
                raise InputError(
                    f"--units names column {column!r}; the columns are time, force and position"
                )
        else:
            unit = token
            dim = dimension_of(unit)
            column = next(
                (
                    c
                    for c, d in COLUMN_DIMENSION.items()
                    if d == dim or dim in ALTERNATIVES.get(c, ())
                ),
                "",
            )
        _check_unit(column, unit)
        if column in chosen:
            raise InputError(
                f"--units gives {column} twice ({chosen[column]} and {unit}); give one"
            )
        chosen[column] = unit
    return ColumnUnits(**chosen, given=frozenset(chosen))


def _check_unit(column: str, unit: str) -> None:
    dim = dimension_of(unit)
    if dim is None:
        known = ", ".join(u for table in UNITS.values() for u in table)
        raise InputError(
            f"unknown unit {unit[:20]!r} in --units; use any of: {known}, optionally scaled "
            "as 0.5*mm or signed as -deg"
        )
    if column == "time" and (unit_factor(unit) or ("", 1.0))[1] < 0:
        raise InputError(f"--units time={unit}: a time unit cannot be negative")
    if column and (dim == COLUMN_DIMENSION[column] or dim in ALTERNATIVES.get(column, ())):
        return
    where = f"for {column}" if column else "for any column"
    raise InputError(f"--units: {unit} is a {dim} unit, not one {where}")


#: a unit at the end of a header: ``t_ms``, ``force (N)``, ``closure [mm]``, ``time/s``
_UNIT_IN_HEADER = re.compile(r"(?:[\s_/-]|\(|\[)\s*([A-Za-zµ]+)\s*[\)\]]?\s*$")


def unit_in_header(header: str, column: str) -> str | None:
    """The unit a column's header names, if it is one that column may have.

    ``t_ms`` gives ``ms`` for time, ``force_g`` ``g`` for force, ``angle (deg)``
    ``deg`` for position; ``force`` alone gives None.
    """
    match = _UNIT_IN_HEADER.search(header.strip())
    return unit_for(match.group(1), column) if match else None


def unit_for(unit: str, column: str) -> str | None:
    """`unit` (``ms``, ``[N]``, ``(mm)``, ``n``) as a unit `column` may have, or None.

    Used for a header's unit and for a units row under the names."""
    unit = unit.strip().strip("[]()").strip()
    for candidate in (unit, unit.lower(), "N" if unit.lower() == "n" else unit):
        dim = dimension_of(candidate)
        if dim is not None and (
            dim == COLUMN_DIMENSION[column] or dim in ALTERNATIVES.get(column, ())
        ):
            return candidate
    return None


#: magnitudes, in SI, beyond any grasp, squeeze or test machine (a giganewton, a
#: thousand kilometres): a value beyond them is a wrong column, a wrong unit or damage,
#: and would overflow the fit's sums of squares
PHYSICAL_LIMITS = {"force": 1e9, "position": 1e6}


def beyond_physical(quantity: str, values: NDArray[np.float64]) -> int | None:
    """Index of the first of `values` (SI) beyond :data:`PHYSICAL_LIMITS`, or None."""
    limit = PHYSICAL_LIMITS[quantity]
    if values.size and -limit <= values.min() and values.max() <= limit:
        return None  # two reductions: no array of flags for the usual block
    bad = np.flatnonzero(np.abs(values) > limit)
    return int(bad[0]) if bad.size else None


def parse_quantity(text: str, dimension: str, option: str) -> float:
    """A number with an optional unit of ``dimension`` (``20mm``, ``0.02``, ``2 cm``) in SI.

    Raises
    ------
    InputError
        For text that is not a finite positive number with a known unit of that dimension.
    """
    match = re.fullmatch(r"\s*([-+0-9.eE]+)\s*([A-Za-zµ]*)\s*", text or "")
    unit = match.group(2) if match else ""
    try:
        value = float(match.group(1)) if match else math.nan
    except ValueError:
        value = math.nan
    factor = UNITS[dimension].get(unit or next(iter(UNITS[dimension])))
    if factor is None or not (math.isfinite(value) and value > 0):
        known = ", ".join(UNITS[dimension])
        raise InputError(
            f"{option} {text[:30]!r}: give a positive {dimension} such as 20mm (units: {known})"
        )
    return value * factor
