"""The whole rendering loop without a port: display physics, one period of delay and
the controller, tick by tick, for tests and for tuning."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..core.flags import FLAG_LIMIT
from ..core.tissue import Tissue
from .check import working_depth
from .controller import Controller
from .gains import choose_gains
from .law import Gains
from .passivity import PassivityController
from .plant import piston_step
from .profile import PAPER_DISPLAY, DisplayProfile

Array = NDArray[np.float64]


def simulate_offline(
    tissue: Tissue,
    operator: Callable[[float], float],
    profile: DisplayProfile = PAPER_DISPLAY,
    rate_hz: float = 1000.0,
    duration_s: float = 3.0,
    gains: Gains | None = None,
    quantise: bool = True,
    passivity: PassivityController | None = None,
    retargets: Sequence[tuple[float, Tissue]] = (),
    **controller_kw: Any,
) -> dict[str, Array]:
    """The whole loop without a port: display physics, one period of delay, controller.

    Tick ``k`` mirrors the real-time display and host: the display applies the
    voltage the host computed from reading ``k - 1``, reads its encoder, and the host
    answers before tick ``k + 1``.

    ``passivity``, if given, runs after the controller every tick (velocity expected
    over the period the voltage acts: ``vp + 1.5 T ap``); ``retargets`` are
    ``(time s, tissue)`` pairs handed to :meth:`Controller.retarget` at those times.

    Returns
    -------
    dict
        Arrays per tick: ``time`` (s), ``x`` (true position, m), ``xp`` (estimate, m),
        ``xm`` (model, m), ``e`` (``xp - xm``, m), ``volts`` (applied, V), ``flags``,
        ``force`` (operator, N), ``force_observed`` (N), ``ap`` (m/s^2), ``energy``
        (taken in by the host side so far, J: see :mod:`.passivity`).
    """
    if gains is None:
        depth = min(working_depth(tissue, profile), profile.stroke)
        gains, _ = choose_gains(tissue, profile, rate_hz, depth, **controller_kw)
    ctrl = Controller(tissue, profile, rate_hz, gains, **controller_kw)
    n = int(round(duration_s * rate_hz))
    dt = 1.0 / rate_hz
    out = {
        k: np.zeros(n)
        for k in ("time", "x", "xp", "xm", "e", "volts", "force", "force_observed", "ap", "energy")
    }
    pending_retargets = sorted(retargets, key=lambda r: r[0])
    observer = passivity if passivity is not None else PassivityController(profile)
    out["flags"] = np.zeros(n, dtype=np.int64)
    x = v = 0.0
    pending = 0.0
    for i in range(n):
        t = i * dt
        applied = pending
        reading = round(x / profile.resolution) * profile.resolution if quantise else x
        while pending_retargets and pending_retargets[0][0] <= t:
            ctrl.retarget(pending_retargets.pop(0)[1])
        step = ctrl.update(reading, applied, dt)
        pending = step.volts
        out["energy"][i] = observer.observe(reading, applied)
        if passivity is not None:
            pending = passivity.act(step.volts, step.vp + 1.5 * dt * step.ap, dt).volts
            ctrl.extra_damping = passivity.damping
        x_new, v, limit = piston_step(profile, x, v, applied, operator, t, dt)
        for key, value in (
            ("time", t),
            ("x", x),
            ("xp", step.xp),
            ("xm", step.xm),
            ("e", step.xp - step.xm),
            ("volts", applied),
            ("force", operator(t)),
            ("force_observed", step.force),
            ("ap", step.ap),
        ):
            out[key][i] = value
        out["flags"][i] = step.flags | (FLAG_LIMIT if limit else 0)
        x = x_new
    return out
