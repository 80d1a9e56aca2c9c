"""Terms of the tissue law: ``F = sum_i c_i r_i(x, xdot, xddot)``, one regressor r_i and
one coefficient c_i per term, in SI units.

A term is one class in a registry (:data:`TERMS`): a new law is a new class and touches
no fitting, rendering, report or file code. The class declares everything the rest of
the program asks of a term: its column (from ``x``, ``xdot``, ``xddot``, or for a term
with memory from their history on a time base), the symbol and SI unit of its
coefficient, its display name, whether a passive tissue's coefficient is non-negative,
its place in a law, its shape parameters with their priors and ranges
(:class:`ShapeParameter`), whether it has memory and how a simulation continues it,
how the display renders it or why it refuses it, and what the default structure
search does with it. :meth:`Law.of` and parameter files look names up here and refuse
an unknown one.

The paper's four laws are ``x`` or ``x^3`` with ``xdot`` or ``xdot|xdot|``, plus
``xddot``; real tissue adds an offset, hardening ``x + x^3``, dry friction
``sign(xdot)``, Hunt-Crossley contact and relaxation branches.
"""

from __future__ import annotations

import math
import re
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


@dataclass(frozen=True)
class SessionSpan:
    """What a session lets a shape parameter's prior span: its sample interval ``dt``
    (s), the cutoff of the filter that formed its kinematics (Hz), its fitted stretch
    (s), and its fitted closure's low end (2nd percentile) and span (m); ``x_floor``,
    the low end (2nd percentile) of the closure over the whole session, free jaw
    motion included, where the fit keeps to the grasps (m; NaN where it fits every
    sample); ``f_ratio``, the force at the fitted closure's low end over that at its
    high end (medians over the lowest and the highest twentieth of the closures), and
    ``x_ends``, those twentieths' median closures (m; NaN where not read)."""

    dt: float
    cutoff_hz: float
    duration_s: float
    x_low: float
    x_span: float
    x_floor: float = math.nan
    f_ratio: float = math.nan
    x_ends: tuple[float, float] = (math.nan, math.nan)


@dataclass(frozen=True)
class ShapeParameter:
    """A nonlinear (shape) parameter a term declares: what it is, its unit, the range a
    parameter file may give it, and its prior, uniform in ``u`` (its logarithm if ``log``,
    else the value) over :meth:`prior_range`.

    Attributes
    ----------
    kind : str
        The parameter's name, or its stem where a repeated term numbers it (``tau``:
        ``tau1``, ``tau2``).
    unit : str
        SI unit.
    meaning : str
        What it is, in words (reports).
    limits : (float, float)
        The values a parameter file may hold, SI.
    prior : (float, float), optional
        The prior's support, SI, when it does not depend on the session.
    log : bool
        Prior uniform in ln(value) (a scale such as a time constant).
    nodes, coarse : int
        Quadrature nodes, and nodes of the coarse grid that only seeds a sampler.
    """

    kind: str
    unit: str
    meaning: str
    limits: tuple[float, float]
    prior: tuple[float, float] | None = None
    log: bool = False
    nodes: int = 7
    coarse: int = 5

    def prior_range(self, span: SessionSpan) -> tuple[float, float]:
        """The prior's support for a session, SI (the fixed ``prior`` unless overridden)."""
        if self.prior is None:
            raise NotImplementedError(f"shape parameter {self.kind} needs a prior range")
        return self.prior

    def nodes_for(self, count: int, coarse: bool = False) -> int:
        """Quadrature nodes per parameter when a law holds ``count`` of this kind."""
        return self.coarse if coarse else self.nodes

    def to_u(self, value: float) -> float:
        """The coordinate the prior is uniform in."""
        return math.log(value) if self.log else float(value)

    def from_u(self, u: float) -> float:
        return math.exp(u) if self.log else float(u)


@dataclass(frozen=True)
class TimeConstant(ShapeParameter):
    """A relaxation time constant: log-uniform between what the filter can resolve and a
    third of the fitted stretch (and within ``widest``). Above twice the filter's time
    scale ``1 / (2 pi f_c)`` (a faster branch is a damper to the filtered data) and below
    a third of the stretch (a slower one is a spring)."""

    kind: str = "tau"
    unit: str = "s"
    meaning: str = "relaxation time constant"
    limits: tuple[float, float] = (1e-4, 1e4)
    log: bool = True
    nodes: int = 16
    coarse: int = 6
    #: the widest range of time constants searched, s
    widest: tuple[float, float] = (0.01, 100.0)
    #: nodes per time constant for one, two and three of them
    per_count: tuple[int, ...] = (16, 10, 6)

    def prior_range(self, span: SessionSpan) -> tuple[float, float]:
        dt = span.dt
        fc = span.cutoff_hz if math.isfinite(span.cutoff_hz) and span.cutoff_hz > 0 else 0.1 / dt
        lo = max(self.widest[0], 2.0 / (2.0 * math.pi * fc), 5.0 * dt)
        hi = min(self.widest[1], span.duration_s / 3.0)
        return lo, hi

    def nodes_for(self, count: int, coarse: bool = False) -> int:
        if coarse:
            return self.coarse
        return self.per_count[min(max(count, 1), len(self.per_count)) - 1]


@dataclass(frozen=True)
class ContactPoint(ShapeParameter):
    """A contact point (closure, m): uniform from a quarter of the closure's span below
    its lowest fitted value to half the span above it, and down to the lowest closure
    of the whole session where the fit keeps to the grasps.

    A fit that keeps to the grasps sees only samples whose force stands above the free
    jaws' (and, of those, the ones whose filter window holds no free motion): the
    samples near the contact point, where the force rises slowly from zero, are the
    ones it leaves out. So the lowest fitted closure says only that the contact point
    lies below it, not how far; what the session does say is that the jaws touched
    nothing at their most open."""

    kind: str = "x0"
    unit: str = "m"
    meaning: str = "contact point (closure)"
    limits: tuple[float, float] = (-1.0, 1.0)
    nodes: int = 7
    coarse: int = 5

    def prior_range(self, span: SessionSpan) -> tuple[float, float]:
        width = span.x_span or 1e-3
        lo = span.x_low - 0.25 * width
        if math.isfinite(span.x_floor):
            lo = min(lo, span.x_floor)
        reach = self.reach(span)
        if math.isfinite(reach):
            lo = min(lo, max(reach - 0.25 * width, span.x_low - 3.0 * width))
        return lo, span.x_low + 0.5 * width

    @staticmethod
    def reach(span: SessionSpan) -> float:
        """The lowest contact point (m) the force across the fitted closures allows a
        contact law of the steepest exponent in :data:`EXPONENT`'s prior: where the
        force at the closure's low end is a share ``r`` of that at its high end,
        ``(x_lo - x0) = r^(1/n) (x_hi - x0)``. A tissue held throughout (the jaws never
        open) leaves the fitted closures far above the touch, its force well clear of
        zero at the lowest; a quarter span below them held the contact point from its
        truth, and an offset and friction took its place. NaN where the force does not
        rise across the closures."""
        r = span.f_ratio
        lo, hi = span.x_ends
        if not (math.isfinite(r) and 0.0 < r < 1.0 and hi > lo):
            return math.nan
        s = r ** (1.0 / EXPONENT.prior[1])
        return (lo - s * hi) / (1.0 - s)


#: the Hunt-Crossley exponent, uniform on [1, 2.5]
EXPONENT = ShapeParameter("n", "1", "contact exponent", (0.5, 5.0), prior=(1.0, 2.5), nodes=5,
                          coarse=4)  # fmt: skip
TIME_CONSTANT = TimeConstant()
CONTACT_POINT = ContactPoint()

#: how the display renders a term (:func:`tissuecli.render.law.split_law` sorts by it):
#: a function of the closure, of the speed, of both (``f(x) xdot``), dry friction (by the
#: reference model), inertia (the reference model's mass), relaxation branches (a state
#: each), left out by design (a sensor's offset), or refused with a reason
DISPLAY = ("position", "speed", "mixed", "friction", "inertia", "relaxation", "omitted", "refused")

#: what the default structure search may do with a term (:attr:`Term.search`)
SEARCH = ("replace", "grow", "prune")

#: where a term without an ``order`` of its own goes in a law, by role
ROLE_ORDER = {"stiffness": 25.0, "relaxation": 40.0, "damping": 65.0, "friction": 80.0,
              "inertia": 90.0, "offset": 100.0}  # fmt: skip


class Term(ABC):
    """One term: a coefficient times a function of the kinematics (or of their history).

    A term is one class: subclass it, set the class attributes below, implement
    ``__call__`` and ``derivative`` (and ``series`` for a term with memory), and
    decorate it with :func:`register`. Fitting, reports, parameter files, simulation and
    the display read everything from it.

    Attributes
    ----------
    name : str
        As written in parameter files and ``--forms``.
    symbol, unit : str
        The coefficient's symbol and SI unit.
    label : str
        The term's display name in reports (``x³``).
    role : str
        stiffness, damping, friction, inertia, offset or relaxation.
    variable : str
        What its column reads: ``"x"``, ``"v"`` (xdot), ``"a"`` (xddot), ``"1"`` (a
        constant), ``"xv"`` (closure and speed) or ``"h"`` (the closure's history).
    passive : bool
        The coefficient of a passive tissue is non-negative.
    rendered : bool
        The display renders it (a sensor offset is not tissue).
    display : str, optional
        How the display renders it, one of :data:`DISPLAY`; by default from
        ``variable``, ``role`` and ``memory`` (see :attr:`rendering`).
    memory : bool
        The force depends on the past: its column needs a time series (:meth:`series`).
    order : float, optional
        Its place in a law (x 10, maxwell 40, xdot 50, xddot 90, offset 100); by
        default from its role (:data:`ROLE_ORDER`).
    max_count : int
        How many of it a law may hold (relaxation branches: 3, each numbered by
        :meth:`instance`).
    requires : tuple of str
        Terms a law must hold beside it (contact damping needs its contact).
    nests : tuple of str
        Terms it equals at one of its shapes (contact at n = 1, ``Kc (x - x0)``, is a
        spring and an offset): a law with those in its place is one of its sub-laws.
    search : str, optional
        What the default structure search does with it (:data:`SEARCH`): ``"replace"``
        (tried, with the others so marked, in place of the best linear law's stiffness
        and damping: contact), ``"grow"`` (added one at a time while it raises the
        evidence: relaxation branches), ``"prune"`` (taken out again where that raises
        the evidence), or None (fitted only when a law names it).
    step : bool
        The regressor steps on the scale of a speed estimate's spread (dry friction at a
        turn): a fit's column is its mean over that spread (:meth:`expected`), and
        position noise reaches the column through that mean's slope
        (:meth:`expected_slope`). A smooth regressor keeps the second-order expansion
        and its own slope.
    shapes, parameters : tuple
        The names of its shape parameters and their :class:`ShapeParameter`
        declarations (unit, prior, range), in the same order; ``shape`` their values
        once bound.
    """

    name: ClassVar[str]
    symbol: str
    unit: str
    label: ClassVar[str]
    role: ClassVar[str]
    variable: ClassVar[str]
    passive: ClassVar[bool] = True
    rendered: ClassVar[bool] = True
    display: ClassVar[str | None] = None
    #: the term's force depends on the past (a relaxation branch): it needs a time series
    memory: ClassVar[bool] = False
    order: ClassVar[float | None] = None
    max_count: ClassVar[int] = 1
    requires: ClassVar[tuple[str, ...]] = ()
    nests: ClassVar[tuple[str, ...]] = ()
    search: ClassVar[str | None] = None
    step: ClassVar[bool] = False

    #: names of the nonlinear (shape) parameters the term reads, their declarations, and
    #: their values once bound (a term with shapes fits as a family; a tissue holds it bound)
    shapes: tuple[str, ...] = ()
    parameters: tuple[ShapeParameter, ...] = ()
    shape: dict[str, float] = {}

    @property
    def bound(self) -> bool:
        """Whether every shape parameter has a value."""
        return all(n in self.shape for n in self.shapes)

    @property
    def unit_by_shape(self) -> bool:
        """Whether the coefficient's unit holds one of its shape parameters (a contact
        stiffness in N/m^n): its value has a meaning only at a shape, so what the data
        say of it is judged there, not across shapes."""
        return any(re.search(rf"\b{re.escape(n)}\b", self.unit) for n in self.shapes)

    def bind(self, values: dict[str, float]) -> Term:
        """This term with its shape parameters set from ``values`` (by name); itself if it
        has none. A term with shapes takes them in ``__init__(shape=...)``."""
        if not self.shapes:
            return self
        return type(self)(shape={k: float(values[k]) for k in self.shapes})  # type: ignore[call-arg]

    def instance(self, index: int) -> Term:
        """The ``index``-th (from 1) of this term in a law: itself, unless it may repeat
        (then numbered, with its own symbol and shape parameters)."""
        return self

    def shape_parameter(self, name: str) -> ShapeParameter:
        """The declaration of one of its shape parameters, by name."""
        return dict(zip(self.shapes, self.parameters, strict=True))[name]

    @property
    def rendering(self) -> str:
        """How the display renders it (one of :data:`DISPLAY`): ``display`` if the class
        declares it, else from what it reads."""
        if self.display is not None:
            return self.display
        if not self.rendered:
            return "omitted"
        if self.memory:
            return "refused"
        by_variable = {"x": "position", "v": "speed", "a": "inertia", "xv": "mixed"}
        kind = by_variable.get(self.variable, "refused")
        return "friction" if kind == "speed" and self.role == "friction" else kind

    def refusal(self) -> str:
        """The sentence the display gives when it cannot render the term."""
        if self.memory:
            return (
                f"term {self.name} ({self.symbol}) has a memory the display's controller "
                "cannot integrate (only relaxation branches, maxwell, can): refit without it"
            )
        return (
            f"term {self.name} ({self.symbol}) reads {self.variable!r}, which the display's "
            "control law has no place for: refit without it"
        )

    def branches(self, c: float) -> list[tuple[float, float]]:
        """For a term the display renders as relaxation: its branches as (Km N/m, tau s)
        at coefficient ``c``; empty when it has none to render."""
        return []

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

    def expected(self, u: ArrayLike, var: ArrayLike) -> Array:
        """The regressor's mean where its variable spreads about ``u`` with variance
        ``var`` (its unit squared; a smoothing window's spread, or an estimate's error;
        negative removes such a spread): ``r(u) + r''(u) var / 2`` to second order. A
        regressor that bends on the scale of the spread (dry friction's step) says
        how it averages instead."""
        u = np.asarray(u, dtype=float)
        return self(u) + 0.5 * self.curvature(u) * np.asarray(var, dtype=float)

    def expected_slope(self, u: ArrayLike, var: ArrayLike) -> Array:
        """d :meth:`expected` / du: how an error in the estimate of ``u`` moves the
        averaged regressor (what the errors-in-variables correction needs of a
        :attr:`step` term). For a smooth regressor its own slope, as the correction has
        always taken it (the spread's share, a third derivative times ``var / 2``, is of
        higher order)."""
        return self.derivative(u)

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

    def closure_factor(self, x: Array) -> Array | None:
        """For a term of closure and speed (``variable`` ``"xv"``) whose regressor is a
        function of the closure times the speed, ``f(x) xdot``: ``f(x)``; else None.
        A long session's fit then filters the speed at each closure level once, and
        each shape's column is their sum weighted by ``f``."""
        return None

    def recursion(self, dt: float) -> tuple[float, float] | None:
        """``(a, b)`` if :meth:`series` is the first-order recursion
        ``r_k = a r_{k-1} + b (x_k - x_{k-1})`` from rest at sample interval ``dt`` (s),
        else None. Such a series is a linear filter of the closure's increments, which
        commutes with the fit's smoothing filter: a long session's fit filters the
        increments once and runs each shape's recursion on them."""
        return None

    def columns(self, x: ArrayLike, v: ArrayLike, a: ArrayLike, dt: float | None = None) -> Array:
        """The term's column at exact kinematics, shape (n,); a term with memory reads the
        series' sample interval ``dt`` (s), the series starting from rest."""
        x, v, a = (np.asarray(z, dtype=float) for z in (x, v, a))
        if self.memory:
            if dt is None:
                raise InputError(f"term {self.name} has memory: give the series' sample interval")
            return self.series(dt, x, v, a)
        return self.regressor(x, v, a)

    def continued(self, x: Array, dt: float, state: object = None) -> tuple[Array, object]:
        """A term with memory over the next closures ``x`` (m, every ``dt`` s), from
        ``state`` (None: at rest before ``x[0]``); returns the regressor there and the
        state to continue from. What a simulation streams block by block.

        By default the state is the closure so far and the series is recomputed over it
        (exact, and cost growing with the length); a term with a recursion overrides it.
        """
        past = np.zeros(0) if state is None else np.asarray(state, dtype=float)
        whole = np.concatenate([past, np.asarray(x, dtype=float)])
        speed = np.gradient(whole, dt) if whole.size > 1 else np.zeros_like(whole)
        r = self.series(dt, whole, speed, np.zeros_like(whole))
        return r[past.size :], whole

    def steady(self, x: float, v: float) -> float:
        """The regressor in steady motion at speed ``v`` (m/s) through closure ``x`` (m):
        the column itself, or for a term with memory its value after a long ramp."""
        if not self.memory:
            return float(self.regressor(np.array([x]), np.array([v]), np.zeros(1))[0])
        duration = 50.0 * max(self.time_scales())
        n = 5000
        t = np.linspace(0.0, duration, n)
        ramp = x - v * (duration - t)
        dt = float(t[1] - t[0])
        return float(self.series(dt, ramp, np.full(n, v), np.zeros(n))[-1])

    def time_scales(self) -> tuple[float, ...]:
        """The times (s) over which a term with memory forgets: its shape parameters in
        seconds, else 1 s."""
        found = tuple(self.shape[n] for n, p in zip(self.shapes, self.parameters, strict=True)
                      if p.unit == "s" and n in self.shape)  # fmt: skip
        return found or (1.0,)

    def step_response(self, t: ArrayLike, step: float) -> Array:
        """The regressor at times ``t`` (s) after a step of ``step`` m in closure from
        rest, with no speed or acceleration after it (the relaxation function)."""
        t = np.asarray(t, dtype=float)
        if not self.memory:
            if self.variable == "x":
                return np.full_like(t, float(self(np.array([step]))[0]))
            return np.zeros_like(t)
        # the series on a uniform grid fine enough for the earliest time asked, the
        # closure stepping between its first two samples (at -dt and 0)
        dt = max(float(np.min(t)) / 20.0, float(np.max(t)) / 200_000.0)
        n = int(math.ceil(float(np.max(t)) / dt)) + 3
        x = np.full(n, step)
        x[0] = 0.0
        r = self.series(dt, x, np.zeros(n), np.zeros(n))
        return np.interp(t, dt * (np.arange(n) - 1.0), r)

    def typical(self, scales: MotionScales) -> float:
        """The regressor's size at a session's typical motion (for prior scales)."""
        u = {"x": scales.x, "v": scales.v, "a": scales.a, "1": 1.0}[self.variable]
        return float(abs(self(np.array([u]))[0])) or 1.0

    def __repr__(self) -> str:
        shape = ", ".join(f"{k}={v:g}" for k, v in self.shape.items())
        return f"{type(self).__name__}({shape})"


#: every registered term's prototype, by name, in the order registered
TERMS: dict[str, Term] = {}


def register(cls: type[Term]) -> type[Term]:
    """Class decorator: add a term to :data:`TERMS` under its name.

    Raises
    ------
    InputError
        If the name is taken by another class, or a shape parameter's name by a
        different declaration (terms that share a shape parameter, as contact and its
        damping share n and x0, declare the same one).
    """
    proto = cls()
    known = TERMS.get(cls.name)
    if known is not None and type(known) is not cls:
        raise InputError(f"term {cls.name!r} is already registered by {type(known).__name__}")
    if proto.rendering not in DISPLAY:
        raise InputError(f"term {cls.name!r}: display {proto.rendering!r} is not one of {DISPLAY}")
    if proto.search is not None and proto.search not in SEARCH:
        raise InputError(f"term {cls.name!r}: search {proto.search!r} is not one of {SEARCH}")
    for name, param in zip(proto.shapes, proto.parameters, strict=True):
        for other in TERMS.values():
            if other.name != cls.name and name in other.shapes:
                if other.shape_parameter(name) != param:
                    raise InputError(
                        f"term {cls.name!r}: shape parameter {name!r} is already declared "
                        f"differently by term {other.name!r}; choose another name"
                    )
    TERMS[cls.name] = proto
    return cls


def unregister(name: str) -> None:
    """Take a term out of :data:`TERMS` (a test's or an example's own term)."""
    TERMS.pop(name, None)


def term(name: str) -> Term:
    """Look a term up by name, with an error that lists the choices."""
    try:
        return TERMS[name]
    except KeyError:
        raise InputError(f"unknown term {name[:30]!r}; choose among: {', '.join(TERMS)}") from None


def term_order(t: Term) -> tuple[float, int]:
    """Where a term goes in a law: its ``order`` (or its role's), then registration."""
    names = list(TERMS)
    place = names.index(t.name) if t.name in TERMS else len(names)
    order = t.order if t.order is not None else ROLE_ORDER.get(t.role, 95.0)
    return (order, place)


def searched(kind: str) -> list[str]:
    """The registered terms the default structure search treats as ``kind`` (one of
    :data:`SEARCH`), in law order (``prune``: last first, as the search takes them out)."""
    names = [t.name for t in sorted(TERMS.values(), key=term_order) if t.search == kind]
    return names[::-1] if kind == "prune" else names


def shape_parameter(name: str) -> ShapeParameter:
    """The declaration of a shape parameter by name (``tau2``, ``n``), from the
    registered terms; a numbered name matches its kind's stem."""
    for proto in TERMS.values():
        for own, param in zip(proto.shapes, proto.parameters, strict=True):
            stem = name[: len(param.kind)]
            numbered = stem == param.kind and name[len(param.kind) :].isdigit()
            if name == own or name == param.kind or numbered:
                return param
    raise InputError(f"unknown shape parameter {name[:30]!r}")


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
    order, display, search = 10.0, "position", "prune"


@register
class Cubic(Term):
    """x^3: hardening stiffness, K3 in N/m^3."""

    name, symbol, unit, label, role, variable = "x^3", "K3", "N/m^3", "x³", "stiffness", "x"
    order, display, search = 20.0, "position", "prune"

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
    order, display = 50.0, "speed"


@register
class Quadratic(Term):
    """xdot |xdot|: quadratic damping, S2 in N s^2/m^2 (``xdot^2`` in version 1 files).

    The sign is kept so that the damping force always opposes motion; a plain
    square would create energy on release.
    """

    name, symbol, unit, label, role, variable = (
        "xdot|xdot|", "S2", "N s^2/m^2", "ẋ|ẋ|", "damping", "v",
    )  # fmt: skip
    order, display = 60.0, "speed"

    def __call__(self, u: ArrayLike) -> Array:
        u = np.asarray(u, dtype=float)
        return u * np.abs(u)

    def scalar(self, u: float) -> float:
        return u * abs(u)

    def derivative(self, u: ArrayLike) -> Array:
        return 2.0 * np.abs(np.asarray(u, dtype=float))

    def expected(self, u: ArrayLike, var: ArrayLike) -> Array:
        """The mean of ``r(u + e)`` over a normal spread ``e`` of variance ``var``
        (m^2/s^2), exactly: ``r(u) + b(u, var)`` with ``b`` the spread's bias,
        ``(u^2 + var)(2 Phi(z) - 1) + 2 u sqrt(var) phi(z) - u|u|`` at ``z = u /
        sqrt(var)``. A negative ``var`` takes the bias of a spread of ``-var`` off.

        The second-order expansion (``r(u) + sign(u) var``) is the same far from a turn
        (``b`` tends to ``sign(u) var``) but steps by ``2 var`` at ``u = 0``, where
        ``r`` bends: with a noisy speed (``var < 0``) that put a step of the wrong sign
        at every turn of a slow squeeze, as large as the column itself, and the
        damping came out several times too large. The exact bias is smooth and zero at
        a turn (a spread about ``u = 0`` averages to nothing)."""
        u = np.asarray(u, dtype=float)
        var = np.asarray(var, dtype=float)
        s = np.sqrt(np.abs(var))
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(s > 0, np.abs(u) / np.where(s > 0, s, 1.0), np.inf)
            # written so that nothing cancels: (u^2 + s^2) erf - u|u| for u of either sign
            erf, tail = _erf_pair(z / math.sqrt(2.0))
            bias = np.sign(u) * (s**2 * erf - u**2 * tail) + 2.0 * u * s * np.exp(
                -0.5 * np.minimum(z, 1e3) ** 2
            ) / math.sqrt(2.0 * math.pi)
        bias = np.where(s > 0, bias, 0.0)
        return u * np.abs(u) + np.sign(var) * bias


@register
class Coulomb(Term):
    """sign(xdot): dry friction, Fc in N, smoothed as tanh(xdot / V_SMOOTH)."""

    name, symbol, unit, label, role, variable = (
        "sign(xdot)", "Fc", "N", "sign(ẋ)", "friction", "v",
    )  # fmt: skip
    order, display, search = 80.0, "friction", "prune"
    step = True

    def __call__(self, u: ArrayLike) -> Array:
        return np.tanh(np.asarray(u, dtype=float) / V_SMOOTH)

    def scalar(self, u: float) -> float:
        return math.tanh(u / V_SMOOTH)

    def derivative(self, u: ArrayLike) -> Array:
        return (1.0 - np.tanh(np.asarray(u, dtype=float) / V_SMOOTH) ** 2) / V_SMOOTH

    def expected(self, u: ArrayLike, var: ArrayLike) -> Array:
        """The mean of tanh((u + e) / V_SMOOTH) over a normal spread e of variance
        ``var`` (m^2/s^2): a speed estimated near a turn has either sign, and the
        friction force is the mean of its two directions weighted by their odds; a
        window smoothing across a turn averages them likewise. With tanh(z) ~
        erf(sqrt(pi) z / 2) that mean is tanh(u / V), the smoothing speed widened to
        V = sqrt(V_SMOOTH^2 + pi var / 2): exact at var = 0, within 0.04 of the exact
        mean at any var (0.02 where the spread's SD is near V_SMOOTH, one sign at every
        turn: a small spread's first-order effect is not the expansion's). A second-order
        expansion (the default) is no use here: the step's curvature, of order
        1/V_SMOOTH^2, turned a spread of 10 mm/s at a turn into a column of +-30 where it
        is +-1. A spread cannot be taken out of a step: a negative ``var`` counts as 0."""
        return np.tanh(np.asarray(u, dtype=float) / _widened(var))

    def expected_slope(self, u: ArrayLike, var: ArrayLike) -> Array:
        """d/du of :meth:`expected`: ``(1 - tanh^2(u / V)) / V``, at most 1/V where the
        plain step's slope is 1/V_SMOOTH (80 times less at a spread of 10 mm/s)."""
        width = _widened(var)
        return (1.0 - np.tanh(np.asarray(u, dtype=float) / width) ** 2) / width


def _erfc(z: Array) -> Array:
    """The complementary error function of ``z >= 0`` (inf gives 0), to a fractional
    error below 1.2e-7 (Numerical Recipes' Chebyshev fit): the package's core needs
    NumPy alone."""
    t = 1.0 / (1.0 + 0.5 * z)
    poly = -1.26551223 + t * (1.00002368 + t * (0.37409196 + t * (0.09678418 + t * (
        -0.18628806 + t * (0.27886807 + t * (-1.13520398 + t * (1.48851587 + t * (
            -0.82215223 + t * 0.17087277))))))))  # fmt: skip
    return t * np.exp(-(np.minimum(z, 1e3) ** 2) + poly)


def _erf_pair(z: Array) -> tuple[Array, Array]:
    """``erf(z)`` and ``erfc(z)`` of ``z >= 0``: below 0.5 erf by its Taylor series (to
    a fractional 3e-8; ``1 - erfc`` would keep only the absolute error of erfc there)."""
    z2 = z * z
    series = (
        (2.0 / math.sqrt(math.pi))
        * z
        * (1.0 - z2 / 3.0 + z2**2 / 10.0 - z2**3 / 42.0 + z2**4 / 216.0 - z2**5 / 1320.0)
    )
    tail = _erfc(z)
    return np.where(z < 0.5, series, 1.0 - tail), tail


def _widened(var: ArrayLike) -> Array:
    """Dry friction's smoothing speed widened by a spread of speeds of variance ``var``
    (m^2/s^2, negative counts as 0): ``sqrt(V_SMOOTH^2 + pi var / 2)``, m/s."""
    spread = np.maximum(np.asarray(var, dtype=float), 0.0)
    return np.sqrt(V_SMOOTH**2 + 0.5 * np.pi * spread)


@register
class Inertia(_Proportional):
    """xddot: moving mass, M in kg."""

    name, symbol, unit, label, role, variable = "xddot", "M", "kg", "ẍ", "inertia", "a"
    order, display = 90.0, "inertia"


@register
class Offset(Term):
    """1: a constant force, F0 in N: the force sensor's offset, or a preload. Of either
    sign, and not rendered (the display feels the tissue, not the sensor)."""

    name, symbol, unit, label, role, variable = "offset", "F0", "N", "1", "offset", "1"
    passive = False
    rendered = False
    order, display, search = 100.0, "omitted", "prune"

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
    order, display, search = 30.0, "position", "replace"
    nests = ("x", "offset")
    shapes = ("n", "x0")
    parameters = (EXPONENT, CONTACT_POINT)

    def __init__(self, shape: dict[str, float] | None = None) -> None:
        self.shape = dict(shape or {})

    def _nd(self) -> tuple[float, float]:
        return self.shape.get("n", 1.5), self.shape.get("x0", 0.0)

    def __call__(self, u: ArrayLike) -> Array:
        n, x0 = self._nd()
        d = np.maximum(np.asarray(u, dtype=float) - x0, 0.0)
        # powers only in contact (0 ** n is 0 for the exponents allowed): the same
        # numbers, at the cost of the samples in contact
        return np.power(d, n, out=np.zeros_like(d), where=d > 0)

    def derivative(self, u: ArrayLike) -> Array:
        n, x0 = self._nd()
        d = np.maximum(np.asarray(u, dtype=float) - x0, 0.0)
        inside = d > 0
        out = np.power(d, n - 1.0, out=np.zeros_like(d), where=inside)
        return np.multiply(n, out, out=out, where=inside)

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
    order, display, requires, search = 70.0, "mixed", ("contact",), "replace"
    nests = ()  # at n = 1 it is (x - x0) xdot, no registered term

    def regressor(self, x: Array, v: Array, a: Array) -> Array:
        return Contact.__call__(self, x) * np.asarray(v, dtype=float)

    def closure_factor(self, x: Array) -> Array | None:
        return Contact.__call__(self, x)

    def typical(self, scales: MotionScales) -> float:
        return float(scales.x ** self._nd()[0] * scales.v) or 1.0


@register
class Maxwell(Term):
    """A relaxation branch (generalised Maxwell, or Prony, series): a spring Km in series
    with a damper Km tau. Its force obeys ``F' = Km xdot - F / tau`` from rest, so a
    step in closure gives ``Km e^(-t/tau)``: the stress relaxation of soft tissue. One
    branch with a spring ``x`` is the standard linear solid. Km in N/m, tau in s.

    A branch that never relaxes (tau without bound) is, from rest, ``Km (x - x(0))``: a
    spring and an offset, the law it nests."""

    name, label, role, variable = "maxwell", "relax", "relaxation", "h"
    unit = "N/m"
    memory = True
    nests = ("x", "offset")
    order, display, max_count, search = 40.0, "relaxation", 3, "grow"
    parameters = (TIME_CONSTANT,)

    def __init__(self, index: int = 1, shape: dict[str, float] | None = None) -> None:
        self.index = index
        self.symbol = f"Km{index}"
        self.shapes = (f"tau{index}",)
        self.shape = dict(shape or {})

    def bind(self, values: dict[str, float]) -> Term:
        return type(self)(self.index, {k: float(values[k]) for k in self.shapes})

    def instance(self, index: int) -> Term:
        return type(self)(index)

    def branches(self, c: float) -> list[tuple[float, float]]:
        tau = self.tau
        return [(c, tau)] if math.isfinite(tau) and tau > 0 else []

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

    def recursion(self, dt: float) -> tuple[float, float] | None:
        tau = self.tau
        if not (math.isfinite(tau) and tau > 0):
            return None
        return math.exp(-dt / tau), (tau / dt) * -math.expm1(-dt / tau)  # as relaxation()

    def continued(self, x: Array, dt: float, state: object = None) -> tuple[Array, object]:
        # the exact recursion carries (r, the last closure): no history kept
        r0, before = state if isinstance(state, tuple) else (0.0, None)
        r, last = relaxation(np.asarray(x, dtype=float), dt, self.tau, r0, before)
        return r, (last, float(x[-1]) if len(x) else before)

    def steady(self, x: float, v: float) -> float:
        return self.tau * v  # the spring's stretch once the damper carries the motion

    def step_response(self, t: ArrayLike, step: float) -> Array:
        return step * np.exp(-np.asarray(t, dtype=float) / self.tau)

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
        held = {t.name for t in self.terms}
        for t in self.terms:
            missing = [r for r in t.requires if r not in held]
            if missing:
                raise InputError(f"{t.name} ({t.role}) needs the term {', '.join(missing)} too")

    @classmethod
    def of(cls, names: Iterable[str]) -> Law:
        """The law of the named registered terms, in their order (:func:`term_order`); a
        term that may repeat (``maxwell``: one relaxation branch each) is numbered, any
        other named twice is held once.

        Raises
        ------
        InputError
            Naming an unknown term (with the choices), or a repeating term given more
            often than it may be.
        """
        counts: dict[str, int] = {}
        for n in names:
            name = term(n).name
            counts[name] = counts.get(name, 0) + 1
        protos = sorted((TERMS[n] for n in counts), key=term_order)
        terms: list[Term] = []
        for proto in protos:
            k = counts[proto.name]
            if k > proto.max_count > 1:  # a term that may not repeat is named once
                what = "relaxation branches" if proto.name == "maxwell" else "terms"
                raise InputError(f"at most {proto.max_count} {what} ({proto.name}) in a law")
            many = proto.max_count > 1
            terms += [proto.instance(i) for i in range(1, k + 1)] if many else [proto]
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

    def shape_parameter(self, name: str) -> ShapeParameter:
        """The declaration of one of the law's shape parameters, by name."""
        for t in self.terms:
            if name in t.shapes:
                return t.shape_parameter(name)
        raise InputError(f"law {self.name} has no shape parameter {name[:30]!r}")

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
        return np.column_stack([t.columns(x, v, a, dt) for t in self.terms])

    def force(
        self, c: ArrayLike, x: ArrayLike, v: ArrayLike, a: ArrayLike, dt: float | None = None
    ) -> Array:
        """F = sum_i c_i r_i at exact kinematics, shape (n,), N."""
        return self.regressors(x, v, a, dt) @ np.asarray(c, dtype=float)

    def prior_scales(self, scales: MotionScales = FORCEPS_SCALES) -> Array:
        """Prior scale of each coefficient (SI): the coefficient that makes its term reach
        ``scales.force`` at the session's typical motion."""
        return np.array([scales.force / t.typical(scales) for t in self.terms])


def shape_kind(name: str) -> str:
    """The kind of a shape parameter (``tau2`` -> ``tau``), from its declaration."""
    return shape_parameter(name).kind


def shape_unit(name: str) -> str:
    """The SI unit of a shape parameter (``tau2`` -> ``s``), from its declaration."""
    return shape_parameter(name).unit


#: most relaxation branches a law may have
MAX_BRANCHES = Maxwell.max_count


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
    by_symbol = {t.symbol: t for law in laws for t in law.terms}
    return sorted(seen, key=lambda s: (term_order(by_symbol[s]), s))
