"""One identification of one session: the Bayesian fit, the paper's pseudoinverse, or
both, as :func:`fit_session` runs them and :class:`FitOutcome` holds them."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..core.errors import FitError
from ..core.progress import Progress, as_progress
from ..core.session import Session
from .bayes import BayesianFit
from .contact import Contact
from .design import design
from .estimator import Estimator
from .pinv import WindowedPinv

METHODS = ("bayes", "pinv", "both")


@dataclass(frozen=True)
class HeldOut:
    """How well the fit predicts samples it did not see.

    Attributes
    ----------
    split_s : float
        The fit used the samples before this time; the score, those after, s.
    r2_fitted, r2_held_out : float
        Coefficient of determination of the filtered force on the fitted and on the
        held-out samples.
    rms_n : float
        RMS error of the predicted filtered force on the held-out samples, N.
    force_sd_n : float
        SD of the held-out filtered force, N (what predicting its mean would leave).
    samples : int
        Filtered samples scored.
    """

    split_s: float
    r2_fitted: float
    r2_held_out: float
    rms_n: float
    force_sd_n: float
    samples: int

    def describe(self) -> str:
        return (
            f"held out after {self.split_s:.3f} s: prediction error {self.rms_n:.4g} N RMS "
            f"against a force SD of {self.force_sd_n:.4g} N (R^2 {self.r2_held_out:.3f}; "
            f"{self.r2_fitted:.3f} on the fitted part), {self.samples} samples"
        )


#: fewest filtered samples a held-out part is scored on
MIN_HELD_OUT = 10


def held_out(est: Estimator, whole: Session, split_s: float) -> HeldOut:
    """Score a fitted estimator on the samples of ``whole`` after ``split_s``, which it
    did not see.

    The law runs over the whole session, fitted part and held-out part together, so a
    law with memory (relaxation) enters the held-out part with the history it has there:
    a hold at constant position is then predicted (the force relaxes), not refused.
    Scored are the filtered samples whose filter window lies wholly after the split,
    so no fitted sample reaches the score.
    """
    try:
        ready = est.prepare(whole)
    except FitError as e:
        reason = str(e).split(";")[0]
        raise FitError(
            f"the held-out part after {split_s:.3f} s cannot be scored ({reason}); hold out "
            "a larger fraction with --hold-out"
        ) from None
    kin = ready.kinematics
    law, coef = est._coefficients()
    predicted = design(law, kin, ready.closure, est._position_noise_sd()) @ coef
    dt = float(np.median(np.diff(ready.session.time)))
    after = kin.time >= split_s + (kin.window // 2 - 0.5) * dt
    if np.count_nonzero(after) < MIN_HELD_OUT:
        raise FitError(
            f"the held-out part after {split_s:.3f} s cannot be scored (it leaves "
            f"{np.count_nonzero(after)} filtered samples, {MIN_HELD_OUT} needed); hold out "
            "a larger fraction with --hold-out"
        )
    y, resid = kin.force[after], kin.force[after] - predicted[after]
    total = y - np.mean(y)
    return HeldOut(
        split_s=split_s,
        r2_fitted=est.score(),
        r2_held_out=1.0 - float(resid @ resid) / max(float(total @ total), 1e-300),
        rms_n=float(np.sqrt(np.mean(resid**2))),
        force_sd_n=float(np.std(y)),
        samples=int(y.size),
    )


@dataclass
class FitOutcome:
    """What :func:`fit_session` produced.

    Attributes
    ----------
    session : Session
        The session as given.
    bayes : BayesianFit or None
        The fitted Bayesian estimator (methods ``bayes`` and ``both``).
    pinv : WindowedPinv or None
        The fitted pseudoinverse (methods ``pinv`` and ``both``).
    grasps : {"all", "none"} or list of int
        The grasps asked for.
    validation : HeldOut or None
        The prediction error on held-out samples, when some were held out.
    """

    session: Session
    bayes: BayesianFit | None
    pinv: WindowedPinv | None
    grasps: str | Sequence[int] = "all"
    validation: HeldOut | None = None

    def _repr_html_(self) -> str:
        """A notebook's view: the chosen law with its coefficients (mean, SD, 95 %
        interval, unit), the best few laws with their probabilities, the held-out
        score and the warnings. Plain HTML, no figure (``tissuecli fit --report`` and
        :func:`tissuecli.report.render_report` draw those)."""
        from html import escape

        s = self.session
        parts = [
            f"<b>tissuecli fit</b> of session {escape(repr(s.name))}: {len(s):,} samples, "
            f"{s.duration_s:.3g} s at {s.rate_hz:.4g} Hz"
        ]
        cell = "style='text-align:right;padding:0 .6em'"
        if self.bayes is not None:
            best = self.bayes.best_
            post = best.posterior
            assert post is not None
            parts.append(
                f"<p>Chosen law <b>{escape(best.name)}</b>, posterior probability "
                f"{best.probability:.3g} among {len(self.bayes.results_)} laws</p>"
            )
            rows = "".join(
                f"<tr><td>{escape(t.symbol)}</td><td {cell}>{post.mean[j]:.6g}</td>"
                f"<td {cell}>{post.sd[j]:.2g}</td><td {cell}>[{post.ci95[j][0]:.6g}, "
                f"{post.ci95[j][1]:.6g}]</td><td>{escape(t.unit)}</td>"
                f"<td>{escape(t.name)}</td></tr>"
                for j, t in enumerate(best.model.terms)
            )
            parts.append(
                "<table><tr><th>parameter</th><th>mean</th><th>SD</th><th>95 % interval</th>"
                f"<th>unit</th><th>term</th></tr>{rows}</table>"
            )
            top = "".join(
                f"<tr><td>{escape(r.name)}</td><td {cell}>{r.probability:.3g}</td>"
                f"<td {cell}>{r.ln_evidence:.2f}</td></tr>"
                for r in self.bayes.results_[:5]
            )
            parts.append(
                "<details><summary>best laws</summary><table><tr><th>law</th>"
                f"<th>probability</th><th>ln evidence</th></tr>{top}</table></details>"
            )
        if self.pinv is not None:
            p = self.pinv
            values = ", ".join(
                f"{escape(t.symbol)} = {v:.6g} {escape(t.unit)}"
                for t, v in zip(p.model_.terms, p.params_, strict=True)
            )
            parts.append(f"<p>Windowed pseudoinverse ({escape(p.model_.name)}): {values}</p>")
        if self.validation is not None:
            parts.append(f"<p>{escape(self.validation.describe())}</p>")
        warnings = self.warnings
        if warnings:
            items = "".join(f"<li>{escape(w)}</li>" for w in warnings)
            parts.append(f"<p>Warnings:</p><ul>{items}</ul>")
        return "<div>" + "".join(parts) + "</div>"

    @property
    def warnings(self) -> list[str]:
        """What the user should know: what the session's recording lost (see
        :func:`session_warnings`), then the Bayesian fit's warnings, else the
        pseudoinverse's."""
        fit = (
            self.bayes.warnings_
            if self.bayes is not None
            else self.pinv.warnings_
            if self.pinv is not None
            else []
        )
        return session_warnings(self.session) + list(fit)

    @property
    def contact(self) -> Contact:
        """The grasps found in the fitted part of the session."""
        fitted = self.bayes if self.bayes is not None else self.pinv
        assert fitted is not None
        return fitted.contact_

    @property
    def fitted_grasps(self) -> list[int]:
        """Numbers (from 1) of the grasps the fit used; empty for a session in contact
        throughout or fitted with ``grasps="none"``."""
        contact = self.contact
        if contact.all_contact or self.grasps == "none" or not contact.kept_to_grasps:
            return []
        if self.grasps == "all":
            return list(range(1, len(contact.grasps) + 1))
        return sorted(set(self.grasps))


def recording_state(session: Session) -> dict[str, Any]:
    """What the session's attributes say of its recording, JSON-ready: ``complete``
    (True, False, or None when the session does not say), ``frames_lost``,
    ``frames_bad`` (0 when not recorded) and ``stop_reason``."""
    meta = session.meta
    complete = meta.get("complete")
    known = complete is not None and not (isinstance(complete, str) and not complete)
    return {
        "complete": bool(complete) if known else None,
        "frames_lost": _count(meta.get("frames_lost")),
        "frames_bad": _count(meta.get("frames_bad")),
        "stop_reason": str(meta.get("stop_reason") or ""),
    }


def _count(value: Any) -> int:
    try:
        return max(int(value), 0)
    except (TypeError, ValueError, OverflowError):
        return 0


def session_warnings(session: Session) -> list[str]:
    """Warnings about the data itself: an incomplete recording (``complete`` False: the
    recorder crashed or was killed, so the last samples are missing) and frames lost or
    rejected as corrupt on the line."""
    state = recording_state(session)
    out = []
    if state["complete"] is False:
        why = f" (stop reason: {state['stop_reason'][:80]})" if state["stop_reason"] else ""
        out.append(
            f"session {session.name[:60]!r} is incomplete: its recording never closed{why}, "
            f"as after a crash or kill; fitted the {len(session)} samples committed before "
            "it ended"
        )
    lost, bad = state["frames_lost"], state["frames_bad"]
    if lost or bad:
        out.append(
            f"the recording lost {lost} frame(s) and rejected {bad} corrupt frame(s): the "
            "fit uses the samples that arrived, leaving out those beside the holes; "
            "check the cable and the line rate"
        )
    return out


def fit_session(
    session: Session,
    *,
    method: str = "bayes",
    forms: str = "all",
    sampler: str = "auto",
    differentiator: str = "gaussian",
    window_s: float = 1.0,
    force_scale: float | None = None,
    seed: int = 0,
    grasps: str | Sequence[int] = "all",
    start_s: float | None = None,
    end_s: float | None = None,
    hold_out: float = 0.0,
    progress: Progress | Callable[[str, int, float], None] | None = None,
) -> FitOutcome:
    """Identify the tissue in a session.

    Parameters
    ----------
    session : Session
        Time (s), force (N) and closure (m).
    method : {"bayes", "pinv", "both"}
        Bayesian fit over the forms, the paper's windowed pseudoinverse, or both.
    forms : str
        ``"all"``, ``"paper"`` or one law such as ``"x,xdot"`` (pinv needs one; with
        ``all`` it takes the Bayesian choice, or x,xdot alone).
    sampler : {"auto", "emcee"}
        See :class:`BayesianFit`.
    differentiator : str
        A name in :data:`~tissuecli.identify.derivatives.DIFFERENTIATORS`.
    window_s : float
        Pseudoinverse window, s.
    force_scale : float, optional
        Prior scale, N (see :class:`BayesianFit`); by default from the session.
    seed : int
        Seed of the sampler and of the plotted posterior draws.
    grasps : {"all", "none"} or list of int
        Which grasps to fit (see :class:`BayesianFit`).
    start_s, end_s : float, optional
        Fit only the samples between these times, s (the session's own clock).
    hold_out : float
        Fraction of the (windowed) session, at its end, kept out of the fit and
        predicted to score it (:class:`HeldOut`); 0 holds nothing out.
    progress : Progress or callable, optional
        Told each stage (see :class:`~tissuecli.core.progress.Progress`); a bare
        callable is called ``progress(form, steps, tau)`` while sampling.
    """
    if method not in METHODS:
        raise FitError(f"unknown method {method!r}; choose bayes, pinv or both")
    part = session.window(start_s, end_s) if start_s is not None or end_s is not None else session
    rest = None
    if hold_out:
        if not 0.0 < hold_out < 1.0:
            raise FitError(f"--hold-out {hold_out:g}: give a fraction between 0 and 1, e.g. 0.3")
        t = part.time
        i = int(np.searchsorted(t, t[0] + (1.0 - hold_out) * (t[-1] - t[0])))
        whole = part
        part, rest = (
            part.replace(t[:i], part.force[:i], part.position[:i]),
            part.replace(t[i:], part.force[i:], part.position[i:]),
        )
    est = pinv = None
    if method in ("bayes", "both"):
        est = BayesianFit(
            forms,
            sampler=sampler,
            differentiator=differentiator,
            force_scale=force_scale,
            seed=seed,
            grasps=grasps,
            progress=progress,
        ).fit(part)
    if method in ("pinv", "both"):
        as_progress(progress).stage("windowed pseudoinverse")
        pinv_forms = (
            forms if forms != "all" else (est.best_.model.name if est is not None else "x,xdot")
        )
        pinv = WindowedPinv(
            pinv_forms, window_s=window_s, differentiator=differentiator, grasps=grasps
        ).fit(part)
    fitted = est if est is not None else pinv
    assert fitted is not None
    if rest is not None:
        as_progress(progress).stage("scoring the held-out part")
    validation = held_out(fitted, whole, float(rest.time[0])) if rest is not None else None
    return FitOutcome(session, est, pinv, grasps, validation)
