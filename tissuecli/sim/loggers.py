"""What other loggers do to a recording: coarse or jittered time stamps, a pause, samples
lost at random. Each takes a session and returns a damaged copy, so that tests and
benchmarks can fit the same samples with and without the damage."""

from __future__ import annotations

import numpy as np

from ..core.session import Session


def host_stamps(
    session: Session,
    rng: np.random.Generator,
    *,
    quantum_s: float = 1e-3,
    jitter_s: float = 0.0,
) -> Session:
    """The samples stamped as a host stamps them on arrival: the true sample time plus
    uniform jitter in ``[-jitter_s, jitter_s]``, rounded down to a clock of
    ``quantum_s`` (0 keeps full resolution). The samples themselves are unchanged.
    """
    t = session.time + rng.uniform(-jitter_s, jitter_s, len(session)) if jitter_s else session.time
    if quantum_s:
        t = np.floor(t / quantum_s) * quantum_s
    return session.replace(t, session.force, session.position)


def pause(session: Session, at_s: float, length_s: float) -> Session:
    """The session without the samples of ``[at_s, at_s + length_s)``, s: a logger that
    stopped for a while."""
    t = session.time
    keep = (t < at_s) | (t >= at_s + length_s)
    return session.replace(t[keep], session.force[keep], session.position[keep])


def lose_at_random(session: Session, fraction: float, rng: np.random.Generator) -> Session:
    """The session without a random ``fraction`` of its samples (never the first or
    last), as a lossy link drops them."""
    n = len(session)
    lost = rng.choice(np.arange(1, n - 1), size=int(round(fraction * n)), replace=False)
    keep = np.ones(n, bool)
    keep[lost] = False
    return session.replace(session.time[keep], session.force[keep], session.position[keep])
