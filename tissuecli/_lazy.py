"""Names a package exports but loads on first use (PEP 562), so importing the package
costs nothing: one helper for the package face and for :mod:`tissuecli.formats`."""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from typing import Any


def lazy_getattr(package: str, exports: Mapping[str, str]) -> Callable[[str], Any]:
    """A module ``__getattr__`` that imports ``exports[name]`` (a module path, relative to
    ``package`` when it starts with a dot) on first access and caches the value."""

    def __getattr__(name: str) -> Any:
        module = exports.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        namespace = importlib.import_module(package).__dict__
        value = getattr(importlib.import_module(module, package), name)
        namespace[name] = value  # later lookups find it without calling back here
        return value

    return __getattr__
