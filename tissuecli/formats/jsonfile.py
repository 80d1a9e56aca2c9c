"""JSON files: read with errors that name the file and say what is wrong; written atomically."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from ..core.errors import InputError
from .atomic import write_text_atomic


def read_json(path: str | os.PathLike[str], what: str) -> dict[str, Any]:
    """Load a JSON object from ``path``; ``what`` names the file's kind in errors."""
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
    """Write ``data`` as indented JSON (no NaN: strict JSON), atomically."""
    write_text_atomic(path, json.dumps(data, indent=2, allow_nan=False) + "\n")
