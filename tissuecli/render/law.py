"""The control law that renders a tissue on the display: the paper's eq. 9 generalised
to any forms, with the solenoid's limits (it only pulls, and only up to v_max).

The display (paper, eq. 6, with the piston's own damping b) and the tissue are::

    Mp xp'' + b xp' + Kp xp + alpha V^2 = F
    M xm'' + D(xm') + E(xm) = F

with ``E`` the tissue's rendered force at rest (its position terms), ``D`` that of
speed (damping and friction) and ``M`` its inertia; a sensor offset is not rendered.
:func:`control_voltage` chooses V so that the error e = xp - xm obeys
``M e'' + (s + Cv) e' + (k + Cp) e = (M - Mp) xp''`` (s, k: the law's local slopes).
Everything is SI: m, m/s, m/s^2, N, kg, V, s.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..core.flags import NONFINITE, SATURATED, UNRENDERABLE
from ..core.tissue import Tissue
from .profile import DisplayProfile

#: A requested force more negative than this counts as unrenderable: about 1 gram-force,
#: so sensor noise around the rest position is not counted.
FORCE_TOLERANCE_N = 0.01


#: Typical closing speed for speed-dependent damping slopes (models.TYPICAL), m/s.
TYPICAL_SPEED = 0.05


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

    @classmethod
    def build(cls, tissue: Tissue, profile: DisplayProfile, gains: Gains) -> RenderLaw:
        static, speed = tissue.scalar_law()
        return cls(
            static=static,
            speed=speed,
            Kp=profile.Kp,
            b=profile.b,
            alpha=profile.alpha,
            v_max=profile.v_max,
            Cp=gains.Cp,
            Cv=gains.Cv,
        )

    def pull(self, xp: float, vp: float, xm: float, vm: float) -> float:
        """The solenoid pull the law asks for, ``alpha V^2`` in N (may be negative or NaN)."""
        return (
            self.speed(vp)
            + self.static(xp)
            - self.Kp * xp
            - self.b * vp
            + self.Cv * (vp - vm)
            + self.Cp * (xp - xm)
        )


def control_voltage(
    law: RenderLaw, xp: float, vp: float, xm: float, vm: float
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
    the first line with b = 0). When the error dynamics are at least critically
    damped their impulse response is non-negative, so
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
        u = float(law.pull(float(xp), float(vp), float(xm), float(vm)))
        arg = u / alpha
    except (ArithmeticError, ValueError, TypeError):
        return 0.0, NONFINITE
    if arg != arg or not all(math.isfinite(z) for z in (xp, vp, xm, vm)):
        return 0.0, NONFINITE
    if arg <= 0.0:
        return 0.0, UNRENDERABLE if u < -law.tolerance else 0
    if arg >= v_max * v_max:
        return v_max, SATURATED
    return min(math.sqrt(arg), v_max), 0


def local_slopes(tissue: Tissue, depth: float, speed: float = TYPICAL_SPEED) -> dict[str, float]:
    """Smallest and largest local stiffness and damping (N/m, N s/m) over the working range."""
    x = np.linspace(0.0, max(depth, 0.0), 101)
    v = np.linspace(-speed, speed, 101)
    k = tissue.stiffness(x)
    s = tissue.damping(v)
    return {
        "k_lo": float(k.min()),
        "k_hi": float(k.max()),
        "s_lo": float(s.min()),
        "s_hi": float(s.max()),
    }


def static_force(tissue: Tissue, x: float) -> float:
    """The tissue's rendered force at rest at depth ``x``, N (inf or NaN, never an
    exception, where a term overflows)."""
    return float(tissue.static_force(np.array([x]))[0])
