"""The control law that renders a tissue on the display: the paper's eq. 9 generalised
to any forms, with the solenoid's limits (it only pulls, and only up to v_max).

The display (paper, eq. 6, with the piston's own damping b) and the tissue are::

    Mp xp'' + b xp' + Kp xp + alpha V^2 = F
    M xm'' + D(xm') + E(xm) = F

with ``E`` the tissue's rendered force at rest (its position terms, Hunt-Crossley
contact included), ``D`` that of speed (damping), ``H`` that of both (Hunt-Crossley contact
damping), ``R`` the relaxation branches' force (a state each, see :class:`Branch`), dry
friction ``Ff`` carried by the reference model, and ``M`` its inertia; a sensor offset
is not rendered. :func:`split_law` sorts a tissue's terms into these parts, and names
any term it cannot render.
:func:`control_voltage` chooses V so that the error e = xp - xm obeys
``M e'' + (s + Cv) e' + (k + Cp) e = (M - Mp) xp''`` (s, k: the law's local slopes).
Everything is SI: m, m/s, m/s^2, N, kg, V, s.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..core.errors import RenderError
from ..core.flags import NONFINITE, SATURATED, UNRENDERABLE
from ..core.terms import Term
from ..core.tissue import Tissue
from .profile import DisplayProfile

#: A requested force more negative than this counts as unrenderable: about 1 gram-force,
#: so sensor noise around the rest position is not counted.
FORCE_TOLERANCE_N = 0.01


#: Typical closing speed for speed-dependent damping slopes (models.TYPICAL), m/s.
TYPICAL_SPEED = 0.05


Array = NDArray[np.float64]


def _zero1(u: float) -> float:
    return 0.0


def _zero2(x: float, v: float) -> float:
    return 0.0


@dataclass(frozen=True)
class Branch:
    """One relaxation branch (generalised Maxwell): a spring ``Km`` (N/m) in series with a
    damper ``Km tau`` (``tau`` in s). Its state ``r`` (m) obeys ``r' = x' - r / tau`` and
    its force is ``Km r``."""

    Km: float
    tau: float

    def step(self, r: float, dx: float, dt: float) -> float:
        """``r`` after ``dt`` s over which the closure moved by ``dx`` at constant speed:
        the exact recursion of :func:`~tissuecli.core.terms.relaxation`,
        ``a r + (tau / dt) (1 - a) dx`` with ``a = exp(-dt / tau)``."""
        if not dt > 0:
            return r + dx
        q = dt / self.tau
        return math.exp(-q) * r - math.expm1(-q) / q * dx


@dataclass(frozen=True)
class LawParts:
    """A tissue's rendered terms, sorted by what they read (see :func:`split_law`).

    Attributes
    ----------
    position, speed, mixed, friction : list of (Term, float)
        Terms of the closure (stiffness, contact), of the speed (damping), of both
        (contact damping ``f(x) v``) and dry friction, with their coefficients (SI).
    branches : tuple of Branch
        The relaxation branches.
    unrendered : list of (Term, float)
        Terms the display leaves out by design (a sensor's offset).
    refusals : list of str
        One sentence per term the display cannot render, naming it.
    """

    position: list[tuple[Term, float]] = field(default_factory=list)
    speed: list[tuple[Term, float]] = field(default_factory=list)
    mixed: list[tuple[Term, float]] = field(default_factory=list)
    friction: list[tuple[Term, float]] = field(default_factory=list)
    branches: tuple[Branch, ...] = ()
    unrendered: list[tuple[Term, float]] = field(default_factory=list)
    refusals: list[str] = field(default_factory=list)

    # vectorised forces and slopes for the check and the gains (SI; NaN or inf where a
    # term overflows, never an exception)

    def elastic(self, x: ArrayLike) -> Array:
        """``E(x)``: the position terms' force at closures ``x``, N."""
        x = np.asarray(x, dtype=float)
        with np.errstate(all="ignore"):
            return sum((c * t(x) for t, c in self.position), np.zeros_like(x))

    def damping_force(self, v: ArrayLike, with_friction: bool = True) -> Array:
        """``D(v)`` (and dry friction): the speed terms' force at speeds ``v``, N."""
        v = np.asarray(v, dtype=float)
        terms = self.speed + (self.friction if with_friction else [])
        with np.errstate(all="ignore"):
            return sum((c * t(v) for t, c in terms), np.zeros_like(v))

    def mixed_force(self, x: ArrayLike, v: ArrayLike) -> Array:
        """``H(x, v)``: the contact damping's force, N (broadcast over ``x`` and ``v``)."""
        x, v = np.broadcast_arrays(np.asarray(x, dtype=float), np.asarray(v, dtype=float))
        with np.errstate(all="ignore"):
            return sum((c * t.regressor(x, v, v) for t, c in self.mixed), np.zeros_like(x))

    def stiffness(self, x: ArrayLike) -> Array:
        """``E'(x)``, N/m (the equilibrium stiffness: the branches relaxed)."""
        x = np.asarray(x, dtype=float)
        with np.errstate(all="ignore"):
            return sum((c * t.derivative(x) for t, c in self.position), np.zeros_like(x))

    def mixed_slopes(self, x: ArrayLike, v: float) -> tuple[Array, Array]:
        """``dH/dx`` (N/m) and ``dH/dv`` (N s/m) at closures ``x`` and speed ``v``: for
        ``f(x) v``, ``f'(x) v`` and ``f(x)``."""
        x = np.asarray(x, dtype=float)
        kx, sv = np.zeros_like(x), np.zeros_like(x)
        with np.errstate(all="ignore"):
            for t, c in self.mixed:
                kx = kx + c * t.derivative(x) * v
                sv = sv + c * t(x)
        return kx, sv

    @property
    def instantaneous(self) -> float:
        """``sum Km``: the stiffness the branches add before they relax, N/m."""
        return float(sum(b.Km for b in self.branches))


def split_law(tissue: Tissue) -> LawParts:
    """Sort a tissue's terms into what the controller renders, and how, as each term
    declares (:attr:`~tissuecli.core.terms.Term.rendering`).

    Position terms (``x``, ``x^3``, ``contact``) and speed terms (``xdot``,
    ``xdot|xdot|``) are rendered at the piston's state, as in eq. 9; mixed terms
    (``f(x) xdot``, contact damping) at the piston's closure and speed; relaxation
    branches (``maxwell``) through a state each, driven by the piston's closure; dry
    friction by the reference model alone, since its slope at rest (``Fc / V_SMOOTH``,
    100 N s/m per 0.1 N) is far beyond the damping a sampled loop renders; inertia by
    the reference model's mass. A term the display leaves out by design (a sensor's
    offset) goes to ``unrendered``; any other term goes to ``refusals`` with the
    sentence the term gives (:meth:`~tissuecli.core.terms.Term.refusal`), never
    silently dropped.
    """
    parts = LawParts()
    branches = []
    for t, c in zip(tissue.law.terms, tissue.coef, strict=True):
        c = float(c)
        how = t.rendering
        if how == "omitted":
            parts.unrendered.append((t, c))
        elif how == "relaxation" and t.branches(c):
            branches += [Branch(km, tau) for km, tau in t.branches(c)]
        elif how == "inertia":
            pass  # the reference model's mass (Tissue.mass)
        elif how == "position":
            parts.position.append((t, c))
        elif how == "speed":
            parts.speed.append((t, c))
        elif how == "friction":
            parts.friction.append((t, c))
        elif how == "mixed" and _is_product(t):
            parts.mixed.append((t, c))
        else:
            parts.refusals.append(t.refusal())
    return LawParts(**{**parts.__dict__, "branches": tuple(branches)})


def _is_product(t: Term) -> bool:
    """Whether a term of closure and speed is ``f(x) v`` with ``f`` its scalar function:
    what :class:`RenderLaw` evaluates in plain arithmetic."""
    x = np.array([-1e-3, 2e-3, 7e-3])
    v = np.array([0.03, -0.05, 0.01])
    with np.errstate(all="ignore"):
        full = t.regressor(x, v, v)
        product = np.array([t.scalar(float(a)) * float(b) for a, b in zip(x, v, strict=True)])
    return bool(np.allclose(full, product, rtol=1e-9, atol=0.0))


def _scalar_sum(terms: list[tuple[Term, float]]) -> Callable[[float], float]:
    if not terms:
        return _zero1
    pairs = tuple(terms)

    def value(u: float) -> float:
        return sum(c * t.scalar(u) for t, c in pairs)

    return value


def _scalar_product(terms: list[tuple[Term, float]]) -> Callable[[float, float], float]:
    if not terms:
        return _zero2
    pairs = tuple(terms)

    def value(x: float, v: float) -> float:
        return sum(c * t.scalar(x) for t, c in pairs) * v

    return value


@dataclass(frozen=True)
class Gains:
    """Error-feedback gains and the reference model's mass.

    Attributes
    ----------
    Cp : float
        Position error gain, N/m.
    Cv : float
        Velocity error gain, N s/m.
    bandwidth_hz : float
        Lowest natural frequency of the error dynamics the gains were chosen for, Hz.
    M : float
        Mass of the reference model, kg (the tissue's M, raised to a floor if
        smaller; see :func:`choose_gains`).
    """

    Cp: float
    Cv: float
    bandwidth_hz: float
    M: float


@dataclass(frozen=True)
class RenderLaw:
    """Everything :func:`control_voltage` needs: tissue, display constants and gains.

    ``static`` and ``speed`` are float -> float callables: the tissue's rendered force
    at rest at a closure (N) and of a speed (N), from :meth:`Tissue.scalar_law`.
    """

    static: Callable[[float], float]
    speed: Callable[[float], float]
    Kp: float
    b: float
    alpha: float
    v_max: float
    Cp: float
    Cv: float
    tolerance: float = FORCE_TOLERANCE_N
    #: ``H(x, v)``: contact damping, N, rendered at the piston's closure and speed
    mixed: Callable[[float, float], float] = _zero2
    #: dry friction of the model's speed, N: carried by the reference model
    friction: Callable[[float], float] = _zero1
    #: the relaxation branches, whose states the controller carries
    branches: tuple[Branch, ...] = ()

    @classmethod
    def build(cls, tissue: Tissue, profile: DisplayProfile, gains: Gains) -> RenderLaw:
        """The law of ``tissue`` (see :func:`split_law`).

        Raises
        ------
        RenderError
            Naming a term the display cannot render.
        """
        parts = split_law(tissue)
        if parts.refusals:
            raise RenderError("; ".join(parts.refusals))
        return cls(
            static=_scalar_sum(parts.position),
            speed=_scalar_sum(parts.speed),
            Kp=profile.Kp,
            b=profile.b,
            alpha=profile.alpha,
            v_max=profile.v_max,
            Cp=gains.Cp,
            Cv=gains.Cv,
            mixed=_scalar_product(parts.mixed),
            friction=_scalar_sum(parts.friction),
            branches=parts.branches,
        )

    def model_force(self, x: float, v: float, memory: float = 0.0) -> float:
        """The tissue's force at the reference model's state, less inertia, N:
        ``E(x) + D(v) + H(x, v) + Ff(v) + memory`` (``memory``: the branches' force)."""
        return self.static(x) + self.speed(v) + self.mixed(x, v) + self.friction(v) + memory

    def pull(self, xp: float, vp: float, xm: float, vm: float, memory: float = 0.0) -> float:
        """The solenoid pull the law asks for, ``alpha V^2`` in N (may be negative or NaN).

        ``memory`` is the relaxation branches' force driven by the piston's closure, N;
        dry friction is taken at the model's speed ``vm``.
        """
        return (
            self.speed(vp)
            + self.static(xp)
            + self.mixed(xp, vp)
            + self.friction(vm)
            + memory
            - self.Kp * xp
            - self.b * vp
            + self.Cv * (vp - vm)
            + self.Cp * (xp - xm)
        )


def control_voltage(
    law: RenderLaw, xp: float, vp: float, xm: float, vm: float, memory: float = 0.0
) -> tuple[float, int]:
    """The solenoid voltage that renders the tissue: paper eq. 9 for any law.

    Derivation. With the pull ``u = alpha V^2`` the display obeys
    ``Mp xp'' + b xp' + Kp xp + u = F`` and the tissue model
    ``M xm'' + D(xm') + E(xm) = F`` (the same force F). Choosing::

        u = D(xp') + E(xp) - Kp xp - b xp' + Cv e' + Cp e,    e = xp - xm

    and subtracting the two equations gives::

        M e'' + (D(xp') - D(xm')) + (E(xp) - E(xm)) + Cv e' + Cp e = (M - Mp) xp''

    and, with the local slopes ``k = E'(x)`` and ``s = D'(x')`` (mean-value
    theorem), the error equation::

        M e'' + (s + Cv) e' + (k + Cp) e = (M - Mp) xp''.

    For the linear law K x + S x' this is the paper's result (its Sm xp' + (Km - Kp) xp is
    the first line with b = 0). The other parts of a law enter the same way
    (:meth:`RenderLaw.pull`): contact damping ``H(xp, xp')`` adds its slopes to ``k``
    and ``s``; the relaxation branches' force driven by the piston's closure (``memory``)
    less the model's is a relaxation branch of ``e`` itself, passive, between ``0`` and
    ``sum Km`` of stiffness; dry friction, at the model's speed, cancels exactly.
    When the error dynamics are at least critically damped their impulse response is
    non-negative, so
    ``|e| <= |M - Mp| max|xp''| / (k + Cp)`` once transients have died out.

    The solenoid can only pull and only up to ``v_max``: ``u < 0`` gives V = 0
    (flagged :data:`UNRENDERABLE` when below ``-law.tolerance``), ``u >= alpha v_max^2``
    gives ``v_max`` (:data:`SATURATED`), and any NaN or infinity among inputs,
    constants or result gives V = 0 (:data:`NONFINITE`).

    Parameters
    ----------
    law : RenderLaw
        Tissue, display and gains.
    xp, vp : float
        Piston position (m) and velocity (m/s), at the time the voltage will act.
    xm, vm : float
        Tissue model position (m) and velocity (m/s), at the same time.
    memory : float
        The relaxation branches' force at the piston's state, N (0 without branches).

    Returns
    -------
    volts : float
        In [0, law.v_max] always (0 if v_max itself is not a positive finite number).
    flags : int
        Bit set of :data:`SATURATED`, :data:`UNRENDERABLE`, :data:`NONFINITE`.
    """
    alpha, v_max = law.alpha, law.v_max
    try:
        if not (0.0 < alpha < math.inf and 0.0 < v_max < math.inf):
            return 0.0, NONFINITE
        u = float(law.pull(float(xp), float(vp), float(xm), float(vm), float(memory)))
        arg = u / alpha
    except (ArithmeticError, ValueError, TypeError):
        return 0.0, NONFINITE
    if arg != arg or not all(math.isfinite(z) for z in (xp, vp, xm, vm, memory)):
        return 0.0, NONFINITE
    if arg <= 0.0:
        return 0.0, UNRENDERABLE if u < -law.tolerance else 0
    if arg >= v_max * v_max:
        return v_max, SATURATED
    return min(math.sqrt(arg), v_max), 0


def local_slopes(tissue: Tissue, depth: float, speed: float = TYPICAL_SPEED) -> dict[str, float]:
    """Smallest and largest local stiffness and damping of the error equation over the
    working range (closures 0..``depth`` m, speeds within +-``speed`` m/s).

    ``k`` is ``E'(x) + dH/dx`` (contact damping's ``f'(x) v`` lowers it on opening), plus
    ``sum Km`` for ``k_hi``: a branch is a spring before it relaxes, so the equilibrium
    stiffness bounds ``k`` below and the instantaneous one above. ``s`` is ``D'(v) + f(x)``
    (contact damping grows with depth). Dry friction, carried by the reference model,
    is not in the error equation: ``s_model_hi`` adds its slope, for the model's
    integration.

    Returns
    -------
    dict
        ``k_lo``, ``k_hi`` (N/m), ``s_lo``, ``s_hi``, ``s_model_hi`` (N s/m).
    """
    parts = split_law(tissue)
    x = np.linspace(0.0, max(depth, 0.0), 101)
    v = np.linspace(-speed, speed, 101)
    with np.errstate(all="ignore"):
        k_eq = parts.stiffness(x)
        k_close, s_x = parts.mixed_slopes(x, speed)
        k_open, _ = parts.mixed_slopes(x, -speed)
        s_v = sum((c * t.derivative(v) for t, c in parts.speed), np.zeros_like(v))
        f_v = sum((c * t.derivative(v) for t, c in parts.friction), np.zeros_like(v))
        k_lo = float(np.min(k_eq + np.minimum(k_close, k_open)))
        k_hi = float(np.max(k_eq + np.maximum(k_close, k_open))) + parts.instantaneous
        s_hi = float(s_v.max() + s_x.max())
        return {
            "k_lo": k_lo,
            "k_hi": k_hi,
            "s_lo": float(s_v.min() + s_x.min()),
            "s_hi": s_hi,
            "s_model_hi": s_hi + float(f_v.max()),
        }


def static_force(tissue: Tissue, x: float) -> float:
    """The tissue's rendered force at rest at depth ``x``, N (inf or NaN, never an
    exception, where a term overflows): its position terms, the branches relaxed."""
    return float(split_law(tissue).elastic(np.array([x]))[0])
