"""What a forceps session looks like, to catch unit mistakes: a closure of metres, a
force of a thousand newtons, or a sample rate of a third of a hertz are numbers in the
wrong unit far more often than they are measurements."""

from __future__ import annotations

import numpy as np

from .session import Session
from .units import dimension_of

#: beyond these a forceps session is implausible (jaws open at most a few cm; liver
#: grasps reach 3.4 N, and no laparoscopic grasp 200 N; loggers sample 10 Hz to 100 kHz)
MAX_CLOSURE_SPAN_M = 0.05
MAX_FORCE_N = 200.0
RATE_RANGE_HZ = (5.0, 1e6)
#: below these a session is implausible too: jaws that move less than 10 um, or a force
#: that varies less than 10 mN (less than a sensor's noise), are a unit a thousand times too small
MIN_CLOSURE_SPAN_M = 1e-5
MIN_FORCE_SPAN_N = 1e-2
#: force and closure this anti-correlated: the force falls as the jaws close, which no
#: tissue does (a closure logged with the wrong sign)
SIGN_CORRELATION = -0.5
#: the force holds its value in runs of one length this often: a load cell read more
#: slowly than the session is sampled (ADC rounding gives runs of every length)
HELD_SHARE = 0.9


def unit_warnings(session: Session, *, position_given: bool | None = None) -> list[str]:
    """Warnings that name the likely mistake when a session is implausible for a
    forceps (a unit a thousand times off either way, a closure of the wrong sign, a
    load cell read more slowly than the closure, a time unit); empty when it is
    plausible. ``position_given`` False says the closure was
    converted from an angle (so its span is not a unit question); by default it is
    read from the units the session was imported with."""
    out: list[str] = []
    if position_given is None:
        units = session.meta.get("import_units")
        unit = str(units.get("position", "m")) if isinstance(units, dict) else "m"
        position_given = dimension_of(unit.split(" ")[0]) != "angle"
    if len(session) < 2:
        return out
    span = float(np.ptp(session.position))
    if position_given and span > MAX_CLOSURE_SPAN_M:
        out.append(
            f"the jaw closure spans {span:.4g} m, more than forceps jaws open "
            f"({MAX_CLOSURE_SPAN_M * 1e3:g} mm): "
            + _guess(span, MAX_CLOSURE_SPAN_M, (("mm", 1e-3), ("um", 1e-6)), "position")
        )
    peak = float(np.max(np.abs(session.force)))
    if peak > MAX_FORCE_N:
        out.append(
            f"the force reaches {peak:.4g} N, more than a grasp ({MAX_FORCE_N:g} N): "
            + _guess(peak, MAX_FORCE_N, (("gf", 9.80665e-3), ("mN", 1e-3)), "force")
        )
    if position_given and 0 < span < MIN_CLOSURE_SPAN_M:
        out.append(
            f"the jaw closure spans only {span * 1e6:.3g} um, less than any grasp moves "
            f"the jaws ({MIN_CLOSURE_SPAN_M * 1e6:g} um): a unit a thousand times too "
            "small? check --units position (e.g. m where mm was given, mm where um was)"
        )
    f_span = float(np.ptp(session.force))
    if 0 < f_span < MIN_FORCE_SPAN_N:
        out.append(
            f"the force varies by only {f_span * 1e3:.3g} mN, less than any grasp "
            f"({MIN_FORCE_SPAN_N * 1e3:g} mN): a unit a thousand times too small? check "
            "--units force (e.g. N where mN was given)"
        )
    sign = _sign_warning(session)
    if sign:
        out.append(sign)
    slow = _held_force_warning(session)
    if slow:
        out.append(slow)
    rate = session.rate_hz
    lo, hi = RATE_RANGE_HZ
    if rate and not lo <= rate <= hi:
        options = (("ms", 1e-3), ("us", 1e-6)) if rate < lo else (("s", 1.0),)
        fix = next(
            (f"is time in {u}? pass --units time={u}" for u, f in options if lo <= rate / f <= hi),
            "check the time column and its unit",
        )
        out.append(f"the samples come {rate:.4g} times a second: {fix}")
    return out


def _sign_warning(session: Session) -> str | None:
    """The force falling as the jaws close: the closure (or the force) logged with the
    wrong sign, which leaves a tissue law no stiffness to find."""
    x, f = session.position, session.force
    if np.ptp(x) <= 0 or np.ptp(f) <= 0:
        return None
    r = float(np.corrcoef(x, f)[0, 1])
    if not r < SIGN_CORRELATION:
        return None
    units = session.meta.get("import_units")
    unit = str(units.get("position", "")).split(" ")[0] if isinstance(units, dict) else ""
    if unit:
        flipped = unit[1:] if unit.startswith("-") else f"-{unit}"
        fix = f"pass --units position={flipped} (the closure was read as {unit})"
    else:
        fix = "negate the closure (--units position=-m, or -mm, -deg, ...)"
    return (
        f"the force falls as the jaws close (correlation {r:+.2f} between force and "
        "closure; tissue pushes back harder the more it is squeezed): is the closure's "
        f"sign reversed? {fix}"
    )


def _held_force_warning(session: Session) -> str | None:
    """A load cell read more slowly than the closure: the force holds each value for
    the same number of samples while the closure moves within them."""
    f, x = session.force, session.position
    changes = np.flatnonzero(np.diff(f) != 0)
    if changes.size < 20:
        return None
    runs = np.diff(changes)
    k = int(np.argmax(np.bincount(runs)))  # the commonest run: one read of the cell
    if k < 2 or np.mean(runs == 1) > 1 - HELD_SHARE:
        return None
    # a held value may repeat across reads (a slow force, a coarse ADC): runs are
    # multiples of one read, give or take a sample of jitter on longer reads
    off = np.abs(runs - k * np.round(runs / k))
    if np.mean(off <= (1 if k >= 4 else 0)) < HELD_SHARE:
        return None
    held = np.ones(f.size - 1, bool)
    held[changes] = False  # consecutive samples with the force held
    moves = np.diff(x) != 0
    if not moves.any() or np.mean(moves[held]) < 0.5 * np.mean(moves):
        return None  # the closure held with it: repeated samples, not a slow load cell
    rate = session.rate_hz
    force_rate = rate / k
    return (
        f"the load cell is read more slowly than the closure: the force changes only "
        f"every {k} samples ({force_rate:.4g} Hz, against {rate:.4g} Hz), too slowly for "
        "the motion, so the fitted damping and mass see a staircase; read the load cell "
        f"at {rate:.4g} Hz, or keep one sample in {k} of both channels"
    )


def _guess(value: float, limit: float, units: tuple[tuple[str, float], ...], column: str) -> str:
    for unit, factor in units:
        if value * factor <= limit:
            return f"is {column} in {unit}? pass --units {column}={unit}"
    return f"check the {column} column and its unit"
