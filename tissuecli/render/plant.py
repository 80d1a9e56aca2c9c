"""The display's piston (paper, eq. 6, plus the piston's own damping b) and the one
integrator every simulated mass in tissuecli uses.

    Mp xp'' + b xp' + Kp xp + alpha V^2 = F        (x positive down, 0 <= x <= stroke)
"""

from __future__ import annotations

import math
from collections.abc import Callable

from .profile import DisplayProfile

#: ``accel(t, x, v)``: acceleration (m/s^2) at time t (s), position x (m), velocity v (m/s).
Acceleration = Callable[[float, float, float], float]


def euler(
    x: float,
    v: float,
    accel: Acceleration,
    t: float,
    h: float,
    steps: int,
    lo: float = -math.inf,
    hi: float = math.inf,
    moved: Callable[[float, float, float], None] | None = None,
) -> tuple[float, float, float]:
    """Semi-implicit (symplectic) Euler: ``v += h a(t_mid, x, v); x += h v``, ``steps`` times.

    Stable for oscillators with ``h w < 2``, and it neither creates nor destroys
    energy on average (a plain explicit Euler creates it). Stops at ``lo`` and
    ``hi`` are inelastic: the mass stops dead against them.

    Parameters
    ----------
    x, v : float
        Position (m) and velocity (m/s) at time ``t``.
    accel : callable
        The acceleration, evaluated at the middle of each step.
    t, h : float
        Start time and step, s.
    steps : int
        Number of steps.
    lo, hi : float
        End stops, m.
    moved : callable, optional
        ``moved(x_before, x_after, h)`` after each step: how a state that the position
        drives (a relaxation branch's) keeps up, step by step.

    Returns
    -------
    x, v : float
        State at ``t + steps h``.
    a : float
        The acceleration of the last step (m/s^2): its sign says whether the
        mass is pressed against a stop it ends at.
    """
    a = 0.0
    for i in range(steps):
        a = accel(t + (i + 0.5) * h, x, v)
        v += h * a
        before = x
        x += h * v
        if x <= lo:
            x, v = lo, max(v, 0.0)
        elif x >= hi:
            x, v = hi, min(v, 0.0)
        if moved is not None:
            moved(before, x, h)
    return x, v, a


def piston_step(
    profile: DisplayProfile,
    x: float,
    v: float,
    volts: float,
    force: Callable[[float], float],
    t: float,
    dt: float,
    substeps: int = 10,
) -> tuple[float, float, bool]:
    """Advance the piston over ``dt`` with the voltage held (zero-order hold).

    Semi-implicit Euler at ``dt / substeps`` (0.1 ms at 1 kHz, where the
    piston's fastest rendered mode, a few hundred rad/s, gives h w < 0.05).
    End stops are inelastic: at 0 or ``stroke`` the piston stops dead.

    Parameters
    ----------
    profile : DisplayProfile
        The display's constants.
    x, v : float
        Position (m, positive down) and velocity (m/s) at time ``t``.
    volts : float
        Solenoid voltage over the step, V (clamped to [0, v_max] here too).
    force : callable
        Operator force on the piston, N (positive down), as a function of time in s.
    t, dt : float
        Start time and length of the step, s.
    substeps : int
        Internal steps.

    Returns
    -------
    x, v : float
        State at ``t + dt``.
    at_limit : bool
        True if the piston ends pressed against an end stop.
    """
    volts = min(max(volts, 0.0), profile.v_max) if volts == volts else 0.0
    pull = profile.alpha * volts * volts
    mp, kp, b = profile.Mp, profile.Kp, profile.b

    def accel(t: float, x: float, v: float) -> float:
        return (force(t) - kp * x - pull - b * v) / mp

    x, v, a = euler(x, v, accel, t, dt / substeps, substeps, 0.0, profile.stroke)
    at_limit = (x <= 0.0 and a < 0.0) or (x >= profile.stroke and a > 0.0)
    return x, v, at_limit


def free_step(
    profile: DisplayProfile,
    x: float,
    v: float,
    volts: float,
    force: float,
    dt: float,
    substeps: int = 10,
) -> tuple[float, float]:
    """:func:`piston_step` without end stops or clamping (a signed pull ``alpha V |V|``)
    under a constant force: the smooth map a linearisation needs."""
    pull = profile.alpha * volts * abs(volts)
    mp, kp, b = profile.Mp, profile.Kp, profile.b

    def accel(t: float, x: float, v: float) -> float:
        return (force - kp * x - pull - b * v) / mp

    x, v, _ = euler(x, v, accel, 0.0, dt / substeps, substeps)
    return x, v
