"""JSON files: read within size and depth limits, with errors that name the file, the item
and what is wrong; written atomically.

Every JSON file tissuecli reads is small (parameter, calibration and display profile
files are a few kB), so :func:`read_json` refuses anything that is not: more than
:data:`MAX_BYTES`, nested deeper than :data:`MAX_DEPTH`, not UTF-8, not strict JSON
(``NaN``, ``Infinity``, numbers beyond a double, duplicate keys). What it returns is a
tree of dicts, lists, str, int, float, bool and None whose every number is finite.
"""

from __future__ import annotations

import json
import math
import os
import re
from typing import Any

from ..core.errors import InputError
from .atomic import write_text_atomic

#: Largest JSON file read, bytes. tissuecli's own files are a few kB (a fit's parameter
#: file with every form and sampler diagnostics is under 10 kB).
MAX_BYTES = 1 << 20
#: Deepest nesting of arrays and objects accepted; tissuecli's files nest 6 levels.
MAX_DEPTH = 32
#: Longest echo of a value from a file in an error message, characters.
SHOW_CHARS = 60

_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
_SPECIAL = re.compile(r'["\\\[\]{}]')
#: An integer with more digits than this cannot be a finite double (1.8e308).
_MAX_INT_DIGITS = 309


def cut(text: str, limit: int = SHOW_CHARS) -> str:
    """``text`` cut to ``limit`` characters (a value from a file may be huge)."""
    return text if len(text) <= limit else text[: limit - 3] + "..."


def shown(value: Any, limit: int = SHOW_CHARS) -> str:
    """``repr(value)`` cut to ``limit`` characters: quoted, escaped, bounded."""
    return cut(repr(value), limit)


class NotANumber(float):
    """A number JSON text held that is no finite double (``NaN``, ``Infinity``, ``1e999``,
    a 400-digit integer): a non-finite float that shows what was written."""

    text: str

    def __new__(cls, value: float, text: str) -> NotANumber:
        obj = super().__new__(cls, value)
        obj.text = text
        return obj

    def __repr__(self) -> str:
        return self.text


def _size(n: int) -> str:
    return f"{n / 2**20:g} MiB" if n >= 2**20 else f"{n / 1024:g} KiB"


def _parse_float(text: str) -> float:
    value = float(text)
    return value if math.isfinite(value) else NotANumber(value, cut(text))


def _parse_int(text: str) -> int | float:
    digits = len(text.lstrip("-"))
    if digits > _MAX_INT_DIGITS:
        sign = -1.0 if text.startswith("-") else 1.0
        return NotANumber(sign * math.inf, f"a {digits}-digit integer")
    return int(text)


def _parse_constant(text: str) -> float:
    return NotANumber(float(text), text)


class _Duplicate(ValueError):
    pass


def _object(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise _Duplicate(f"key {shown(key)} appears twice in one object")
        out[key] = value
    return out


def json_type(value: Any) -> str:
    """The JSON name of a parsed value's type, for messages."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if value is None:
        return "null"
    if isinstance(value, (int, float)):
        return "a number"
    return {dict: "an object", list: "an array", str: "a string"}.get(type(value), "a value")


def item_name(path: tuple[str | int, ...]) -> str:
    """``("parameters", "K", "mean")`` as ``parameters.K.mean``; ``ci95[0]`` for indices."""
    out = ""
    for part in path:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            name = part if re.fullmatch(r"[A-Za-z0-9_^,]{1,40}", part) else shown(part, 40)
            out += ("." if out else "") + name
    return out or "the top level"


def _nesting(text: str, limit: int) -> int:
    """Deepest nesting of ``[`` and ``{`` outside strings, counted up to ``limit + 1``
    (read before parsing, so a deep file never reaches the parser's recursion). One pass
    over the special characters: linear in the text whatever it holds."""
    depth = deepest = 0
    in_string = False
    escaped = -1  # index of a character escaped by a backslash
    for match in _SPECIAL.finditer(text):
        i = match.start()
        if i == escaped:
            continue
        c = match.group()
        if in_string:
            if c == "\\":
                escaped = i + 1
            elif c == '"':
                in_string = False
        elif c == '"':
            in_string = True
        elif c in "[{":
            depth += 1
            if depth > deepest:
                deepest = depth
                if deepest > limit:
                    break
        elif c in "]}":
            depth -= 1
    return deepest


def _walk(data: Any, where: str, max_depth: int) -> None:
    """Refuse non-finite numbers anywhere, naming the item."""
    stack: list[tuple[Any, tuple[str | int, ...]]] = [(data, ())]
    while stack:
        value, path = stack.pop()
        if len(path) > max_depth:
            raise InputError(f"{where}: {item_name(path)} is nested deeper than {max_depth}")
        if isinstance(value, dict):
            stack.extend((v, (*path, k)) for k, v in value.items())
        elif isinstance(value, list):
            stack.extend((v, (*path, i)) for i, v in enumerate(value))
        elif isinstance(value, float) and not math.isfinite(value):
            raise InputError(
                f"{where}: {item_name(path)} = {shown(value)} is not a finite number; "
                "JSON numbers must be finite doubles"
            )


def read_json(
    path: str | os.PathLike[str],
    what: str,
    *,
    max_bytes: int = MAX_BYTES,
    max_depth: int = MAX_DEPTH,
) -> dict[str, Any]:
    """Load a JSON object from ``path``; ``what`` names the file's kind in errors.

    Parameters
    ----------
    path : path
        The file.
    what : str
        Its kind, e.g. ``"parameter"``: errors start ``"parameter file PATH: ..."``.
    max_bytes, max_depth : int
        Size (bytes) and nesting limits.

    Returns
    -------
    dict
        The object; every number in it is finite.

    Raises
    ------
    InputError
        One line naming the file, and the item where there is one, for a file that is
        missing, unreadable, too big, binary, not UTF-8, not strict JSON, nested too
        deeply, holding a non-finite number, or not an object.
    """
    where = f"{what} file {path}"
    try:
        with open(path, "rb") as fh:
            raw = fh.read(max_bytes + 1)
    except FileNotFoundError:
        raise InputError(f"{where} does not exist") from None
    except IsADirectoryError:
        raise InputError(f"{where} is a directory; give a JSON file") from None
    except OSError as exc:
        raise InputError(f"cannot read {where}: {exc.strerror}") from None
    if len(raw) > max_bytes:
        raise InputError(
            f"{where} is larger than {_size(max_bytes)}; a {what} file is a few kB "
            "of JSON (see docs/formats.md)"
        )
    if raw.startswith(_HDF5_SIGNATURE):
        raise InputError(f"{where} is an HDF5 file, not JSON; give the {what} file (.json)")
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(
            f"{where} is not UTF-8 text (byte 0x{raw[exc.start]:02x} at offset {exc.start}); "
            f"give the {what} file (JSON)"
        ) from None
    if _nesting(text, max_depth) > max_depth:
        raise InputError(f"{where} nests arrays or objects more than {max_depth} deep")
    try:
        data = json.loads(
            text,
            parse_float=_parse_float,
            parse_int=_parse_int,
            parse_constant=_parse_constant,
            object_pairs_hook=_object,
        )
    except json.JSONDecodeError as exc:
        raise InputError(
            f"{where} is not valid JSON (line {exc.lineno} column {exc.colno}: {exc.msg})"
        ) from None
    except _Duplicate as exc:
        raise InputError(f"{where}: {exc}") from None
    except RecursionError:  # the nesting check should make this unreachable
        raise InputError(f"{where} nests arrays or objects too deeply") from None
    if not isinstance(data, dict):
        raise InputError(f"{where} must hold a JSON object {{...}}, not {json_type(data)}")
    _walk(data, where, max_depth)
    return data


def write_json(path: str | os.PathLike[str], data: dict[str, Any]) -> None:
    """Write ``data`` as indented JSON (no NaN: strict JSON), atomically."""
    write_text_atomic(path, json.dumps(data, indent=2, allow_nan=False) + "\n")
