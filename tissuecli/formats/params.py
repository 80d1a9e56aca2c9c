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
from numpy.typing import NDArray

from .._version import __version__
from ..core.calibration import SI_UNITS, Calibration, calibration_from_dict
from ..core.errors import InputError
from ..core.terms import TERMS, Law, MotionScales, Term
from ..core.tissue import Tissue
from ..render.profile import DisplayProfile, profile_from_dict
from .jsonfile import item_name, json_type, read_json, shown, write_json

Array = NDArray[np.float64]

if TYPE_CHECKING:  # a fit's results are read, never built, here
    from ..identify.bayes import ModelResult
    from ..identify.outcome import FitOutcome

FORMAT = "tissuecli-parameters"
FORMAT_VERSION = 2
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
RANGE_MOTION = {"x": 1e-3, "v": 1e-2, "a": 1.0, "1": 1.0}
#: Calibration ranges, per channel: largest and smallest magnitude of one count (SI per
#: count) and largest magnitude of the offset (SI). A forceps measures tens of newtons
#: over millimetres of jaw travel: 10 N a count is an 8-bit ADC spanning +-1.3 kN, 1 mm a
#: count one spanning +-13 cm; 1e-12 a count is below any sensor's noise.
CALIBRATION_RANGES = {"force": (1e-12, 10.0, 1e3), "position": (1e-12, 1e-3, 1.0)}


def _header() -> dict[str, Any]:
    return {"format": FORMAT, "version": FORMAT_VERSION, "software": f"tissuecli {__version__}"}


def _terms(law: Law, mean: Any, sd: Any = None, ci95: Any = None) -> list[dict[str, Any]]:
    """One entry per term: its name, its coefficient's symbol and unit, and the values."""
    out = []
    for j, t in enumerate(law.terms):
        entry: dict[str, Any] = {"term": t.name, "symbol": t.symbol, "unit": t.unit}
        entry["mean"] = float(mean[j])
        if sd is not None:
            entry["sd"] = float(sd[j])
        if ci95 is not None:
            entry["ci95"] = [float(ci95[j][0]), float(ci95[j][1])]
        out.append(entry)
    return out


def _law(
    law: Law,
    mean: Any,
    sd: Any = None,
    ci95: Any = None,
    shape: Mapping[str, Mapping[str, Any]] | None = None,
) -> dict[str, Any]:
    out: dict[str, Any] = {"name": law.name, "terms": _terms(law, mean, sd, ci95)}
    if law.shape_names:
        # the nonlinear parameters: their posterior where the fit has one, else the values
        out["shape"] = [
            {
                "name": n,
                "unit": law.shape_parameter(n).unit,
                **(dict(shape[n]) if shape and n in shape else {"mean": law.shape[n]}),
            }
            for n in law.shape_names
        ]
    return out


def tissue_to_dict(tissue: Tissue) -> dict[str, Any]:
    """The minimal parameter file for a tissue (``fit`` adds uncertainty and evidence)."""
    return {**_header(), "law": _law(tissue.law, tissue.coef)}


def _result_law(res: ModelResult) -> dict[str, Any]:
    post = res.posterior
    assert post is not None
    out = _law(res.model, post.mean, post.sd, post.ci95, res.shape_posterior)
    # the coefficients' covariance, for predictive bands (``tissuecli predict``)
    out["cov"] = [[float(v) for v in row] for row in np.asarray(post.cov)]
    return out


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
    contact = outcome.contact
    if not contact.all_contact:
        data["grasps"] = {
            "baseline_N": contact.baseline_n,
            "found": [
                {"start_s": g.start_s, "end_s": g.end_s, "peak_force_N": g.peak_force_n}
                for g in contact.grasps
            ],
            "fitted": outcome.fitted_grasps,
        }
    if outcome.validation is not None:
        v = outcome.validation
        doc["validation"] = {
            "split_s": v.split_s,
            "r2_fitted": v.r2_fitted,
            "r2_held_out": v.r2_held_out,
            "rms_N": v.rms_n,
            "force_sd_N": v.force_sd_n,
            "samples": v.samples,
        }
    if est is not None:
        best = est.best_
        kin = est.kinematics_
        doc["law"] = {**_result_law(best), "probability": best.probability}
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
        # the laws whose evidence could not be evaluated: never chosen, each with why
        doc["not_evaluated"] = {r.name: r.reason for r in getattr(est, "not_evaluated_", [])}
        doc["laws"] = {
            r.name: {
                "terms": _result_law(r)["terms"],
                "flags": r.flags,
                "cond": r.cond,
                "cond_scaled": r.cond_scaled,
                "residual_rms_N": r.residual_rms,
                "cv_rms_N": r.cv_rms,
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
                # the columns' closure: as read, or a coarse ADC's staircase rebuilt
                "closure": "rebuilt" if est.rebuilt_ else "read",
            }
        )
    if pinv is not None:
        doc["pinv"] = {**pinv.summary(), "terms": _terms(pinv.model_, pinv.params_)}
        if est is None:
            doc["warnings"] = outcome.warnings
            doc["law"] = _law(pinv.model_, pinv.params_)
    doc["data"] = data
    return doc


def write_params(path: str | os.PathLike[str], outcome: FitOutcome) -> dict[str, Any]:
    """Write the parameter file of a fit to ``path`` (atomically); the document written.
    A figure that is infinite or undefined (the condition number of a singular
    design) is written as null: JSON has no infinity."""
    data = _finite(document(outcome))
    write_json(path, data)
    return data


def _finite(value: Any) -> Any:
    """``value`` with every non-finite float, at any depth, replaced by None."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    return value


def parameter_range(t: Term) -> float:
    """Largest magnitude a parameter file may give the coefficient of term ``t``, SI: the
    coefficient whose term alone reaches :data:`RANGE_FORCE_N` at :data:`RANGE_MOTION`.
    A passive coefficient is at least 0 (no negative stiffness, damping or mass); an
    offset may have either sign.

    x: K <= 1e6 N/m; x^3: K3 <= 1e12 N/m^3; xdot: S <= 1e5 N s/m; xdot|xdot|: S2 <= 1e7
    N s^2/m^2; sign(xdot): Fc <= 1e3 N; xddot: M <= 1e3 kg; offset: |F0| <= 1e3 N.
    """
    scales = MotionScales(
        x=RANGE_MOTION["x"], v=RANGE_MOTION["v"], a=RANGE_MOTION["a"], force=RANGE_FORCE_N
    )
    return RANGE_FORCE_N / abs(t.typical(scales))


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
    top-level key known and of its type, and the law: in version 2 a list of known
    terms, each with a finite coefficient within :func:`parameter_range` in its unit; in
    version 1 a pair of forms ``model: {f0, f1}`` with ``parameters`` K, S and M.

    Raises
    ------
    InputError
        One line naming ``source``, the item and what is wrong.
    """
    sc = _Schema(source, "parameter")
    if not isinstance(data, Mapping):
        raise InputError(f"{source} must hold a JSON object")
    sc.header(data, FORMAT, FORMAT_VERSION)  # first: a newer file is told to upgrade
    # a file without a version tells its layout by its keys
    version = data.get("version", 1 if "model" in data and "law" not in data else FORMAT_VERSION)
    top = _TOP_LEVEL if version >= 2 else _TOP_LEVEL_V1
    sc.keys(data, (), tuple(top), required=("law",) if version >= 2 else ("model", "parameters"))
    for key, kind in top.items():
        if key in data and kind is not None:
            sc.typed(data, (key,), kind)
    for j, w in enumerate(data.get("warnings", [])):
        if not isinstance(w, str):
            raise sc.fail(("warnings", j), f"must be a string, not {json_type(w)}")
    if version >= 2:
        law, values = _read_law(sc, data["law"])
    else:
        law, values = _read_v1(sc, data)
    return Tissue(law, *values).validate()


def _coefficient(sc: _Schema, t: Term, entry: Any, path: tuple[str | int, ...]) -> float:
    """A term's coefficient: a number, or ``{"mean", "sd", "ci95", "unit"}``, in range."""
    if isinstance(entry, Mapping):
        sc.keys(entry, path, ("term", "symbol", "mean", "sd", "ci95", "unit"), required=("mean",))
        given = entry.get("unit", t.unit)
        if given != t.unit:
            raise sc.fail((*path, "unit"), f"= {shown(given)}, but {t.name} needs {t.unit!r}")
        if "sd" in entry:
            sc.number(entry["sd"], (*path, "sd"), 0.0, unit=t.unit)
        if "ci95" in entry:
            ci = entry["ci95"]
            if not isinstance(ci, list) or len(ci) != 2:
                raise sc.fail((*path, "ci95"), "must be an array [low, high]")
            for i, v in enumerate(ci):
                sc.number(v, (*path, "ci95", i), unit=t.unit)
        path, entry = (*path, "mean"), entry["mean"]
    top = parameter_range(t)
    return sc.number(
        entry,
        path,
        0.0 if t.passive else -top,
        top,
        t.unit,
        f" (larger makes a term of over {RANGE_FORCE_N:g} N at 1 mm, 10 mm/s or 1 m/s^2, "
        "no tissue a forceps meets; docs/formats.md)",
    )


def _read_law(sc: _Schema, spec: Any) -> tuple[Law, list[float]]:
    if not isinstance(spec, Mapping):
        raise sc.fail(("law",), f"must be an object, not {json_type(spec)}")
    sc.keys(spec, ("law",), ("name", "terms", "probability", "shape", "cov"), required=("terms",))
    terms = spec["terms"]
    if not isinstance(terms, list) or not terms:
        raise sc.fail(("law", "terms"), "must be a non-empty array of terms")
    names: list[str] = []
    for j, entry in enumerate(terms):
        path: tuple[str | int, ...] = ("law", "terms", j)
        if not isinstance(entry, Mapping):
            raise sc.fail(path, f"must be an object, not {json_type(entry)}")
        name = entry.get("term")
        if not isinstance(name, str) or name not in TERMS:
            raise sc.fail(
                (*path, "term"), f"= {shown(name)} is not a term; choose among: {', '.join(TERMS)}"
            )
        if name in names and TERMS[name].max_count == 1:
            raise sc.fail((*path, "term"), f"= {name!r} appears twice")
        names.append(name)
    try:
        law = Law.of(names)
    except InputError as exc:
        raise sc.fail(("law", "terms"), f"do not make a law: {exc}") from None
    if law.shape_names:
        law = law.bind(_read_shape(sc, spec.get("shape"), law))
    # entries in the file's order; a repeated term's (relaxation branches) in theirs
    by_symbol: dict[str, int] = {}
    seen: dict[str, int] = {}
    for j, name in enumerate(names):
        seen[name] = seen.get(name, 0) + 1
        proto = TERMS[name]
        by_symbol[proto.instance(seen[name]).symbol if proto.max_count > 1 else proto.symbol] = j
    values = [
        _coefficient(sc, t, terms[by_symbol[t.symbol]], ("law", "terms", by_symbol[t.symbol]))
        for t in law.terms
    ]
    return law, values


def _read_shape(sc: _Schema, spec: Any, law: Law) -> dict[str, float]:
    """The nonlinear parameters: ``[{"name", "mean", "unit", ...}]``, each in the range its
    term declares."""
    wanted = law.shape_names
    if not isinstance(spec, list):
        raise sc.fail(
            ("law", "shape"), f"must list the law's nonlinear parameters {', '.join(wanted)}"
        )
    out: dict[str, float] = {}
    for j, entry in enumerate(spec):
        path: tuple[str | int, ...] = ("law", "shape", j)
        if not isinstance(entry, Mapping):
            raise sc.fail(path, f"must be an object, not {json_type(entry)}")
        # method and tau_steps: how the shape was marginalised (emcee's autocorrelation time)
        known = ("name", "unit", "mean", "sd", "ci95", "method", "tau_steps")
        sc.keys(entry, path, known, required=("name", "mean"))
        name = entry["name"]
        if name not in wanted or name in out:
            raise sc.fail((*path, "name"), f"= {shown(name)}; the law's are {', '.join(wanted)}")
        declared = law.shape_parameter(name)
        unit = declared.unit
        if entry.get("unit", unit) != unit:
            given = shown(entry.get("unit"))
            raise sc.fail((*path, "unit"), f"= {given}, but {name} is in {unit!r}")
        lo, hi = declared.limits
        out[name] = sc.number(entry["mean"], (*path, "mean"), lo, hi, unit)
    missing = [n for n in wanted if n not in out]
    if missing:
        raise sc.fail(("law", "shape"), f"lacks {', '.join(missing)}")
    return out


#: version 1 form names and parameters
_V1_FORMS = {"stiffness": ("x", "x^3"), "damping": ("xdot", "xdot^2")}
_V1_PARAMETERS = ("K", "S", "M")


def _read_v1(sc: _Schema, data: Mapping[str, Any]) -> tuple[Law, list[float]]:
    """A version 1 file: ``model: {f0, f1}`` and ``parameters: {K, S, M}``."""
    spec = data["model"]
    sc.keys(spec, ("model",), ("f0", "f1"), required=("f0", "f1"))
    names = []
    for key, role in (("f0", "stiffness"), ("f1", "damping")):
        name = spec[key]
        if not isinstance(name, str) or name not in _V1_FORMS[role]:
            raise sc.fail(
                ("model", key),
                f"= {shown(name)} is not a {role} form; choose one of: "
                + ", ".join(_V1_FORMS[role]),
            )
        names.append(name)
    law = Law.paper(*names)
    params = data["parameters"]
    sc.keys(params, ("parameters",), _V1_PARAMETERS, required=_V1_PARAMETERS)
    return law, [
        _coefficient(sc, t, params[v1], ("parameters", v1))
        for t, v1 in zip(law.terms, _V1_PARAMETERS, strict=True)
    ]


#: Top-level keys of a parameter file (version 2) and their JSON types (None: any).
_TOP_LEVEL: dict[str, type | None] = {
    "format": None,
    "version": None,
    "software": None,
    "law": dict,
    "noise": dict,
    "evidence": dict,
    "probabilities": dict,
    "not_evaluated": dict,
    "laws": dict,
    "warnings": list,
    "pinv": dict,
    "validation": dict,
    "data": dict,
}
_TOP_LEVEL_V1: dict[str, type | None] = {
    **{k: v for k, v in _TOP_LEVEL.items() if k not in ("law", "laws", "validation")},
    "model": dict,
    "parameters": dict,
    "models": dict,
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
        ("format", "version", "software", "note", "force", "position", "fit"),
        required=("force", "position"),
    )
    if "note" in data:
        sc.typed(data, ("note",), str)
    if "fit" in data:  # how tissuecli calibrate forceps fitted it: for people, not used
        sc.typed(data, ("fit",), dict)
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


def read_fitted(path: str | os.PathLike[str]) -> tuple[Tissue, Array | None, float | None]:
    """A fitted tissue with what a prediction needs: the coefficients' covariance
    (``law.cov``, SI, None if the file has none) and the residual SD of the filtered
    force (``noise.sd``, N, None if absent); both validated."""
    data = read_json(path, "parameter")
    source = f"parameter file {path}"
    tissue = tissue_from_dict(data, source=source)
    sc = _Schema(source, "parameter")
    law = data.get("law") if isinstance(data.get("law"), Mapping) else {}
    cov = None
    if "cov" in law:
        p = len(tissue.law.terms)
        raw = law["cov"]
        if not (
            isinstance(raw, list)
            and len(raw) == p
            and all(isinstance(row, list) and len(row) == p for row in raw)
        ):
            raise sc.fail(("law", "cov"), f"must be a {p} x {p} array of numbers")
        cov = np.array(
            [[sc.number(v, ("law", "cov", i, j)) for j, v in enumerate(row)]
             for i, row in enumerate(raw)]
        )  # fmt: skip
        if not np.allclose(cov, cov.T, rtol=1e-6, atol=0.0):
            raise sc.fail(("law", "cov"), "must be symmetric")
    noise = data.get("noise")
    sd = None
    if isinstance(noise, Mapping) and "sd" in noise:
        sd = sc.number(noise["sd"], ("noise", "sd"), 0.0, unit="N")
    return tissue, cov, sd


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
