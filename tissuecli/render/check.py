"""Can the display render this tissue? The renderable band, the force limit, the damping
at the speeds of a grasp, the gains, the sampled loop's stability and Colgate's passivity
margin, and a verdict with reasons."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..core.errors import InputError
from ..core.tissue import Tissue
from .gains import choose_gains, loop_is_stable
from .law import FORCE_TOLERANCE_N, Gains, LawParts, local_slopes, split_law
from .profile import PAPER_DISPLAY, DisplayProfile

Array = NDArray[np.float64]

#: Largest grasp force measured on porcine liver (field notes, section 2): a display that
#: saturates below it lets the tissue give way under a firm squeeze.
GRASP_FORCE_N = 3.4
#: Rule for tissues softer than the display's spring near rest (e.g. x^3), and for
#: damping that outweighs the tissue's elastic force on release: refused when the
#: solenoid would have to push over more than this fraction of the working depth.
MAX_SOFT_FRACTION = 0.5
#: Closing and opening speed of the jaws a grasp reaches, m/s. A hand, not the tissue,
#: sets the speed of a grasp: 50 mm/s is the jaw-scale closing speed of the fit's priors
#: (core.terms.FORCEPS_SCALES), and on the offline loop the simulated finger (1-2.5 N presses
#: rising and releasing in 0.25-0.5 s) moves the piston at 30-60 mm/s on liver-like
#: tissues. The damping must be renderable at that speed, closing and opening.
GRASP_SPEED_M_S = 0.05
#: How long a grasp holds, s: the simulated finger holds 0.2-0.8 s between a rise and a
#: release of 0.25-0.5 s each. A tissue with relaxation branches is judged on a grasp
#: closing at the grasp speed from rest, holding this long and opening again.
GRASP_HOLD_S = 1.0


class Grasp:
    """The tissue's rendered force on the check's grasp: closing at ``speed`` (m/s) from
    rest at closure 0, holding :data:`GRASP_HOLD_S`, opening at ``speed``.

    Without relaxation branches the held force is ``E(x)``, closing adds ``D(v) +
    H(x, v)`` and opening ``D(-v) + H(x, -v)``. A branch's state follows its exact
    response (:class:`~tissuecli.render.law.Branch`): ``tau v (1 - exp(-x / (v tau)))``
    on closing to ``x``, times ``exp(-hold / tau)`` after the hold, then on opening
    from ``x_top`` that decays as ``exp(-(x_top - x) / (v tau))`` while
    ``tau v (1 - exp(-(x_top - x) / (v tau)))`` is taken off. All arrays are SI (m, N).
    """

    def __init__(self, parts: LawParts, speed: float, hold: float = GRASP_HOLD_S) -> None:
        self.parts, self.speed, self.hold = parts, speed, hold

    def _ramp(self, tau: float, x: Array) -> Array:
        """A branch's state after closing by ``x`` at the grasp speed from relaxed, m."""
        v = self.speed
        if not v > 0:
            return np.zeros_like(x)
        return tau * v * -np.expm1(-np.maximum(x, 0.0) / (v * tau))

    def held(self, x: Array) -> Array:
        """Force after closing to ``x`` and holding, N: what the static rules use."""
        out = self.parts.elastic(x)
        for br in self.parts.branches:
            out = out + br.Km * self._ramp(br.tau, x) * math.exp(-self.hold / br.tau)
        return out

    def rate_force(self, x: Array) -> Array:
        """Closing at ``x`` less the held force at ``x``, N: the part of the force the
        speed of the grasp adds (damping, friction and the branches' share that relaxes
        within the hold)."""
        return self.closing(x) - self.held(x)

    def closing(self, x: Array) -> Array:
        """Force while closing through ``x``, N."""
        v = self.speed
        out = (
            self.parts.elastic(x)
            + self.parts.damping_force(np.full_like(x, v))
            + self.parts.mixed_force(x, v)
        )
        for br in self.parts.branches:
            out = out + br.Km * self._ramp(br.tau, x)
        return out

    def opening(self, x: Array, top: float) -> Array:
        """Force while opening through ``x`` after a hold at ``top``, N."""
        v = self.speed
        out = (
            self.parts.elastic(x)
            + self.parts.damping_force(np.full_like(x, -v))
            + self.parts.mixed_force(x, -v)
        )
        back = np.maximum(top - x, 0.0)
        for br in self.parts.branches:
            start = self._ramp(br.tau, np.array([top]))[0] * math.exp(-self.hold / br.tau)
            decay = np.exp(-back / (v * br.tau)) if v > 0 else np.ones_like(x)
            out = out + br.Km * (start * decay - self._ramp(br.tau, back))
        return out

    def resting(self, x: Array, top: float) -> Array:
        """What the tissue pushes with at rest at ``x`` after opening from a hold at
        ``top``, less what dry friction can hold, N: where it is not positive, a model
        released there stays (friction) or is drawn deeper (the branches' recovery)."""
        out = self.parts.elastic(x)
        v = self.speed
        back = np.maximum(top - x, 0.0)
        for br in self.parts.branches:
            start = self._ramp(br.tau, np.array([top]))[0] * math.exp(-self.hold / br.tau)
            decay = np.exp(-back / (v * br.tau)) if v > 0 else np.ones_like(x)
            out = out + br.Km * (start * decay - self._ramp(br.tau, back))
        return out - sum(abs(c) for _, c in self.parts.friction)

    def held_at(self, x: float) -> float:
        return float(self.held(np.array([x]))[0])


def finite_or_none(value: float) -> float | None:
    """``value``, or None for an infinity or NaN (JSON has neither)."""
    return value if math.isfinite(value) else None


def working_depth(
    tissue: Tissue,
    profile: DisplayProfile,
    force: float = GRASP_FORCE_N,
    speed: float = GRASP_SPEED_M_S,
) -> float:
    """Depth at which the tissue's held force (:meth:`Grasp.held`) reaches ``force``, m
    (``inf`` if never within twice the stroke)."""
    return _depth(Grasp(split_law(tissue), speed), profile, force)


def _depth(grasp: Grasp, profile: DisplayProfile, force: float) -> float:
    return _solve(lambda x: grasp.held_at(x) - force, 0.0, 2 * profile.stroke)


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
    assumptions : list of str
        How the terms beyond the paper's were judged and rendered (relaxation
        branches, contact, contact damping, dry friction, an offset left out).
    depth : ndarray
        Piston depths of the band, m.
    k_min, k_max : ndarray
        Softest and stiffest secant stiffness ``F / x`` the display can show at each
        depth, N/m: ``Kp`` (solenoid off) and ``Kp + alpha v_max^2 / x``.
    k_tissue : ndarray
        The tissue's secant stiffness ``E(x) / x`` at each depth, N/m.
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
    grasp_speed : float
        Closing and opening speed the damping is judged at, m/s.
    damping_force : float
        The tissue's damping force ``D(v)`` at that speed, N.
    closing_saturation_depth : float
        Depth from which closing at ``grasp_speed`` saturates the solenoid, m
        (``inf`` if nowhere within the working depth).
    release_push_fraction : float
        Fraction of the working depth over which opening at ``grasp_speed`` asks the
        solenoid to push (the tissue's damping outweighs its elastic force less the
        display's spring).
    soft_gap : float
        Where the tissue is softer than the display's spring, the largest gap between
        the tissue's depth and the unpowered piston's under the same force, m, or, if
        larger, how deep the tissue may stay after a release (dry friction, relaxation
        branches: see :func:`_release_gap`): a tracking error the display cannot
        avoid (0 if none).
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
    grasp_speed: float = GRASP_SPEED_M_S
    damping_force: float = 0.0
    closing_saturation_depth: float = math.inf
    release_push_fraction: float = 0.0
    soft_gap: float = 0.0
    assumptions: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready summary (the band arrays left out)."""
        out = {
            "renderable": self.renderable,
            "verdict": self.verdict,
            "reasons": list(self.reasons),
            "caveats": list(self.caveats),
            "assumptions": list(self.assumptions),
            "force_limit_n": self.force_limit,
            "saturation_depth_m": self.saturation_depth,
            "working_depth_m": self.working_depth,
            "force_n": self.force,
            "grasp_speed_m_s": self.grasp_speed,
            "damping_force_n": self.damping_force,
            "closing_saturation_depth_m": self.closing_saturation_depth,
            "release_push_fraction": self.release_push_fraction,
            "soft_gap_m": self.soft_gap,
            "gains": {k: finite_or_none(v) for k, v in asdict(self.gains).items()},
            "passivity_required_ns_per_m": self.passivity_required,
            "passivity_margin_ns_per_m": self.passivity_margin,
            "spectral_radius": self.spectral_radius,
            "rate_hz": self.rate_hz,
        }
        return {k: finite_or_none(v) if isinstance(v, float) else v for k, v in out.items()}

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
        v = self.grasp_speed
        closing = (
            f"saturates closing from {self.closing_saturation_depth * mm:.2f} mm"
            if math.isfinite(self.closing_saturation_depth)
            else "closing never saturates"
        )
        out.append(
            f"  at {v * mm:.0f} mm/s: damping force {self.damping_force:.3g} N; {closing}; "
            f"opening asks a push over {self.release_push_fraction:.0%} of the working depth"
        )
        g = self.gains
        out.append(
            f"  gains Cp {g.Cp:.1f} N/m, Cv {g.Cv:.2f} N s/m ({g.bandwidth_hz:.0f} Hz), "
            f"model mass {g.M * 1e3:.1f} g; loop spectral radius {self.spectral_radius:.4f}"
        )
        out.append(
            f"  passivity (Colgate): needs b > {self.passivity_required:.2f} N s/m, "
            f"margin {self.passivity_margin:+.2f} N s/m"
        )
        out += [f"  assumed: {a}" for a in self.assumptions]
        out += [f"  refused: {r}" for r in self.reasons]
        out += [f"  caveat: {c}" for c in self.caveats]
        return out


def check(
    tissue: Tissue,
    profile: DisplayProfile = PAPER_DISPLAY,
    rate_hz: float = 1000.0,
    force: float = GRASP_FORCE_N,
    speed: float = GRASP_SPEED_M_S,
) -> CheckResult:
    """Can this display render this tissue at this loop rate, up to ``force`` and at the
    speed of a grasp?

    Refused (``renderable`` False) when:

    * the solenoid saturates before the tissue's force reaches ``force`` (the
      band's upper edge ``Kp + alpha v_max^2 / x``): the tissue would give way;
    * the tissue is softer than the display's spring (below ``Kp``, the band's
      lower edge, the solenoid would have to push) over more than
      ``MAX_SOFT_FRACTION`` of its working depth;
    * the damping force alone at the closing ``speed``, less the piston's own
      damping, exceeds the solenoid's pull ``alpha v_max^2``;
    * opening at ``speed``, the damping outweighs the tissue's elastic force less
      the display's spring (the solenoid would have to push) over more than
      ``MAX_SOFT_FRACTION`` of the working depth;
    * the working depth exceeds the stroke;
    * the linearised sampled loop is unstable (spectral radius >= 1), or cannot
      be analysed at all (forces beyond floating point).

    Caveats (rendered, but not exactly): a part of the depth where the tissue is
    softer than the spring, or asks for a push when opening fast; closing fast
    saturating deep in the grasp; a model mass raised to the floor; Colgate's
    passivity condition ``b > K T / 2 + |B|`` not met.

    Any finite tissue gets a verdict: the only exception raised is
    :class:`InputError`, for a tissue, profile, rate, force or speed that is not a
    finite non-negative number.

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
    speed : float
        Closing and opening speed of a grasp, m/s (default 50 mm/s,
        :data:`GRASP_SPEED_M_S`).
    """
    tissue.validate()
    profile.validate()
    for name, value, unit in (("loop rate", rate_hz, "Hz"), ("force", force, "N")):
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            raise InputError(f"{name} {value} {unit} must be a positive number")
    if not (isinstance(speed, (int, float)) and math.isfinite(speed) and speed >= 0):
        raise InputError(f"grasp speed {speed} m/s must be a number >= 0")
    parts = split_law(tissue)
    grasp = Grasp(parts, speed)
    reasons: list[str] = list(parts.refusals)
    caveats: list[str] = []
    with np.errstate(all="ignore"):
        depth, k_min, k_max, k_tissue = _band(grasp, profile)
        x_work, x_sat, f_limit = _limits(grasp, profile, force, reasons)
        x_eval = min(x_work, x_sat, profile.stroke)
        soft, soft_gap = _softness(grasp, profile, x_eval, reasons, caveats)
        soft_gap = max(soft_gap, _release_gap(grasp, x_eval, soft_gap, caveats))
        damping = _damping(grasp, profile, x_eval, soft, reasons, caveats)
        assumptions = _assumptions(grasp, profile, x_eval, caveats)
        if parts.refusals:  # no controller to analyse
            nan = math.nan
            gains = Gains(Cp=nan, Cv=nan, bandwidth_hz=nan, M=max(tissue.mass, 0.0))
            radius = required = math.inf
        else:
            gains, radius, required = _loop(tissue, profile, rate_hz, x_eval, reasons, caveats)
    margin = profile.b - required
    if margin <= 0:
        caveats.append(
            f"passivity not guaranteed (Colgate: b = {profile.b:g} N s/m <= K T/2 + |B| = "
            f"{required:.4g} N s/m); a stiff grip could feel a buzz"
        )
    verdict = (
        "not renderable" if reasons else "renderable with caveats" if caveats else "renderable"
    )
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
        grasp_speed=speed,
        soft_gap=soft_gap,
        assumptions=assumptions,
        **damping,
    )


def _loop(
    tissue: Tissue,
    profile: DisplayProfile,
    rate_hz: float,
    x_eval: float,
    reasons: list[str],
    caveats: list[str],
) -> tuple[Gains, float, float]:
    """Gains, the sampled loop's spectral radius and Colgate's required damping; a
    refusal when the loop is unstable or its analysis overflows."""
    try:
        gains, radius = choose_gains(tissue, profile, rate_hz, x_eval)
        required = _passivity_required(tissue, profile, gains, x_eval, 1.0 / rate_hz)
        stable = loop_is_stable(radius, tissue, gains.M, rate_hz)
        finite = all(math.isfinite(z) for z in (*asdict(gains).values(), radius, required))
    except (ArithmeticError, ValueError, np.linalg.LinAlgError):
        finite = False
    if not finite:
        reasons.append(
            f"the {rate_hz:g} Hz loop cannot be analysed for this tissue: its forces over "
            "the stroke overflow floating point"
        )
        nan = math.nan
        return Gains(Cp=nan, Cv=nan, bandwidth_hz=nan, M=max(tissue.mass, 0.0)), math.inf, math.inf
    if gains.M > tissue.mass:
        caveats.append(
            f"model mass raised from {tissue.mass * 1e3:.3g} g to {gains.M * 1e3:.3g} g "
            f"({gains.M / profile.Mp:.0%} of the piston's) to keep the {rate_hz:g} Hz loop "
            "stable: the tissue's inertia is felt heavier"
        )
    if not stable:
        reasons.append(
            f"the sampled loop at {rate_hz:g} Hz is unstable (spectral radius {radius:.6g}); "
            "raise the loop rate"
        )
    return gains, radius, required


def _damping(
    grasp: Grasp,
    profile: DisplayProfile,
    x_eval: float,
    soft_fraction: float,
    reasons: list[str],
    caveats: list[str],
) -> dict[str, float]:
    """The pull the law asks for at the speed of a grasp, closing and opening.

    With the piston at depth ``x`` moving at ``v`` and the model tracking it, the law
    asks for ``u = F(x, v) - Kp x - b v`` with ``F`` the tissue's force on the grasp
    (:class:`Grasp`; ``E(x) + D(v)`` for the paper's laws). Closing (``v = speed``) it
    must stay within the solenoid's pull; opening (``v = -speed``) it must not ask for a
    push (``u < 0``), which the solenoid cannot give. The force the speed adds alone
    (``F`` closing less the held force: damping, and the share of the relaxation
    branches that relaxes within a hold) must not exceed the pull over more than
    :data:`MAX_SOFT_FRACTION` of the working depth (for the paper's laws: anywhere).
    """
    mm = 1e3
    speed = grasp.speed
    pull = profile.max_pull
    own = profile.b * speed  # the piston's own damping, which the law subtracts
    grid = np.linspace(0.0, x_eval, 201)[1:] if math.isfinite(x_eval) else np.zeros(0)
    spring = profile.Kp * grid
    closing = grasp.closing(grid) - spring - own
    opening = grasp.opening(grid, x_eval if grid.size else 0.0) - spring + own
    rate = grasp.rate_force(grid) if grid.size else grasp.rate_force(np.zeros(1))
    damping_force = float(np.max(rate)) if np.all(rate == rate) else math.nan
    above = np.nonzero(~(closing <= pull))[0]  # NaN counts as saturated
    x_close = float(grid[above[0]]) if above.size else math.inf
    push = float(np.mean(~(opening >= -FORCE_TOLERANCE_N))) if grid.size else 0.0
    rate_over = float(np.mean(~(rate - own <= pull)))
    v = f"{speed * mm:g} mm/s"
    if rate_over > MAX_SOFT_FRACTION or not damping_force == damping_force:
        where = "" if rate_over == 1.0 else f" over {rate_over:.0%} of the working depth"
        reasons.append(
            f"damping too strong: closing at {v} (the speed of a grasp) the tissue's damping "
            f"alone is {damping_force:.3g} N{where}, more than the solenoid's {pull:.3g} N pull"
        )
    elif math.isfinite(x_close):
        caveats.append(
            f"closing at {v} saturates the solenoid from {x_close * mm:.2f} mm: a fast "
            "grasp feels softer there"
        )
    if push > MAX_SOFT_FRACTION >= soft_fraction:  # else softness alone is the reason
        reasons.append(
            f"damping outweighs the tissue's spring on release: opening at {v} the solenoid "
            f"would have to push over {push:.0%} of the working depth (it can only pull)"
        )
    elif soft_fraction < push <= MAX_SOFT_FRACTION:
        caveats.append(
            f"opening at {v} asks the solenoid to push over {push:.0%} of the working depth: "
            "a fast release feels the display's spring there"
        )
    return {
        "damping_force": damping_force,
        "closing_saturation_depth": x_close,
        "release_push_fraction": push,
    }


def _band(grasp: Grasp, profile: DisplayProfile) -> tuple[Array, Array, Array, Array]:
    """Depths (m) and, at each, the softest and stiffest secant stiffness the display can
    show and the tissue's own (held force over depth, N/m)."""
    depth = np.linspace(profile.stroke / 300, profile.stroke, 300)
    with np.errstate(all="ignore"):
        k_tissue = grasp.held(depth) / depth
    return depth, np.full_like(depth, profile.Kp), profile.Kp + profile.max_pull / depth, k_tissue


def _limits(
    grasp: Grasp, profile: DisplayProfile, force: float, reasons: list[str]
) -> tuple[float, float, float]:
    """Working depth at ``force``, saturation depth (m) and the force at saturation (N),
    all of the held force; refusals for a tissue deeper than the stroke or stiffer than
    the solenoid can hold."""
    x_work = _depth(grasp, profile, force)
    x_sat = _solve(
        lambda x: grasp.held_at(x) - profile.Kp * x - profile.max_pull,
        0.0,
        profile.stroke,
    )
    f_limit = grasp.held_at(x_sat) if math.isfinite(x_sat) else math.inf
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
    return x_work, x_sat, f_limit


def _softness(
    grasp: Grasp,
    profile: DisplayProfile,
    x_eval: float,
    reasons: list[str],
    caveats: list[str],
) -> tuple[float, float]:
    """Where the tissue is softer than the display's spring, the solenoid would have to
    push: the fraction of the working depth where it is, and the largest gap there
    between the tissue's depth and the unpowered piston's under the same force, m."""
    grid = np.linspace(0.0, x_eval, 201)[1:]
    with np.errstate(all="ignore"):
        force = grasp.held(grid)
    soft = force < profile.Kp * grid
    soft_fraction = float(np.mean(soft)) if grid.size else 1.0
    # under the force that holds the tissue at x, the unpowered piston sits at F / Kp
    gap = grid[soft] - force[soft] / profile.Kp
    soft_gap = float(np.max(gap)) if gap.size and np.all(np.isfinite(gap)) else 0.0
    if soft_fraction > MAX_SOFT_FRACTION:
        reasons.append(
            f"the tissue is softer than the display's spring (Kp = {profile.Kp:.0f} N/m) over "
            f"{soft_fraction:.0%} of its working depth; the solenoid can only pull"
        )
    elif soft_fraction > 0:
        caveats.append(
            f"softer than the display's spring over {soft_fraction:.0%} of the working depth "
            f"(near rest): felt as the spring there, the piston up to {soft_gap * 1e3:.2f} mm "
            "shallower than the tissue"
        )
    return soft_fraction, soft_gap


def _release_gap(grasp: Grasp, x_eval: float, soft_gap: float, caveats: list[str]) -> float:
    """How deep the tissue may stay after a grasp's release (dry friction holding it, or
    relaxation branches drawing it back in while they recover), m: the deepest closure
    of the working depth where :meth:`Grasp.resting` is not positive. The piston, which
    the solenoid cannot push, returns to rest meanwhile: a tracking error no controller
    can avoid, added to the soft gap."""
    parts = grasp.parts
    if not (parts.friction or parts.branches) or not math.isfinite(x_eval) or x_eval <= 0:
        return 0.0
    grid = np.linspace(0.0, x_eval, 201)[1:]
    held = ~(grasp.resting(grid, x_eval) > 0)
    gap = float(grid[held].max()) if held.any() else 0.0
    if gap > soft_gap:
        why = " and ".join(
            w
            for w, on in (
                ("dry friction holds it", parts.friction),
                ("its relaxation branches draw it back while they recover", parts.branches),
            )
            if on
        )
        caveats.append(
            f"after a release the tissue may stay up to {gap * 1e3:.2f} mm deep ({why}) "
            "while the piston, which the solenoid cannot push, returns to rest: a tracking "
            "error of that size"
        )
    return gap


def _assumptions(
    grasp: Grasp, profile: DisplayProfile, x_eval: float, caveats: list[str]
) -> list[str]:
    """What the check and the controller assumed of the terms beyond the paper's, one
    sentence each; a caveat when a long hold relaxes the tissue below the display's
    spring."""
    parts, mm = grasp.parts, 1e3
    out = []
    x_end = x_eval if math.isfinite(x_eval) and x_eval > 0 else profile.stroke
    grid = np.linspace(0.0, x_end, 201)[1:]
    if parts.branches:
        k_eq = float(np.min(parts.stiffness(grid))) if grid.size else 0.0
        branches = ", ".join(
            f"Km{i} = {br.Km:.4g} N/m (tau{i} = {br.tau:.4g} s)"
            for i, br in enumerate(parts.branches, 1)
        )
        out.append(
            f"relaxation branches {branches}: each carried as a state in the reference "
            "model and in the pull (exact recursion every control step); instantaneous "
            f"stiffness adds {parts.instantaneous:.4g} N/m to the springs' "
            f"{k_eq:.4g} N/m (equilibrium); the force limit, working depth and softness "
            f"use the force after closing at {grasp.speed * mm:g} mm/s and holding "
            f"{grasp.hold:g} s, closing and opening the branches' exact response"
        )
        relaxed = parts.elastic(grid) < profile.Kp * grid
        if grid.size and np.mean(relaxed) > MAX_SOFT_FRACTION:
            caveats.append(
                "held much longer than the branches' time constants the tissue relaxes to "
                f"its springs alone, softer than the display's spring over "
                f"{np.mean(relaxed):.0%} of the working depth: a long hold feels the spring"
            )
    for t, c in parts.position:
        if t.name == "contact":
            n, x0 = t.shape["n"], t.shape["x0"]
            d = max(x_end - x0, 0.0)
            k_end = n * c * d ** (n - 1) if d > 0 else 0.0
            out.append(
                f"contact Kc d^n from x0 = {x0 * mm:.3g} mm (n = {n:.3g}): local stiffness "
                f"n Kc d^(n-1), {k_end:.4g} N/m at {x_end * mm:.2f} mm"
                + (", unbounded at the contact point (the gains take it from 1 % of the "
                   "working depth)" if n < 1 else "")
            )  # fmt: skip
    for t, _ in parts.mixed:
        _, s_end = parts.mixed_slopes(np.array([x_end]), grasp.speed)
        out.append(
            f"contact damping {t.symbol} d^n xdot at the piston's closure and speed: "
            f"{float(s_end[0]):.4g} N s/m at {x_end * mm:.2f} mm, none before contact"
        )
    for t, c in parts.friction:
        out.append(
            f"dry friction {t.symbol} = {c:.4g} N carried by the reference model alone "
            f"(its slope at rest, {t.symbol} / 1 mm/s, is beyond what the loop renders as "
            "damping); the piston follows the model's stick and slip"
        )
    for t, c in parts.unrendered:
        out.append(
            f"{t.name} {t.symbol} = {c:.4g} {t.unit} not rendered (a sensor's, not the tissue's)"
        )
    return out


def _passivity_required(
    tissue: Tissue, profile: DisplayProfile, gains: Gains, depth: float, period: float
) -> float:
    """Colgate's ``K_d T / 2 + |B_d|`` (N s/m) with the digitally rendered stiffness
    ``K_d = max k - Kp + Cp`` and damping ``B_d = max s + Cv - b``."""
    sl = local_slopes(tissue, depth)
    k_d = sl["k_hi"] - profile.Kp + gains.Cp
    b_d = sl["s_hi"] + gains.Cv - profile.b
    return abs(k_d) * period / 2 + abs(b_d)
