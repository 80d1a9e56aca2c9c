"""The solenoid display's constants: a :class:`DisplayProfile` (SI), the paper's
prototype, and the profile as a JSON object (files and the display's IDENTIFY reply)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields, replace
from typing import Any

from ..core.errors import InputError


@dataclass(frozen=True)
class DisplayProfile:
    """Constants of one solenoid display, SI. Defaults are the paper's prototype.

    Attributes
    ----------
    Mp : float
        Piston mass, kg (83.35 g weighed).
    Kp : float
        Spring stiffness, N/m (27 gf/mm).
    alpha : float
        Solenoid force constant, N/V^2 (12e-5 gf/mV^2): the pull is ``alpha V^2``.
    v_max : float
        Largest amplifier input, V (pull ``alpha v_max^2`` = 2.648 N).
    stroke : float
        Piston travel, m; end stops at 0 (rest, top) and ``stroke``.
    resolution : float
        Encoder resolution, m per count.
    b : float
        Piston viscous damping, N s/m. The paper gives none; 0.5 N s/m (damping
        ratio 0.05) is an assumption to be replaced by a ring-down measurement.
    """

    Mp: float = 0.08335
    Kp: float = 264.78
    alpha: float = 1.1768
    v_max: float = 1.5
    stroke: float = 0.015
    resolution: float = 1e-6
    b: float = 0.5

    @property
    def max_pull(self) -> float:
        """Largest solenoid force ``alpha v_max^2``, N."""
        return self.alpha * self.v_max**2

    def validate(self) -> DisplayProfile:
        """Raise :class:`InputError` unless every constant is finite and positive (b >= 0)."""
        for f in fields(self):
            value = getattr(self, f.name)
            ok = isinstance(value, (int, float)) and math.isfinite(value)
            ok = ok and (value >= 0 if f.name == "b" else value > 0)
            if not ok:
                sign = ">= 0" if f.name == "b" else "> 0"
                raise InputError(
                    f"display profile: {f.name} = {value!r} {PROFILE_UNITS[f.name]} "
                    f"must be finite and {sign}"
                )
        return self

    def as_dict(self) -> dict[str, Any]:
        """The profile as JSON-ready ``{"Mp": {"value": ..., "unit": "kg"}, ...}``."""
        out: dict[str, Any] = {"format": "tissuecli-display", "version": 1}
        for key, value in asdict(self).items():
            out[key] = {"value": value, "unit": PROFILE_UNITS[key]}
        return out


PAPER_DISPLAY = DisplayProfile()


#: SI unit of each profile constant, as written in profile files
PROFILE_UNITS = {
    "Mp": "kg",
    "Kp": "N/m",
    "alpha": "N/V^2",
    "v_max": "V",
    "stroke": "m",
    "resolution": "m",
    "b": "N s/m",
}


def profile_from_dict(data: Mapping[str, Any], source: str = "display profile") -> DisplayProfile:
    """Build a :class:`DisplayProfile` from a JSON object.

    Each constant is a number in SI or ``{"value": number, "unit": "..."}``; missing
    constants keep the paper's values. Unknown keys are refused, so a typo is not
    silently ignored.

    Parameters
    ----------
    data : mapping
        E.g. ``{"Mp": 0.1, "Kp": {"value": 300, "unit": "N/m"}}``.
    source : str
        Names the input in error messages (a file name).

    Raises
    ------
    InputError
        For unknown keys, wrong units, or values that are not finite and positive.
    """
    if not isinstance(data, Mapping):
        raise InputError(f"{source} must be a JSON object")
    units = PROFILE_UNITS
    unknown = sorted(set(data) - set(units) - {"format", "version", "name", "note"})
    if unknown:
        raise InputError(
            f"{source}: unknown key(s) {', '.join(unknown)}; known: {', '.join(units)}"
        )
    values: dict[str, float] = {}
    for key, unit in units.items():
        if key not in data:
            continue
        entry = data[key]
        value = entry.get("value") if isinstance(entry, Mapping) else entry
        if isinstance(entry, Mapping) and entry.get("unit", unit) != unit:
            raise InputError(f"{source}: {key} is in {entry['unit']!r}; give it in {unit!r}")
        if not isinstance(value, (int, float)) or isinstance(value, bool):
            raise InputError(f"{source}: {key} must be a number in {unit}")
        values[key] = float(value)
    return replace(PAPER_DISPLAY, **values).validate()
