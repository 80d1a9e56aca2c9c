"""The solenoid display's constants: a :class:`DisplayProfile` (SI), the paper's
prototype, and the profile as a JSON object (files and the display's IDENTIFY reply)."""

from __future__ import annotations

import math
import struct
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
        ratio 0.05) is an assumption: ``tissuecli calibrate display`` measures it
        by ring-downs.
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
        """Raise :class:`InputError` unless every constant is a finite number within
        :data:`PROFILE_RANGES` and the encoder resolves at least 100 steps of the stroke."""
        for f in fields(self):
            value = getattr(self, f.name)
            lo, hi = PROFILE_RANGES[f.name]
            ok = isinstance(value, (int, float)) and not isinstance(value, bool)
            ok = ok and math.isfinite(value) and lo <= value <= hi and (value > 0 or f.name == "b")
            if not ok:
                raise InputError(
                    f"display profile: {f.name} = {_shown(value)} {PROFILE_UNITS[f.name]} must "
                    f"be finite and in {'[' if f.name == 'b' else '('}{lo:g}, {hi:g}] "
                    f"{PROFILE_UNITS[f.name]} (docs/formats.md)"
                )
        if self.resolution > self.stroke / 100:
            raise InputError(
                f"display profile: resolution {self.resolution:g} m resolves fewer than 100 "
                f"steps of the {self.stroke:g} m stroke"
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


#: Physical range of each constant, SI: a hand-held solenoid display, with margins of
#: orders of magnitude around the paper's prototype, so a typo in a unit (g for kg, mm
#: for m) or an absurd value is refused before any arithmetic. ``b`` may be 0; every
#: other constant must be > 0.
PROFILE_RANGES = {
    "Mp": (1e-3, 10.0),  # a piston of a gram to 10 kg
    "Kp": (1e-3, 1e6),  # N/m
    "alpha": (1e-6, 1e3),  # N/V^2
    "v_max": (1e-3, 1e3),  # V
    "stroke": (1e-4, 1.0),  # 0.1 mm to 1 m
    "resolution": (1e-9, 1e-2),  # m per count
    "b": (0.0, 1e4),  # N s/m
}

PROFILE_FORMAT = "tissuecli-display"
PROFILE_VERSION = 1
_SHOW_CHARS = 60


def _shown(value: Any) -> str:
    """``repr(value)`` cut to 60 characters (a value from a file may be huge)."""
    text = repr(value)
    return text if len(text) <= _SHOW_CHARS else text[: _SHOW_CHARS - 3] + "..."


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
    fmt = data.get("format", PROFILE_FORMAT)
    if fmt != PROFILE_FORMAT:
        raise InputError(
            f"{source}: format {_shown(fmt)} is not {PROFILE_FORMAT!r}; is it a display profile?"
        )
    version = data.get("version", PROFILE_VERSION)
    if not isinstance(version, int) or isinstance(version, bool) or version < 1:
        raise InputError(f"{source}: version = {_shown(version)} must be a whole number >= 1")
    if version > PROFILE_VERSION:
        raise InputError(
            f"{source} has format version {_shown(version)}, written by a newer tissuecli; "
            f"this one reads up to version {PROFILE_VERSION}: upgrade tissuecli"
        )
    units = PROFILE_UNITS
    unknown = [k for k in data if k not in units and k not in ("format", "version", "name", "note")]
    if unknown:
        raise InputError(f"{source}: unknown key {_shown(unknown[0])}; known: {', '.join(units)}")
    for key in ("name", "note"):
        if key in data and not isinstance(data[key], str):
            raise InputError(f"{source}: {key} must be a string")
    values: dict[str, float] = {}
    for key, unit in units.items():
        if key not in data:
            continue
        entry = data[key]
        if isinstance(entry, Mapping):
            # ci95: the interval a calibration measured, kept for people, not used
            extra = [k for k in entry if k not in ("value", "unit", "ci95")]
            if extra or "value" not in entry:
                raise InputError(
                    f'{source}: {key} must be a number or {{"value": number, "unit": "{unit}"}}'
                )
            if entry.get("unit", unit) != unit:
                raise InputError(
                    f"{source}: {key} is in {_shown(entry['unit'])}; give it in {unit!r}"
                )
            value = entry["value"]
            ci = entry.get("ci95")
            if ci is not None and not (
                isinstance(ci, list)
                and len(ci) == 2
                and all(isinstance(c, (int, float)) and not isinstance(c, bool) for c in ci)
            ):
                raise InputError(f"{source}: {key}.ci95 must be [low, high] in {unit}")
        else:
            value = entry
        if not isinstance(value, (int, float)) or isinstance(value, bool):
            raise InputError(f"{source}: {key} must be a number in {unit}")
        if not math.isfinite(float(value)):
            raise InputError(f"{source}: {key} = {_shown(value)} is not a finite number")
        values[key] = float(value)
    try:
        return replace(PAPER_DISPLAY, **values).validate()
    except InputError as exc:
        raise InputError(str(exc).replace("display profile", source, 1)) from None


#: Relative slack when a profile's limits are compared with a display's (float32 and
#: decimal round trips of the same number).
LIMIT_SLACK = 1e-6


def exceeded_limits(asked: DisplayProfile, reported: DisplayProfile) -> list[str]:
    """Where ``asked`` (a ``--profile``) asks more of the display than it reports.

    The display's amplifier limit ``v_max``, its piston's ``stroke`` and its largest
    pull ``alpha v_max^2`` bound every command: a profile above any of them would let
    the host command more than the hardware allows (and judge renderable what is
    not). Each item names both numbers.

    Returns
    -------
    list of str
        One phrase per limit exceeded, e.g. ``"v_max 100 V > 1.5 V"``; empty if none.
    """
    out = []
    for name, unit, a, r in (
        ("v_max", "V", asked.v_max, reported.v_max),
        ("stroke", "m", asked.stroke, reported.stroke),
        ("force alpha v_max^2", "N", asked.max_pull, reported.max_pull),
    ):
        if a > r * (1 + LIMIT_SLACK):
            out.append(f"{name} {a:.4g} {unit} > {r:.4g} {unit}")
    return out


def clamp_volts(volts: float, v_max: float) -> tuple[float, bool]:
    """``volts`` within [0, ``v_max``] (NaN read as 0), also once rounded to the float32
    a SetVoltage frame carries; and whether it was changed."""
    if not volts == volts or volts < 0.0:
        return 0.0, True
    clamped = volts > v_max
    if clamped:
        volts = v_max
    if _float32(volts) > v_max:  # the frame's float32 would round above the limit
        bits = struct.unpack("<I", struct.pack("<f", volts))[0] - 1
        volts = struct.unpack("<f", struct.pack("<I", bits))[0]
    return volts, clamped


def _float32(value: float) -> float:
    return float(struct.unpack("<f", struct.pack("<f", value))[0])
