"""Small lab-protocol generators for the evidence and identifiability tests: a
specimen pulled at constant speed, and a standard linear solid ramped and held.

Plain NumPy, SI units; each returns a :class:`Session` and the truth it was made from.
"""

from __future__ import annotations

import numpy as np

from tissuecli.core.session import Session


def constant_speed(
    seed: int = 0,
    *,
    k: float = 350.0,
    damping: float = 0.0,
    offset: float = 0.0,
    noise: float = 10e-3,
    rate: float = 1000.0,
    duration: float = 10.0,
    start: float = 1e-3,
    stop: float = 3e-3,
    position_noise: float = 0.0,
) -> tuple[Session, dict[str, float]]:
    """A linear-elastic specimen pulled at constant speed: ``F = k x + c xdot + offset``
    plus white force noise (N), closure ``start -> stop`` (m) over ``duration`` (s)."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(round(duration * rate))) / rate
    speed = (stop - start) / duration
    x = start + speed * t
    f = k * x + damping * speed + offset + rng.normal(0.0, noise, t.size)
    if position_noise:
        x = x + rng.normal(0.0, position_noise, t.size)
    return Session(t, f, x), {"K": k, "S": damping, "offset": offset, "noise": noise}


def relaxation(
    seed: int = 0,
    *,
    k: float = 300.0,
    k1: float = 200.0,
    tau: float = 1.5,
    ramp: float = 1.0,
    hold: float = 19.0,
    rate: float = 500.0,
    start: float = 1e-3,
    stop: float = 3e-3,
    noise: float = 10e-3,
) -> tuple[Session, dict[str, float]]:
    """A standard linear solid (spring ``k`` beside a Maxwell branch of stiffness ``k1``
    and time constant ``tau``) ramped from ``start`` to ``stop`` over ``ramp`` seconds
    and held: the branch's force is integrated exactly sample by sample."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(round((ramp + hold) * rate))) / rate
    x = np.where(t < ramp, start + (stop - start) * t / ramp, stop)
    dt = 1.0 / rate
    # branch force q: dq/dt = k1 xdot - q / tau; exact for piecewise-constant speed
    v = np.diff(x) / dt
    decay = np.exp(-dt / tau)
    q = np.zeros(t.size)
    for i in range(1, t.size):
        q[i] = q[i - 1] * decay + k1 * tau * v[i - 1] * (1.0 - decay)
    f = k * x + q + rng.normal(0.0, noise, t.size)
    return Session(t, f, x), {"K": k, "K1": k1, "tau": tau, "noise": noise}
