"""Terms of the tissue law: ``F = sum_i c_i r_i(x, xdot, xddot)``, one regressor r_i and
one coefficient c_i per term, in SI units.

Each term is one small class in a registry (:data:`TERMS`), so a new law is a new
class and touches no fitting, rendering or file code. A term says which kinematic
variable it reads (``x``, ``v`` for xdot, ``a`` for xddot, or none for a constant),
the symbol and SI unit of its coefficient, whether the coefficient of a passive
tissue is non-negative (``passive``), and whether the display renders it (a sensor
offset is not tissue, so it is not rendered).

The paper's four laws are ``x`` or ``x^3`` with ``xdot`` or ``xdot|xdot|``, plus
``xddot``; real tissue adds an offset, hardening ``x + x^3``, dry friction
``sign(xdot)``.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import InputError

Array = NDArray[np.float64]

#: speed below which dry friction is smoothed: sign(v) ~ tanh(v / V_SMOOTH), m/s. A
#: grasp closes at tens of mm/s; 1 mm/s keeps the law smooth for differentiation and
#: rendering without changing it at grasping speeds (tanh(10) = 1 - 4e-9).
V_SMOOTH = 1e-3


class Term(ABC):
    """One term: a coefficient times a function of one kinematic variable.

    Subclasses set ``name`` (as written in parameter files and ``--forms``),
    ``symbol`` and ``unit`` (the coefficient's), ``label`` (for reports),
    ``role``, ``variable`` (``"x"``, ``"v"``, ``"a"`` or ``"1"``), ``passive``
    (the coefficient is non-negative for a passive tissue) and ``rendered``.
    """

    name: ClassVar[str]
    symbol: ClassVar[str]
    unit: ClassVar[str]
    label: ClassVar[str]
    role: ClassVar[str]
    variable: ClassVar[str]
    passive: ClassVar[bool] = True
    rendered: ClassVar[bool] = True

    @abstractmethod
    def __call__(self, u: ArrayLike) -> Array:
        """The regressor at ``u`` (its variable, SI), shape like ``u``."""

    @abstractmethod
    def derivative(self, u: ArrayLike) -> Array:
        """d regressor / du: the local slope a controller needs."""

    def curvature(self, u: ArrayLike) -> Array:
        """Second derivative (central difference of :meth:`derivative`): what turns noise
        or smoothing inside the function into bias."""
        u = np.asarray(u, dtype=float)
        h = 1e-6 * max(float(np.max(np.abs(u))) if u.size else 0.0, 1e-12)
        return (self.derivative(u + h) - self.derivative(u - h)) / (2 * h)

    def scalar(self, u: float) -> float:
        """The regressor at one float, for real-time loops (subclasses use plain arithmetic)."""
        with np.errstate(all="ignore"):
            return float(self(np.array([u]))[0])

    def regressor(self, x: Array, v: Array, a: Array) -> Array:
        """The regressor at exact kinematics, shape (n,)."""
        u = {"x": x, "v": v, "a": a, "1": np.ones_like(np.asarray(x, dtype=float))}
        return self(u[self.variable])

    def typical(self, scales: MotionScales) -> float:
        """The regressor's size at a session's typical motion (for prior scales)."""
        u = {"x": scales.x, "v": scales.v, "a": scales.a, "1": 1.0}[self.variable]
        return float(abs(self(np.array([u]))[0])) or 1.0

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"


TERMS: dict[str, Term] = {}


def register(cls: type[Term]) -> type[Term]:
    """Class decorator: add a term to :data:`TERMS` under its name."""
    TERMS[cls.name] = cls()
    return cls


def term(name: str) -> Term:
    """Look a term up by name, with an error that lists the choices."""
    try:
        return TERMS[name]
    except KeyError:
        raise InputError(f"unknown term {name[:30]!r}; choose among: {', '.join(TERMS)}") from None


@register
class Linear(Term):
    """x: Hookean stiffness, K in N/m."""

    name, symbol, unit, label, role, variable = "x", "K", "N/m", "x", "stiffness", "x"

    def __call__(self, u: ArrayLike) -> Array:
        return np.asarray(u, dtype=float)

    def scalar(self, u: float) -> float:
        return u

    def derivative(self, u: ArrayLike) -> Array:
        return np.ones_like(np.asarray(u, dtype=float))


@register
class Cubic(Term):
    """x^3: hardening stiffness, K3 in N/m^3."""

    name, symbol, unit, label, role, variable = "x^3", "K3", "N/m^3", "x³", "stiffness", "x"

    def __call__(self, u: ArrayLike) -> Array:
        u = np.asarray(u, dtype=float)
        return u * u * u

    def scalar(self, u: float) -> float:
        return u * u * u

    def derivative(self, u: ArrayLike) -> Array:
        return 3.0 * np.asarray(u, dtype=float) ** 2


@register
class Viscous(Term):
    """xdot: Newtonian damping, S in N s/m."""

    name, symbol, unit, label, role, variable = "xdot", "S", "N s/m", "ẋ", "damping", "v"

    def __call__(self, u: ArrayLike) -> Array:
        return np.asarray(u, dtype=float)

    def scalar(self, u: float) -> float:
        return u

    def derivative(self, u: ArrayLike) -> Array:
        return np.ones_like(np.asarray(u, dtype=float))


@register
class Quadratic(Term):
    """xdot |xdot|: quadratic damping, S2 in N s^2/m^2 (``xdot^2`` in version 1 files).

    The sign is kept so that the damping force always opposes motion; a plain
    square would create energy on release.
    """

    name, symbol, unit, label, role, variable = (
        "xdot|xdot|", "S2", "N s^2/m^2", "ẋ|ẋ|", "damping", "v",
    )  # fmt: skip

    def __call__(self, u: ArrayLike) -> Array:
        u = np.asarray(u, dtype=float)
        return u * np.abs(u)

    def scalar(self, u: float) -> float:
        return u * abs(u)

    def derivative(self, u: ArrayLike) -> Array:
        return 2.0 * np.abs(np.asarray(u, dtype=float))


@register
class Coulomb(Term):
    """sign(xdot): dry friction, Fc in N, smoothed as tanh(xdot / V_SMOOTH)."""

    name, symbol, unit, label, role, variable = (
        "sign(xdot)", "Fc", "N", "sign(ẋ)", "friction", "v",
    )  # fmt: skip

    def __call__(self, u: ArrayLike) -> Array:
        return np.tanh(np.asarray(u, dtype=float) / V_SMOOTH)

    def scalar(self, u: float) -> float:
        return math.tanh(u / V_SMOOTH)

    def derivative(self, u: ArrayLike) -> Array:
        return (1.0 - np.tanh(np.asarray(u, dtype=float) / V_SMOOTH) ** 2) / V_SMOOTH


@register
class Inertia(Term):
    """xddot: moving mass, M in kg."""

    name, symbol, unit, label, role, variable = "xddot", "M", "kg", "ẍ", "inertia", "a"

    def __call__(self, u: ArrayLike) -> Array:
        return np.asarray(u, dtype=float)

    def scalar(self, u: float) -> float:
        return u

    def derivative(self, u: ArrayLike) -> Array:
        return np.ones_like(np.asarray(u, dtype=float))


@register
class Offset(Term):
    """1: a constant force, F0 in N: the force sensor's offset, or a preload. Of either
    sign, and not rendered (the display feels the tissue, not the sensor)."""

    name, symbol, unit, label, role, variable = "offset", "F0", "N", "1", "offset", "1"
    passive = False
    rendered = False

    def __call__(self, u: ArrayLike) -> Array:
        return np.ones_like(np.asarray(u, dtype=float))

    def scalar(self, u: float) -> float:
        return 1.0

    def derivative(self, u: ArrayLike) -> Array:
        return np.zeros_like(np.asarray(u, dtype=float))


@dataclass(frozen=True)
class MotionScales:
    """A session's typical closure (m), speed (m/s) and acceleration (m/s^2) and force
    (N): what makes a coefficient large or small for this session."""

    x: float
    v: float
    a: float
    force: float


#: the scales the priors assume for a forceps when a session gives none (a 5 mm
#: closure, 50 mm/s, 10 m/s^2 and 20 N, six times the largest liver grasp)
FORCEPS_SCALES = MotionScales(x=5e-3, v=0.05, a=10.0, force=20.0)


@dataclass(frozen=True)
class Law:
    """A tissue law: the sum of its terms, each with a coefficient.

    Attributes
    ----------
    terms : tuple of Term
        In a fixed order: stiffness, damping, friction, inertia, offset.
    """

    terms: tuple[Term, ...]

    def __post_init__(self) -> None:
        names = [t.name for t in self.terms]
        if len(set(names)) != len(names) or not names:
            raise InputError(f"a law needs distinct terms, got {', '.join(names) or 'none'}")

    @classmethod
    def of(cls, names: Iterable[str]) -> Law:
        """The law of the named terms, in the canonical order."""
        chosen = {term(n).name: term(n) for n in names}
        return cls(tuple(t for t in TERMS.values() if t.name in chosen))

    @classmethod
    def paper(cls, f0: str = "x", f1: str = "xdot", *extra: str) -> Law:
        """``K f0(x) + S f1(xdot) + M xddot`` (paper eq. 7), plus ``extra`` terms;
        ``xdot^2`` is read as ``xdot|xdot|``."""
        return cls.of([f0, "xdot|xdot|" if f1 == "xdot^2" else f1, "xddot", *extra])

    @property
    def name(self) -> str:
        """The terms joined by ``+``: ``x+xdot+xddot``."""
        return "+".join(t.name for t in self.terms)

    @property
    def symbols(self) -> tuple[str, ...]:
        return tuple(t.symbol for t in self.terms)

    @property
    def units(self) -> dict[str, str]:
        """SI unit of each coefficient, by symbol."""
        return {t.symbol: t.unit for t in self.terms}

    @property
    def passive(self) -> NDArray[np.bool_]:
        """Which coefficients are non-negative, shape (p,)."""
        return np.array([t.passive for t in self.terms])

    def has(self, role: str) -> bool:
        return any(t.role == role for t in self.terms)

    def regressors(self, x: ArrayLike, v: ArrayLike, a: ArrayLike) -> Array:
        """The law's columns at exact kinematics, shape (n, p)."""
        x, v, a = (np.asarray(z, dtype=float) for z in (x, v, a))
        return np.column_stack([t.regressor(x, v, a) for t in self.terms])

    def force(self, c: ArrayLike, x: ArrayLike, v: ArrayLike, a: ArrayLike) -> Array:
        """F = sum_i c_i r_i at exact kinematics, shape (n,), N."""
        return self.regressors(x, v, a) @ np.asarray(c, dtype=float)

    def prior_scales(self, scales: MotionScales = FORCEPS_SCALES) -> Array:
        """Prior scale of each coefficient (SI): the coefficient that makes its term reach
        ``scales.force`` at the session's typical motion."""
        return np.array([scales.force / t.typical(scales) for t in self.terms])


def parse_law(spec: str) -> Law:
    """``x,xdot`` (the paper's f0,f1 with inertia) or terms joined by ``+``
    (``x+x^3+xdot+offset+xddot``)."""
    spec = spec.strip()
    if "+" in spec or spec in TERMS:
        return Law.of(p.strip() for p in spec.split("+") if p.strip())
    parts = [p.strip() for p in spec.split(",")]
    if len(parts) != 2:
        raise InputError(
            f"--forms {spec[:40]!r}: give f0,f1 such as x,xdot, or terms joined by + such as "
            "x+x^3+xdot+offset+xddot"
        )
    for role, name in zip(("stiffness", "damping"), parts, strict=True):
        found = TERMS.get("xdot|xdot|" if name == "xdot^2" else name)
        if found is None or found.role != role:
            choices = ", ".join(t.name for t in TERMS.values() if t.role == role)
            raise InputError(f"unknown {role} form {name[:30]!r}; choose one of: {choices}")
    return Law.paper(*parts)


def paper_laws(*extra: str) -> list[Law]:
    """The paper's four laws (x or x^3 with xdot or xdot|xdot|, and xddot), plus ``extra``."""
    return [Law.paper(f0, f1, *extra) for f0 in ("x", "x^3") for f1 in ("xdot", "xdot|xdot|")]


def symbols_of(laws: Sequence[Law]) -> list[str]:
    """Every coefficient symbol the laws use, in canonical order."""
    seen = {s for law in laws for s in law.symbols}
    return [t.symbol for t in TERMS.values() if t.symbol in seen]
