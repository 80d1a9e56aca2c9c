"""The host side of the rendering loop: per Encoder frame, estimate the piston's state,
observe the operator's force, advance the tissue model and compute the voltage."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..core.tissue import Tissue
from .law import (
    NONFINITE,
    TYPICAL_SPEED,
    Gains,
    RenderLaw,
    control_voltage,
    local_slopes,
    split_law,
)
from .plant import euler
from .profile import DisplayProfile


@dataclass
class Step:
    """What the controller computed for one Encoder frame (SI)."""

    volts: float
    flags: int
    xp: float  # estimated piston position, m
    vp: float  # estimated piston velocity, m/s
    ap: float  # estimated piston acceleration, m/s^2
    xm: float  # tissue model position, m
    vm: float  # tissue model velocity, m/s
    force: float  # force observed over the last period, N
    pull: float  # pull the law asked for, N


class Controller:
    """Host side of the rendering loop: estimate, observe, model, control.

    Call :meth:`update` once per Encoder frame. Per frame ``k`` (time ``t_k``):

    1. a second-order fading-memory (alpha-beta-gamma) filter turns the encoder
       reading into position, velocity and acceleration with no lag on
       constant-acceleration motion;
    2. the force over ``[t_{k-1}, t_k]`` is observed from eq. 6,
       ``F = Mp (v_k - v_{k-1}) / T + b (x_k - x_{k-1}) / T + Kp x_mid + alpha V_{k-1}^2``,
       with ``V_{k-1}`` the voltage the display reported applying; the acceleration
       is a difference of filtered velocities, so its noise telescopes in the model's
       momentum instead of accumulating;
    3. the tissue model ``M xm'' + D(xm') + E(xm) + H(xm, xm') + Ff(xm') + R = F``
       advances over the same period (semi-implicit Euler, sub-stepped), ``R`` the
       force of its relaxation branches, whose states follow the model's closure by
       the exact recursion at each sub-step; a second set of branch states follows
       the piston's estimated closure, by the same recursion over the frame's ``dt``;
    4. :func:`control_voltage` is evaluated at the states predicted ``delay`` ahead,
       which cancels most of the phase the loop delay costs: the voltage acts from the
       display's next tick, and the middle of its hold is 1.5 periods ahead, but the
       observed force (a mean over the last period) already lags by half a period, so
       one period aligns model and piston (and tracked best on the offline loop).
       The piston's branch states are predicted the same way (the recursion over
       ``delay`` with the predicted closure) and their force enters the pull.

    Parameters
    ----------
    tissue : Tissue
        The law to render.
    profile : DisplayProfile
        The display.
    rate_hz : float
        Loop rate, Hz.
    gains : Gains
        Error gains and model mass (see :func:`choose_gains`).
    theta : float
        Fading-memory factor of the filter, 0 < theta < 1 (memory about
        ``1 / (1 - theta)`` periods). Larger smooths more but its phase lag, multiplied
        by the error gains, destabilised light models (0.7 and above on the offline
        loop); 0.5 kept every stable design stable.
    delay_periods : float
        Prediction horizon in periods.
    """

    def __init__(
        self,
        tissue: Tissue,
        profile: DisplayProfile,
        rate_hz: float,
        gains: Gains,
        theta: float = 0.5,
        delay_periods: float = 1.0,
    ) -> None:
        self.tissue, self.profile, self.gains = tissue, profile, gains
        self.law = RenderLaw.build(tissue, profile, gains)
        self.parts = split_law(tissue)
        self.branches = self.law.branches
        self.taus = [br.tau for br in self.branches]
        # each branch's state driven by the piston's closure and by the model's, m
        self.rp = [0.0] * len(self.branches)
        self.rm = [0.0] * len(self.branches)
        self.period = 1.0 / rate_hz
        self.delay = delay_periods * self.period
        self.g = 1.0 - theta**3
        self.h = 1.5 * (1.0 - theta**2) * (1.0 - theta)
        self.k = 0.5 * (1.0 - theta) ** 3
        self.mass = gains.M
        # sub-steps keep the model's own mode well inside semi-implicit Euler's stability
        sl = local_slopes(tissue, profile.stroke)
        w = math.sqrt(max(sl["k_hi"] + gains.Cp, 0.0) / self.mass) if self.mass > 0 else 0.0
        rate = (sl["s_model_hi"] + gains.Cv) / self.mass if self.mass > 0 else 0.0
        self.substeps = int(min(50, max(1, math.ceil(self.period * max(w, rate) / 0.2))))
        self.started = False
        self.x = self.v = self.a = self.xm = self.vm = self.volts_prev = 0.0

    STATE = ("x", "v", "a", "xm", "vm", "volts_prev")

    def state(self) -> list[float]:
        """The controller's state, for linearisation: :data:`STATE`, then the branch
        states driven by the piston, then those driven by the model (m)."""
        return [getattr(self, n) for n in self.STATE] + self.rp + self.rm

    def set_state(self, values: list[float]) -> None:
        base = len(self.STATE)
        nb = len(self.branches)
        for n, value in zip(self.STATE, values[:base], strict=True):
            setattr(self, n, float(value))
        self.rp = [float(r) for r in values[base : base + nb]]
        self.rm = [float(r) for r in values[base + nb : base + 2 * nb]]
        self.started = True

    def start(self, position: float, volts: float) -> None:
        """Initialise at rest at the first reading: model and piston coincide."""
        self.x, self.v, self.a = position, 0.0, 0.0
        self.xm, self.vm = position, 0.0
        self.volts_prev = volts
        # the tissue at rest, relaxed
        self.rp = [0.0] * len(self.branches)
        self.rm = [0.0] * len(self.branches)
        self.started = True

    def update(self, position: float, volts: float, dt: float | None = None) -> Step:
        """Process one Encoder frame.

        Parameters
        ----------
        position : float
            Encoder reading, m (positive down).
        volts : float
            Voltage the display reports applying from this reading on, V.
        dt : float, optional
            Time since the previous frame, s (default one period; pass the device
            clock difference so lost frames are accounted for).

        Returns
        -------
        Step
            The voltage to send and the states behind it.
        """
        if not (math.isfinite(position) and math.isfinite(volts)):
            # nothing sane to act on: switch off for this frame, keep the estimates
            return Step(
                0.0, NONFINITE, self.x, self.v, self.a, self.xm, self.vm, math.nan, math.nan
            )
        if not self.started:
            self.start(position, volts)
        dt = self.period if dt is None or not dt > 0 else dt
        p = self.profile
        x0, v0 = self.x, self.v
        # 1. fading-memory filter: predict, then correct with the innovation
        xp = x0 + dt * (v0 + 0.5 * dt * self.a)
        vp = v0 + dt * self.a
        r = position - xp
        x = xp + self.g * r
        v = vp + self.h * r / dt
        a = self.a + 2.0 * self.k * r / (dt * dt)
        # 2. force observed over the last period from eq. 6
        static = p.Kp * 0.5 * (x + x0) + p.alpha * self.volts_prev * self.volts_prev
        force = p.Mp * (v - v0) / dt + p.b * (x - x0) / dt + static
        # at an end stop the stop's reaction (an impact, then a steady push) is in the
        # balance too; it only ever pushes away from the stop, so it bounds the finger's
        if position <= 0.0:
            force = min(force, static)
        elif position >= p.stroke:
            force = max(force, static)
        # 3. tissue model over the same period
        law, m, branches = self.law, self.mass, self.branches
        rp = [br.step(r, x - x0, dt) for br, r in zip(branches, self.rp, strict=True)]
        rm = list(self.rm)

        def accel(t: float, xm: float, vm: float) -> float:
            memory = sum(br.Km * r for br, r in zip(branches, rm, strict=True))
            return (force - law.model_force(xm, vm, memory)) / m

        def moved(before: float, after: float, h: float) -> None:
            for i, br in enumerate(branches):
                rm[i] = br.step(rm[i], after - before, h)

        # x = 0 is where the jaws meet the tissue: the model, like the piston at its top
        # stop, cannot go above it
        xm, vm, _ = euler(
            self.xm,
            self.vm,
            accel,
            0.0,
            dt / self.substeps,
            self.substeps,
            0.0,
            moved=moved if branches else None,
        )
        am = accel(0.0, xm, vm)
        # 4. control at the states predicted for when the voltage acts
        tau = self.delay
        xp_f = x + tau * (v + 0.5 * tau * a)
        vp_f = v + tau * a
        if self.parts.friction and tau > 0:
            # dry friction makes the model stiff (its slope at rest is Fc / V_SMOOTH): a
            # Taylor step would overshoot its sticking speed, so integrate it ahead instead
            saved = list(rm)
            steps = max(1, round(self.substeps * tau / dt))
            xm_f, vm_f, _ = euler(
                xm, vm, accel, 0.0, tau / steps, steps, 0.0, moved=moved if branches else None
            )
            rm[:] = saved
        else:
            xm_f = xm + tau * (vm + 0.5 * tau * am)
            vm_f = vm + tau * am
        memory = sum(br.Km * br.step(r, xp_f - x, tau) for br, r in zip(branches, rp, strict=True))
        volts_out, flags = control_voltage(law, xp_f, vp_f, xm_f, vm_f, memory)
        pull = law.pull(xp_f, vp_f, xm_f, vm_f, memory)
        finite = all(math.isfinite(z) for z in (x, v, a, xm, vm, *rp, *rm))
        if not finite:
            # never carry NaN into the next period: restart the estimate at the reading
            self.start(position, 0.0)
            return Step(0.0, NONFINITE, self.x, 0.0, 0.0, self.xm, 0.0, math.nan, math.nan)
        self.x, self.v, self.a, self.xm, self.vm = x, v, a, xm, vm
        self.rp, self.rm = rp, rm
        self.volts_prev = volts
        return Step(volts_out, flags, x, v, a, xm, vm, force, pull)

    def local_stiffness(self, x: float) -> float:
        """``E'(x) + dH/dx + Cp``, N/m: the error equation's softest stiffness at depth
        ``x`` (branches relaxed, contact damping opening at the typical speed)."""
        at = np.array([x])
        k = float(self.parts.stiffness(at)[0])
        if self.parts.mixed:
            k += min(
                float(self.parts.mixed_slopes(at, s)[0][0]) for s in (TYPICAL_SPEED, -TYPICAL_SPEED)
            )
        return k + self.gains.Cp


def tracking_bound(
    model_mass: float,
    piston_mass: float,
    max_accel: float,
    min_stiffness: float,
    resolution: float,
) -> float:
    """Bound on |e| from the error equation, m.

    ``|M - Mp| max|xp''| / min(k + Cp) + resolution``: the error equation's forced
    response (critically damped or slower, so its gain is its static gain) plus the
    encoder's quantisation, which no controller can see below.
    """
    if not min_stiffness > 0:
        return math.inf
    return abs(model_mass - piston_mass) * max_accel / min_stiffness + resolution
