"""When a run of the haptic loop is faulty: the rules of ``play`` and ``live``, each
fault with the exit status of its class (docs/rendering.md, "When a play is faulty").

The loop (:class:`~tissuecli.app.play.HostLoop`) only counts; these rules judge its
figures afterwards, so the same figures read the same way in ``play``, ``live``,
``demo`` and the benchmarks.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from ..core.errors import (
    EXIT_LOST_DATA,
    EXIT_NOT_RENDERED,
    EXIT_OFF_RATE,
    EXIT_WATCHDOG,
)

#: When a play is faulty (docs/rendering.md, "When a play is faulty"): the loop's rate
#: (the display's frames the host ran through the loop per second) more than this
#: fraction off nominal (on an idle machine it stays within 0.2 %) ...
MAX_RATE_ERROR = 0.02
#: ... more periods without a frame, more periods the display ran on a late answer, or
#: more frames lost or corrupt on the line, than this fraction of the frames (each such
#: period runs on a stale voltage; normal plays on a 2-core machine running the
#: simulated display miss 0.1-1.1 %) ...
MAX_MISSED_FRACTION = 0.05
#: ... the tracking error above its bound plus the check's soft gap (where the tissue is
#: softer than the display's spring) by more than this, m: the bound holds for an
#: unclamped law in steady state, and touch-down transients, the estimator's lag and
#: frames where the solenoid is clamped added up to 0.27 mm at most over 197 random
#: tissues the check accepts, on the offline loop ...
TRACKING_ALLOWANCE_M = 4e-4
#: ... or more saturated or unrenderable frames than a tissue the check accepts shows
#: on the offline loop (at most 0.9 % and 11 % of all frames over 197 accepted tissues:
#: docs/rendering.md).
MAX_SATURATED_FRACTION = 0.05
MAX_UNRENDERABLE_FRACTION = 0.3


def play_faults(summary: Mapping[str, Any], rate_hz: float) -> list[str]:
    """What went wrong in a play, one short sentence each (empty if nothing did); see
    :func:`classify_faults` for the rules."""
    return [text for _, text in classify_faults(summary, rate_hz)]


def classify_faults(summary: Mapping[str, Any], rate_hz: float) -> list[tuple[int, str]]:
    """What went wrong in a play: ``(exit status of its class, sentence)`` each.

    A play is faulty when the display's watchdog cut the solenoid (watchdog frames
    > 0; :data:`~tissuecli.core.errors.EXIT_WATCHDOG`), the loop ran more than
    :data:`MAX_RATE_ERROR` off ``rate_hz`` or more than :data:`MAX_MISSED_FRACTION` of
    the periods went without a frame or ran on a late answer (``EXIT_OFF_RATE``), frames
    were lost or corrupt on the line beyond that fraction (``EXIT_LOST_DATA``), or the
    rendering left what the check promised (``EXIT_NOT_RENDERED``): the controller met a
    non-finite value, the tracking error exceeded its bound (plus the check's
    ``soft_gap_m``) by more than :data:`TRACKING_ALLOWANCE_M`, or the solenoid was
    saturated or unable to follow on more frames than :data:`MAX_SATURATED_FRACTION` and
    :data:`MAX_UNRENDERABLE_FRACTION`.
    A watchdog cut or a slow loop names what the loop's scheduling could guarantee.
    """

    def num(key: str) -> float:
        value = summary.get(key)
        return float(value) if isinstance(value, (int, float)) and value == value else 0.0

    faults: list[tuple[int, str]] = []
    frames = max(num("frames"), 1.0)
    sched = summary.get("realtime")
    scheduler = sched.get("scheduler") if isinstance(sched, Mapping) else None
    guarantee = (
        f"; the loop's longest period was {num('period_max_ms'):.3g} ms under {scheduler}"
        + ("" if scheduler == "SCHED_FIFO" else ", real-time scheduling not granted")
        if scheduler
        else ""
    )
    if num("watchdog_frames") > 0:
        limit = num("watchdog_periods") or 5  # as the display stated it, else the firmware's
        faults.append(
            (
                EXIT_WATCHDOG,
                f"the display's watchdog cut the solenoid on {num('watchdog_frames'):.0f} "
                f"frame(s): the host stopped answering for {limit:.0f} periods "
                f"({limit * 1e3 / rate_hz:g} ms)" + guarantee,
            )
        )
    rate = num("loop_rate_hz")
    if num("frames") > 1 and abs(rate - rate_hz) > MAX_RATE_ERROR * rate_hz:
        faults.append(
            (
                EXIT_OFF_RATE,
                f"the loop ran at {rate:.1f} Hz, {100 * abs(rate / rate_hz - 1):.1f} % off "
                f"{rate_hz:g} Hz (p99 period {num('period_p99_ms'):.2f} ms)",
            )
        )
    # periods on a late answer: as the display reports them, else the frames the host
    # could answer only together with a later one (a period on a stale voltage each)
    stale = summary.get("stale_frames")
    beyond = " beyond its local model" if summary.get("modelled_frames") is not None else ""
    late, what = (
        (num("stale_frames"), "the display ran {n:.0f} periods on a late answer" + beyond)
        if isinstance(stale, (int, float))
        else (num("unanswered_frames"), "{n:.0f} frames reached the host too late to answer")
    )
    if late > MAX_MISSED_FRACTION * frames:
        faults.append(
            (
                EXIT_OFF_RATE,
                what.format(n=late)
                + f" ({100 * late / frames:.1f} % of {frames:.0f}"
                + (
                    f", longest run {num('stale_run_max'):.0f})"
                    if isinstance(stale, (int, float))
                    else ")"
                ),
            )
        )
    if num("missed_periods") > MAX_MISSED_FRACTION * frames:
        faults.append(
            (
                EXIT_OFF_RATE,
                f"{num('missed_periods'):.0f} periods passed without a frame "
                f"({100 * num('missed_periods') / frames:.1f} % of {frames:.0f})",
            )
        )
    lost = num("frames_lost") + num("frames_bad")
    if lost > MAX_MISSED_FRACTION * frames:
        faults.append((EXIT_LOST_DATA, f"{lost:.0f} frame(s) lost or corrupt on the line"))
    if num("nonfinite_frames") > 0:
        faults.append(
            (EXIT_NOT_RENDERED, f"{num('nonfinite_frames'):.0f} frame(s) with non-finite values")
        )
    err, bound = num("tracking_max_m"), summary.get("tracking_bound_m")
    check = summary.get("check")
    gap = check.get("soft_gap_m") if isinstance(check, Mapping) else None
    gap = float(gap) if isinstance(gap, (int, float)) else 0.0
    if isinstance(bound, (int, float)) and err > bound + gap + TRACKING_ALLOWANCE_M:
        faults.append(
            (
                EXIT_NOT_RENDERED,
                f"tracking error reached {err * 1e3:.3g} mm, above its bound "
                f"{bound * 1e3:.3g} mm"
                + (f" + soft gap {gap * 1e3:.3g} mm" if gap else "")
                + f" + {TRACKING_ALLOWANCE_M * 1e3:g} mm",
            )
        )
    for key, limit, what in (
        ("saturated_fraction", MAX_SATURATED_FRACTION, "saturated"),
        ("unrenderable_fraction", MAX_UNRENDERABLE_FRACTION, "unrenderable (a push asked)"),
    ):
        if num(key) > limit:
            faults.append(
                (
                    EXIT_NOT_RENDERED,
                    f"{100 * num(key):.1f} % of frames {what}, more than {100 * limit:g} %",
                )
            )
    return faults


def live_faults(summary: Mapping[str, Any], rate_hz: float) -> list[tuple[int, str]]:
    """What went wrong in a ``live`` run: ``(exit status of its class, sentence)`` each.

    The recording's lost, corrupt or rejected frames (``EXIT_LOST_DATA``), and the
    display loop's own faults as ``play`` judges them (the watchdog, a loop off its
    rate, missed periods, frames lost on the display's line; see
    :func:`classify_faults`). The tracking rules of ``play`` do not
    apply: the display rests at 0 V until the estimate is confident.
    """
    rec = summary.get("recording") or {}
    faults: list[tuple[int, str]] = []
    lost = [
        f"{n} {what}"
        for n, what in (
            (rec.get("lost_frames", 0), "frame(s) lost"),
            (rec.get("bad_frames", 0), "corrupt"),
            (rec.get("rejected_frames", 0), "rejected"),
        )
        if n
    ]
    if lost:
        faults.append((EXIT_LOST_DATA, "the recording lost data: " + ", ".join(lost)))
    render = summary.get("render") or {}
    if render.get("frames"):
        faults.extend(
            (code, text)
            for code, text in classify_faults(render, rate_hz)
            if code in (EXIT_WATCHDOG, EXIT_OFF_RATE, EXIT_LOST_DATA)
        )
    return faults
