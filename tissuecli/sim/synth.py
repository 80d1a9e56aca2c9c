"""Synthetic forceps data with known truth: an operator, a tissue, sensors and an ADC.

The simulated forceps streams from here, and tests and benchmarks draw their
sessions with known parameters from here, so all three see the same physics.

The operator imposes the jaw closure ``x(t)`` (a smooth multi-sine, so every
derivative is exact); the tissue answers with ``F = K f0(x) + S f1(xdot) + M xddot``;
each sensor adds white Gaussian noise and is read by a signed ADC of ``bits`` bits.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..core.calibration import Adc, Calibration, Channel
from ..core.session import Session
from ..core.tissue import DEFAULT_TISSUE, Tissue

Array = NDArray[np.float64]

CLOCK_HZ = 1_000_000  # the device clock ticks in microseconds


@dataclass(frozen=True)
class Operator:
    """Jaw closure imposed by the operator: ``x(t) = mean + sum_i a_i sin(2 pi f_i t + phi_i)``.

    The defaults squeeze and release about every 2 s between roughly 0.2 and
    7 mm, with faster components that give acceleration content (so that the
    mass M is identifiable at all). ``mean`` exceeds the sum of amplitudes, so
    the jaws never leave the tissue.
    """

    mean_m: float = 3.6e-3
    amplitudes_m: tuple[float, ...] = (2.0e-3, 1.0e-3, 0.3e-3, 0.15e-3)
    frequencies_hz: tuple[float, ...] = (0.5, 1.3, 3.1, 6.7)
    phases_rad: tuple[float, ...] = (0.0, 1.0, 2.0, 3.0)

    @classmethod
    def random(cls, rng: np.random.Generator) -> Operator:
        """A different but similar operator: jittered frequencies and amplitudes, random phases."""
        base = cls()
        amps = tuple(float(a * rng.uniform(0.7, 1.3)) for a in base.amplitudes_m)
        freqs = tuple(float(f * rng.uniform(0.8, 1.25)) for f in base.frequencies_hz)
        phases = tuple(float(p) for p in rng.uniform(0, 2 * np.pi, len(amps)))
        return cls(
            mean_m=sum(amps) * 1.1, amplitudes_m=amps, frequencies_hz=freqs, phases_rad=phases
        )

    def kinematics(self, t: ArrayLike) -> tuple[Array, Array, Array]:
        """Exact jaw closure (m), velocity (m/s) and acceleration (m/s^2) at times ``t`` (s)."""
        t = np.asarray(t, dtype=float)
        x = np.full_like(t, self.mean_m)
        v = np.zeros_like(t)
        a = np.zeros_like(t)
        for amp, f, phi in zip(
            self.amplitudes_m, self.frequencies_hz, self.phases_rad, strict=True
        ):
            w = 2 * np.pi * f
            s, c = np.sin(w * t + phi), np.cos(w * t + phi)
            x += amp * s
            v += amp * w * c
            a -= amp * w * w * s
        return x, v, a


@dataclass(frozen=True)
class GraspingOperator:
    """Grasps separated by free jaw motion, as a surgeon works.

    The session opens with ``free_s`` of free motion, the jaws ``open_m`` short of
    the tissue (closure ``-open_m``, no force); then each grasp closes onto the
    tissue over ``ramp_s`` (a raised cosine), squeezes it as ``squeeze`` does for
    ``grasp_s - 2 ramp_s``, and releases over ``ramp_s``; and so on.
    """

    squeeze: Operator = field(default_factory=Operator)
    grasp_s: float = 3.0
    free_s: float = 1.0
    ramp_s: float = 0.3
    open_m: float = 2e-3

    def window(self, t: Array) -> tuple[Array, Array, Array]:
        """The grasp window ``w`` (1 in a grasp, 0 free) and its first two derivatives."""
        u = np.mod(t, self.free_s + self.grasp_s) - self.free_s  # time into the grasp
        r, g = self.ramp_s, self.grasp_s
        w, w1, w2 = np.zeros_like(t), np.zeros_like(t), np.zeros_like(t)
        for lo, hi, sign in ((0.0, r, 1.0), (g - r, g, -1.0)):
            inside = (u >= lo) & (u < hi)
            phase = np.pi * (u[inside] - lo) / r
            w[inside] = (1 - sign * np.cos(phase)) / 2
            w1[inside] = sign * np.pi / (2 * r) * np.sin(phase)
            w2[inside] = sign * np.pi**2 / (2 * r**2) * np.cos(phase)
        w[(u >= r) & (u < g - r)] = 1.0
        return w, w1, w2

    def kinematics(self, t: ArrayLike) -> tuple[Array, Array, Array]:
        """Exact jaw closure (m), velocity (m/s) and acceleration (m/s^2) at times ``t`` (s)."""
        t = np.asarray(t, dtype=float)
        x0, v0, a0 = self.squeeze.kinematics(t)
        w, w1, w2 = self.window(t)
        lift = x0 + self.open_m  # from the open jaws to the squeeze
        return (
            w * lift - self.open_m,
            w1 * lift + w * v0,
            w2 * lift + 2 * w1 * v0 + w * a0,
        )


@dataclass(frozen=True)
class Sensors:
    """Strain-gauge force sensor and optical jaw sensor, read by one ADC.

    Noise is the analogue noise before quantisation; the ADC step adds its own
    (step / sqrt(12)). Ranges are the SI values at the ADC's two ends.
    """

    bits: int = 8
    force_noise_n: float = 0.005
    position_noise_m: float = 5e-6
    force_range_n: tuple[float, float] = (-1.0, 5.0)
    position_range_m: tuple[float, float] = (-0.5e-3, 15e-3)
    force_offset_n: float = 0.0  # what the force sensor reads with nothing in the jaws

    @property
    def calibration(self) -> Calibration:
        return Calibration(
            force=Channel.spanning(*self.force_range_n, self.bits, "N"),
            position=Channel.spanning(*self.position_range_m, self.bits, "m"),
        )

    def read(self, force: Array, position: Array, rng: np.random.Generator) -> NDArray[np.int16]:
        """Raw counts, shape (n, 2): columns force and position."""
        cal = self.calibration
        f = force + self.force_offset_n + rng.normal(0.0, self.force_noise_n, force.shape)
        x = position + rng.normal(0.0, self.position_noise_m, position.shape)
        return np.column_stack(
            [cal.force.to_counts(f, self.bits), cal.position.to_counts(x, self.bits)]
        )


@dataclass
class ForcepsModel:
    """Everything the simulated forceps needs to produce sample ``k``.

    The device's crystal runs ``drift_ppm`` fast: it samples every
    ``1/rate_hz`` seconds of *its* clock, so sample ``k`` happens at true time
    ``k / (rate_hz (1 + drift_ppm 1e-6))`` and is stamped ``k CLOCK_HZ / rate_hz`` ticks.
    """

    tissue: Tissue = DEFAULT_TISSUE
    operator: Operator | GraspingOperator = field(default_factory=Operator)
    sensors: Sensors = field(default_factory=Sensors)
    rate_hz: float = 1000.0
    drift_ppm: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        self._rng = np.random.default_rng(self.seed)
        # the memory terms' force at samples 0.. computed so far, and the state each term
        # continues from (a relaxation branch's: its recursion and the last closure)
        self._memory = np.zeros(0)
        self._states: list[object] = []

    def true_time(self, k: ArrayLike) -> Array:
        """True (host) time of samples ``k``, in s."""
        return np.asarray(k, dtype=float) / (self.rate_hz * (1.0 + self.drift_ppm * 1e-6))

    def ticks(self, k: ArrayLike) -> NDArray[np.int64]:
        """Device clock stamps of samples ``k``, in ticks (not wrapped)."""
        return np.rint(np.asarray(k, dtype=float) * (CLOCK_HZ / self.rate_hz)).astype(np.int64)

    def truth(self, k: ArrayLike) -> tuple[Array, Array, Array, Array]:
        """True x (m), xdot (m/s), xddot (m/s^2) and F (N) at samples ``k``; the jaws
        touch the tissue at closure 0, so there is no force below it. A law with
        memory (relaxation branches, or any term whose force depends on the past) starts
        from rest at sample 0."""
        k = np.asarray(k)
        x, v, a = self.operator.kinematics(self.true_time(k))
        law = self.tissue.law
        if not law.memory:
            return x, v, a, np.where(x > 0, self.tissue.force(x, v, a), 0.0)
        now = [(t, c) for t, c in zip(law.terms, self.tissue.coef, strict=True) if not t.memory]
        f = sum((c * t.regressor(x, v, a) for t, c in now), np.zeros_like(x))
        f = f + self._memory_force(int(k.max()) + 1 if k.size else 0)[k]
        return x, v, a, np.where(x > 0, f, 0.0)

    #: fine steps per sample for the memory terms' integration
    SUBSTEPS = 8

    def _memory_force(self, n: int) -> Array:
        """The memory terms' summed force at samples ``0 .. n-1``, N, each term continued
        from where the last call left it (:meth:`~tissuecli.core.terms.Term.continued`)
        on a grid :data:`SUBSTEPS` times finer than the samples (the operator's closure
        is exact there), extending what earlier calls computed."""
        done = self._memory.size
        if n <= done:
            return self._memory
        law, coef = self.tissue.law, self.tissue.coef
        memory = [(t, c) for t, c in zip(law.terms, coef, strict=True) if t.memory]
        sub = self.SUBSTEPS
        # fine points after the last one done (sample done-1), up to sample n-1
        first = (done - 1) * sub + 1 if done else 0
        fine = np.arange(first, (n - 1) * sub + 1) / sub  # in samples
        x, _, _ = self.operator.kinematics(self.true_time(fine))
        dt = float(self.true_time(1.0)) / sub
        total = np.zeros(x.size)
        states = []
        for i, (term, c) in enumerate(memory):
            r, state = term.continued(x, dt, self._states[i] if done else None)
            total += c * r
            states.append(state)
        self._states = states
        picked = total[sub - 1 :: sub] if done else total[::sub]
        self._memory = np.concatenate([self._memory, picked])
        return self._memory

    def samples(self, k0: int, k1: int) -> tuple[NDArray[np.int64], NDArray[np.int16]]:
        """Device ticks (n,) and raw counts (n, 2) of samples ``k0 .. k1-1``, noise included.

        Calls must run in order of ``k``: noise is drawn from one stream.
        """
        k = np.arange(k0, k1)
        x, _, _, f = self.truth(k)
        return self.ticks(k), self.sensors.read(f, x, self._rng)


def synthesize(model: ForcepsModel, duration_s: float) -> tuple[Session, dict[str, Array]]:
    """A whole session as the recorder would store it, plus the truth.

    Returns
    -------
    session : Session
        Calibrated time (device clock, s), force (N) and position (m).
    truth : dict
        ``x``, ``v``, ``a``, ``F`` at the same samples, noise-free, and ``counts``.
    """
    n = int(round(duration_s * model.rate_hz))
    ticks, counts = model.samples(0, n)
    cal = model.sensors.calibration
    session = Session(
        time=ticks / CLOCK_HZ,
        force=cal.force.to_si(counts[:, 0]),
        position=cal.position.to_si(counts[:, 1]),
        name="synthetic",
        meta={
            "source": "synthetic",
            "rate_hz": model.rate_hz,
            # what a recording keeps from the device's reply
            "device": {"adc_bits": model.sensors.bits, "calibration": cal.as_dict()},
        },
        adc=Adc(model.sensors.bits, cal),
    )
    x, v, a, f = model.truth(np.arange(n))
    return session, {"x": x, "v": v, "a": a, "F": f, "counts": counts}


def random_session(
    tissue: Tissue,
    *,
    rate_hz: float = 1000.0,
    seed: int = 0,
    duration_s: float = 10.0,
    within_range: bool = True,
    **sensors: float,
) -> tuple[Session, ForcepsModel]:
    """A session with known truth and its own random operator, as tests and benchmarks draw.

    The operator's frequencies, amplitudes and phases come from ``seed`` (see
    :meth:`Operator.random`), and so does the noise; ``sensors`` are
    :class:`Sensors` fields (``bits=12``, ...). The session knows its ADC, as a
    recorded one does.

    With ``within_range`` (the default) operators are drawn from the seed's
    stream until the true force and closure, widened by 4 noise SDs, stay inside
    the sensors' ranges: a clipped session has no recoverable truth to score
    against. Clipping itself is exercised with ``within_range=False``.

    Raises
    ------
    ValueError
        If 100 operators in a row leave the sensor range (the tissue is too stiff
        for the force sensor).
    """
    rng = np.random.default_rng(seed)
    sens = Sensors(**sensors)  # type: ignore[arg-type]
    for _ in range(100):
        model = ForcepsModel(
            tissue=tissue, rate_hz=rate_hz, seed=seed, operator=Operator.random(rng), sensors=sens
        )
        if not within_range or _inside(model, duration_s):
            break
    else:
        raise ValueError(
            f"{tissue} leaves the sensor ranges (force {sens.force_range_n} N, closure "
            f"{sens.position_range_m} m) for 100 random operators"
        )
    session, _ = synthesize(model, duration_s)
    return session, model


def _inside(model: ForcepsModel, duration_s: float) -> bool:
    """Whether the true force and closure (+- 4 noise SDs) stay inside the sensor ranges."""
    x, _, _, f = model.truth(np.arange(int(round(duration_s * model.rate_hz))))
    s = model.sensors
    cal = s.calibration
    return all(
        lo + 2 * ch.gain < u.min() - 4 * sd and u.max() + 4 * sd < hi - 2 * ch.gain
        for u, sd, (lo, hi), ch in (
            (f, s.force_noise_n, s.force_range_n, cal.force),
            (x, s.position_noise_m, s.position_range_m, cal.position),
        )
    )
