"""The priors of the coefficients: each term may reach a force scale at the session's
typical motion (its closure, speed and acceleration), and passive coefficients are
non-negative; and the warning when the data put a law far outside them."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..core.errors import FitError
from ..core.terms import Law, MotionScales
from .derivatives import Kinematics
from .posterior import Prior

Array = NDArray[np.float64]


def session_scales(kin: Kinematics, force_scale: float | None = None) -> MotionScales:
    """A session's typical closure, speed and acceleration (RMS of the filtered ones) and
    force scale (five times its largest force, or ``force_scale``): the priors' yardsticks.

    Priors in these physical units let a law of any size be fitted, a 100 kg stage as
    readily as a liver, while each coefficient stays weakly informed: its term may
    reach five times the session's largest force at the session's typical motion.
    """

    def ms(u: Array) -> float:
        return float(np.mean(np.square(u))) if u.size else 0.0

    gate = kin.gate
    on = slice(None) if gate is None else gate > 0  # the motion in contact: the tissue's
    x, v, a, force = kin.x[on], kin.v[on], kin.a[on], kin.force[on]
    peak = float(np.max(np.abs(force))) if force.size else 0.0
    return scales_from(ms(x), ms(v), ms(a), peak, force_scale)


def scales_from(
    ms_x: float, ms_v: float, ms_a: float, peak_force: float, force_scale: float | None = None
) -> MotionScales:
    """:class:`MotionScales` from the mean squares of the filtered closure (m^2), speed
    (m^2/s^2) and acceleration (m^2/s^4) and the largest filtered force (N): what
    :func:`session_scales` computes from a whole session, and the online fit from its
    running sums."""

    def root(u: float) -> float:
        value = float(np.sqrt(u)) if u > 0 else 0.0
        return value if value > 0 and np.isfinite(value) else 1.0

    force = force_scale if force_scale else 5.0 * peak_force
    return MotionScales(x=root(ms_x), v=root(ms_v), a=root(ms_a), force=force or 1.0)


def law_prior(law: Law, scales: MotionScales) -> Prior:
    """The prior of a law's coefficients for a session of these scales (each term may
    reach the force scale at the typical motion; passive coefficients non-negative)."""
    return Prior(scales=law.prior_scales(scales), passive=law.passive)


def prior_conflict(law: Law, beta: Array, scales: MotionScales) -> list[str]:
    """A warning when the best least-squares fit lies far outside the priors: a law that
    explains the data only with terms beyond five times the largest force is suspect."""
    if not np.all(np.isfinite(beta)):
        raise FitError("the least-squares fit is not finite; check the session for extreme values")
    ratio = np.abs(beta) / law.prior_scales(scales)
    j = int(np.argmax(ratio))
    if ratio[j] <= 10:
        return []
    t = law.terms[j]
    return [
        f"the data put {t.symbol} ({t.name}) at {beta[j]:.3g} {t.unit}, {ratio[j]:.0f} prior "
        f"scales: its term alone would reach {ratio[j] * scales.force:.3g} N; the law "
        f"{law.name} may not suit this session"
    ]
