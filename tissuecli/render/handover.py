"""Handing a tissue to a haptic loop that runs in another process.

A message between processes is pickled; a :class:`~tissuecli.core.tissue.Tissue` is
immutable and does not pickle, and a loop should not depend on how a class pickles. So
a tissue crosses as plain data: the law's term names, its shape parameters and the
coefficients, with the gains it is to be rendered with::

    ("tissue", ("x", "xdot", "xddot"), (), (350.0, 3.0, 0.05), (Cp, Cv, bandwidth_hz, M))

:func:`tissue_message` makes one and :func:`read_tissue_message` reads it back.
"""

from __future__ import annotations

from dataclasses import astuple
from typing import Any

from ..core.errors import InputError
from ..core.terms import Law
from ..core.tissue import Tissue
from .law import Gains

#: The first item of a tissue message.
TISSUE = "tissue"


def tissue_data(tissue: Tissue) -> tuple[Any, ...]:
    """``tissue`` as plain data: term names, shape parameters, coefficients."""
    law = tissue.law
    return (
        tuple(t.name for t in law.terms),
        tuple(sorted(law.shape.items())),
        tuple(float(c) for c in tissue.coef),
    )


def tissue_from_data(data: tuple[Any, ...]) -> Tissue:
    """The tissue of :func:`tissue_data`'s plain data."""
    names, shape, coef = data
    law = Law.of(names)
    if shape:
        law = law.bind(dict(shape))
    return Tissue(law, *coef).validate()


def tissue_message(tissue: Tissue, gains: Gains) -> tuple[Any, ...]:
    """The message that hands ``tissue``, rendered with ``gains``, to a loop."""
    return (TISSUE, *tissue_data(tissue), tuple(float(g) for g in astuple(gains)))


def read_tissue_message(message: tuple[Any, ...]) -> tuple[Tissue, Gains]:
    """The tissue and gains of a message made by :func:`tissue_message`."""
    if len(message) != 5 or message[0] != TISSUE:
        raise InputError(f"not a tissue message: {message!r:.80}")
    return tissue_from_data(message[1:4]), Gains(*message[4])
