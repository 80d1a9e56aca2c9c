"""Forms of the tissue law: the functions f0(x) (stiffness) and f1(xdot) (damping).

Each form is one small class in a registry, so a new stiffness or damping law is
one new class and touches no fitting or rendering code. Everything is SI:
x in m, xdot in m/s, and the coefficient's unit makes each term a force in N.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import ClassVar

import numpy as np
from numpy.typing import NDArray

from .errors import InputError

Array = NDArray[np.float64]


class Form(ABC):
    """A nonlinear function of one kinematic variable, with its parameter's unit.

    Subclasses set ``name`` (as written in parameter files), ``role``
    (``"stiffness"`` acts on x, ``"damping"`` on xdot) and ``unit`` (the SI
    unit of the coefficient multiplying the form, so that the product is N).
    """

    name: ClassVar[str]
    role: ClassVar[str]
    unit: ClassVar[str]
    label: ClassVar[str]  # for plots and reports

    def prior_scale(self, force_scale: float = 20.0) -> float:  # N
        """Half-normal prior scale of the coefficient (SI): the coefficient that makes
        this term give ``force_scale`` (N) at the role's typical value (:data:`TYPICAL`)."""
        return force_scale / float(abs(self(np.array([TYPICAL[self.role]]))[0]))

    @abstractmethod
    def __call__(self, u: Array) -> Array:
        """The form evaluated at ``u`` (shape (n,), SI)."""

    @abstractmethod
    def derivative(self, u: Array) -> Array:
        """d form / du at ``u``: the local slope a controller needs."""

    def curvature(self, u: Array) -> Array:
        """Second derivative at ``u`` (central difference of :meth:`derivative`); what
        turns noise or smoothing inside the form into bias."""
        u = np.asarray(u, dtype=float)
        h = 1e-6 * max(float(np.max(np.abs(u))) if u.size else 0.0, 1e-12)
        return (self.derivative(u + h) - self.derivative(u - h)) / (2 * h)

    def scalar(self, u: float) -> float:
        """The form at one float, for real-time loops where a numpy call per sample costs
        too much; forms override it with plain arithmetic."""
        with np.errstate(all="ignore"):
            return float(self(np.array([u]))[0])

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"


FORMS: dict[str, dict[str, Form]] = {"stiffness": {}, "damping": {}}


#: Weakly informative prior scales: a term of the law reaching 20 N (six times the
#: largest grasp force measured on liver, 3.4 N) at a typical jaw closure of 5 mm,
#: closing speed of 50 mm/s or acceleration of 10 m/s^2.
FORCE_SCALE = 20.0  # N


TYPICAL = {"stiffness": 5e-3, "damping": 0.05, "inertia": 10.0}  # m, m/s, m/s^2


def register(cls: type[Form]) -> type[Form]:
    """Class decorator: add a form to :data:`FORMS` under its role and name."""
    FORMS[cls.role][cls.name] = cls()
    return cls


@register
class Linear(Form):
    """f0(x) = x: Hookean stiffness, K in N/m."""

    name, role, unit, label = "x", "stiffness", "N/m", "x"

    def __call__(self, u: Array) -> Array:
        return np.asarray(u, dtype=float)

    def scalar(self, u: float) -> float:
        return u

    def derivative(self, u: Array) -> Array:
        return np.ones_like(u, dtype=float)


@register
class Cubic(Form):
    """f0(x) = x^3: hardening stiffness, K in N/m^3."""

    name, role, unit, label = "x^3", "stiffness", "N/m^3", "x³"

    def __call__(self, u: Array) -> Array:
        u = np.asarray(u, dtype=float)
        return u * u * u

    def scalar(self, u: float) -> float:
        return u * u * u

    def derivative(self, u: Array) -> Array:
        return 3.0 * np.asarray(u, dtype=float) ** 2


@register
class Viscous(Form):
    """f1(xdot) = xdot: Newtonian damping, S in N s/m."""

    name, role, unit, label = "xdot", "damping", "N s/m", "ẋ"

    def __call__(self, u: Array) -> Array:
        return np.asarray(u, dtype=float)

    def scalar(self, u: float) -> float:
        return u

    def derivative(self, u: Array) -> Array:
        return np.ones_like(u, dtype=float)


@register
class Quadratic(Form):
    """f1(xdot) = xdot |xdot|: quadratic damping, S in N s^2/m^2.

    Written ``"xdot^2"`` in files. The sign is kept so that the damping force
    always opposes motion; a plain square would create energy on release.
    """

    name, role, unit, label = "xdot^2", "damping", "N s^2/m^2", "ẋ|ẋ|"

    def __call__(self, u: Array) -> Array:
        u = np.asarray(u, dtype=float)
        return u * np.abs(u)

    def scalar(self, u: float) -> float:
        return u * abs(u)

    def derivative(self, u: Array) -> Array:
        return 2.0 * np.abs(np.asarray(u, dtype=float))


def form(role: str, name: str) -> Form:
    """Look a form up by role and name, with an error that lists the choices."""
    try:
        return FORMS[role][name]
    except KeyError:
        choices = ", ".join(FORMS[role])
        raise InputError(f"unknown {role} form {name!r}; choose one of: {choices}") from None
