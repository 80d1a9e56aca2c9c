"""A tissue: a law (:class:`~tissuecli.core.terms.Law`) with the value of each coefficient,
in SI units; what ``simulate``, ``fit`` and ``play`` share."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import InputError
from .terms import Law, Term

Array = NDArray[np.float64]


class Tissue:
    """A law with its coefficients.

    ``Tissue(law, 350.0, 3.0, 0.05)`` gives the coefficients in the law's order;
    ``Tissue(law, K=350.0, S=3.0, M=0.05)`` by symbol. Coefficients read as
    attributes by symbol (``tissue.K``) or as an array (``tissue.coef``).

    Parameters
    ----------
    law : Law
        The terms.
    *values : float
        Coefficients in the order of ``law.terms``, SI.
    **by_symbol : float
        Or by symbol (``K``, ``S``, ``M``, ``F0``, ...).
    """

    __slots__ = ("law", "coef")

    def __init__(self, law: Law, *values: float, **by_symbol: float) -> None:
        if values and by_symbol:
            raise TypeError("give the coefficients in order or by symbol, not both")
        if by_symbol:
            unknown = sorted(set(by_symbol) - set(law.symbols))
            missing = [s for s in law.symbols if s not in by_symbol]
            if unknown or missing:
                raise InputError(
                    f"law {law.name} has coefficients {', '.join(law.symbols)}; unknown "
                    f"{', '.join(unknown) or 'none'}, missing {', '.join(missing) or 'none'}"
                )
            values = tuple(by_symbol[s] for s in law.symbols)
        if len(values) != len(law.terms):
            raise InputError(f"law {law.name} has {len(law.terms)} coefficients, got {len(values)}")
        if not law.bound:
            raise InputError(
                f"law {law.name} needs values for its shape parameters "
                f"{', '.join(law.shape_names)}: bind them with Law.bind"
            )
        object.__setattr__(self, "law", law)
        object.__setattr__(self, "coef", np.array(values, dtype=float))

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError("a Tissue is immutable")

    def __getattr__(self, symbol: str) -> float:
        law = object.__getattribute__(self, "law")
        if symbol in law.symbols:
            return float(self.coef[law.symbols.index(symbol)])
        raise AttributeError(f"{type(self).__name__} of {law.name} has no coefficient {symbol!r}")

    def __eq__(self, other: object) -> bool:
        return (
            isinstance(other, Tissue)
            and other.law == self.law
            and bool(np.array_equal(other.coef, self.coef))
        )

    def __hash__(self) -> int:
        return hash((self.law, tuple(self.coef)))

    def __repr__(self) -> str:
        values = ", ".join(f"{s}={c:g}" for s, c in zip(self.law.symbols, self.coef, strict=True))
        shape = "".join(f", {k}={v:g}" for k, v in self.law.shape.items())
        return f"Tissue({self.law.name}: {values}{shape})"

    def get(self, symbol: str, default: float = 0.0) -> float:
        """The coefficient of ``symbol``, or ``default`` if the law has no such term."""
        return (
            float(self.coef[self.law.symbols.index(symbol)])
            if symbol in self.law.symbols
            else default
        )

    @property
    def mass(self) -> float:
        """The inertia coefficient M, kg (0 for a law without inertia)."""
        return self.get("M")

    def describe(self) -> dict[str, Any]:
        """JSON-ready: the law's name, each coefficient by symbol and each shape
        parameter by name, SI."""
        return {
            "law": self.law.name,
            **{s: float(c) for s, c in zip(self.law.symbols, self.coef, strict=True)},
            **self.law.shape,
        }

    def force(self, x: ArrayLike, v: ArrayLike, a: ArrayLike, dt: float | None = None) -> Array:
        """The law's force at exact kinematics, shape (n,), N; a law with memory needs the
        series' sample interval ``dt`` (s), starting from rest."""
        return self.law.force(self.coef, x, v, a, dt)

    def validate(self) -> Tissue:
        """Raise :class:`InputError` unless every coefficient is finite, and the passive
        ones non-negative."""
        for t, c in zip(self.law.terms, self.coef, strict=True):
            if not math.isfinite(c) or (t.passive and c < 0):
                sign = " and >= 0" if t.passive else ""
                raise InputError(f"coefficient {t.symbol} = {c} {t.unit} must be finite{sign}")
        return self

    # the display renders the tissue's own terms (not a sensor's offset) without inertia,
    # which the controller's reference model carries

    def _rendered(self, variable: str) -> list[tuple[Term, float]]:
        # as each term declares it rendered: of the closure, or of the speed (with friction)
        kinds = {"x": ("position",), "v": ("speed", "friction")}[variable]
        return [
            (t, float(c))
            for t, c in zip(self.law.terms, self.coef, strict=True)
            if t.rendered and t.rendering in kinds
        ]

    def static_force(self, x: ArrayLike) -> Array:
        """The rendered force at rest at closures ``x`` (m), N: the position terms."""
        x = np.asarray(x, dtype=float)
        with np.errstate(all="ignore"):
            return sum((c * t(x) for t, c in self._rendered("x")), np.zeros_like(x))

    def damping_force(self, v: ArrayLike) -> Array:
        """The rendered force of speed ``v`` (m/s), N: damping and friction."""
        v = np.asarray(v, dtype=float)
        with np.errstate(all="ignore"):
            return sum((c * t(v) for t, c in self._rendered("v")), np.zeros_like(v))

    def stiffness(self, x: ArrayLike) -> Array:
        """Local stiffness d static_force / dx at ``x``, N/m."""
        x = np.asarray(x, dtype=float)
        with np.errstate(all="ignore"):
            return sum((c * t.derivative(x) for t, c in self._rendered("x")), np.zeros_like(x))

    def damping(self, v: ArrayLike) -> Array:
        """Local damping d damping_force / dv at ``v``, N s/m."""
        v = np.asarray(v, dtype=float)
        with np.errstate(all="ignore"):
            return sum((c * t.derivative(v) for t, c in self._rendered("v")), np.zeros_like(v))

    def scalar_law(self) -> tuple[Any, Any]:
        """Two float -> float functions, the static and the speed part of the rendered force,
        in plain arithmetic for a real-time loop."""
        xs = tuple(self._rendered("x"))
        vs = tuple(self._rendered("v"))

        def static(x: float) -> float:
            return sum(c * t.scalar(x) for t, c in xs)

        def speed(v: float) -> float:
            return sum(c * t.scalar(v) for t, c in vs)

        return static, speed


DEFAULT_TISSUE = Tissue(Law.paper("x", "xdot"), K=350.0, S=3.0, M=0.05)
"""A liver-like default: 350 N/m, 3 N s/m, 50 g moving mass (field notes, section 2)."""
