"""The whole pipeline on simulated devices, in one call."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path

from ..core.errors import EXIT_LOST_DATA, RunFault, worst_fault
from ..core.tissue import DEFAULT_TISSUE
from ..formats.outputs import Output, check_outputs
from ..formats.params import read_tissue
from ..formats.sessions import list_sessions, session_names
from ..render.check import check
from ..render.profile import PAPER_DISPLAY
from ..sim.process import SimulatorProcess
from .faults import classify_faults
from .fit import fit_file
from .play import play
from .record import record
from .summaries import play_lines
from .transfer import export_csv


def run_demo(
    duration_s: float = 5.0,
    workdir: str | os.PathLike[str] | None = None,
    say: Callable[[str], None] = print,
    force: bool = False,
) -> dict[str, str]:
    """Simulate a forceps, record, list, export and fit the session, then play the fitted
    tissue on a simulated display; return the files made.

    Parameters
    ----------
    duration_s : float
        Seconds to record.
    workdir : path, optional
        Where to keep the files; a temporary directory (removed afterwards) by default.
    say : callable
        Receives one line of narration per step.
    force : bool
        Replace the CSV, parameter file and report in ``workdir`` if they exist (the
        HDF5 files only ever gain a session or a play log).

    Raises
    ------
    RunFault
        After every step is narrated, when the recording lost frames or the play was
        faulty; its ``exit_code`` is the class of the worst fault (docs/usage.md).
    DeviceLost
        When a simulated device went (exit 7).
    """
    with ExitStack() as stack:
        if workdir is None:
            root = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="tissuecli-demo-")))
        else:
            root = Path(workdir)
            root.mkdir(parents=True, exist_ok=True)
        h5, csv = root / "grasp.h5", root / "demo.csv"
        params, report, log = root / "tissue.json", root / "report.html", root / "play.h5"
        check_outputs(
            [
                Output(h5, "--dir", appends=True),
                Output(csv, "--dir"),
                Output(params, "--dir"),
                Output(report, "--dir"),
                Output(log, "--dir", appends=True),
            ],
            force=force,
        )
        t = DEFAULT_TISSUE
        say(
            f"1. simulated forceps: {t.law.name} tissue K={t.K:g} N/m, S={t.S:g} N s/m, "
            f"M={t.M:g} kg, 1 kHz, 8-bit ADC"
        )
        with SimulatorProcess("forceps", root / "forceps", ["--seed", "1"]) as sim:
            say(f"   listening on {sim.link}")
            name = f"demo-{len(session_names(h5)) + 1}" if h5.exists() else "demo-1"
            res = record(str(sim.link), h5, name, duration_s=duration_s, tissue="simulated liver")
        say(
            f"2. recorded {res.samples} samples ({res.duration_s:.2f} s at {res.rate_hz:.1f} Hz), "
            f"{res.lost_frames} lost, {res.bad_frames} bad frames -> {h5} session {name!r}"
        )
        faults: list[tuple[int, str]] = []
        lost = res.lost_frames + res.bad_frames + res.faults.frames_rejected
        if lost:
            faults.append((EXIT_LOST_DATA, f"the recording lost {lost} frame(s)"))
        for row in list_sessions(h5):
            say(
                f"3. {row['name']}: {row['samples']} samples, {row['duration_s']:.3f} s, "
                f"{row['rate_hz']:.1f} Hz"
            )
        export_csv(h5, name, csv, force=force)
        say(f"4. exported to {csv}")
        outcome = fit_file(h5, name, out=params, report=report, force=force)
        best = outcome.bayes.best_  # type: ignore[union-attr]
        post = best.posterior
        say(f"5. fitted all laws: {best.name} chosen with probability {best.probability:.3f}")
        for j, term in enumerate(best.model.terms):
            truth = t.get(term.symbol, float("nan"))
            error = (
                f"true {truth:g}, error {100 * (post.mean[j] / truth - 1):+.2f} %"
                if truth
                else "true 0"
                if truth == 0
                else "not in the simulated law"
            )
            say(f"   {term.symbol} = {post.mean[j]:.5g} ± {post.sd[j]:.2g} {term.unit}  ({error})")
        for w in outcome.bayes.warnings_:  # type: ignore[union-attr]
            say(f"   warning: {w}")
        say(f"   parameters -> {params}, report -> {report}")
        tissue = read_tissue(params)
        verdict = check(tissue, PAPER_DISPLAY, 1000.0)
        say(f"6. display check: {verdict.verdict}")
        with SimulatorProcess("display", root / "display") as disp:
            # a loop process of its own: this one has run the fit, and its threads would
            # share an interpreter lock with the haptic loop
            summary = play(
                tissue, str(disp.link), duration_s=min(duration_s, 5.0), log=log, loop="process"
            )
        say("7. played the fitted tissue on the simulated display:")
        for line in play_lines(summary):
            say(f"   {line}")
        limit = summary.get("watchdog_periods") or 5
        say(
            f"   display watchdog {limit} periods ({limit:g} ms), as the simulated display "
            "judged it against its port at start-up (the firmware's: 5)"
        )
        sched = summary.get("realtime") or {}
        say(
            f"   scheduling: haptic loop {sched.get('scheduler', 'n/a')}, simulated display "
            f"{sched.get('display_scheduler') or 'n/a'}"
        )
        faults.extend(classify_faults(summary, 1000.0))
        if workdir is None:
            say("   (temporary files removed; pass --dir DIR to keep them)")
        if faults:
            raise RunFault(
                "the demo ran with faults: " + "; ".join(text for _, text in faults),
                worst_fault({code for code, _ in faults}),
            )
        return {
            "h5": str(h5),
            "csv": str(csv),
            "session": name,
            "params": str(params),
            "report": str(report),
            "play_log": str(log),
        }
