"""Rendering a tissue on the solenoid haptic display: pure numerics.

The display (paper, eq. 6) is a piston of mass ``Mp`` on a spring ``Kp``
inside a solenoid that can only pull::

    Mp xp'' + b xp' + Kp xp + alpha V^2 = F        (x positive down, 0 <= x <= stroke)

with ``V`` the amplifier input voltage (unity-gain transconductance, so V
stands for the current) and ``b`` the piston's own viscous damping, which the
paper's eq. 6 neglects. The tissue is the identified law::

    M xm'' + S f1(xm') + K f0(xm) = F.

This module holds the display's constants (:class:`DisplayProfile`), the
piston integrator (:func:`piston_step`), a simulated operator
(:class:`OperatorForce`), the control law (:func:`control_voltage`,
:class:`Controller`), the renderability check (:func:`check`) and an offline
closed-loop simulation (:func:`simulate_offline`). It touches no port and no
file; :mod:`tissuecli.play` runs it in real time.

Everything is SI: m, m/s, m/s^2, N, kg, V, s.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, fields, replace
from functools import lru_cache
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .errors import InputError
from .models import Tissue
from .protocol import FLAG_LIMIT

Array = NDArray[np.float64]

#: Controller flags, logged together with the display's Encoder flags (0x01, 0x02),
#: so they use higher bits.
SATURATED = 0x10  # the law asked for more than v_max: V = v_max
UNRENDERABLE = 0x20  # the law asked the solenoid to push: V = 0
NONFINITE = 0x40  # an input or the law was NaN/inf: V = 0

#: Largest grasp force measured on porcine liver (field notes, section 2): a display that
#: saturates below it lets the tissue give way under a firm squeeze.
GRASP_FORCE_N = 3.4
#: A requested force more negative than this counts as unrenderable: about 1 gram-force,
#: so sensor noise around the rest position is not counted.
FORCE_TOLERANCE_N = 0.01
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
#: Typical closing speed for speed-dependent damping slopes (models.TYPICAL), m/s.
TYPICAL_SPEED = 0.05
#: Rule for tissues softer than the display's spring near rest (e.g. x^3): refused when
#: that happens over more than this fraction of the working depth.
MAX_SOFT_FRACTION = 0.5


# --------------------------------------------------------------------------- profile


@dataclass(frozen=True)
class DisplayProfile:
    """Constants of one solenoid display, SI. Defaults are the paper's prototype.

    Attributes
    ----------
    Mp : float
        Piston mass, kg (83.35 g weighed).
    Kp : float
        Spring stiffness, N/m (27 gf/mm).
    alpha : float
        Solenoid force constant, N/V^2 (12e-5 gf/mV^2): the pull is ``alpha V^2``.
    v_max : float
        Largest amplifier input, V (pull ``alpha v_max^2`` = 2.648 N).
    stroke : float
        Piston travel, m; end stops at 0 (rest, top) and ``stroke``.
    resolution : float
        Encoder resolution, m per count.
    b : float
        Piston viscous damping, N s/m. The paper gives none; 0.5 N s/m (damping
        ratio 0.05) is an assumption to be replaced by a ring-down measurement.
    """

    Mp: float = 0.08335
    Kp: float = 264.78
    alpha: float = 1.1768
    v_max: float = 1.5
    stroke: float = 0.015
    resolution: float = 1e-6
    b: float = 0.5

    @property
    def max_pull(self) -> float:
        """Largest solenoid force ``alpha v_max^2``, N."""
        return self.alpha * self.v_max**2

    def validate(self) -> DisplayProfile:
        """Raise :class:`InputError` unless every constant is finite and positive (b >= 0)."""
        for f in fields(self):
            value = getattr(self, f.name)
            ok = isinstance(value, (int, float)) and math.isfinite(value)
            ok = ok and (value >= 0 if f.name == "b" else value > 0)
            if not ok:
                sign = ">= 0" if f.name == "b" else "> 0"
                raise InputError(
                    f"display profile: {f.name} = {value!r} {PROFILE_UNITS[f.name]} "
                    f"must be finite and {sign}"
                )
        return self

    def as_dict(self) -> dict[str, Any]:
        """The profile as JSON-ready ``{"Mp": {"value": ..., "unit": "kg"}, ...}``."""
        out: dict[str, Any] = {"format": "tissuecli-display", "version": 1}
        for key, value in asdict(self).items():
            out[key] = {"value": value, "unit": PROFILE_UNITS[key]}
        return out


PAPER_DISPLAY = DisplayProfile()
#: SI unit of each profile constant, as written in profile files
PROFILE_UNITS = {
    "Mp": "kg",
    "Kp": "N/m",
    "alpha": "N/V^2",
    "v_max": "V",
    "stroke": "m",
    "resolution": "m",
    "b": "N s/m",
}


def profile_from_dict(data: Mapping[str, Any], source: str = "display profile") -> DisplayProfile:
    """Build a :class:`DisplayProfile` from a JSON object.

    Each constant is a number in SI or ``{"value": number, "unit": "..."}``; missing
    constants keep the paper's values. Unknown keys are refused, so a typo is not
    silently ignored.

    Parameters
    ----------
    data : mapping
        E.g. ``{"Mp": 0.1, "Kp": {"value": 300, "unit": "N/m"}}``.
    source : str
        Names the input in error messages (a file name).

    Raises
    ------
    InputError
        For unknown keys, wrong units, or values that are not finite and positive.
    """
    if not isinstance(data, Mapping):
        raise InputError(f"{source} must be a JSON object")
    units = PROFILE_UNITS
    unknown = sorted(set(data) - set(units) - {"format", "version", "name", "note"})
    if unknown:
        raise InputError(
            f"{source}: unknown key(s) {', '.join(unknown)}; known: {', '.join(units)}"
        )
    values: dict[str, float] = {}
    for key, unit in units.items():
        if key not in data:
            continue
        entry = data[key]
        value = entry.get("value") if isinstance(entry, Mapping) else entry
        if isinstance(entry, Mapping) and entry.get("unit", unit) != unit:
            raise InputError(f"{source}: {key} is in {entry['unit']!r}; give it in {unit!r}")
        if not isinstance(value, (int, float)) or isinstance(value, bool):
            raise InputError(f"{source}: {key} must be a number in {unit}")
        values[key] = float(value)
    return replace(PAPER_DISPLAY, **values).validate()


# --------------------------------------------------------------------------- physics


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
    mp, kp, b, stroke = profile.Mp, profile.Kp, profile.b, profile.stroke
    h = dt / substeps
    net = 0.0
    for i in range(substeps):
        net = force(t + (i + 0.5) * h) - kp * x - pull
        v += h * (net - b * v) / mp
        x += h * v
        if x <= 0.0:
            x, v = 0.0, max(v, 0.0)
        elif x >= stroke:
            x, v = stroke, min(v, 0.0)
    at_limit = (x <= 0.0 and net < 0.0) or (x >= stroke and net > 0.0)
    return x, v, at_limit


# --------------------------------------------------------------------------- operator


@dataclass(frozen=True)
class Press:
    """One press: raised-cosine rise, hold, raised-cosine release (smooth in force and
    its rate, so the piston is not kicked)."""

    start: float  # s
    rise: float  # s
    hold: float  # s
    fall: float  # s
    force: float  # N, peak

    def __call__(self, t: float) -> float:
        u = t - self.start
        if u <= 0.0:
            return 0.0
        if u < self.rise:
            return 0.5 * self.force * (1.0 - math.cos(math.pi * u / self.rise))
        u -= self.rise
        if u <= self.hold:
            return self.force
        u -= self.hold
        if u < self.fall:
            return 0.5 * self.force * (1.0 + math.cos(math.pi * u / self.fall))
        return 0.0


@dataclass(frozen=True)
class OperatorForce:
    """A simulated finger on the piston: smooth presses, a force source (N, positive down).

    Presses come one per ``slot`` seconds (3.3 per 10 s by default), the first
    starting at ``first`` s. Press ``i`` starts up to 0.3 s into its slot, peaks at
    a force drawn uniformly from ``force_range`` (1..2.5 N: firm grasps, below the
    3.4 N maximum on liver), rises and releases in 0.25..0.5 s and holds for
    0.2..0.8 s, all drawn from ``seed`` and ``i`` alone, so any time can be
    evaluated without the past and a run of any length is reproducible.
    A 2.5 s run therefore always contains one whole press.

    A force source is the hardest operator for tracking (nothing in the finger
    damps the piston) and the easiest to reproduce; a real finger adds its own
    mass and damping.
    """

    seed: int = 0
    first: float = 0.1
    slot: float = 3.0
    force_range: tuple[float, float] = (1.0, 2.5)

    @property
    def max_force(self) -> float:
        """Largest force any press reaches, N."""
        return self.force_range[1]

    def press(self, i: int) -> Press:
        """The ``i``-th press (``i >= 0``)."""
        return _press(self.seed, i, self.first, self.slot, self.force_range)

    def __call__(self, t: float) -> float:
        if t < self.first:
            return 0.0
        return self.press(int((t - self.first) // self.slot))(t)


@lru_cache(maxsize=64)
def _press(seed: int, i: int, first: float, slot: float, force_range: tuple[float, float]) -> Press:
    rng = np.random.default_rng([seed % 2**32, i])  # any int seed, negative ones too
    jitter, rise, hold, fall, force = rng.uniform(
        [0.0, 0.25, 0.2, 0.25, force_range[0]], [0.3, 0.5, 0.8, 0.5, force_range[1]]
    )
    return Press(
        first + i * slot + float(jitter), float(rise), float(hold), float(fall), float(force)
    )


# --------------------------------------------------------------------------- control law


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

    ``f0`` and ``f1`` are float -> float callables (see :func:`RenderLaw.build`).
    """

    K: float
    S: float
    f0: Callable[[float], float]
    f1: Callable[[float], float]
    Kp: float
    b: float
    alpha: float
    v_max: float
    Cp: float
    Cv: float
    tolerance: float = FORCE_TOLERANCE_N

    @classmethod
    def build(cls, tissue: Tissue, profile: DisplayProfile, gains: Gains) -> RenderLaw:
        return cls(
            K=tissue.K,
            S=tissue.S,
            f0=tissue.model.f0.scalar,
            f1=tissue.model.f1.scalar,
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
            self.S * self.f1(vp)
            + self.K * self.f0(xp)
            - self.Kp * xp
            - self.b * vp
            + self.Cv * (vp - vm)
            + self.Cp * (xp - xm)
        )


def control_voltage(
    law: RenderLaw, xp: float, vp: float, xm: float, vm: float
) -> tuple[float, int]:
    """The solenoid voltage that renders the tissue: paper eq. 9 for any forms.

    Derivation. With the pull ``u = alpha V^2`` the display obeys
    ``Mp xp'' + b xp' + Kp xp + u = F`` and the tissue model
    ``M xm'' + S f1(xm') + K f0(xm) = F`` (the same force F). Choosing::

        u = S f1(xp') + K f0(xp) - Kp xp - b xp' + Cv e' + Cp e,    e = xp - xm

    and subtracting the two equations gives::

        M e'' + S (f1(xp') - f1(xm')) + K (f0(xp) - f0(xm)) + Cv e' + Cp e = (M - Mp) xp''

    and, with the local slopes ``k = K f0'(x)`` and ``s = S f1'(x')`` (mean-value
    theorem), the error equation::

        M e'' + (s + Cv) e' + (k + Cp) e = (M - Mp) xp''.

    For linear forms this is the paper's result (its Sm xp' + (Km - Kp) xp is
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


# --------------------------------------------------------------------------- gains


def _local_slopes(tissue: Tissue, depth: float, speed: float = TYPICAL_SPEED) -> dict[str, float]:
    """Smallest and largest local stiffness and damping (N/m, N s/m) over the working range."""
    x = np.linspace(0.0, max(depth, 0.0), 101)
    v = np.linspace(-speed, speed, 101)
    with np.errstate(all="ignore"):
        k = tissue.K * tissue.model.f0.derivative(x)
        s = tissue.S * tissue.model.f1.derivative(v)
    return {
        "k_lo": float(k.min()),
        "k_hi": float(k.max()),
        "s_lo": float(s.min()),
        "s_hi": float(s.max()),
    }


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
    mass = max(tissue.M, mass_floor * profile.Mp)
    w = 2 * math.pi * bandwidth_fraction * rate_hz
    sl = _local_slopes(tissue, depth)
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
    sl_k = tissue.K * float(tissue.model.f0.derivative(np.array([max(depth, 1e-3)]))[0])
    sl_s = tissue.S * float(tissue.model.f1.derivative(np.array([0.0]))[0])
    roots = np.roots([mass, sl_s, sl_k]) if mass > 0 else np.array([0.0])
    return float(np.max(np.abs(np.exp(roots / rate_hz))))


# --------------------------------------------------------------------------- controller


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
    3. the tissue model ``M xm'' + S f1(xm') + K f0(xm) = F`` advances over the same
       period (semi-implicit Euler, sub-stepped);
    4. :func:`control_voltage` is evaluated at the states predicted ``delay`` ahead,
       which cancels most of the phase the loop delay costs: the voltage acts from the
       display's next tick, and the middle of its hold is 1.5 periods ahead, but the
       observed force (a mean over the last period) already lags by half a period, so
       one period aligns model and piston (and tracked best on the offline loop).

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
        self.period = 1.0 / rate_hz
        self.delay = delay_periods * self.period
        self.g = 1.0 - theta**3
        self.h = 1.5 * (1.0 - theta**2) * (1.0 - theta)
        self.k = 0.5 * (1.0 - theta) ** 3
        self.mass = gains.M
        # sub-steps keep the model's own mode well inside semi-implicit Euler's stability
        sl = _local_slopes(tissue, profile.stroke)
        w = math.sqrt(max(sl["k_hi"] + gains.Cp, 0.0) / self.mass) if self.mass > 0 else 0.0
        rate = (sl["s_hi"] + gains.Cv) / self.mass if self.mass > 0 else 0.0
        self.substeps = int(min(50, max(1, math.ceil(self.period * max(w, rate) / 0.2))))
        self.started = False
        self.x = self.v = self.a = self.xm = self.vm = self.volts_prev = 0.0

    STATE = ("x", "v", "a", "xm", "vm", "volts_prev")

    def state(self) -> list[float]:
        """The controller's state, for linearisation."""
        return [getattr(self, n) for n in self.STATE]

    def set_state(self, values: list[float]) -> None:
        for n, value in zip(self.STATE, values, strict=True):
            setattr(self, n, float(value))
        self.started = True

    def start(self, position: float, volts: float) -> None:
        """Initialise at rest at the first reading: model and piston coincide."""
        self.x, self.v, self.a = position, 0.0, 0.0
        self.xm, self.vm = position, 0.0
        self.volts_prev = volts
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
        law, m = self.law, self.mass
        xm, vm = self.xm, self.vm
        hs = dt / self.substeps
        for _ in range(self.substeps):
            vm += hs * (force - law.S * law.f1(vm) - law.K * law.f0(xm)) / m
            xm += hs * vm
            if xm < 0.0:
                # x = 0 is where the jaws meet the tissue: the model, like the piston at
                # its top stop, cannot go above it
                xm, vm = 0.0, max(vm, 0.0)
        am = (force - law.S * law.f1(vm) - law.K * law.f0(xm)) / m
        # 4. control at the states predicted for when the voltage acts
        tau = self.delay
        xp_f = x + tau * (v + 0.5 * tau * a)
        vp_f = v + tau * a
        xm_f = xm + tau * (vm + 0.5 * tau * am)
        vm_f = vm + tau * am
        volts_out, flags = control_voltage(law, xp_f, vp_f, xm_f, vm_f)
        pull = law.pull(xp_f, vp_f, xm_f, vm_f)
        if not all(math.isfinite(z) for z in (x, v, a, xm, vm)):
            # never carry NaN into the next period: restart the estimate at the reading
            self.start(position, 0.0)
            return Step(0.0, NONFINITE, self.x, 0.0, 0.0, self.xm, 0.0, math.nan, math.nan)
        self.x, self.v, self.a, self.xm, self.vm = x, v, a, xm, vm
        self.volts_prev = volts
        return Step(volts_out, flags, x, v, a, xm, vm, force, pull)

    def local_stiffness(self, x: float) -> float:
        """``K f0'(x) + Cp``, N/m: the error equation's stiffness at depth ``x``."""
        with np.errstate(all="ignore"):
            k = self.tissue.K * float(self.tissue.model.f0.derivative(np.array([x]))[0])
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


# --------------------------------------------------------------------------- offline loop


def simulate_offline(
    tissue: Tissue,
    profile: DisplayProfile = PAPER_DISPLAY,
    rate_hz: float = 1000.0,
    duration_s: float = 3.0,
    operator: Callable[[float], float] | None = None,
    gains: Gains | None = None,
    quantise: bool = True,
    **controller_kw: Any,
) -> dict[str, Array]:
    """The whole loop without a port: display physics, one period of delay, controller.

    Tick ``k`` mirrors the real-time display and host: the display applies the
    voltage the host computed from reading ``k - 1``, reads its encoder, and the host
    answers before tick ``k + 1``.

    Returns
    -------
    dict
        Arrays per tick: ``time`` (s), ``x`` (true position, m), ``xp`` (estimate, m),
        ``xm`` (model, m), ``e`` (``xp - xm``, m), ``volts`` (applied, V), ``flags``,
        ``force`` (operator, N), ``force_observed`` (N), ``ap`` (m/s^2).
    """
    operator = operator if operator is not None else OperatorForce()
    if gains is None:
        depth = min(working_depth(tissue, profile), profile.stroke)
        gains, _ = choose_gains(tissue, profile, rate_hz, depth, **controller_kw)
    ctrl = Controller(tissue, profile, rate_hz, gains, **controller_kw)
    n = int(round(duration_s * rate_hz))
    dt = 1.0 / rate_hz
    out = {
        k: np.zeros(n)
        for k in ("time", "x", "xp", "xm", "e", "volts", "force", "force_observed", "ap")
    }
    out["flags"] = np.zeros(n, dtype=np.int64)
    x = v = 0.0
    pending = 0.0
    for i in range(n):
        t = i * dt
        applied = pending
        reading = round(x / profile.resolution) * profile.resolution if quantise else x
        step = ctrl.update(reading, applied, dt)
        pending = step.volts
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


# --------------------------------------------------------------------------- check


def working_depth(tissue: Tissue, profile: DisplayProfile, force: float = GRASP_FORCE_N) -> float:
    """Depth at which the tissue's static force reaches ``force``, m (``inf`` if never
    within twice the stroke)."""
    return _solve(lambda x: tissue.K * _f0(tissue, x) - force, 0.0, 2 * profile.stroke)


def _f0(tissue: Tissue, x: float) -> float:
    with np.errstate(all="ignore"):
        return float(tissue.model.f0(np.array([x]))[0])


def _solve(fn: Callable[[float], float], lo: float, hi: float) -> float:
    """Smallest root of an increasing-then-positive ``fn`` on [lo, hi] by scan and bisection;
    ``inf`` if ``fn(hi) < 0``."""
    grid = np.linspace(lo, hi, 401)
    vals = np.array([fn(float(z)) for z in grid])
    above = np.nonzero(vals >= 0)[0]
    if above.size == 0:
        return math.inf
    j = int(above[0])
    if j == 0:
        return float(grid[0])
    a, b = float(grid[j - 1]), float(grid[j])
    for _ in range(60):
        mid = 0.5 * (a + b)
        a, b = (mid, b) if fn(mid) < 0 else (a, mid)
    return b


@dataclass
class CheckResult:
    """Whether and how well a display can render a tissue.

    Attributes
    ----------
    renderable : bool
        The verdict: False means ``play`` refuses the tissue.
    verdict : str
        ``"renderable"``, ``"renderable with caveats"`` or ``"not renderable"``.
    reasons : list of str
        Why it is refused (empty if renderable).
    caveats : list of str
        What will not be exact even so.
    depth : ndarray
        Piston depths of the band, m.
    k_min, k_max : ndarray
        Softest and stiffest secant stiffness ``F / x`` the display can show at each
        depth, N/m: ``Kp`` (solenoid off) and ``Kp + alpha v_max^2 / x``.
    k_tissue : ndarray
        The tissue's secant stiffness ``K f0(x) / x`` at each depth, N/m.
    force_limit : float
        Largest static tissue force rendered before the solenoid saturates, N.
    saturation_depth : float
        Depth at which it saturates, m (``inf`` if never within the stroke).
    working_depth : float
        Depth at which the tissue's force reaches ``force``, m.
    force : float
        Force the tissue must be rendered up to, N.
    gains : Gains
        Gains :func:`choose_gains` picks for this tissue.
    passivity_required : float
        Colgate's ``K_d T / 2 + |B_d|`` with the digitally rendered stiffness
        ``K_d = max k - Kp + Cp`` and damping ``B_d = max s + Cv - b``, N s/m.
    passivity_margin : float
        ``b - passivity_required``, N s/m: negative means passivity against any
        passive grip is not guaranteed (the bound is conservative).
    spectral_radius : float
        Largest pole magnitude of the linearised sampled loop (one period of
        delay, filter, model); >= 1 means the loop itself oscillates.
    rate_hz : float
        Loop rate of the analysis, Hz.
    """

    renderable: bool
    verdict: str
    reasons: list[str]
    caveats: list[str]
    depth: Array
    k_min: Array
    k_max: Array
    k_tissue: Array
    force_limit: float
    saturation_depth: float
    working_depth: float
    force: float
    gains: Gains
    passivity_required: float
    passivity_margin: float
    spectral_radius: float
    rate_hz: float

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready summary (the band arrays left out)."""
        return {
            "renderable": self.renderable,
            "verdict": self.verdict,
            "reasons": list(self.reasons),
            "caveats": list(self.caveats),
            "force_limit_n": _finite(self.force_limit),
            "saturation_depth_m": _finite(self.saturation_depth),
            "working_depth_m": _finite(self.working_depth),
            "force_n": self.force,
            "gains": asdict(self.gains),
            "passivity_required_ns_per_m": self.passivity_required,
            "passivity_margin_ns_per_m": self.passivity_margin,
            "spectral_radius": self.spectral_radius,
            "rate_hz": self.rate_hz,
        }

    def lines(self) -> list[str]:
        """A short human report."""
        mm = 1e3
        out = [f"{self.verdict} at {self.rate_hz:g} Hz"]
        sat = (
            f"saturates at {self.saturation_depth * mm:.2f} mm ({self.force_limit:.2f} N)"
            if math.isfinite(self.saturation_depth)
            else "never saturates within the stroke"
        )
        out.append(f"  working depth {self.working_depth * mm:.2f} mm at {self.force:g} N; {sat}")
        i = np.searchsorted(self.depth, [1e-3, 5e-3, 10e-3])
        band = ", ".join(
            f"{self.depth[j] * mm:.0f} mm: {self.k_min[j]:.0f}..{self.k_max[j]:.0f} N/m"
            for j in i
            if j < self.depth.size
        )
        out.append(f"  renderable secant stiffness {band}")
        g = self.gains
        out.append(
            f"  gains Cp {g.Cp:.1f} N/m, Cv {g.Cv:.2f} N s/m ({g.bandwidth_hz:.0f} Hz), "
            f"model mass {g.M * 1e3:.1f} g; loop spectral radius {self.spectral_radius:.4f}"
        )
        out.append(
            f"  passivity (Colgate): needs b > {self.passivity_required:.2f} N s/m, "
            f"margin {self.passivity_margin:+.2f} N s/m"
        )
        out += [f"  refused: {r}" for r in self.reasons]
        out += [f"  caveat: {c}" for c in self.caveats]
        return out


def _finite(value: float) -> float | None:
    return value if math.isfinite(value) else None


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
    f_static = tissue.K * _f0(tissue, depth)
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
        x1, v1 = _free_step(profile, x, v, applied, f_static, dt)
        return np.array([x1, v1, pending, *ctrl.state()])

    s0 = np.array([depth, 0.0, v0, depth, 0.0, 0.0, depth, 0.0, v0])
    n = s0.size
    jac = np.zeros((n, n))
    scale = np.array([1e-3, 1e-2, 0.1, 1e-3, 1e-2, 1.0, 1e-3, 1e-2, 0.1]) * 1e-6
    for j in range(n):
        d = np.zeros(n)
        d[j] = scale[j]
        jac[:, j] = (tick(s0 + d) - tick(s0 - d)) / (2 * scale[j])
    return float(np.max(np.abs(np.linalg.eigvals(jac))))


def _free_step(
    profile: DisplayProfile,
    x: float,
    v: float,
    volts: float,
    force: float,
    dt: float,
    substeps: int = 10,
) -> tuple[float, float]:
    """:func:`piston_step` without end stops or clamping (signed pull), for linearisation."""
    pull = profile.alpha * volts * abs(volts)
    h = dt / substeps
    for _ in range(substeps):
        v += h * (force - profile.Kp * x - pull - profile.b * v) / profile.Mp
        x += h * v
    return x, v


def check(
    tissue: Tissue,
    profile: DisplayProfile = PAPER_DISPLAY,
    rate_hz: float = 1000.0,
    force: float = GRASP_FORCE_N,
) -> CheckResult:
    """Can this display render this tissue at this loop rate, up to ``force``?

    Refused (``renderable`` False) when:

    * the solenoid saturates before the tissue's force reaches ``force`` (the
      band's upper edge ``Kp + alpha v_max^2 / x``): the tissue would give way;
    * the tissue is softer than the display's spring (below ``Kp``, the band's
      lower edge, the solenoid would have to push) over more than
      ``MAX_SOFT_FRACTION`` of its working depth;
    * the working depth exceeds the stroke;
    * the linearised sampled loop is unstable (spectral radius >= 1).

    Caveats (rendered, but not exactly): a part of the depth where the tissue is
    softer than the spring; a model mass raised to the floor; Colgate's passivity
    condition ``b > K T / 2 + |B|`` not met.

    Parameters
    ----------
    tissue : Tissue
        The identified law.
    profile : DisplayProfile
        The display.
    rate_hz : float
        Control-loop rate, Hz.
    force : float
        Force up to which the tissue must be rendered, N (default: the largest
        grasp force measured on liver, 3.4 N).
    """
    tissue.validate()
    profile.validate()
    if not (rate_hz > 0 and math.isfinite(rate_hz)):
        raise InputError(f"loop rate {rate_hz} Hz must be a positive number")
    T = 1.0 / rate_hz
    reasons: list[str] = []
    caveats: list[str] = []
    depth = np.linspace(profile.stroke / 300, profile.stroke, 300)
    with np.errstate(all="ignore"):
        k_tissue = tissue.K * tissue.model.f0(depth) / depth
    k_min = np.full_like(depth, profile.Kp)
    k_max = profile.Kp + profile.max_pull / depth

    x_work = working_depth(tissue, profile, force)
    x_sat = _solve(
        lambda x: tissue.K * _f0(tissue, x) - profile.Kp * x - profile.max_pull,
        0.0,
        profile.stroke,
    )
    f_limit = tissue.K * _f0(tissue, x_sat) if math.isfinite(x_sat) else math.inf
    mm = 1e3
    if not math.isfinite(x_work) or x_work > profile.stroke:
        reasons.append(
            f"at {force:g} N the tissue is deeper than the {profile.stroke * mm:g} mm stroke"
        )
    if f_limit < force:
        x_at = min(x_work, profile.stroke)
        reasons.append(
            f"too stiff: the solenoid saturates at {x_sat * mm:.2f} mm, where the tissue "
            f"pushes {f_limit:.2f} N, below the {force:g} N to render; at {x_at * mm:.2f} mm "
            f"the display renders at most Kp + alpha Vmax^2/x = "
            f"{profile.Kp + profile.max_pull / x_at:.0f} N/m, the tissue needs "
            f"{force / x_at:.0f} N/m"
        )
    x_eval = min(x_work, x_sat, profile.stroke)
    grid = np.linspace(0.0, x_eval, 201)[1:]
    with np.errstate(all="ignore"):
        soft = tissue.K * tissue.model.f0(grid) < profile.Kp * grid
    soft_fraction = float(np.mean(soft)) if grid.size else 1.0
    if soft_fraction > MAX_SOFT_FRACTION:
        reasons.append(
            f"the tissue is softer than the display's spring (Kp = {profile.Kp:.0f} N/m) over "
            f"{soft_fraction:.0%} of its working depth; the solenoid can only pull"
        )
    elif soft_fraction > 0:
        caveats.append(
            f"softer than the display's spring over {soft_fraction:.0%} of the working depth "
            "(near rest): felt as the spring there"
        )

    gains, radius = choose_gains(tissue, profile, rate_hz, x_eval)
    if gains.M > tissue.M:
        caveats.append(
            f"model mass raised from {tissue.M * 1e3:.1f} g to {gains.M * 1e3:.1f} g "
            f"({gains.M / profile.Mp:.0%} of the piston's) to keep the {rate_hz:g} Hz loop "
            "stable: the tissue's inertia is felt heavier"
        )
    sl = _local_slopes(tissue, x_eval)
    k_d = sl["k_hi"] - profile.Kp + gains.Cp
    b_d = sl["s_hi"] + gains.Cv - profile.b
    required = abs(k_d) * T / 2 + abs(b_d)
    margin = profile.b - required
    if margin <= 0:
        caveats.append(
            f"passivity not guaranteed (Colgate: b = {profile.b:g} N s/m <= K T/2 + |B| = "
            f"{required:.2f} N s/m); a stiff grip could feel a buzz"
        )
    if not loop_is_stable(radius, tissue, gains.M, rate_hz):
        reasons.append(
            f"the sampled loop at {rate_hz:g} Hz is unstable (spectral radius {radius:.4f}); "
            "raise the loop rate"
        )
    if reasons:
        verdict = "not renderable"
    elif caveats:
        verdict = "renderable with caveats"
    else:
        verdict = "renderable"
    return CheckResult(
        renderable=not reasons,
        verdict=verdict,
        reasons=reasons,
        caveats=caveats,
        depth=depth,
        k_min=k_min,
        k_max=k_max,
        k_tissue=k_tissue,
        force_limit=f_limit,
        saturation_depth=x_sat,
        working_depth=x_work,
        force=force,
        gains=gains,
        passivity_required=required,
        passivity_margin=margin,
        spectral_radius=radius,
        rate_hz=rate_hz,
    )
