"""The ``fit`` service: read a session, identify the tissue, export and report."""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from . import __version__, storage
from .errors import FitError
from .identify import BayesianFit, ModelResult, WindowedPinv
from .models import PARAMETERS
from .params import FORMAT_VERSION, write_json
from .session import Session


@dataclass
class FitOutcome:
    """What ``fit`` produced: the estimators and the exported document."""

    session: Session
    bayes: BayesianFit | None
    pinv: WindowedPinv | None
    document: dict[str, Any]


def _param_block(res: ModelResult) -> dict[str, Any]:
    post = res.posterior
    assert post is not None
    return {
        name: {
            "mean": float(post.mean[j]),
            "sd": float(post.sd[j]),
            "ci95": [float(post.ci95[j, 0]), float(post.ci95[j, 1])],
            "unit": res.model.units[name],
        }
        for j, name in enumerate(PARAMETERS)
    }


def document(
    session: Session, est: BayesianFit | None, pinv: WindowedPinv | None
) -> dict[str, Any]:
    """The parameter file (docs/formats.md): best model, uncertainty, evidence, provenance."""
    doc: dict[str, Any] = {
        "format": "tissuecli-parameters",
        "version": FORMAT_VERSION,
        "software": f"tissuecli {__version__}",
    }
    data = {
        "session": session.name,
        "file": str(session.meta.get("file", "")),
        "tissue": session.meta.get("tissue", ""),
        "samples": len(session),
        "duration_s": session.duration_s,
        "rate_hz": session.rate_hz,
    }
    if est is not None:
        best = est.best_
        kin = est.kinematics_
        doc["model"] = {"f0": best.model.f0.name, "f1": best.model.f1.name}
        doc["parameters"] = _param_block(best)
        doc["noise"] = {
            "sd": best.posterior.sigma_mean,  # type: ignore[union-attr]
            "ci95": list(best.posterior.sigma_ci95),
            "unit": "N",
        }  # type: ignore[union-attr]
        doc["evidence"] = {
            r.name: {
                "ln_evidence": r.ln_evidence,
                "ln_evidence_sampler": r.ln_evidence_sampler,
                "method": r.status,
                "note": r.reason,
            }
            for r in est.results_
        }
        doc["probabilities"] = {r.name: r.probability for r in est.results_}
        doc["models"] = {
            r.name: {
                "parameters": _param_block(r),
                "flags": r.flags,
                "cond": r.cond,
                "cond_scaled": r.cond_scaled,
                "residual_rms_N": r.residual_rms,
                "sampler": (r.posterior.diagnostics if r.posterior else {}),
            }
            for r in est.results_
        }
        doc["warnings"] = est.warnings_
        data.update(
            {
                "differentiator": kin.method,
                "cutoff_hz": kin.cutoff_hz,
                "noise_gain": {
                    "position": kin.noise_gain[0],
                    "velocity_per_s": kin.noise_gain[1],
                    "acceleration_per_s2": kin.noise_gain[2],
                },
                "samples_used": int(kin.time.size),
                "residual_tau_samples": est.tau_,
                "effective_samples": est.n_eff_,
                "position_noise_sd_m": est.sigma_x_,
            }
        )
    if pinv is not None:
        block = {
            name: {"value": float(pinv.params_[j]), "unit": pinv.model_.units[name]}
            for j, name in enumerate(PARAMETERS)
        }
        doc["pinv"] = {**pinv.summary(), "parameters": block}
        if est is None:
            doc["warnings"] = pinv.warnings_
            doc["model"] = {"f0": pinv.model_.f0.name, "f1": pinv.model_.f1.name}
            doc["parameters"] = {
                name: {"mean": v["value"], "unit": v["unit"]} for name, v in block.items()
            }
    doc["data"] = data
    return doc


def fit_session(
    session: Session,
    *,
    method: str = "bayes",
    forms: str = "all",
    sampler: str = "auto",
    differentiator: str = "gaussian",
    window_s: float = 1.0,
    force_scale: float = 20.0,
    seed: int = 0,
    progress: Callable[[str, int, float], None] | None = None,
) -> FitOutcome:
    """Identify the tissue in a session.

    Parameters
    ----------
    method : {"bayes", "pinv", "both"}
        Bayesian fit over the forms, the paper's windowed pseudoinverse, or both.
    forms : str
        ``"all"`` or one form such as ``"x,xdot"`` (pinv needs one; all gives x,xdot).
    sampler : {"auto", "emcee"}
    """
    if method not in ("bayes", "pinv", "both"):
        raise FitError(f"unknown method {method!r}; choose bayes, pinv or both")
    est = pinv = None
    if method in ("bayes", "both"):
        est = BayesianFit(
            forms,
            sampler=sampler,
            differentiator=differentiator,
            force_scale=force_scale,
            seed=seed,
            progress=progress,
        ).fit(session)
    if method in ("pinv", "both"):
        pinv_forms = (
            forms if forms != "all" else (est.best_.model.name if est is not None else "x,xdot")
        )
        pinv = WindowedPinv(pinv_forms, window_s=window_s, differentiator=differentiator).fit(
            session
        )
    return FitOutcome(session, est, pinv, document(session, est, pinv))


def load_session(path: str | os.PathLike[str], name: str | None) -> Session:
    """A stored session, with the ADC step of position when the file knows it."""
    s = storage.read_session(path, name)
    device = s.meta.get("device") or {}
    cal = (device.get("calibration") if isinstance(device, dict) else None) or {}
    gain = (cal.get("position") or {}).get("gain") if isinstance(cal, dict) else None
    if gain:
        s.meta["position_resolution_m"] = abs(float(gain))
    return s


def fit_file(
    path: str | os.PathLike[str],
    session: str | None = None,
    *,
    out: str | os.PathLike[str] | None = None,
    report: str | os.PathLike[str] | None = None,
    **options: Any,
) -> FitOutcome:
    """Fit a stored session; write the parameter file and the HTML report if asked."""
    s = load_session(path, session)
    outcome = fit_session(s, **options)
    if out is not None:
        write_json(out, outcome.document)
    if report is not None:
        from .report import write_report  # matplotlib only when a report is asked for

        write_report(report, outcome)
    return outcome


def summary_lines(outcome: FitOutcome) -> list[str]:
    """A short terminal summary."""
    lines = []
    s = outcome.session
    lines.append(
        f"session {s.name!r}: {len(s)} samples, {s.duration_s:.2f} s at {s.rate_hz:.0f} Hz"
    )
    est = outcome.bayes
    if est is not None:
        lines.append(f"{'form':<12} {'ln Z':>12} {'P':>7}  method")
        for r in est.results_:
            lines.append(f"{r.name:<12} {r.ln_evidence:12.2f} {r.probability:7.3f}  {r.status}")
        best = est.best_
        post = best.posterior
        assert post is not None
        lines.append(
            f"best: {best.name}  (noise {post.sigma_mean * 1e3:.2f} mN, "
            f"{est.n_eff_:.0f} effective samples)"
        )
        for j, name in enumerate(PARAMETERS):
            lo, hi = post.ci95[j]
            lines.append(
                f"  {name} = {post.mean[j]:.6g} ± {post.sd[j]:.2g} {best.model.units[name]}"
                f"  (95 % [{lo:.6g}, {hi:.6g}])"
            )
        lines.extend(f"warning: {w}" for w in est.warnings_)
    if outcome.pinv is not None:
        p = outcome.pinv
        vals = ", ".join(
            f"{n}={v:.6g} {p.model_.units[n]}" for n, v in zip(PARAMETERS, p.params_, strict=True)
        )
        lines.append(
            f"pinv ({p.model_.name}, best of {p.windows_.shape[0]} windows of "
            f"{p.window_samples_} samples): {vals}; cond {p.cond_:.3g}, scaled {p.cond_scaled_:.3g}"
        )
        if est is None:
            lines.extend(f"warning: {w}" for w in p.warnings_)
    return lines


def fitted_series(outcome: FitOutcome) -> dict[str, np.ndarray]:
    """Arrays for plots: time, measured (filtered) and fitted force, kinematics."""
    est = outcome.bayes
    if est is None:
        raise FitError("plots need the Bayesian fit")
    kin = est.kinematics_
    return {
        "time": kin.time,
        "force": kin.force,
        "fitted": est.fitted_force(),
        "x": kin.x,
        "v": kin.v,
        "a": kin.a,
    }
