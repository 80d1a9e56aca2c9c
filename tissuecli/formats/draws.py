"""Posterior draws of the chosen law and the structure probabilities, as CSV that pandas
reads as it is and ArviZ takes through a DataFrame (docs/formats.md).

``FILE`` (e.g. ``draws.csv``) holds one row per draw: ``chain``, ``draw``, then one
column per coefficient named with its symbol and SI unit (``K [N/m]``), and ``sigma
[N]``, the noise SD of the filtered force. Beside it, ``FILE``'s stem with
``.structures.csv`` holds one row per law: its name, posterior probability, ln
evidence (nats), how its posterior was found, and whether it was chosen.
"""

from __future__ import annotations

import csv
import io
import math
import os
from pathlib import Path

from ..identify.outcome import FitOutcome
from .atomic import write_text_atomic

#: the columns of the structures file
STRUCTURE_COLUMNS = ("law", "probability", "ln_evidence", "method", "chosen")


def structures_path(path: str | os.PathLike[str]) -> Path:
    """Where the structure probabilities go beside draws written to ``path``:
    ``draws.csv`` -> ``draws.structures.csv``."""
    p = Path(path)
    stem = p.name[: -len(p.suffix)] if p.suffix else p.name
    return p.with_name(f"{stem}.structures.csv")


def draw_columns(outcome: FitOutcome) -> list[str]:
    """The draws file's header: ``chain``, ``draw``, ``SYMBOL [unit]`` per coefficient,
    ``sigma [N]``."""
    best = _best(outcome)
    return ["chain", "draw", *(f"{t.symbol} [{t.unit}]" for t in best.model.terms), "sigma [N]"]


def write_draws(path: str | os.PathLike[str], outcome: FitOutcome) -> tuple[Path, Path]:
    """Write the chosen law's posterior draws to ``path`` and the structure
    probabilities beside it (each file atomically).

    Returns
    -------
    (Path, Path)
        The draws file and the structures file.

    Raises
    ------
    InputError
        If the fit has no Bayesian posterior (``--method pinv``) or a file cannot be
        written.
    """
    from ..core.errors import InputError

    if outcome.bayes is None:
        raise InputError(
            "--draws needs the Bayesian fit (--method bayes or both): the windowed "
            "pseudoinverse has no posterior"
        )
    best = _best(outcome)
    post = best.posterior
    assert post is not None
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(draw_columns(outcome))
    for k, row in enumerate(post.samples):
        writer.writerow([0, k, *(repr(float(v)) for v in row)])
    draws = Path(path)
    write_text_atomic(draws, out.getvalue())
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(STRUCTURE_COLUMNS)
    for r in outcome.bayes.results_:
        prob = r.probability if math.isfinite(r.probability) else 0.0
        writer.writerow(
            [r.name, repr(float(prob)), repr(float(r.ln_evidence)), r.status,
             "yes" if r is best else "no"]
        )  # fmt: skip
    structures = structures_path(draws)
    write_text_atomic(structures, out.getvalue())
    return draws, structures


def _best(outcome: FitOutcome):  # noqa: ANN202 (identify's ModelResult)
    assert outcome.bayes is not None
    return outcome.bayes.best_
