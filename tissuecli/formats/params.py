"""Tissue parameter files (written by ``fit``, read by ``simulate`` and ``play``),
calibration files and display profile files; docs/formats.md describes them.

This module is the only owner of the parameter file's schema: it builds the
document from a fit, writes it, and reads a :class:`~tissuecli.core.tissue.Tissue`
back from it.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from .._version import __version__
from ..core.calibration import SI_UNITS, Calibration, calibration_from_dict
from ..core.errors import InputError
from ..core.forms import FORMS
from ..core.tissue import PARAMETERS, Tissue, TissueModel
from ..render.profile import DisplayProfile, profile_from_dict
from .jsonfile import item_name, json_type, read_json, shown, write_json

if TYPE_CHECKING:  # a fit's results are read, never built, here
    from ..identify.bayes import ModelResult
    from ..identify.outcome import FitOutcome

FORMAT = "tissuecli-parameters"
FORMAT_VERSION = 1
CALIBRATION_FORMAT = "tissuecli-calibration"
CALIBRATION_VERSION = 1

#: What each ``format`` string names, so a file given in the wrong place is recognised.
KINDS = {
    FORMAT: "parameter",
    CALIBRATION_FORMAT: "calibration",
    "tissuecli-display": "display profile",
}

#: The largest force one term of the law may reach at :data:`RANGE_MOTION`, N: 300 times
#: the largest grasp force measured on liver (3.4 N) and beyond what a laparoscopic
#: forceps' jaws exert.
RANGE_FORCE_N = 1000.0
#: Small jaw motion for the ranges: 1 mm closure, 10 mm/s, 1 m/s^2 (a fifth to a tenth
#: of the jaw-scale motion of the fit's priors, 5 mm, 50 mm/s, 10 m/s^2).
RANGE_MOTION = {"stiffness": 1e-3, "damping": 1e-2, "inertia": 1.0}
#: Calibration ranges, per channel: largest and smallest magnitude of one count (SI per
#: count) and largest magnitude of the offset (SI). A forceps measures tens of newtons
#: over millimetres of jaw travel: 10 N a count is an 8-bit ADC spanning +-1.3 kN, 1 mm a
#: count one spanning +-13 cm; 1e-12 a count is below any sensor's noise.
CALIBRATION_RANGES = {"force": (1e-12, 10.0, 1e3), "position": (1e-12, 1e-3, 1.0)}


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
    from ..identify.outcome import recording_state  # loaded by the fit already

    session, est, pinv = outcome.session, outcome.bayes, outcome.pinv
    doc = _header()
    data = {
        "session": session.name,
        "file": str(session.meta.get("file", "")),
        "tissue": session.meta.get("tissue", ""),
        "samples": len(session),
        "duration_s": session.duration_s,
        "rate_hz": session.rate_hz,
        **recording_state(session),
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
        doc["warnings"] = outcome.warnings
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
            doc["warnings"] = outcome.warnings
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


def parameter_range(model: TissueModel, name: str) -> float:
    """Largest value a parameter file may give ``name`` (K, S or M) for ``model``, SI: the
    coefficient whose term alone reaches :data:`RANGE_FORCE_N` at :data:`RANGE_MOTION`.
    Smallest is 0: a passive tissue has no negative stiffness, damping or mass.

    x: K <= 1e6 N/m; x^3: K <= 1e12 N/m^3; xdot: S <= 1e5 N s/m; xdot^2: S <= 1e7
    N s^2/m^2; M <= 1e3 kg.
    """
    if name == "M":
        return RANGE_FORCE_N / RANGE_MOTION["inertia"]
    f = model.f0 if name == "K" else model.f1
    return RANGE_FORCE_N / abs(float(f(np.array([RANGE_MOTION[f.role]]))[0]))


class _Schema:
    """Checks of one document's items, each failing with one line that names the file
    (``where``), the item and what is wrong."""

    def __init__(self, where: str, kind: str) -> None:
        self.where, self.kind = where, kind

    def fail(self, path: tuple[str | int, ...], problem: str) -> InputError:
        return InputError(f"{self.where}: {item_name(path)} {problem}")

    def header(self, data: Mapping[str, Any], fmt: str, version: int) -> None:
        """``format`` (if given) must be ``fmt`` and ``version`` (if given) at most
        ``version``."""
        given = data.get("format", fmt)
        if given != fmt:
            other = KINDS.get(given) if isinstance(given, str) else None
            raise InputError(
                f"{self.where} is a {other} file (format {shown(given)}), not a {self.kind} file"
                if other
                else f"{self.where}: format {shown(given)} is not {fmt!r}; "
                f"is it a {self.kind} file?"
            )
        ver = data.get("version", version)
        if not isinstance(ver, int) or isinstance(ver, bool) or ver < 1:
            raise self.fail(("version",), f"= {shown(ver)} must be a whole number >= 1")
        if ver > version:
            raise InputError(
                f"{self.where} has format version {shown(ver)}, written by a newer tissuecli; this "
                f"one ({__version__}) reads up to version {version}: upgrade tissuecli"
            )
        if "software" in data:
            self.typed(data, ("software",), str)

    def keys(
        self,
        data: Mapping[str, Any],
        path: tuple[str | int, ...],
        allowed: tuple[str, ...],
        required: tuple[str, ...] = (),
    ) -> None:
        """Refuse missing and unknown keys (a typo is not silently ignored)."""
        for key in required:
            if key not in data:
                raise self.fail((*path, key), f"is missing ({self.kind} files: docs/formats.md)")
        unknown = [k for k in data if k not in allowed]
        if unknown:
            raise self.fail((*path, unknown[0]), f"is an unknown key; known: {', '.join(allowed)}")

    def typed(self, data: Mapping[str, Any], path: tuple[str | int, ...], kind: type) -> Any:
        """``data[path[-1]]``, refused unless of JSON type ``kind`` (dict, list or str)."""
        value = data[path[-1]]
        if not isinstance(value, kind):
            name = {dict: "an object", list: "an array", str: "a string"}[kind]
            raise self.fail(path, f"must be {name}, not {json_type(value)}")
        return value

    def number(
        self,
        value: Any,
        path: tuple[str | int, ...],
        lo: float = -math.inf,
        hi: float = math.inf,
        unit: str = "",
        why: str = "",
    ) -> float:
        """``value`` as a float, refused unless a finite number in [lo, hi]."""
        if not isinstance(value, (int, float)) or isinstance(value, bool):
            raise self.fail(
                path, f"must be a number{' in ' + unit if unit else ''}, not {json_type(value)}"
            )
        x = float(value)  # ints are at most 309 digits (read_json): finite
        if not math.isfinite(x):
            raise self.fail(path, f"= {shown(value)} is not a finite number")
        if not lo <= x <= hi:
            u = f" {unit}" if unit else ""
            bound = f">= {lo:g}{u}" if x < lo else f"<= {hi:g}{u}{why}"
            raise self.fail(path, f"= {x:g}{u} must be {bound}")
        return x


def tissue_from_dict(data: Mapping[str, Any], source: str = "parameter file") -> Tissue:
    """Validate a parameter document (docs/formats.md) and build its :class:`Tissue`.

    Checked: the header (``format``, ``version`` no newer than this tissuecli's), every
    top-level key known and of its type, ``model`` a known pair of forms, ``parameters``
    holding exactly K, S and M, each a number or ``{"mean", "sd", "ci95", "unit"}`` with
    a finite mean within :func:`parameter_range` and the form's unit.

    Raises
    ------
    InputError
        One line naming ``source``, the item and what is wrong.
    """
    sc = _Schema(source, "parameter")
    if not isinstance(data, Mapping):
        raise InputError(f"{source} must hold a JSON object")
    sc.header(data, FORMAT, FORMAT_VERSION)  # first: a newer file is told to upgrade
    sc.keys(data, (), tuple(_TOP_LEVEL), required=("model", "parameters"))
    for key, kind in _TOP_LEVEL.items():
        if key in data and kind is not None:
            sc.typed(data, (key,), kind)
    for j, w in enumerate(data.get("warnings", [])):
        if not isinstance(w, str):
            raise sc.fail(("warnings", j), f"must be a string, not {json_type(w)}")
    spec = data["model"]
    sc.keys(spec, ("model",), ("f0", "f1"), required=("f0", "f1"))
    names = []
    for key, role in (("f0", "stiffness"), ("f1", "damping")):
        name = spec[key]
        if not isinstance(name, str) or name not in FORMS[role]:
            raise sc.fail(
                ("model", key),
                f"= {shown(name)} is not a {role} form; choose one of: {', '.join(FORMS[role])}",
            )
        names.append(name)
    model = TissueModel.from_names(*names)
    params = data["parameters"]
    sc.keys(params, ("parameters",), PARAMETERS, required=PARAMETERS)
    values = {}
    for name in PARAMETERS:
        unit = model.units[name]
        entry = params[name]
        path: tuple[str | int, ...] = ("parameters", name)
        if isinstance(entry, Mapping):
            sc.keys(entry, path, ("mean", "sd", "ci95", "unit"), required=("mean",))
            given = entry.get("unit", unit)
            if given != unit:
                raise sc.fail(
                    (*path, "unit"),
                    f"= {shown(given)}, but model {model.name} needs {name} in {unit!r}",
                )
            if "sd" in entry:
                sc.number(entry["sd"], (*path, "sd"), 0.0, unit=unit)
            if "ci95" in entry:
                ci = entry["ci95"]
                if not isinstance(ci, list) or len(ci) != 2:
                    raise sc.fail((*path, "ci95"), "must be an array [low, high]")
                for i, v in enumerate(ci):
                    sc.number(v, (*path, "ci95", i), unit=unit)
            path, entry = (*path, "mean"), entry["mean"]
        values[name] = sc.number(
            entry,
            path,
            0.0,
            parameter_range(model, name),
            unit,
            f" (larger makes a term of over {RANGE_FORCE_N:g} N at 1 mm, 10 mm/s or 1 m/s^2, "
            "no tissue a forceps meets; docs/formats.md)",
        )
    return Tissue(model, **values).validate()


#: Top-level keys of a parameter file and their JSON types (None: any).
_TOP_LEVEL: dict[str, type | None] = {
    "format": None,
    "version": None,
    "software": None,
    "model": dict,
    "parameters": dict,
    "noise": dict,
    "evidence": dict,
    "probabilities": dict,
    "models": dict,
    "warnings": list,
    "pinv": dict,
    "data": dict,
}


def calibration_from_file_dict(data: Mapping[str, Any], source: str) -> Calibration:
    """Validate a calibration document (docs/formats.md) and build its
    :class:`~tissuecli.core.calibration.Calibration`.

    Raises
    ------
    InputError
        One line naming ``source``, the item and what is wrong.
    """
    sc = _Schema(source, "calibration")
    sc.header(data, CALIBRATION_FORMAT, CALIBRATION_VERSION)
    sc.keys(
        data,
        (),
        ("format", "version", "software", "note", "force", "position"),
        required=("force", "position"),
    )
    if "note" in data:
        sc.typed(data, ("note",), str)
    for name, (g_lo, g_hi, o_hi) in CALIBRATION_RANGES.items():
        entry = sc.typed(data, (name,), dict)
        sc.keys(entry, (name,), ("gain", "offset", "unit"), required=("gain",))
        si = SI_UNITS[name]
        unit = entry.get("unit", si)
        if unit != si:
            raise sc.fail((name, "unit"), f"= {shown(unit)}; give gain and offset in {si!r}")
        gain = sc.number(entry["gain"], (name, "gain"), -g_hi, g_hi, f"{si}/count")
        if abs(gain) < g_lo:
            raise sc.fail(
                (name, "gain"), f"= {gain:g} {si}/count is too small (|gain| >= {g_lo:g})"
            )
        if "offset" in entry:
            sc.number(entry["offset"], (name, "offset"), -o_hi, o_hi, si)
    return calibration_from_dict(data)


def read_tissue(path: str | os.PathLike[str]) -> Tissue:
    """Read a tissue parameter file (validated: see :func:`tissue_from_dict`)."""
    return tissue_from_dict(read_json(path, "parameter"), source=f"parameter file {path}")


def read_calibration(path: str | os.PathLike[str]) -> Calibration:
    """Read a calibration file: ``{"force": {"gain", "offset"}, "position": {...}}`` in SI
    (validated: see :func:`calibration_from_file_dict`)."""
    return calibration_from_file_dict(
        read_json(path, "calibration"), source=f"calibration file {path}"
    )


def read_profile(path: str | os.PathLike[str]) -> DisplayProfile:
    """Read a display profile (JSON; see :func:`tissuecli.render.profile.profile_from_dict`)."""
    return profile_from_dict(
        read_json(path, "display profile"), source=f"display profile file {path}"
    )
