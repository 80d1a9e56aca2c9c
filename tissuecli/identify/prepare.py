"""From a session to what the estimators fit: validated, on its sample grid, with lost
frames and clipped samples as holes, and differentiated without looking through them."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..core.errors import FitError
from ..core.session import Session
from .derivatives import Differentiator, Kinematics

MIN_SAMPLES = 200


def longest_gapless(session: Session) -> tuple[Session, list[str]]:
    """The longest stretch without gaps (lost frames), and a warning if that is not all of it.

    The derivative filters need evenly spaced samples; rather than refuse a
    session with a few lost frames, fit its longest gap-free stretch and say so.
    """
    steps = np.diff(session.time)
    if steps.size == 0:
        return session, []
    dt = float(np.median(steps))
    cuts = np.flatnonzero(np.abs(steps - dt) > 0.25 * dt) + 1
    if cuts.size == 0:
        return session, []
    edges = np.concatenate([[0], cuts, [len(session)]])
    i = int(np.argmax(np.diff(edges)))
    a, b = int(edges[i]), int(edges[i + 1])
    part = session.replace(session.time[a:b], session.force[a:b], session.position[a:b])
    return part, [
        f"the session has {cuts.size} gap(s) (lost frames); fitted the longest gap-free "
        f"stretch, {session.time[a]:.3f}-{session.time[b - 1]:.3f} s "
        f"({100 * (b - a) / len(session):.0f} % of the samples)"
    ]


def prepare(session: Session, diff: Differentiator) -> tuple[Session, Kinematics, list[str]]:
    """Validate a session, put it on its sample grid, check that it can identify anything,
    and differentiate it without looking through holes.

    Lost frames become holes in the sample grid (filled by interpolation so the
    filters run, but marked), and so do samples at either end of the ADC, when
    the session knows its ADC: a clipped value is not a measurement. Filtered
    samples whose window holds a hole are left out of the fit, so nothing else
    is lost. A grid that cannot be built (repeated or reordered sample times, or
    more lost than kept) falls back to the longest gap-free stretch.

    Returns
    -------
    session : Session
        What is fitted, on a regular grid; holes hold interpolated stand-ins.
    kinematics : Kinematics
    warnings : list of str
        Says what lost frames and clipping cost.
    """
    session.validate()
    n = len(session)
    if n < MIN_SAMPLES:
        raise FitError(f"session has {n} samples; at least {MIN_SAMPLES} are needed to fit")
    grid = on_grid(session)
    warnings: list[str] = []
    if grid is None:
        session, warnings = longest_gapless(session)
        if len(session) < MIN_SAMPLES:
            raise FitError(
                f"the session's sample times do not fall on one grid and its longest gap-free "
                f"stretch has {len(session)} samples; at least {MIN_SAMPLES} are needed to fit"
            )
        valid = np.ones(len(session), bool)
        lost = 0
    else:
        session, valid = grid
        lost = int(np.count_nonzero(~valid))
    x, f = (
        (session.position, session.force)
        if not lost
        else (u[valid] for u in (session.position, session.force))
    )
    if np.ptp(x) <= 0 or np.std(x) < 1e-9:
        raise FitError(
            "jaw position is constant: nothing to identify; the jaws must move "
            "while the forceps records"
        )
    if np.ptp(f) <= 0:
        raise FitError("force is constant: check the force sensor and its calibration")
    present = valid.copy()
    clipped = adc_ends(session)
    for _, mask in clipped:
        valid &= ~mask
    kin = diff(session.time, session.position, session.force, valid)
    if lost:
        gaps = int(np.count_nonzero(np.diff(present.astype(np.int8)) == 1))
        warnings.append(
            f"the session has {gaps} gap(s) ({lost} lost frame(s)): the fit leaves out the "
            "filtered samples whose window spans one"
        )
    for message, mask in clipped:
        warnings.append(
            f"{message} in {100 * np.mean(mask[present]):.1f} % of samples: clipped values are "
            "not measurements, so the fit leaves out the filtered samples whose window holds "
            "one; grasp more gently or widen the sensor range"
        )
    if lost or clipped:
        full = len(session) - kin.window + 1
        warnings.append(
            f"{100 * (full - kin.time.size) / full:.1f} % of the filtered samples were left "
            "out for lost or clipped samples in their window"
        )
    return session, kin, warnings


def on_grid(session: Session) -> tuple[Session, NDArray[np.bool_]] | None:
    """The session on its regular sample grid, and which grid points were recorded.

    Lost samples get interpolated time, force and position, and ``False``.
    None when the times do not fall on one grid (repeated or reordered), or
    when more samples are missing than present.
    """
    t = session.time
    dt = float(np.median(np.diff(t)))
    k = np.rint((t - t[0]) / dt).astype(np.int64)
    if np.all(np.diff(k) == 1):
        return session, np.ones(len(session), bool)
    if np.any(np.diff(k) < 1) or k[-1] + 1 > 2 * k.size:
        return None
    dt = float((t[-1] - t[0]) / k[-1])  # refined over the whole span
    if np.max(np.abs(t - t[0] - k * dt)) > 0.25 * dt:
        return None
    grid = np.arange(k[-1] + 1)
    valid = np.zeros(grid.size, bool)
    valid[k] = True
    filled = session.replace(*(np.interp(grid, k, u) for u in (t, session.force, session.position)))
    return filled, valid


def adc_ends(session: Session) -> list[tuple[str, NDArray[np.bool_]]]:
    """Samples at either end of the ADC, per channel that has any, when the session
    knows its ADC (as recordings do): ``(description, mask)``."""
    adc = session.adc
    if adc is None:
        return []
    out = []
    for channel, values in (("force", session.force), ("position", session.position)):
        ends, half = adc.ends(channel), adc.step(channel) / 2
        mask = (np.abs(values - ends[0]) < half) | (np.abs(values - ends[1]) < half)
        if np.any(mask):
            where = f"({ends[0]:.4g} or {ends[1]:.4g})"
            out.append((f"{channel} is at an end of the {adc.bits}-bit ADC {where}", mask))
    return out
