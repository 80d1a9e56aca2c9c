"""Gains of the error feedback: designed from the tissue's local slopes, then checked on
the linearised sampled loop (one period of delay, the velocity filter, the model)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..core.tissue import Tissue
from .controller import Controller
from .law import Gains, local_slopes, static_force
from .plant import free_step
from .profile import DisplayProfile

Array = np.ndarray


#: Error-dynamics bandwidths tried, as fractions of the loop rate (20 Hz first at 1 kHz):
#: well below the rate so that the period of delay costs little phase.
BANDWIDTH_FRACTIONS = (1 / 50, 1 / 75, 1 / 110, 1 / 160)


#: Floors tried for the reference model's mass, as fractions of Mp. The error feedback
#: sees the piston through (1 - Mp / M): a model much lighter than the piston turns the
#: velocity gain into negative damping once delay and filtering are counted.
MASS_FLOORS = (0.1, 0.25, 0.5, 1.0)


#: Largest spectral radius accepted for the sampled loop, unless the tissue's own
#: (lightly damped) mode is the slower one.
MAX_RADIUS = 0.999


def design_gains(
    tissue: Tissue,
    profile: DisplayProfile,
    rate_hz: float,
    depth: float,
    bandwidth_fraction: float = BANDWIDTH_FRACTIONS[0],
    mass_floor: float = MASS_FLOORS[0],
) -> Gains:
    """Gains making the error dynamics critically damped or slower, never below a bandwidth.

    The model mass is ``M`` raised to ``mass_floor * Mp``. With ``k`` and ``s`` the
    local stiffness and damping over ``[0, depth]``, ``Cp`` lifts the softest
    ``k + Cp`` to ``min(M, Mp) w^2`` (``w = 2 pi bandwidth_fraction rate_hz``; the
    lighter of model and piston, so the piston's own loop stays near ``w``) and
    ``Cv`` gives ``s + Cv >= 2 sqrt(M (k + Cp))`` at the stiffest point, so the error
    equation is at least critically damped everywhere: its impulse response never
    changes sign and the bound of :func:`tracking_bound` holds.

    Parameters
    ----------
    tissue : Tissue
        The law to render.
    profile : DisplayProfile
        The display.
    rate_hz : float
        Control-loop rate, Hz.
    depth : float
        Deepest piston position to be rendered, m.
    bandwidth_fraction : float
        Error bandwidth as a fraction of the loop rate.
    mass_floor : float
        Smallest model mass as a fraction of Mp.
    """
    mass = max(tissue.mass, mass_floor * profile.Mp)
    w = 2 * math.pi * bandwidth_fraction * rate_hz
    sl = local_slopes(tissue, depth)
    cp = max(0.0, min(mass, profile.Mp) * w * w - sl["k_lo"])
    cv = max(0.0, 2.0 * math.sqrt(mass * (sl["k_hi"] + cp)) - sl["s_lo"])
    return Gains(Cp=cp, Cv=cv, bandwidth_hz=w / (2 * math.pi), M=mass)


def choose_gains(
    tissue: Tissue,
    profile: DisplayProfile,
    rate_hz: float,
    depth: float,
    **controller_kw: Any,
) -> tuple[Gains, float]:
    """The first well-damped design, from the fastest error bandwidth and the lightest model.

    Tries :func:`design_gains` over :data:`MASS_FLOORS` (inner) and
    :data:`BANDWIDTH_FRACTIONS` (outer) and keeps the first whose linearised sampled
    loop (:func:`loop_radius`, at a quarter, 60 % and 95 % of ``depth``) has a
    spectral radius below :data:`MAX_RADIUS` or no larger than the tissue's own
    mode's; failing that, the design of smallest radius.

    Returns
    -------
    gains : Gains
        The design.
    radius : float
        Its loop spectral radius (see :func:`loop_is_stable`).
    """
    best: tuple[float, Gains] | None = None
    for fraction in BANDWIDTH_FRACTIONS:
        for floor in MASS_FLOORS:
            gains = design_gains(tissue, profile, rate_hz, depth, fraction, floor)
            radius = max(
                loop_radius(tissue, profile, rate_hz, gains, frac * depth, **controller_kw)
                for frac in (0.25, 0.6, 0.95)
            )
            if radius < MAX_RADIUS or radius <= tissue_radius(tissue, gains.M, rate_hz) + 1e-4:
                return gains, radius
            if best is None or radius < best[0]:
                best = (radius, gains)
    assert best is not None
    return best[1], best[0]


def loop_is_stable(radius: float, tissue: Tissue, mass: float, rate_hz: float) -> bool:
    """Whether a loop of spectral ``radius`` renders ``tissue`` without growing oscillation.

    Strictly inside the unit circle; or, for a tissue with no damping at rest
    (``xdot^2``, or S = 0), within 1e-3 of it: the loop's small-signal deficit is
    then a fraction of a rad/s, and any damping the tissue gains with amplitude
    limits it.
    """
    if radius < 1.0:
        return True
    return tissue_radius(tissue, mass, rate_hz) >= 1.0 - 1e-9 and radius <= 1.0 + 1e-3


def tissue_radius(tissue: Tissue, mass: float, rate_hz: float, depth: float = 0.0) -> float:
    """|z| of the tissue's own mode at ``rate_hz``, linearised at ``depth`` and at rest.

    Parameters
    ----------
    tissue : Tissue
        The law.
    mass : float
        Model mass used, kg.
    rate_hz : float
        Sample rate, Hz.
    depth : float
        Linearisation depth, m; the stiffness only sets the frequency, so the
        default (rest) matters only for forms whose slope vanishes there.
    """
    sl_k = float(tissue.stiffness(np.array([max(depth, 1e-3)]))[0])
    sl_s = float(tissue.damping(np.array([0.0]))[0])
    roots = np.roots([mass, sl_s, sl_k]) if mass > 0 else np.array([0.0])
    return float(np.max(np.abs(np.exp(roots / rate_hz))))


def loop_radius(
    tissue: Tissue,
    profile: DisplayProfile,
    rate_hz: float,
    gains: Gains,
    depth: float,
    **controller_kw: Any,
) -> float:
    """Spectral radius of the sampled loop linearised at static equilibrium at ``depth``.

    The closed loop of :func:`simulate_offline` (without quantisation) is one
    map from tick to tick; its Jacobian by central differences, at rest under the
    tissue's static force, gives the poles.
    """
    dt = 1.0 / rate_hz
    f_static = static_force(tissue, depth)
    ctrl = Controller(tissue, profile, rate_hz, gains, **controller_kw)
    pull0 = max(f_static - profile.Kp * depth, 0.0)
    v0 = min(math.sqrt(pull0 / profile.alpha), profile.v_max)

    def tick(s: Array) -> Array:
        # the voltage computed at the last tick acts over this period, as in simulate_offline
        x, v, applied = s[:3]
        ctrl.set_state(list(s[3:]))
        step = ctrl.update(x, applied, dt)
        # unclamped, signed voltage: the linearisation is of the law, not of its limits
        pending = math.copysign(math.sqrt(abs(step.pull) / profile.alpha), step.pull)
        x1, v1 = free_step(profile, x, v, applied, f_static, dt)
        return np.array([x1, v1, pending, *ctrl.state()])

    # at rest long enough for the relaxation branches to have relaxed: their states are 0
    nb = len(ctrl.branches)
    s0 = np.array([depth, 0.0, v0, depth, 0.0, 0.0, depth, 0.0, v0, *[0.0] * (2 * nb)])
    n = s0.size
    jac = np.zeros((n, n))
    base = [1e-3, 1e-2, 0.1, 1e-3, 1e-2, 1.0, 1e-3, 1e-2, 0.1]
    scale = np.array(base + [1e-3] * (2 * nb)) * 1e-6
    for j in range(n):
        d = np.zeros(n)
        d[j] = scale[j]
        jac[:, j] = (tick(s0 + d) - tick(s0 - d)) / (2 * scale[j])
    poles = np.linalg.eigvals(jac)
    if nb:
        poles = _without_relaxation(poles, 2 * nb, max(math.exp(-dt / min(ctrl.taus)), MAX_RADIUS))
    return float(np.max(np.abs(poles)))


def _without_relaxation(poles: Array, count: int, slow: float) -> Array:
    """``poles`` less the ``count`` largest real ones in ``[slow, 1]``: the relaxation
    branches' own modes.

    Each branch adds two states to the loop (driven by the piston and by the model) and
    two real modes at least as slow as its ``tau``: the tissue's creep under a constant
    force (time constant ``tau (K + Km) / K``, a pole at 1 for a tissue with no spring
    of its own) and the relaxation of the tracking error (``tau (1 + Km / (k + Cp))``).
    They are the tissue's behaviour, not the loop's, and with ``tau`` of seconds they
    would hide the loop's own modes behind a radius of 0.99999; only real poles slower
    than both the fastest branch and :data:`MAX_RADIUS` are taken as theirs.
    """
    slowest = [
        i
        for i in np.argsort(-poles.real)
        if abs(poles[i].imag) <= 1e-9 and slow * (1 - 1e-9) <= poles[i].real <= 1 + 1e-9
    ][:count]
    return np.delete(poles, slowest) if len(slowest) < poles.size else poles
