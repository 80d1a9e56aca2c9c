"""The host side of the rendering loop: per Encoder frame, estimate the piston's state,
observe the operator's force, advance the tissue model and compute the voltage."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..core.errors import RenderError
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

#: Time over which :meth:`Controller.retarget` moves from one law to the next, s: several
#: times the slowest error dynamics (20 Hz bandwidth, 50 ms) so the model follows the
#: blend, and short against a grasp (0.25-0.5 s to rise) so an update is felt at once.
RETARGET_SLEW_S = 0.2

#: Energy a retarget may add to what the rendered law stores at the present closure, J
#: (see :meth:`Controller.retarget`): K up by 1000 N/m at 0.2 mm.
RETARGET_ENERGY_J = 2e-5


@dataclass
class _Blend:
    """A retarget under way: the law it goes to, its weight (a cell the blended force
    closures read) and its length, s."""

    target: RenderLaw
    source: RenderLaw
    weight: list[float]
    slew_s: float


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
        self.substeps = self._substeps(tissue)
        self.started = False
        self.x = self.v = self.a = self.xm = self.vm = self.volts_prev = 0.0
        self.blend: _Blend | None = None
        # damping a passivity controller adds to the output, N s/m; the model carries it
        # too, so the error feedback does not undo it
        self.extra_damping = 0.0

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
        if self.blend is not None:
            self._advance_blend(dt, position)
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
        law, m, branches, extra = self.law, self.mass, self.branches, self.extra_damping
        rp = [br.step(r, x - x0, dt) for br, r in zip(branches, self.rp, strict=True)]
        rm = list(self.rm)

        def accel(t: float, xm: float, vm: float) -> float:
            memory = sum(br.Km * r for br, r in zip(branches, rm, strict=True))
            return (force - law.model_force(xm, vm, memory) - extra * vm) / m

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

    def retarget(self, tissue: Tissue, slew_s: float = RETARGET_SLEW_S) -> None:
        """Move to rendering ``tissue`` without a step in force.

        The rendered forces at rest and of speed (and with them the tissue model's) go
        from the current law's to the new one's over ``slew_s`` seconds of frames, as a
        linear blend ``(1 - w) old + w new`` with ``w`` rising from 0 to 1; a retarget
        during a blend starts from the blend as it stands. Gains and model mass stay.

        A blend removes the jolt, not the energy: a law that stores more at the
        present closure (a stiffness raised while the tissue is compressed) would give
        back more than it took in. So ``w`` only rises while the new law stores at most
        :data:`RETARGET_ENERGY_J` more than the old at the present closure
        (``int_0^x (E_new - E_old)``): a softer law blends in at once, a stiffer one
        during a grasp waits for the jaws to open. What remains (the loop's own delay)
        is for a :class:`~tissuecli.render.passivity.PassivityController`.
        """
        tissue.validate()
        new = RenderLaw.build(tissue, self.profile, self.gains)
        old = self.law
        if new.branches or old.branches:
            # a branch's state is the history of the closure under its own law: there is
            # no blend of two histories that conserves energy
            raise RenderError(
                "a law with relaxation branches cannot be retargeted while rendering; "
                "start a new play with it"
            )
        w = [0.0]

        def static(x: float) -> float:
            return (1.0 - w[0]) * old.static(x) + w[0] * new.static(x)

        def speed(v: float) -> float:
            return (1.0 - w[0]) * old.speed(v) + w[0] * new.speed(v)

        def mixed(x: float, v: float) -> float:
            return (1.0 - w[0]) * old.mixed(x, v) + w[0] * new.mixed(x, v)

        def friction(v: float) -> float:
            return (1.0 - w[0]) * old.friction(v) + w[0] * new.friction(v)

        self.law = replace(new, static=static, speed=speed, mixed=mixed, friction=friction)
        self.blend = _Blend(new, old, w, max(slew_s, 0.0))
        self.tissue = tissue
        self.parts = split_law(tissue)
        # sub-steps for the stiffer of the two laws
        self.substeps = max(self.substeps, self._substeps(tissue))

    def _substeps(self, tissue: Tissue) -> int:
        """Model sub-steps per frame that keep the model's own mode of ``tissue`` well
        inside semi-implicit Euler's stability."""
        sl = local_slopes(tissue, self.profile.stroke)
        m, g = self.mass, self.gains
        w = math.sqrt(max(sl["k_hi"] + g.Cp, 0.0) / m) if m > 0 else 0.0
        rate = (sl["s_model_hi"] + g.Cv) / m if m > 0 else 0.0
        return int(min(50, max(1, math.ceil(self.period * max(w, rate) / 0.2))))

    def _advance_blend(self, dt: float, position: float) -> None:
        blend = self.blend
        assert blend is not None
        x = max(position, 0.0)
        if x > 0.0:
            old = blend.source
            n = 8  # Simpson over [0, x]: the stored energy's change, J
            gap = sum(
                (1 if i in (0, n) else 4 if i % 2 else 2)
                * (blend.target.static(x * i / n) - old.static(x * i / n))
                for i in range(n + 1)
            ) * (x / (3 * n))
            if gap > RETARGET_ENERGY_J:
                return
        blend.weight[0] = min(1.0, blend.weight[0] + (dt / blend.slew_s if blend.slew_s else 1.0))
        if blend.weight[0] >= 1.0:
            self.law, self.blend = blend.target, None

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
