"""Tissue parameter files (written by ``fit``, read by ``simulate`` and ``play``),
calibration files and display profile files; docs/formats.md describes them.

This module is the only owner of the parameter file's schema: it builds the
document from a fit, writes it, and reads a :class:`~tissuecli.core.tissue.Tissue`
back from it.
"""

from __future__ import annotations

import math
import os
from typing import TYPE_CHECKING, Any

from .._version import __version__
from ..core.calibration import Calibration, calibration_from_dict
from ..core.errors import InputError
from ..core.tissue import PARAMETERS, Tissue, TissueModel
from ..render.profile import DisplayProfile, profile_from_dict
from .jsonfile import read_json, write_json

if TYPE_CHECKING:  # a fit's results are read, never built, here
    from ..identify.bayes import ModelResult
    from ..identify.outcome import FitOutcome

FORMAT = "tissuecli-parameters"
FORMAT_VERSION = 1


def _header() -> dict[str, Any]:
    return {"format": FORMAT, "version": FORMAT_VERSION, "software": f"tissuecli {__version__}"}


def _model(model: TissueModel) -> dict[str, str]:
    return {"f0": model.f0.name, "f1": model.f1.name}


def tissue_to_dict(tissue: Tissue) -> dict[str, Any]:
    """The minimal parameter file for a tissue (``fit`` adds uncertainty and evidence)."""
    return {
        **_header(),
        "model": _model(tissue.model),
        "parameters": {
            name: {"mean": getattr(tissue, name), "unit": tissue.model.units[name]}
            for name in PARAMETERS
        },
    }


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


def document(outcome: FitOutcome) -> dict[str, Any]:
    """The parameter file of a fit (docs/formats.md): best model, uncertainty, evidence,
    provenance."""
    session, est, pinv = outcome.session, outcome.bayes, outcome.pinv
    doc = _header()
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
        doc["model"] = _model(best.model)
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
            doc["model"] = _model(pinv.model_)
            doc["parameters"] = {
                name: {"mean": v["value"], "unit": v["unit"]} for name, v in block.items()
            }
    doc["data"] = data
    return doc


def write_params(path: str | os.PathLike[str], outcome: FitOutcome) -> dict[str, Any]:
    """Write the parameter file of a fit to ``path`` (atomically); the document written."""
    data = document(outcome)
    write_json(path, data)
    return data


def tissue_from_dict(data: dict[str, Any], source: str = "parameter file") -> Tissue:
    """Parse the ``model`` and ``parameters`` of a parameter file into a :class:`Tissue`."""
    model_spec = data.get("model")
    params = data.get("parameters")
    if not isinstance(model_spec, dict) or not isinstance(params, dict):
        raise InputError(
            f'{source} needs "model": {{"f0": ..., "f1": ...}} and "parameters": '
            '{"K": {"mean": ...}, "S": {...}, "M": {...}} (see docs/formats.md)'
        )
    model = TissueModel.from_names(
        str(model_spec.get("f0", "x")), str(model_spec.get("f1", "xdot"))
    )
    values = {}
    for name in PARAMETERS:
        entry = params.get(name)
        mean = entry.get("mean") if isinstance(entry, dict) else entry
        if not isinstance(mean, (int, float)) or isinstance(mean, bool) or not math.isfinite(mean):
            raise InputError(f"{source}: parameters.{name}.mean must be a finite number")
        unit = entry.get("unit") if isinstance(entry, dict) else None
        if unit is not None and unit != model.units[name]:
            raise InputError(
                f"{source}: {name} is in {unit!r} but model {model.name} "
                f"needs {model.units[name]!r}"
            )
        values[name] = float(mean)
    return Tissue(model, **values).validate()


def read_tissue(path: str | os.PathLike[str]) -> Tissue:
    """Read a tissue parameter file."""
    return tissue_from_dict(read_json(path, "parameter"), source=str(path))


def read_calibration(path: str | os.PathLike[str]) -> Calibration:
    """Read a calibration file: ``{"force": {"gain", "offset"}, "position": {...}}`` in SI."""
    return calibration_from_dict(read_json(path, "calibration"))


def read_profile(path: str | os.PathLike[str]) -> DisplayProfile:
    """Read a display profile (JSON; see :func:`tissuecli.render.profile.profile_from_dict`)."""
    return profile_from_dict(read_json(path, "display profile"), source=str(path))
