"""JSON files: tissue parameter files (written by ``fit``, read by ``simulate`` and
``play``) and forceps calibration files. docs/formats.md describes both."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

from .calibration import Calibration, calibration_from_dict
from .errors import InputError
from .models import PARAMETERS, Tissue, TissueModel

FORMAT_VERSION = 1


def read_json(path: str | os.PathLike[str], what: str) -> dict[str, Any]:
    """Load a JSON object, with errors that name the file and say what is wrong."""
    try:
        text = Path(path).read_text()
    except FileNotFoundError:
        raise InputError(f"{what} file {path} does not exist") from None
    except OSError as exc:
        raise InputError(f"cannot read {what} file {path}: {exc.strerror}") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(
            f"{what} file {path} is not valid JSON (line {exc.lineno}: {exc.msg})"
        ) from None
    if not isinstance(data, dict):
        raise InputError(f"{what} file {path} must hold a JSON object")
    return data


def write_json(path: str | os.PathLike[str], data: dict[str, Any]) -> None:
    """Write atomically (temporary file + rename), so a crash never leaves half a file."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text(json.dumps(data, indent=2, allow_nan=False) + "\n")
        os.replace(tmp, path)
    except OSError as exc:
        raise InputError(f"cannot write {path}: {exc.strerror}") from None


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


def tissue_to_dict(tissue: Tissue) -> dict[str, Any]:
    """The minimal parameter file for a tissue (``fit`` adds uncertainty and evidence)."""
    return {
        "format": "tissuecli-parameters",
        "version": FORMAT_VERSION,
        "model": {"f0": tissue.model.f0.name, "f1": tissue.model.f1.name},
        "parameters": {
            name: {"mean": getattr(tissue, name), "unit": tissue.model.units[name]}
            for name in PARAMETERS
        },
    }


def read_tissue(path: str | os.PathLike[str]) -> Tissue:
    """Read a tissue parameter file."""
    return tissue_from_dict(read_json(path, "parameter"), source=str(path))


def read_calibration(path: str | os.PathLike[str]) -> Calibration:
    """Read a calibration file: ``{"force": {"gain", "offset"}, "position": {...}}`` in SI."""
    return calibration_from_dict(read_json(path, "calibration"))
