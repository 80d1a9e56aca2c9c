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
    symbol: str
    unit: str
    label: ClassVar[str]
    role: ClassVar[str]
    variable: ClassVar[str]
    passive: ClassVar[bool] = True
    rendered: ClassVar[bool] = True
    #: the term's force depends on the past (a relaxation branch): it needs a time series
    memory: ClassVar[bool] = False

    #: names of the nonlinear (shape) parameters the term reads, and their values once
    #: bound (a term with shapes fits as a family; a tissue holds it bound)
    shapes: tuple[str, ...] = ()
    shape: dict[str, float] = {}

    @property
    def bound(self) -> bool:
        """Whether every shape parameter has a value."""
        return all(n in self.shape for n in self.shapes)

    def bind(self, values: dict[str, float]) -> Term:
        """This term with its shape parameters set from ``values`` (by name); itself if it
        has none."""
        return self

    def _key(self) -> tuple[object, ...]:
        return (type(self), self.symbol, tuple(sorted(self.shape.items())))

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Term) and self._key() == other._key()

    def __hash__(self) -> int:
        return hash(self._key())

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

    def series(self, dt: float, x: Array, v: Array, a: Array) -> Array:
        """The regressor over a uniformly sampled series (``dt`` s apart, from rest before
        the first sample): what a term with memory needs; the others ignore ``dt``."""
        return self.regressor(x, v, a)

    def typical(self, scales: MotionScales) -> float:
        """The regressor's size at a session's typical motion (for prior scales)."""
        u = {"x": scales.x, "v": scales.v, "a": scales.a, "1": 1.0}[self.variable]
        return float(abs(self(np.array([u]))[0])) or 1.0

    def __repr__(self) -> str:
        shape = ", ".join(f"{k}={v:g}" for k, v in self.shape.items())
        return f"{type(self).__name__}({shape})"


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


class _Proportional(Term):
    """A term equal to its variable (a spring's x, a damper's xdot, a mass's xddot)."""

    def __call__(self, u: ArrayLike) -> Array:
        return np.asarray(u, dtype=float)

    def scalar(self, u: float) -> float:
        return u

    def derivative(self, u: ArrayLike) -> Array:
        return np.ones_like(np.asarray(u, dtype=float))


@register
class Linear(_Proportional):
    """x: Hookean stiffness, K in N/m."""

    name, symbol, unit, label, role, variable = "x", "K", "N/m", "x", "stiffness", "x"


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
class Viscous(_Proportional):
    """xdot: Newtonian damping, S in N s/m."""

    name, symbol, unit, label, role, variable = "xdot", "S", "N s/m", "ẋ", "damping", "v"


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
class Inertia(_Proportional):
    """xddot: moving mass, M in kg."""

    name, symbol, unit, label, role, variable = "xddot", "M", "kg", "ẍ", "inertia", "a"


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


@register
class Contact(Term):
    """Hunt-Crossley contact stiffness: ``Kc d^n`` with ``d = max(x - x0, 0)``, the
    indentation past the contact point x0 (m), exponent n; Kc in N/m^n."""

    name, symbol, unit, label, role, variable = (
        "contact", "Kc", "N/m^n", "dⁿ", "stiffness", "x",
    )  # fmt: skip
    shapes = ("n", "x0")

    def __init__(self, shape: dict[str, float] | None = None) -> None:
        self.shape = dict(shape or {})

    def bind(self, values: dict[str, float]) -> Term:
        return type(self)({k: float(values[k]) for k in self.shapes})

    def _nd(self) -> tuple[float, float]:
        return self.shape.get("n", 1.5), self.shape.get("x0", 0.0)

    def __call__(self, u: ArrayLike) -> Array:
        n, x0 = self._nd()
        d = np.maximum(np.asarray(u, dtype=float) - x0, 0.0)
        return d**n

    def derivative(self, u: ArrayLike) -> Array:
        n, x0 = self._nd()
        d = np.maximum(np.asarray(u, dtype=float) - x0, 0.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(d > 0, n * d ** (n - 1.0), 0.0)

    def scalar(self, u: float) -> float:
        n, x0 = self._nd()
        d = u - x0
        return d**n if d > 0 else 0.0

    def typical(self, scales: MotionScales) -> float:
        return float(scales.x ** self._nd()[0]) or 1.0


@register
class ContactDamping(Contact):
    """Hunt-Crossley contact damping: ``Lc d^n xdot``, the damping that grows with the
    indentation (no force before contact, none created on release); Lc in N s/m^(n+1).
    Shares n and x0 with :class:`Contact`."""

    name, symbol, unit, label, role, variable = (
        "contact*xdot", "Lc", "N s/m^(n+1)", "dⁿẋ", "damping", "xv",
    )  # fmt: skip

    def regressor(self, x: Array, v: Array, a: Array) -> Array:
        return Contact.__call__(self, x) * np.asarray(v, dtype=float)

    def typical(self, scales: MotionScales) -> float:
        return float(scales.x ** self._nd()[0] * scales.v) or 1.0


@register
class Maxwell(Term):
    """A relaxation branch (generalised Maxwell, or Prony, series): a spring Km in series
    with a damper Km tau. Its force obeys ``F' = Km xdot - F / tau`` from rest, so a
    step in closure gives ``Km e^(-t/tau)``: the stress relaxation of soft tissue. One
    branch with a spring ``x`` is the standard linear solid. Km in N/m, tau in s."""

    name, label, role, variable = "maxwell", "relax", "relaxation", "h"
    unit = "N/m"
    memory = True

    def __init__(self, index: int = 1, shape: dict[str, float] | None = None) -> None:
        self.index = index
        self.symbol = f"Km{index}"
        self.shapes = (f"tau{index}",)
        self.shape = dict(shape or {})

    def bind(self, values: dict[str, float]) -> Term:
        return type(self)(self.index, {k: float(values[k]) for k in self.shapes})

    @property
    def tau(self) -> float:
        return self.shape.get(self.shapes[0], math.nan)

    def __call__(self, u: ArrayLike) -> Array:
        raise TypeError("a relaxation branch needs the closure's history: use series()")

    def derivative(self, u: ArrayLike) -> Array:
        # the instantaneous stiffness of the branch: the spring, before it relaxes
        return np.ones_like(np.asarray(u, dtype=float))

    def regressor(self, x: Array, v: Array, a: Array) -> Array:
        raise TypeError("a relaxation branch needs the closure's history: use series()")

    def series(self, dt: float, x: Array, v: Array, a: Array) -> Array:
        return relaxation(np.asarray(x, dtype=float), dt, self.tau)[0]

    def typical(self, scales: MotionScales) -> float:
        return scales.x or 1.0


def relaxation(
    x: Array, dt: float, tau: float, state: float = 0.0, x_before: float | None = None
) -> tuple[Array, float]:
    """The force per unit branch stiffness of a Maxwell branch, sample by sample.

    With the closure linear between samples, ``r' = xdot - r / tau`` integrates
    exactly to ``r_k = a r_{k-1} + (tau / dt) (1 - a) (x_k - x_{k-1})``,
    ``a = exp(-dt / tau)``. The recursion runs in blocks short enough that ``a^-j``
    stays finite, so it is exact and vectorised.

    Parameters
    ----------
    x : ndarray, shape (n,)
        Closure, m, every ``dt`` s.
    dt, tau : float
        Sample interval and time constant, s.
    state : float
        ``r`` before the first sample (0: at rest).
    x_before : float, optional
        The closure before the first sample (default: the first sample, no step).

    Returns
    -------
    r : ndarray, shape (n,)
        m (times Km: N).
    last : float
        ``r`` at the last sample, to continue from.
    """
    n = x.size
    out = np.empty(n)
    if n == 0:
        return out, state
    a = math.exp(-dt / tau)
    gain = (tau / dt) * -math.expm1(-dt / tau)
    u = gain * np.diff(x, prepend=x[0] if x_before is None else x_before)
    lam = dt / tau
    block = max(1, min(n, int(30.0 / lam) if lam > 0 else n))
    r = state
    for start in range(0, n, block):
        seg = u[start : start + block]
        j = np.arange(seg.size, dtype=float)
        grow = np.exp(-lam * j)  # a^j, decaying, never overflows
        # r_k = a^k (a r + sum_{i<=k} a^-i u_i), with a^-i = 1 / grow_i below e^30
        out[start : start + seg.size] = grow * (a * r + np.cumsum(seg / grow))
        r = float(out[start + seg.size - 1])
    return out, r


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
        symbols = [t.symbol for t in self.terms]
        if len(set(symbols)) != len(symbols) or not symbols:
            names = ", ".join(t.name for t in self.terms)
            raise InputError(f"a law needs distinct terms, got {names or 'none'}")
        if any(t.name == "contact*xdot" for t in self.terms) and not any(
            t.name == "contact" for t in self.terms
        ):
            raise InputError("contact*xdot (Hunt-Crossley damping) needs its contact term too")

    @classmethod
    def of(cls, names: Iterable[str]) -> Law:
        """The law of the named terms, in the canonical order; ``maxwell`` may repeat (one
        relaxation branch each)."""
        names = list(names)
        branches = sum(1 for n in names if n == "maxwell")
        if branches > MAX_BRANCHES:
            raise InputError(f"at most {MAX_BRANCHES} relaxation branches (maxwell) in a law")
        chosen = {term(n).name: term(n) for n in names if n != "maxwell"}
        terms: list[Term] = []
        for name in CANONICAL:
            if name == "maxwell":
                terms += [Maxwell(i) for i in range(1, branches + 1)]
            elif name in chosen:
                terms.append(chosen[name])
        return cls(tuple(terms))

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

    @property
    def shape_names(self) -> tuple[str, ...]:
        """The nonlinear parameters of the law, each once (contact terms share n, x0)."""
        seen: dict[str, None] = {}
        for t in self.terms:
            seen.update(dict.fromkeys(t.shapes))
        return tuple(seen)

    @property
    def shape(self) -> dict[str, float]:
        """The shape parameters' values, once bound."""
        out: dict[str, float] = {}
        for t in self.terms:
            out.update(t.shape)
        return out

    @property
    def bound(self) -> bool:
        return all(t.bound for t in self.terms)

    @property
    def memory(self) -> bool:
        """Whether the force depends on the past (relaxation branches)."""
        return any(t.memory for t in self.terms)

    def bind(self, values: dict[str, float]) -> Law:
        """The law with its shape parameters set (by name, SI)."""
        missing = [n for n in self.shape_names if n not in values]
        if missing:
            raise InputError(f"law {self.name} needs values for {', '.join(missing)}")
        return Law(tuple(t.bind(values) for t in self.terms))

    def has(self, role: str) -> bool:
        return any(t.role == role for t in self.terms)

    def regressors(
        self, x: ArrayLike, v: ArrayLike, a: ArrayLike, dt: float | None = None
    ) -> Array:
        """The law's columns at exact kinematics, shape (n, p); a law with memory needs
        the sample interval ``dt`` (s), the series starting from rest."""
        x, v, a = (np.asarray(z, dtype=float) for z in (x, v, a))
        if self.memory and dt is None:
            raise InputError(f"law {self.name} has memory: give the series' sample interval")
        return np.column_stack(
            [t.series(dt, x, v, a) if t.memory else t.regressor(x, v, a) for t in self.terms]  # type: ignore[arg-type]
        )

    def force(
        self, c: ArrayLike, x: ArrayLike, v: ArrayLike, a: ArrayLike, dt: float | None = None
    ) -> Array:
        """F = sum_i c_i r_i at exact kinematics, shape (n,), N."""
        return self.regressors(x, v, a, dt) @ np.asarray(c, dtype=float)

    def prior_scales(self, scales: MotionScales = FORCEPS_SCALES) -> Array:
        """Prior scale of each coefficient (SI): the coefficient that makes its term reach
        ``scales.force`` at the session's typical motion."""
        return np.array([scales.force / t.typical(scales) for t in self.terms])


#: units and the range a file may give each kind of shape parameter (SI): time
#: constants, Hunt-Crossley exponents and contact points
SHAPE_UNITS = {"tau": "s", "n": "1", "x0": "m"}
SHAPE_RANGES = {"tau": (1e-4, 1e4), "n": (0.5, 5.0), "x0": (-1.0, 1.0)}
#: what each kind of shape parameter is, in words
SHAPE_MEANING = {
    "tau": "relaxation time constant",
    "n": "contact exponent",
    "x0": "contact point (closure)",
}


def shape_kind(name: str) -> str:
    """``tau`` for a branch's time constant (``tau2``), else the name (``n``, ``x0``)."""
    return "tau" if name.startswith("tau") else name


def shape_unit(name: str) -> str:
    """The SI unit of a shape parameter (``tau2`` -> ``s``)."""
    return SHAPE_UNITS[shape_kind(name)]


#: most relaxation branches a law may have
MAX_BRANCHES = 3
#: the order of terms in a law: stiffness, relaxation, damping, friction, inertia, offset
CANONICAL = (
    "x", "x^3", "contact", "maxwell", "xdot", "xdot|xdot|", "contact*xdot", "sign(xdot)",
    "xddot", "offset",
)  # fmt: skip


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
    seen: dict[str, None] = {}
    for law in sorted(laws, key=lambda law: -len(law.terms)):
        seen.update(dict.fromkeys(law.symbols))
    order = {name: i for i, name in enumerate(CANONICAL)}
    by_symbol = {t.symbol: t for law in laws for t in law.terms}
    return sorted(seen, key=lambda s: (order[by_symbol[s].name], s))
