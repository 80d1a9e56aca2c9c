"""Randomised scenes with known truth: a tissue, how it was moved, how it was sensed.

A :class:`Scene` is one session as a lab would record it together with everything that
made it: the true law and coefficients, the noise-free force at every sample, the true
kinematics, and the settings drawn (rate, ADC bits, noise, contact, excitation). The
generalisation benchmark and the protocol stress suite draw their sessions here, and
the tests draw theirs from the same functions.

:func:`random_scene` draws over a wide space: every family the package simulates (the
paper's four forms, hardening, friction, offsets, Hunt-Crossley contact, one and two
relaxation branches), 250 Hz to 10 kHz, 8 to 16 bits, force noise 0.5 to 10 % of the
force range, continuous contact or grasps separated by free jaw motion, sessions of 3
to 60 s, excitations from slow squeezes to fast taps.

:func:`render` turns any motion (anything with ``kinematics(t) -> (x, v, a)``) and a
tissue into a scene; :mod:`~tissuecli.sim.protocols` uses it for lab protocols.

The truth is physical: the force is zero while the jaws are open (closure <= 0), a
relaxation branch is driven by the indentation ``max(x, 0)`` (integrated exactly on a
grid eight times finer than the samples), and an offset is the force sensor's, so it
is there in free motion too.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from ..core.calibration import Adc, Calibration, Channel
from ..core.session import Session
from ..core.terms import Law, relaxation
from ..core.tissue import Tissue
from .synth import GraspingOperator, Operator

Array = NDArray[np.float64]

#: fine steps per sample for the relaxation branches' integration
SUBSTEPS = 8

#: the families a random scene is drawn from: the terms of each law, and its weight
FAMILIES: dict[str, tuple[tuple[str, ...], float]] = {
    "paper x+xdot": (("x", "xdot", "xddot"), 0.1),
    "paper x+xdot|xdot|": (("x", "xdot|xdot|", "xddot"), 0.1),
    "paper x^3+xdot": (("x^3", "xdot", "xddot"), 0.1),
    "paper x^3+xdot|xdot|": (("x^3", "xdot|xdot|", "xddot"), 0.1),
    "hardening": (("x", "x^3", "xdot", "xddot"), 0.6 / 7),
    "friction": (("x", "xdot", "sign(xdot)", "xddot"), 0.6 / 7),
    "offset": (("x", "xdot", "xddot", "offset"), 0.6 / 7),
    "friction+offset": (("x", "xdot", "sign(xdot)", "xddot", "offset"), 0.6 / 7),
    "Hunt-Crossley": (("contact", "contact*xdot", "xddot"), 0.6 / 7),
    "one branch": (("x", "maxwell", "xdot", "xddot"), 0.6 / 7),
    "two branches": (("x", "maxwell", "maxwell", "xdot", "xddot"), 0.6 / 7),
}

#: a term below this detectability (its force's RMS over the noise SD, times the
#: square root of the independent samples) counts as not excited: either choice is right
DETECTABLE = 5.0

#: the power of the closure scale in each term's regressor (a change of length unit
#: scales its coefficient by the inverse); contact terms add their exponent
LENGTH_POWER = {
    "x": 1.0, "x^3": 3.0, "xdot": 1.0, "xdot|xdot|": 2.0, "sign(xdot)": 0.0,
    "xddot": 1.0, "offset": 0.0, "maxwell": 1.0, "contact": 0.0, "contact*xdot": 1.0,
}  # fmt: skip


class Motion(Protocol):
    """Anything that gives exact closure (m), velocity (m/s) and acceleration (m/s^2)."""

    def kinematics(self, t: Array) -> tuple[Array, Array, Array]: ...


@dataclass(frozen=True)
class Scene:
    """One session with its truth.

    Attributes
    ----------
    session : Session
        What was measured, in the session's units (force ``units[0]`` N, closure
        ``units[1]`` m per unit).
    tissue : Tissue
        The true law and coefficients, SI.
    force : ndarray, shape (n,)
        The true noise-free force at every sample, in the session's force unit.
    x, v, a : ndarray, shape (n,)
        The true closure, velocity and acceleration, SI.
    noise_n : float
        SD of the force noise before quantisation, SI (N).
    settings : dict
        What was drawn: family, rate, bits, contact, excitation, duration...
    units : (float, float)
        Factors from SI to the session's force and closure units (1, 1 for SI).
    indistinct : tuple of frozenset
        Terms whose columns this design cannot tell apart (count as one).
    unexcited : frozenset
        Terms the design does not excite: present or absent, a choice is right.
    visible_branches : int, optional
        How many of the truth's relaxation branches stand above the noise beside its
        other terms (:func:`branch_detectability`): a law with between that many and
        the truth's count is right. None: all of them, or none if ``"maxwell"`` is
        unexcited.
    """

    session: Session
    tissue: Tissue
    force: Array
    x: Array
    v: Array
    a: Array
    noise_n: float
    settings: dict[str, Any] = field(default_factory=dict)
    units: tuple[float, float] = (1.0, 1.0)
    indistinct: tuple[frozenset[str], ...] = ()
    unexcited: frozenset[str] = frozenset()
    visible_branches: int | None = None

    @property
    def family(self) -> str:
        return str(self.settings.get("family", self.tissue.law.name))

    @property
    def coefficients(self) -> Array:
        """The true coefficients in the session's units, shape (p,)."""
        cf, cx = self.units
        return np.array(
            [
                c * cf / cx ** _length_power(t.name, t.shape)
                for t, c in zip(self.tissue.law.terms, self.tissue.coef, strict=True)
            ]
        )

    @property
    def shapes(self) -> dict[str, float]:
        """The true shape parameters in the session's units (contact points scale with
        the closure unit; exponents and time constants do not)."""
        cx = self.units[1]
        return {k: v * cx if k == "x0" else v for k, v in self.tissue.law.shape.items()}

    def classes(self, names: Sequence[str]) -> frozenset[str]:
        """The distinguishable classes of ``names`` on this design: each name replaced by
        the first of its indistinct set (sorted), unexcited terms dropped."""
        out = set()
        for n in names:
            if n in self.unexcited:
                continue
            group = next((g for g in self.indistinct if n in g), None)
            out.add(min(group) if group else n)
        return frozenset(out)

    def right(self, law: Law) -> bool:
        """Whether ``law`` has the truth's structure, as far as this design can tell."""
        truth = [t.name for t in self.tissue.law.terms]
        n, top = _branches(law), _branches(self.tissue.law)
        if self.visible_branches is not None:
            if not self.visible_branches <= n <= top:
                return False
        elif n != top and "maxwell" not in self.unexcited:
            return False
        return self.classes([t.name for t in law.terms]) == self.classes(truth)

    def judged_on(self, n: int) -> Scene:
        """The scene as a fit of its first ``n`` samples can tell it: the terms whose
        force stands below the noise over those samples (:func:`detectability`) are
        unexcited, and the branches counted visible are those that stand above it
        beside the law's other terms there (:func:`branch_detectability`).

        A benchmark that fits the head of a session and holds out the rest scores the
        chosen law against this: a term only the held-out part excites is not one the
        fit could have found."""
        rate = float(self.settings.get("rate_hz", 0.0)) or 1.0 / float(
            np.median(np.diff(self.session.time[: max(n, 2)]))
        )
        x, v, a = self.x[:n], self.v[:n], self.a[:n]
        snr = detectability(self.tissue, x, v, a, rate, self.noise_n)
        branches = branch_detectability(self.tissue, x, v, a, rate, self.noise_n)
        visible = None
        if branches:
            snr["maxwell"] = branches[0]
            visible = sum(b >= DETECTABLE for b in branches)
        weak = frozenset(k for k, s in snr.items() if s < DETECTABLE)
        return replace(self, unexcited=weak, visible_branches=visible,
                       settings={**self.settings, "detectability": snr,
                                 "branch_detectability": branches})  # fmt: skip

    def within_truth(self, law: Law) -> bool:
        """Whether ``law`` uses only terms the truth is written with (indistinct columns
        count as one, unexcited ones are free)."""
        truth = self.classes([t.name for t in self.tissue.law.terms])
        if _branches(law) > _branches(self.tissue.law):
            return False
        return self.classes([t.name for t in law.terms]) <= truth

    def describe(self) -> str:
        s = self.settings
        keys = ("family", "rate_hz", "bits", "quantisation", "noise_frac", "contact",
                "excitation", "duration_s")  # fmt: skip
        parts = [f"{k}={_fmt(s[k])}" for k in keys if k in s]
        return " ".join(parts)


def _fmt(v: Any) -> str:
    return f"{v:.4g}" if isinstance(v, float) else str(v)


def _branches(law: Law) -> int:
    return sum(1 for t in law.terms if t.memory)


def _length_power(name: str, shape: dict[str, float]) -> float:
    power = LENGTH_POWER.get(name, 1.0)
    if name.startswith("contact"):
        power += shape.get("n", 1.0)
    return power


def true_force(
    tissue: Tissue, motion: Motion, t: Array, *, gate: bool = True
) -> tuple[Array, Array, Array, Array]:
    """The true kinematics and noise-free force of ``tissue`` moved by ``motion`` at the
    uniformly spaced times ``t`` (s).

    Parameters
    ----------
    gate : bool
        The jaws touch the tissue at closure 0: no tissue force below it, and
        relaxation branches see the indentation ``max(x, 0)``. The offset (the
        sensor's) is there throughout.

    Returns
    -------
    x, v, a, force : ndarray, shape (n,)
        m, m/s, m/s^2, N.
    """
    t = np.asarray(t, dtype=float)
    x, v, a = motion.kinematics(t)
    law, coef = tissue.law, tissue.coef
    f = np.zeros_like(x)
    offset = 0.0
    for term, c in zip(law.terms, coef, strict=True):
        if term.name == "offset":
            offset += c
        elif not term.memory:
            f += c * term.regressor(x, v, a)
    if law.memory and t.size:
        dt = float(t[1] - t[0]) if t.size > 1 else 1.0
        fine = t[0] + np.arange((t.size - 1) * SUBSTEPS + 1) * (dt / SUBSTEPS)
        xf = motion.kinematics(fine)[0]
        if gate:
            xf = np.maximum(xf, 0.0)
        for term, c in zip(law.terms, coef, strict=True):
            if term.memory:
                f += c * relaxation(xf, dt / SUBSTEPS, term.tau)[0][::SUBSTEPS]  # type: ignore[attr-defined]
    if gate:
        f = np.where(x > 0, f, 0.0)
    return x, v, a, f + offset


def render(
    tissue: Tissue,
    motion: Motion,
    *,
    rate_hz: float,
    duration_s: float,
    rng: np.random.Generator,
    noise_frac: float,
    position_noise_frac: float = 2e-4,
    quantisation: str | int = 16,
    units: tuple[float, float] = (1.0, 1.0),
    gate: bool = True,
    settings: dict[str, Any] | None = None,
    indistinct: tuple[frozenset[str], ...] = (),
    unexcited: frozenset[str] = frozenset(),
    truth: tuple[Array, Array, Array, Array] | None = None,
) -> Scene:
    """A scene: ``tissue`` moved by ``motion``, sampled at ``rate_hz`` for ``duration_s``.

    Parameters
    ----------
    noise_frac : float
        SD of the force noise over the true force's range (peak to peak).
    position_noise_frac : float
        SD of the closure noise over the closure's range.
    quantisation : int or {"float64", "float32"}
        An ADC of this many bits whose range spans the signal with a margin (the
        session knows it, as a recording does); or exported floats.
    units : (float, float)
        The session's force and closure in these multiples of SI values
        (``(1e3, 1e6)``: mN and um).
    truth : tuple, optional
        ``(x, v, a, force)`` already computed (a force-controlled protocol).
    """
    n = max(int(round(duration_s * rate_hz)), 2)
    t = np.arange(n) / rate_hz
    x, v, a, f = truth if truth is not None else true_force(tissue, motion, t, gate=gate)
    span_f = float(np.ptp(f)) or max(abs(float(f[0])), 1e-12)
    span_x = float(np.ptp(x)) or max(abs(float(x[0])), 1e-12)
    sd_f = noise_frac * span_f
    sd_x = position_noise_frac * span_x
    fm = f + rng.normal(0.0, sd_f, n)
    xm = x + rng.normal(0.0, sd_x, n)
    cf, cx = units
    adc = None
    meta: dict[str, Any] = {"source": "synthetic", "rate_hz": rate_hz}
    if isinstance(quantisation, int):
        bits = quantisation
        margin_f, margin_x = 0.1 * span_f + 6 * sd_f, 0.1 * span_x + 6 * sd_x
        cal = Calibration(
            force=Channel.spanning(cf * (f.min() - margin_f), cf * (f.max() + margin_f), bits, "N"),
            position=Channel.spanning(
                cx * (x.min() - margin_x), cx * (x.max() + margin_x), bits, "m"
            ),
        )
        force_s = cal.force.to_si(cal.force.to_counts(cf * fm, bits))
        position_s = cal.position.to_si(cal.position.to_counts(cx * xm, bits))
        adc = Adc(bits, cal)
        meta["device"] = {"adc_bits": bits, "calibration": cal.as_dict()}
    else:
        force_s, position_s = cf * fm, cx * xm
        if quantisation == "float32":
            force_s = force_s.astype(np.float32).astype(float)
            position_s = position_s.astype(np.float32).astype(float)
            t = t.astype(np.float32).astype(float)
        elif quantisation != "float64":
            raise ValueError(f"quantisation {quantisation!r}: bits, 'float32' or 'float64'")
    session = Session(t, force_s, position_s, name="scene", meta=meta, adc=adc)
    info = {"rate_hz": float(rate_hz), "duration_s": float(duration_s), "noise_frac": noise_frac,
            "quantisation": quantisation, "bits": quantisation if adc else None,
            **(settings or {})}  # fmt: skip
    scene = Scene(
        session=session,
        tissue=tissue,
        force=cf * f,
        x=x,
        v=v,
        a=a,
        noise_n=sd_f,
        settings=info,
        units=units,
        indistinct=indistinct,
        unexcited=unexcited,
    )
    return scene


def detectability(tissue: Tissue, x: Array, v: Array, a: Array, rate_hz: float,
                  noise_n: float, gate: bool = True) -> dict[str, float]:  # fmt: skip
    """How far above the noise each term's force stands: its RMS over the noise SD times
    the square root of the independent samples (a bandwidth of 25 Hz, or the samples'
    count if fewer). A term below :data:`DETECTABLE` cannot be told from its absence."""
    n = x.size
    independent = min(n, 50.0 * n / rate_hz)
    out: dict[str, float] = {}
    dt = 1.0 / rate_hz
    xs = np.maximum(x, 0.0) if gate else x
    for term, c in zip(tissue.law.terms, tissue.coef, strict=True):
        col = term.series(dt, xs, v, a) if term.memory else term.regressor(x, v, a)
        if gate:
            col = np.where(x > 0, col, 0.0) if term.name != "offset" else col
        rms = abs(c) * float(np.sqrt(np.mean(col**2)))
        snr = rms / max(noise_n, 1e-300) * math.sqrt(independent)
        out[term.name] = max(out.get(term.name, 0.0), snr) if term.memory else snr
    return out


def branch_detectability(tissue: Tissue, x: Array, v: Array, a: Array, rate_hz: float,
                         noise_n: float, gate: bool = True) -> list[float]:  # fmt: skip
    """How far above the noise each relaxation branch's force stands where the law's
    other terms cannot stand in for it, strongest first (as :func:`detectability`).

    A branch whose time constant is far below the motion's time scales is a damper
    (``tau v``) and one far above the session's length a spring (``x``): the law's
    own damping and stiffness then carry its force, and no recording of that motion
    can tell the law with the branch from the law without it. So each branch's force
    is taken less its least-squares part on the columns of the law's terms without
    memory and of the branches counted before it (the strongest first)."""
    n = x.size
    independent = min(n, 50.0 * n / rate_hz)
    dt = 1.0 / rate_hz
    xs = np.maximum(x, 0.0) if gate else x
    touching = x > 0 if gate else np.ones(n, bool)
    base, forces = [], []
    for term, c in zip(tissue.law.terms, tissue.coef, strict=True):
        if term.memory:
            col = term.series(dt, xs, v, a)
            forces.append(c * (np.where(touching, col, 0.0) if gate else col))
        else:
            col = term.regressor(x, v, a)
            base.append(np.where(touching, col, 0.0) if gate and term.name != "offset" else col)
    out: list[float] = []
    remaining = list(forces)
    while remaining:
        B = np.column_stack(base) if base else np.zeros((n, 0))
        scores = []
        for f in remaining:
            r = f - B @ np.linalg.lstsq(B, f, rcond=None)[0] if B.shape[1] else f
            scores.append(float(np.sqrt(np.mean(r**2))) / max(noise_n, 1e-300))
        k = int(np.argmax(scores))
        out.append(scores[k] * math.sqrt(independent))
        base.append(remaining.pop(k))
    return out


def _log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def _choose_family(rng: np.random.Generator, families: Sequence[str] | None) -> str:
    names = list(families) if families else list(FAMILIES)
    w = np.array([FAMILIES[n][1] for n in names])
    return names[int(rng.choice(len(names), p=w / w.sum()))]


def random_scene(
    seed: int,
    *,
    families: Sequence[str] | None = None,
    max_samples: int = 200_000,
    noise_seed: int | None = None,
    **fixed: Any,
) -> Scene:
    """One scene drawn from the wide space (see the module's docstring).

    Parameters
    ----------
    seed : int
        Everything is drawn from it: the same seed gives the same scene.
    families : list of str, optional
        Draw among these names of :data:`FAMILIES` only.
    max_samples : int
        The session is cut shorter where it would have more samples.
    noise_seed : int, optional
        Draw the force and position noise from this seed instead: the same tissue,
        motion and settings under another realisation of the noise.
    **fixed
        Settings to impose rather than draw: ``family``, ``rate_hz``, ``bits``,
        ``noise_frac``, ``contact`` (``"continuous"`` or ``"grasps"``), ``tempo``,
        ``duration_s``, ``force_span_n``.
    """
    rng = np.random.default_rng(seed)
    draw: dict[str, Any] = {
        "family": _choose_family(rng, families),
        "rate_hz": _log_uniform(rng, 250.0, 10_000.0),
        "bits": int(rng.integers(8, 17)),
        "noise_frac": _log_uniform(rng, 0.005, 0.10),
        "contact": "grasps" if rng.random() < 0.5 else "continuous",
        "tempo": _log_uniform(rng, 0.25, 4.0),
        "duration_s": _log_uniform(rng, 3.0, 60.0),
        "force_span_n": _log_uniform(rng, 0.2, 20.0),
        "amplitude": _log_uniform(rng, 0.3, 2.0),
    }
    unknown = set(fixed) - set(draw)
    if unknown:
        raise TypeError(f"unknown settings {sorted(unknown)}; choose among {sorted(draw)}")
    draw.update(fixed)
    names = FAMILIES[draw["family"]][0]
    tempo = float(draw["tempo"])
    base = Operator()
    amp = float(draw["amplitude"])
    amps = tuple(a * amp * rng.uniform(0.7, 1.3) for a in base.amplitudes_m)
    freqs = tuple(f * tempo * rng.uniform(0.8, 1.25) for f in base.frequencies_hz)
    phases = tuple(float(p) for p in rng.uniform(0, 2 * np.pi, len(amps)))
    squeeze = Operator(sum(amps) * 1.1, amps, freqs, phases)
    motion: Motion = squeeze
    duration = float(draw["duration_s"])
    rate = float(draw["rate_hz"])
    if draw["contact"] == "grasps":
        grasp_s = float(np.clip(rng.uniform(1.0, 3.0) / math.sqrt(tempo), 0.5, 4.0))
        free_s = rng.uniform(0.3, 1.0)
        # three and a half grasps at least, quicker ones where the samples run short
        fit = min(1.0, max_samples / rate / (3.5 * (grasp_s + free_s)))
        grasp_s, free_s = grasp_s * fit, free_s * fit
        motion = GraspingOperator(
            squeeze=squeeze,
            grasp_s=grasp_s,
            free_s=free_s,
            ramp_s=0.1 * grasp_s,
            open_m=rng.uniform(0.5e-3, 3e-3),
        )
        duration = max(duration, 3.5 * (grasp_s + free_s))
    duration = min(duration, max_samples / rate)
    draw["duration_s"] = duration
    draw["excitation"] = (
        "slow squeeze" if tempo < 0.6 else "fast taps" if tempo > 2.0 else "squeeze"
    )
    n = max(int(round(duration * rate)), 2)
    t = np.arange(n) / rate
    x, v, a = motion.kinematics(t)
    tissue = _coefficients(names, x, v, a, rate, duration, float(draw["force_span_n"]), rng)
    position_noise_frac = _log_uniform(rng, 1e-4, 1e-3)
    scene = render(
        tissue,
        motion,
        rate_hz=rate,
        duration_s=duration,
        rng=rng if noise_seed is None else np.random.default_rng(noise_seed),
        noise_frac=float(draw["noise_frac"]),
        position_noise_frac=position_noise_frac,
        quantisation=int(draw["bits"]),
        settings={**draw, "seed": seed},
    )
    return scene.judged_on(len(scene.session))


def _coefficients(
    names: Sequence[str],
    x: Array,
    v: Array,
    a: Array,
    rate_hz: float,
    duration_s: float,
    span_n: float,
    rng: np.random.Generator,
) -> Tissue:
    """Coefficients for a law of ``names`` on these kinematics: the stiffness spans
    ``span_n``; damping, friction and contact damping each add 5-40 % of the stiffness
    force's RMS (so that each is there to be found); the mass is a forceps' (20-100 g);
    each branch is 0.3-1.5 times the spring, its time constant within what the fitted
    part resolves."""
    touching = x > 0
    shape: dict[str, float] = {}
    if "contact" in names:
        lo, hi = float(x[touching].min()), float(x.max())
        shape["x0"] = lo + rng.uniform(0.1, 0.4) * (hi - lo)
        shape["n"] = rng.uniform(1.2, 2.5)
    branches = sum(1 for n in names if n == "maxwell")
    if branches:
        lo = max(0.03, 20.0 / rate_hz)
        hi = max(min(3.0, 0.7 * duration_s / 6.0), 1.5 * lo)
        if branches == 1:
            shape["tau1"] = _log_uniform(rng, lo, hi)
        else:
            t1 = _log_uniform(rng, lo, max(hi / 8.0, lo * 1.01))
            shape["tau1"] = t1
            shape["tau2"] = t1 * _log_uniform(rng, 8.0, max(hi / t1, 8.01))
    law = Law.of(names)
    law = law.bind(shape) if law.shape_names else law
    cols = {}
    dt = 1.0 / rate_hz
    xs = np.maximum(x, 0.0)
    for i, term in enumerate(law.terms):
        col = term.series(dt, xs, v, a) if term.memory else term.regressor(x, v, a)
        cols[i] = np.where(touching, col, 0.0)
    stiff = [i for i, t in enumerate(law.terms) if t.role == "stiffness"]
    coef = np.zeros(len(law.terms))
    # stiffness: the first term carries the span, a second adds 30-100 % of it
    for k, i in enumerate(stiff):
        share = 1.0 if k == 0 else rng.uniform(0.3, 1.0)
        coef[i] = share * span_n / max(float(np.ptp(cols[i])), 1e-300)
    spring = sum((coef[i] * cols[i] for i in stiff), np.zeros_like(x))
    k_linear = coef[stiff[0]] if law.terms[stiff[0]].name == "x" else None
    rms = float(np.sqrt(np.mean(spring**2))) or span_n
    for i, term in enumerate(law.terms):
        col = cols[i]
        if term.memory:
            ref = k_linear if k_linear is not None else span_n / max(float(np.ptp(x)), 1e-12)
            coef[i] = ref * rng.uniform(0.3, 1.5)
        elif term.role in ("damping", "friction"):
            share = _log_uniform(rng, 0.05, 0.4)
            coef[i] = share * rms / max(float(np.sqrt(np.mean(col**2))), 1e-300)
        elif term.role == "inertia":
            coef[i] = _log_uniform(rng, 0.02, 0.1)
        elif term.role == "offset":
            coef[i] = rng.uniform(-0.3, 0.3) * span_n
    return Tissue(law, *coef)


def scenes(seed: int, count: int, **kwargs: Any) -> list[Scene]:
    """``count`` scenes from one seed (scene i draws from ``seed + i``)."""
    return [random_scene(seed + i, **kwargs) for i in range(count)]


#: callable type of a protocol or scene factory: seed to scene
SceneFactory = Callable[[int], Scene]
