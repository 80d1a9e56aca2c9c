"""The ``fit`` service: read a session, identify the tissue, write the parameter file and
the report."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from ..core.errors import InputError, Interrupted
from ..core.progress import as_progress
from ..core.session import Session
from ..formats.atomic import write_bytes_atomic, write_text_atomic
from ..formats.draws import structures_path, write_draws
from ..formats.outputs import Output, check_directory_outputs, check_outputs
from ..formats.params import write_params
from ..formats.sessions import is_session_file, read_session, session_rows
from ..identify.outcome import FitOutcome, fit_session
from ..identify.stream import StreamedFit
from .transfer import load_session, may_hold_more_rows, staged_recording

#: a stored session longer than this (samples) is fitted from sums streamed block by
#: block (:class:`~tissuecli.identify.stream.StreamedFit`): the full fit keeps about
#: 600 bytes a sample, the streamed one a fixed few hundred MB
STREAM_ABOVE = 2_000_000
#: the streamed fit's pilot stretch and block, samples
STREAM_PILOT = 400_000
STREAM_BLOCK = 500_000


def fit_file(
    path: str | os.PathLike[str],
    session: str | None = None,
    *,
    out: str | os.PathLike[str] | None = None,
    report: str | os.PathLike[str] | None = None,
    force: bool = False,
    reading: dict[str, Any] | None = None,
    draws: str | os.PathLike[str] | None = None,
    plots: str | os.PathLike[str] | None = None,
    plot_format: str = "png",
    **options: Any,
) -> FitOutcome:
    """Fit a stored session, or another logger's recording read on the fly; write the
    parameter file and the HTML report if asked.

    Parameters
    ----------
    path : path
        A tissuecli HDF5 file, or any recording ``import`` reads (text table, .mat,
        .npz).
    session : str, optional
        Session name (may be omitted when the file holds one); for a recording, the
        name it is given (default: the file's name).
    out, report : path, optional
        Parameter file (JSON) and HTML report to write (checked before the fit).
    force : bool
        Replace ``out`` and ``report`` if they exist (never the file read).
    reading : dict, optional
        For a recording: ``columns``, ``units``, ``jaw_length_m``, ``rate_hz``, as
        :func:`tissuecli.app.transfer.import_recording` takes them.
    draws : path, optional
        CSV of the chosen law's posterior draws, and beside it the structure
        probabilities (:mod:`tissuecli.formats.draws`).
    plots : path, optional
        Directory to write the report's plots into, as files (created if missing).
    plot_format : {"png", "svg", "pdf"}
        Format of those files.
    **options
        Passed to :func:`tissuecli.identify.fit_session` (method, forms, sampler, ...).

    Returns
    -------
    FitOutcome
        For a recording, ``outcome.session.meta["import_report"]`` holds the lines
        that say how it was read (columns, units, time base), as ``import`` prints.
    """
    check_outputs(
        [
            Output(out, "--out") if out else None,
            Output(report, "--report") if report else None,
            Output(draws, "--draws") if draws else None,
            Output(structures_path(draws), "--draws") if draws else None,
        ],
        [path],
        force=force,
    )
    if draws and options.get("method", "bayes") == "pinv":
        raise InputError(
            "--draws needs the Bayesian fit (--method bayes or both): the windowed "
            "pseudoinverse has no posterior"
        )
    if plots is not None:
        check_plots(plots, plot_format, force=force)
    progress = as_progress(options.get("progress"))
    # outputs this run creates; an interrupted run removes them (a finished one keeps them)
    made = [
        Path(o)
        for o in (out, report, draws, structures_path(draws) if draws else None)
        if o is not None and not Path(o).exists()
    ]
    try:
        outcome = _streamed(path, session, reading, options, progress)
        if outcome is None:
            progress.stage(f"reading {os.fspath(path)}")
            data, read = load_session(path, session, **(reading or {}))
            if read is not None:
                data.meta["import_report"] = read.lines()
            outcome = fit_session(data, **options)
        if out is not None:
            write_params(out, outcome)
        if draws is not None:
            write_draws(draws, outcome)
        if report is not None:
            progress.stage("writing the report")
            write_report(report, outcome)
        if plots is not None:
            progress.stage("writing the plots")
            write_plots(plots, outcome, plot_format)
    except (KeyboardInterrupt, Interrupted):
        for made_path in made:
            made_path.unlink(missing_ok=True)
        raise
    finally:
        progress.close()
    return outcome


def _streamed(
    path: str | os.PathLike[str],
    session: str | None,
    reading: dict[str, Any] | None,
    options: dict[str, Any],
    progress: Any,
) -> FitOutcome | None:
    """The fit of a stored session too long to hold, from streamed sums; None where the
    session is short enough, or the options ask for what only the full fit gives (the
    pseudoinverse, a time window, held-out samples, the sampler)."""
    plain = (
        options.get("method", "bayes") == "bayes"
        and not options.get("hold_out")
        and options.get("start_s") is None
        and options.get("end_s") is None
        and options.get("sampler", "auto") == "auto"
    )
    if not plain:
        return None
    if may_hold_more_rows(path, STREAM_ABOVE):
        # another logger's long recording: stored block by block as `import` stores it,
        # then fitted from there as a stored session is
        with staged_recording(path, session, **(reading or {})) as (h5, name):
            outcome = _streamed(h5, name, None, options, progress)
            if outcome is not None:
                outcome.session.meta["file"] = os.fspath(path)
            return outcome
    if any(v is not None for v in (reading or {}).values()) or not is_session_file(path):
        return None
    rows = session_rows(path, session)
    if rows <= STREAM_ABOVE:
        return None
    name = session

    def read(a: int, b: int) -> Session:
        return read_session(path, name, rows=(a, b))

    bayes = {
        k: options[k]
        for k in ("forms", "differentiator", "force_scale", "seed", "grasps")
        if k in options
    }
    bayes["progress"] = progress
    fit = StreamedFit(STREAM_PILOT, STREAM_BLOCK, bayes=bayes).fit(read, rows, progress)
    pilot = fit.pilot_
    a, b = fit.pilot_rows_
    note = (
        f"{rows:,} samples: too many to hold, so fitted from sums streamed block by "
        f"block; the filter, noise, data weight and candidate laws come from samples "
        f"{a:,} to {b:,} fitted in full, and the plots show those"
    )
    if fit.skipped_blocks_:
        note += f"; {fit.skipped_blocks_} block(s) too irregular to filter were left out"
    pilot.results_, pilot.best_, pilot.n_eff_ = fit.results_, fit.best_, fit.n_eff_
    pilot.warnings_ = [note, *fit.warnings_]
    shown = pilot.session_
    shown.meta["streamed"] = {"rows": rows, "pilot_rows": [a, b], "summed": fit.n_samples_}
    return FitOutcome(session=shown, bayes=pilot, pinv=None, grasps=options.get("grasps", "all"))


def check_plots(
    directory: str | os.PathLike[str], plot_format: str, *, force: bool = False
) -> None:
    """Refuse, before the fit, a plot directory that cannot take the plots."""
    from ..report import PLOT_FORMATS, PLOT_NAMES

    if plot_format not in PLOT_FORMATS:
        raise InputError(f"--plot-format {plot_format}: choose one of {', '.join(PLOT_FORMATS)}")
    names = [f"{name}.{plot_format}" for name in PLOT_NAMES]
    check_directory_outputs(directory, names, "--plots", force=force)


def plots_beside(report: str | os.PathLike[str]) -> str:
    """Where ``--plot-format`` alone puts the plots: beside the report, in a directory
    named after it (``lab.html`` -> ``lab_plots``)."""
    path = os.fspath(report)
    stem, _ = os.path.splitext(path)
    return f"{stem}_plots"


def write_plots(
    directory: str | os.PathLike[str], outcome: FitOutcome, plot_format: str = "png"
) -> list[str]:
    """Write the report's plots into ``directory`` (created if missing), each file
    atomically; returns their paths."""
    from ..report import plot_files  # matplotlib only when plots are asked for

    os.makedirs(directory, exist_ok=True)
    written = []
    for name, data in plot_files(outcome, plot_format).items():
        target = os.path.join(directory, name)
        write_bytes_atomic(target, data)
        written.append(target)
    return written


def write_report(path: str | os.PathLike[str], outcome: FitOutcome) -> None:
    """Write the HTML report of a fit to ``path`` (atomically)."""
    from ..report import render_report  # matplotlib only when a report is asked for

    write_text_atomic(path, render_report(outcome))


#: grasps listed one per line in the summary; more are counted
LISTED_GRASPS = 12


def grasp_lines(outcome: FitOutcome) -> list[str]:
    """The grasps found, one line each (none for a session in contact throughout)."""
    contact = outcome.contact
    if contact.all_contact:
        return []
    fitted = set(outcome.fitted_grasps)
    lines = [
        f"{len(contact.grasps)} grasp(s) against a free-jaw baseline of "
        f"{contact.baseline_n:.4g} N; fitted: "
        + (
            ", ".join(map(str, sorted(fitted)))
            if fitted
            else "every sample" + (" (--grasps none)" if outcome.grasps == "none" else "")
        )
    ]
    for i, g in enumerate(contact.grasps[:LISTED_GRASPS], 1):
        mark = "*" if i in fitted else " "
        lines.append(
            f" {mark}{i:3d}  {g.start_s:9.3f}-{g.end_s:.3f} s  ({g.duration_s:.2f} s, "
            f"peak {g.peak_force_n:.3g} N)"
        )
    if len(contact.grasps) > LISTED_GRASPS:
        lines.append(f"  ... and {len(contact.grasps) - LISTED_GRASPS} more")
    return lines


def summary_lines(outcome: FitOutcome) -> list[str]:
    """A short terminal summary."""
    s = outcome.session
    read = s.meta.get("import_report", [])
    lines = ["read as another logger's recording:", *(f"  {line}" for line in read)] if read else []
    streamed = s.meta.get("streamed")
    if streamed:
        a, b = streamed["pilot_rows"]
        lines.append(
            f"session {s.name!r}: {streamed['rows']:,} samples at {s.rate_hz:.0f} Hz, "
            f"fitted from sums streamed block by block (the pilot: samples {a:,} to {b:,})"
        )
    else:
        lines.append(
            f"session {s.name!r}: {len(s)} samples, {s.duration_s:.2f} s at {s.rate_hz:.0f} Hz"
        )
    lines.extend(grasp_lines(outcome))
    est = outcome.bayes
    if est is not None:
        width = max(len(r.name) for r in est.results_)
        lines.append(f"{'law':<{width}} {'ln Z':>12} {'P':>7}  method")
        for r in est.results_:
            lines.append(
                f"{r.name:<{width}} {r.ln_evidence:12.2f} {r.probability:7.3f}  {r.status}"
            )
        best = est.best_
        post = best.posterior
        assert post is not None
        lines.append(
            f"best: {best.name}  (noise {post.sigma_mean * 1e3:.2f} mN, "
            f"{est.n_eff_:.0f} effective samples)"
        )
        for j, t in enumerate(best.model.terms):
            lo, hi = post.ci95[j]
            lines.append(
                f"  {t.symbol} = {post.mean[j]:.6g} ± {post.sd[j]:.2g} {t.unit}"
                f"  (95 % [{lo:.6g}, {hi:.6g}]; {t.name})"
            )
    if outcome.pinv is not None:
        p = outcome.pinv
        vals = ", ".join(
            f"{t.symbol}={v:.6g} {t.unit}" for t, v in zip(p.model_.terms, p.params_, strict=True)
        )
        lines.append(
            f"pinv ({p.model_.name}, best of {p.windows_.shape[0]} windows of "
            f"{p.window_samples_} samples): {vals}; cond {p.cond_:.3g}, scaled {p.cond_scaled_:.3g}"
        )
    if outcome.validation is not None:
        lines.append(outcome.validation.describe())
    lines.extend(f"warning: {w}" for w in outcome.warnings)
    return lines
