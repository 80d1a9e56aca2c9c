"""What ``play`` and ``live`` print: their summaries as a few lines for people, the
faults last (the figures are :mod:`tissuecli.app.loopstats`', the faults
:mod:`tissuecli.app.faults`').
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any


def play_lines(summary: Mapping[str, Any]) -> list[str]:
    """The summary of :func:`~tissuecli.app.play.play` as a few lines for people."""

    def num(key: str, scale: float = 1.0, fmt: str = ".1f") -> str:
        value = summary.get(key)
        return "n/a" if value is None else format(value * scale, fmt)

    lines = [
        f"played {num('duration_s', fmt='.2f')} s: {summary.get('frames', 0)} frames at "
        f"{num('loop_rate_hz')} Hz (period p99 {num('period_p99_ms', fmt='.2f')} ms, max "
        f"{num('period_max_ms', fmt='.2f')} ms), {summary.get('frames_lost', 0)} lost, "
        f"{summary.get('frames_bad', 0)} bad, {summary.get('missed_periods', 0)} periods "
        "without a frame, " + _late(summary),
        f"tracking error rms {num('tracking_rms_m', 1e6, '.2f')} um, max "
        f"{num('tracking_max_m', 1e6)} um, bound {num('tracking_bound_m', 1e6)} um "
        "(|M - Mp| max|xp''| / (k + Cp) + encoder resolution)",
        f"saturated {num('saturated_fraction', 100, '.2f')} %, unrenderable "
        f"{num('unrenderable_fraction', 100, '.2f')} % of frames; watchdog frames "
        f"{summary.get('watchdog_frames', 0)}; solenoid work "
        f"{num('actuator_work_j', 1e3, '.3f')} mJ (> 0: energy created)",
        f"stopped: {summary.get('stop_reason', '')}",
    ]
    log = summary.get("log")
    if log:
        lines.append(f"log: {log['path']}, group {log['group']}")
    faults = summary.get("faults") or []
    lines.extend(f"FAULT: {f}" for f in faults)
    if faults:
        lines.append("the display did not render the tissue as checked (docs/rendering.md)")
    return lines


def _late(summary: Mapping[str, Any]) -> str:
    """``48 on a late answer (longest run 6)``: the periods the display ran on a command
    that did not answer its previous frame, as it reported them (else the host's count
    of frames it answered only together with a later one); from a display that renders
    late answers from their local model, how many it did and how many were beyond it."""
    stale = summary.get("stale_frames")
    if stale is None:
        return f"{summary.get('unanswered_frames', 0)} answered only with a later frame"
    modelled = summary.get("modelled_frames")
    if modelled is None:
        return f"{stale} on a late answer (longest run {summary.get('stale_run_max', 0)})"
    return (
        f"{stale + modelled} on a late answer (longest run {summary.get('late_run_max', 0)}), "
        f"{modelled} of them rendered from the display's local model and {stale} beyond it "
        f"(longest run {summary.get('stale_run_max', 0)})"
    )


def tissue_words(described: Mapping[str, Any] | None) -> str:
    """A tissue as :meth:`~tissuecli.core.tissue.Tissue.describe` gives it, in words:
    ``x+xdot+xddot: K = 350 N/m, S = 3.02 N s/m, M = 0.0501 kg``."""
    if not described:
        return "none"
    name = str(described.get("law", "?"))
    units = described.get("units") or {}
    parts = [
        f"{key} = {value:.4g}" + (f" {units[key]}" if key in units else "")
        for key, value in described.items()
        if key not in ("law", "units") and isinstance(value, (int, float))
    ]
    return f"{name}: " + ", ".join(parts) if parts else name


def live_lines(summary: Mapping[str, Any]) -> list[str]:
    """The summary of :func:`~tissuecli.app.live.live` as a few lines for people, the
    faults last."""
    rec, pas, ren = summary["recording"], summary["passivity"], summary.get("render") or {}
    delay = summary.get("first_render_delay_s")
    rms = summary.get("tracking_rms_n")
    estimate = summary.get("estimate") or {}
    sched = ren.get("realtime") or {}
    lines = [
        f"recorded {rec['samples']} samples ({rec['duration_s']:.2f} s) to {rec['path']}, "
        f"session {rec['session']}: {rec.get('lost_frames', 0)} lost, "
        f"{rec.get('bad_frames', 0)} bad, {rec.get('rejected_frames', 0)} rejected frames",
        f"online estimate: {estimate_words(estimate)}",
        f"rendered: {tissue_words(summary.get('rendered'))}"
        if summary.get("rendered")
        else "rendered: never",
        "first rendering "
        + (f"{delay:.2f} s after the grasp began" if delay is not None else "never"),
        f"display loop {ren.get('loop_rate_hz') or 0:.1f} Hz (period p99 "
        f"{ren.get('period_p99_ms') or 0:.2f} ms, max {ren.get('period_max_ms') or 0:.2f} ms), "
        f"{ren.get('missed_periods', 0)} periods without a frame, {_late(ren)}, watchdog frames "
        f"{ren.get('watchdog_frames', 0)}; scheduling {sched.get('scheduler', 'n/a')}",
        f"passivity: energy observed {pas['energy_observed_j'] * 1e3:.3f} mJ (min "
        f"{pas['energy_min_j'] * 1e3:.3f} mJ), dissipated "
        f"{pas['energy_dissipated_j'] * 1e3:.3f} mJ on {pas['acting_frames']} frames",
        f"offline law: {tissue_words(summary.get('offline'))}; rendered force vs offline "
        "law: RMS " + (f"{rms:.3f} N" if rms is not None else "n/a"),
        f"stopped: {summary.get('stop_reason', '')}",
    ]
    if summary.get("note"):
        lines.append(summary["note"])
    faults = summary.get("faults") or []
    lines.extend(f"FAULT: {f}" for f in faults)
    return lines


def estimate_words(estimate: Mapping[str, Any]) -> str:
    """The last online estimate (its ``as_dict``) in words: the law, its probability and
    each coefficient with half its 95 % interval and unit."""
    if not estimate:
        return "none (too few samples in contact)"
    law = estimate.get("law", "?")
    prob = (estimate.get("probabilities") or {}).get(law)
    head = f"{law}" + (f" ({100 * prob:.0f} %)" if isinstance(prob, (int, float)) else "")
    if not estimate.get("confident"):
        return f"{head}, not confident"
    parts = []
    for name, unit, mean, ci in zip(
        estimate.get("names", []),
        estimate.get("units", []),
        estimate.get("mean", []),
        estimate.get("ci95", []),
        strict=False,
    ):
        half = (ci[1] - ci[0]) / 2 if ci and None not in ci else math.nan
        parts.append(f"{name} {mean:.4g} +- {half:.2g} {unit}")
    return f"{head}: " + ", ".join(parts)
