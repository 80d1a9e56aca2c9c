"""Lab protocols with known truth: what mechanical testing machines run on a specimen.

Each protocol is a function ``(rng, **settings) -> Scene`` in :data:`PROTOCOLS`:
constant-speed ramps (linear, stiffening, with a load-cell offset, damped), loading-
unloading triangle cycles, ramp-and-hold relaxation (a standard linear solid, two
branches), a staircase, creep under constant force and a sine sweep. Each scene names
the terms its design cannot tell apart (on a constant speed, ``xdot``, ``xdot|xdot|``,
``sign(xdot)`` and the offset are one column) and those it does not excite (``xddot``
where the acceleration is zero but at a few corners).

:func:`random_protocol` draws a protocol's settings over the stress space: closure
amplitudes 1 um to 10 mm, rates 20 Hz to 20 kHz, units scaled by 1e-6 to 1e6, float32
exports or 16-bit quantisation, force noise 0.1 to 10 % of the force range.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..core.terms import Law, relaxation
from ..core.tissue import Tissue
from .scenes import Scene, render, true_force

Array = NDArray[np.float64]

#: on a constant speed these are one column: a speed, its square and its sign are
#: constants like the offset
CONSTANT_SPEED = frozenset({"xdot", "xdot|xdot|", "sign(xdot)", "offset"})
#: where the speed is +-V or 0, the speed's powers and its sign are one column
TWO_SPEEDS = frozenset({"xdot", "xdot|xdot|", "sign(xdot)"})
#: smallest number of samples a protocol's session has
MIN_SAMPLES = 400


@dataclass(frozen=True)
class Knots:
    """Closure driven by a piecewise-constant speed: ``speeds[i]`` (m/s) from
    ``times[i]`` (s; ``times[0] = 0``), each change blended over ``blend_s`` by a
    raised cosine (0: a corner). Closure, speed and acceleration are exact."""

    start_m: float
    times: tuple[float, ...]
    speeds: tuple[float, ...]
    blend_s: float = 0.0

    def kinematics(self, t: Array) -> tuple[Array, Array, Array]:
        t = np.asarray(t, dtype=float)
        v0 = self.speeds[0]
        x = self.start_m + v0 * t
        v = np.full_like(t, v0)
        a = np.zeros_like(t)
        w = self.blend_s
        for tk, before, after in zip(self.times[1:], self.speeds, self.speeds[1:], strict=False):
            dv = after - before
            if w <= 0:
                x += dv * np.maximum(t - tk, 0.0)
                v += np.where(t >= tk, dv, 0.0)
                continue
            s = tk - w / 2
            u = np.clip((t - s) / w, 0.0, 1.0)
            inside = (t > s) & (t < s + w)
            # the integral of the blend (1 - cos(pi u)) / 2 over time
            x += dv * np.where(
                t >= s + w,
                w / 2 + (t - s - w),
                np.where(inside, (t - s) / 2 - w / (2 * math.pi) * np.sin(math.pi * u), 0.0),
            )
            v += dv * (1 - np.cos(math.pi * u)) / 2
            a += np.where(inside, dv * math.pi / (2 * w) * np.sin(math.pi * u), 0.0)
        return x, v, a


@dataclass(frozen=True)
class Sweep:
    """A linear sine sweep about ``mean_m``: amplitude ``amplitude_m``, frequency from
    ``f0_hz`` to ``f1_hz`` over ``duration_s``."""

    mean_m: float
    amplitude_m: float
    f0_hz: float
    f1_hz: float
    duration_s: float

    def kinematics(self, t: Array) -> tuple[Array, Array, Array]:
        t = np.asarray(t, dtype=float)
        k = (self.f1_hz - self.f0_hz) / self.duration_s
        phase = 2 * math.pi * (self.f0_hz * t + k * t * t / 2)
        w = 2 * math.pi * (self.f0_hz + k * t)
        dw = 2 * math.pi * k
        s, c = np.sin(phase), np.cos(phase)
        A = self.amplitude_m
        return self.mean_m + A * s, A * w * c, A * (dw * c - w * w * s)


def _blend(t: Array, ramp_s: float) -> tuple[Array, Array, Array, Array]:
    """A raised-cosine step over ``[0, ramp_s]``: its value, first and second
    derivatives, and its integral from 0."""
    u = np.clip(t / ramp_s, 0.0, 1.0)
    inside = (t > 0) & (t < ramp_s)
    h = (1 - np.cos(math.pi * u)) / 2
    h1 = np.where(inside, math.pi / (2 * ramp_s) * np.sin(math.pi * u), 0.0)
    h2 = np.where(inside, math.pi**2 / (2 * ramp_s**2) * np.cos(math.pi * u), 0.0)
    ih = np.where(
        t >= ramp_s, ramp_s / 2 + (t - ramp_s), t / 2 - ramp_s / (2 * math.pi) * np.sin(math.pi * u)
    )
    return h, h1, h2, ih


def creep_kinematics(
    K: float, Km: float, tau: float, preload_m: float, step_n: float, ramp_s: float, t: Array
) -> tuple[Array, Array, Array]:
    """Closure of a standard linear solid (spring ``K`` beside a branch ``Km``, ``tau``)
    at rest at ``preload_m`` under a force raised by ``step_n`` over ``ramp_s`` and
    held: ``xdot = (F' + (F - K x) / tau) / (K + Km)``, integrated exactly on ``t``
    (uniform, s) as a relaxation recursion of its forcing's integral.

    Returns
    -------
    x, v, a : ndarray
        m, m/s, m/s^2.
    """
    t = np.asarray(t, dtype=float)
    total = K + Km
    tau_c = tau * total / K
    h, h1, h2, ih = _blend(t, ramp_s)
    f0 = K * preload_m
    force, d1, d2 = f0 + step_n * h, step_n * h1, step_n * h2
    # xdot = -x / tau_c + g, g = (F' + F / tau) / (K + Km); x = y with y' = G' - y / tau_c
    # and G = int g, whose integral is exact: (F - F0 + (F0 t + step int h) / tau) / total
    G = (force - f0 + (f0 * t + step_n * ih) / tau) / total
    dt = float(t[1] - t[0])
    # the recursion integrates G' exactly for G linear between points; x starts at rest
    x = relaxation(G, dt, tau_c, state=preload_m)[0]
    g = (d1 + force / tau) / total
    v = -x / tau_c + g
    a = -v / tau_c + (d2 + d1 / tau) / total
    return x, v, a


@dataclass(frozen=True)
class Creep:
    """The closure of a standard linear solid under a constant force (see
    :func:`creep_kinematics`), on a grid fine enough for every use."""

    K: float
    Km: float
    tau: float
    preload_m: float
    step_n: float
    ramp_s: float

    def kinematics(self, t: Array) -> tuple[Array, Array, Array]:
        t = np.asarray(t, dtype=float)
        if t.size < 2:
            x = np.full_like(t, self.preload_m)
            return x, np.zeros_like(t), np.zeros_like(t)
        # integrate on a grid twice as fine and pick the samples
        sub = 2
        dt = float(t[1] - t[0])
        fine = t[0] + np.arange((t.size - 1) * sub + 1) * (dt / sub)
        x, v, a = creep_kinematics(
            self.K, self.Km, self.tau, self.preload_m, self.step_n, self.ramp_s, fine
        )
        return x[::sub], v[::sub], a[::sub]


# -- the protocols ---------------------------------------------------------------------


def _settings(rng: np.random.Generator, fixed: dict[str, Any]) -> dict[str, Any]:
    """The stress space: amplitude, rate, units, quantisation, noise."""
    draw: dict[str, Any] = {
        "amplitude_m": math.exp(rng.uniform(math.log(1e-6), math.log(1e-2))),
        "rate_hz": math.exp(rng.uniform(math.log(20.0), math.log(20_000.0))),
        "force_unit": float(10.0 ** rng.choice([-6, -3, 0, 3, 6])),
        "length_unit": float(10.0 ** rng.choice([-6, -3, 0, 3, 6])),
        "quantisation": [16, "float32", "float64"][int(rng.integers(0, 3))],
        "noise_frac": math.exp(rng.uniform(math.log(1e-3), math.log(0.1))),
        "stiffness": math.exp(rng.uniform(math.log(50.0), math.log(5000.0))),
        "max_samples": 100_000,
    }
    unknown = set(fixed) - set(draw)
    if unknown:
        raise TypeError(f"unknown settings {sorted(unknown)}; choose among {sorted(draw)}")
    draw.update(fixed)
    return draw


def _duration(s: dict[str, Any], wanted: float) -> float:
    """``wanted`` s, at least :data:`MIN_SAMPLES` samples, at most ``max_samples``."""
    rate = float(s["rate_hz"])
    return float(min(max(wanted, MIN_SAMPLES / rate), max(s["max_samples"], MIN_SAMPLES) / rate))


def _scene(
    name: str,
    tissue: Tissue,
    motion: Any,
    s: dict[str, Any],
    duration: float,
    rng: np.random.Generator,
    indistinct: tuple[frozenset[str], ...],
    unexcited: frozenset[str],
    truth: tuple[Array, Array, Array, Array] | None = None,
) -> Scene:
    return render(
        tissue,
        motion,
        rate_hz=float(s["rate_hz"]),
        duration_s=duration,
        rng=rng,
        noise_frac=float(s["noise_frac"]),
        position_noise_frac=1e-4,
        quantisation=s["quantisation"],
        units=(float(s["force_unit"]), float(s["length_unit"])),
        gate=False,
        settings={"family": name, "protocol": name, **{k: s[k] for k in s if k != "max_samples"}},
        indistinct=indistinct,
        unexcited=unexcited,
        truth=truth,
    )


def _ramp(kind: str) -> Callable[..., Scene]:
    def build(rng: np.random.Generator, **fixed: Any) -> Scene:
        s = _settings(rng, fixed)
        duration = _duration(s, 10.0)
        amp, K = float(s["amplitude_m"]), float(s["stiffness"])
        start = amp * rng.uniform(0.3, 1.0)
        motion = Knots(start, (0.0,), (amp / duration,))
        span = K * amp
        names = {"linear": ["x"], "offset": ["x", "offset"], "damped": ["x", "xdot"],
                 "stiffening": ["x", "x^3"]}[kind]  # fmt: skip
        coef = []
        for n in names:
            if n == "x":
                coef.append(K)
            elif n == "offset":
                coef.append(rng.uniform(0.2, 1.0) * span * rng.choice([-1, 1]))
            elif n == "xdot":
                coef.append(rng.uniform(0.05, 0.3) * span / (amp / duration))
            elif n == "x^3":
                top = start + amp
                coef.append(rng.uniform(0.5, 2.0) * K * amp / (top**3 - start**3))
        tissue = Tissue(Law.of(names), *coef)
        return _scene(f"ramp {kind}", tissue, motion, s, duration, rng, (CONSTANT_SPEED,),
                      frozenset({"xddot"}))  # fmt: skip

    return build


def _triangle(kind: str) -> Callable[..., Scene]:
    def build(rng: np.random.Generator, **fixed: Any) -> Scene:
        s = _settings(rng, fixed)
        cycles = int(rng.integers(3, 8))
        duration = _duration(s, cycles * rng.uniform(1.0, 4.0))
        half = duration / (2 * cycles)
        amp, K = float(s["amplitude_m"]), float(s["stiffness"])
        speed = amp / half
        times = tuple(i * half for i in range(2 * cycles))
        speeds = tuple(speed if i % 2 == 0 else -speed for i in range(2 * cycles))
        start = amp * rng.uniform(0.3, 1.0)
        motion = Knots(start, times, speeds, blend_s=0.02 * half)
        names = ["x", "xdot"] if kind == "viscoelastic" else ["x", "x^3", "xdot"]
        coef = [K]
        if "x^3" in names:
            top = start + amp
            coef.append(rng.uniform(0.5, 2.0) * K * amp / (top**3 - start**3))
        coef.append(rng.uniform(0.05, 0.3) * K * amp / speed)
        tissue = Tissue(Law.of(names), *coef)
        return _scene(f"triangle {kind}", tissue, motion, s, duration, rng, (TWO_SPEEDS,),
                      frozenset({"xddot"}))  # fmt: skip

    return build


def _relaxation_law(
    rng: np.random.Generator, K: float, branches: int, hold_s: float, shortest_s: float = 0.05
) -> Tissue:
    # a hold cut short (by a cap on the samples) still draws time constants it can show:
    # at most a quarter of the hold
    longest = hold_s / 4
    shortest = min(shortest_s, longest)
    taus = sorted(math.exp(rng.uniform(math.log(shortest), math.log(longest)))
                  for _ in range(branches))  # fmt: skip
    if branches == 2 and taus[1] < 8 * taus[0]:
        taus[1] = min(8 * taus[0], hold_s / 3)
    law = Law.of(["x", *["maxwell"] * branches]).bind(
        {f"tau{i + 1}": t for i, t in enumerate(taus)}
    )
    return Tissue(law, K, *(K * rng.uniform(0.3, 1.5, branches)))


def _ramp_hold(branches: int) -> Callable[..., Scene]:
    def build(rng: np.random.Generator, **fixed: Any) -> Scene:
        s = _settings(rng, fixed)
        duration = _duration(s, 20.0)
        ramp = duration * rng.uniform(0.03, 0.08)
        amp, K = float(s["amplitude_m"]), float(s["stiffness"])
        motion = Knots(amp * rng.uniform(0.3, 1.0), (0.0, ramp), (amp / ramp, 0.0),
                       blend_s=0.05 * ramp)  # fmt: skip
        tissue = _relaxation_law(rng, K, branches, duration - ramp)
        name = "ramp-hold SLS" if branches == 1 else "ramp-hold two branches"
        return _scene(name, tissue, motion, s, duration, rng, (TWO_SPEEDS,), frozenset({"xddot"}))

    return build


def _staircase(rng: np.random.Generator, **fixed: Any) -> Scene:
    s = _settings(rng, fixed)
    steps = int(rng.integers(3, 7))
    duration = _duration(s, steps * rng.uniform(3.0, 6.0))
    period = duration / steps
    ramp = 0.1 * period
    amp, K = float(s["amplitude_m"]), float(s["stiffness"])
    speed = amp / (steps * ramp)
    times, speeds = [], []
    for i in range(steps):
        times += [i * period, i * period + ramp]
        speeds += [speed, 0.0]
    motion = Knots(amp * rng.uniform(0.3, 1.0), tuple(times), tuple(speeds), blend_s=0.05 * ramp)
    tissue = _relaxation_law(rng, K, 1, period - ramp)
    return _scene("staircase SLS", tissue, motion, s, duration, rng, (TWO_SPEEDS,),
                  frozenset({"xddot"}))  # fmt: skip


def _creep(rng: np.random.Generator, **fixed: Any) -> Scene:
    s = _settings(rng, fixed)
    duration = _duration(s, 20.0)
    amp, K = float(s["amplitude_m"]), float(s["stiffness"])
    # a time constant that leaves the creep to be seen in the hold
    tissue = _relaxation_law(rng, K, 1, duration, shortest_s=duration / 20)
    Km, tau = float(tissue.coef[1]), float(tissue.law.terms[1].tau)  # type: ignore[attr-defined]
    preload = amp * rng.uniform(0.3, 1.0)
    # the step that creeps by ``amp`` in the end: x_inf - x_pre = step / K
    motion = Creep(K, Km, tau, preload, K * amp, duration * rng.uniform(0.02, 0.05))
    # the force is the law on the exact closure (to the integration's accuracy, the
    # constant force the machine holds)
    n = max(int(round(duration * float(s["rate_hz"]))), 2)
    t = np.arange(n) / float(s["rate_hz"])
    truth = true_force(tissue, motion, t, gate=False)
    return _scene("creep SLS", tissue, motion, s, duration, rng,
                  (frozenset({"sign(xdot)", "offset"}),), frozenset({"xddot"}), truth)  # fmt: skip


def _sweep(rng: np.random.Generator, **fixed: Any) -> Scene:
    s = _settings(rng, fixed)
    duration = _duration(s, 10.0)
    rate = float(s["rate_hz"])
    amp, K = float(s["amplitude_m"]), float(s["stiffness"])
    f1 = min(rng.uniform(5.0, 30.0), rate / 10)
    f0 = min(rng.uniform(0.2, 1.0), f1 / 2)
    motion = Sweep(amp * 1.2, amp, f0, f1, duration)
    w1 = 2 * math.pi * f1
    # damping and mass each 10-40 % of the spring's force at the top frequency
    S = rng.uniform(0.1, 0.4) * K / w1
    M = rng.uniform(0.1, 0.4) * K / w1**2
    tissue = Tissue(Law.of(["x", "xdot", "xddot"]), K, S, M)
    return _scene("sine sweep", tissue, motion, s, duration, rng, (), frozenset())


#: every protocol by name
PROTOCOLS: dict[str, Callable[..., Scene]] = {
    "ramp linear": _ramp("linear"),
    "ramp offset": _ramp("offset"),
    "ramp damped": _ramp("damped"),
    "ramp stiffening": _ramp("stiffening"),
    "triangle viscoelastic": _triangle("viscoelastic"),
    "triangle stiffening": _triangle("stiffening"),
    "ramp-hold SLS": _ramp_hold(1),
    "ramp-hold two branches": _ramp_hold(2),
    "staircase SLS": _staircase,
    "creep SLS": _creep,
    "sine sweep": _sweep,
}

#: the protocols the stability bounds are stated for (constant-speed ramps, triangle
#: cycles, ramp-and-hold of a standard linear solid)
MUST_HOLD = (
    "ramp linear", "ramp offset", "ramp stiffening", "triangle viscoelastic",
    "ramp-hold SLS",
)  # fmt: skip


def random_protocol(seed: int, name: str | None = None, **fixed: Any) -> Scene:
    """A scene of protocol ``name`` (drawn too when None) with settings drawn from
    ``seed`` over the stress space; ``fixed`` imposes settings (``rate_hz``,
    ``amplitude_m``, ``force_unit``, ``length_unit``, ``quantisation``, ``noise_frac``,
    ``stiffness``, ``max_samples``)."""
    rng = np.random.default_rng(seed)
    names: Sequence[str] = list(PROTOCOLS)
    chosen = name if name is not None else names[int(rng.integers(0, len(names)))]
    scene = PROTOCOLS[chosen](rng, **fixed)
    scene.settings["seed"] = seed
    return scene
