"""The space of laws a fit compares: the linear laws the default search starts from,
and the candidate laws named by ``--forms`` (``all``, ``linear``, ``paper``, a law or a
list of them)."""

from __future__ import annotations

from collections.abc import Sequence

from ..core.errors import FitError
from ..core.terms import Law, paper_laws, parse_law


def linear_laws() -> list[Law]:
    """Every law linear in its coefficients that the default search enumerates: stiffness
    x, x^3 or both; damping xdot or xdot|xdot|; with or without dry friction; with or
    without an offset; all with inertia (24 laws)."""
    out = []
    for stiffness in (("x",), ("x^3",), ("x", "x^3")):
        for damping in ("xdot", "xdot|xdot|"):
            for friction in ((), ("sign(xdot)",)):
                for offset in ((), ("offset",)):
                    out.append(Law.of([*stiffness, damping, *friction, "xddot", *offset]))
    return out


def parse_forms(spec: str | Sequence[str | Law] | None) -> list[Law]:
    """The candidate laws: ``"all"``/None or ``"linear"`` (the 24 of :func:`linear_laws`;
    ``all`` then searches relaxation and contact from the best of them), ``"paper"``
    (the paper's four), one law (``x,xdot`` or ``x+x^3+xdot+offset+xddot``,
    ``x+maxwell+xdot+xddot``), or a list of them."""
    if spec is None or spec in ("all", "linear"):
        return linear_laws()
    if spec == "paper":
        return paper_laws()
    specs = [spec] if isinstance(spec, (str, Law)) else list(spec)
    laws = [item if isinstance(item, Law) else parse_law(item) for item in specs]
    if not laws:
        raise FitError("no law to fit; give --forms all, paper or a law such as x,xdot")
    return list(dict.fromkeys(laws))
