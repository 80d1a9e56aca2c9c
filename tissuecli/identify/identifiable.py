"""What a recording can tell apart, examined before the structure search.

A laboratory protocol often leaves some of the law's columns without content of their
own: at constant speed ``xdot``, ``xdot|xdot|``, ``sign(xdot)`` and an offset are the
same column and ``xddot`` is noise; on ramps and holds the three speed terms are one
step function; over a narrow closure ``x^3`` is ``x``. Evidence among laws that differ
only by such columns measures rounding and the prior, not the tissue, so the search
never compares them: a column that is only noise is taken out of every candidate, and
of terms that are one column only the first (in :data:`PREFERENCE`) is kept.

Everything works on the Gram matrix of the candidate columns, formed once.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ..core.terms import Law, MotionScales, Term
from .derivatives import Kinematics
from .design import term_column, term_noise_path
from .noise import filter_tau

Array = NDArray[np.float64]

#: the terms of the default search's linear laws, in the order a merged group keeps
#: them (the first present stands for the others; the columns position noise leaves
#: alone come first, so that a noisy column is measured against clean ones)
PREFERENCE = ("x", "offset", "xdot", "x^3", "xdot|xdot|", "sign(xdot)", "xddot")

#: a column is noise when its mean square is below this many times what position
#: noise alone puts into it (the noise's mean square is a chi-square over the
#: samples; 4 is far beyond its spread on any fitted session)
NOISE_RATIO = 4.0
#: a column noise alone may merge with others must be at least this much theirs
MOSTLY = 0.01
#: a column is one with others when what is its own, times the largest coefficient
#: its prior allows, moves the force by less than this many noise SDs over the session
DETECT_SDS = 3.0
#: and in any case when all but this fraction of its sum of squares is theirs (rounding)
COLLINEAR = 1e-12
#: a variable is not excited when it changes by less than this fraction of the next
#: lower derivative's RMS over one sample (an acceleration of rounding at constant speed)
ROUNDING = 1e-6

#: how the report names each term
WORDS = {
    "x": "K",
    "x^3": "K3",
    "xdot": "S",
    "xdot|xdot|": "S2",
    "sign(xdot)": "friction",
    "xddot": "M",
    "offset": "the offset",
}


@dataclass
class Design:
    """What one recording can identify among the candidate terms.

    Attributes
    ----------
    names : list of str
        The candidate terms examined, in :data:`PREFERENCE` order.
    unexcited : list of str
        Terms whose column is noise or rounding on this recording.
    groups : list of list of str
        Terms whose columns are one column here (two or more each; the first is kept).
    combined : dict of str to list of str
        Terms whose column is, here, a combination of two or more other terms' columns
        (and no one of them alone), with those terms: all are kept, and a law holding
        all of them is collinear.
    summary : str
        One line saying so, or "" when every term is its own column.
    """

    names: list[str]
    gram: Array = field(repr=False)
    noise: Array = field(repr=False)
    n: int = 0
    #: the smallest sum of squares of its own a column needs to be told apart, by term
    floor: Array = field(default_factory=lambda: np.zeros(0), repr=False)
    unexcited: list[str] = field(default_factory=list)
    groups: list[list[str]] = field(default_factory=list)
    #: terms whose column is a combination of two or more kept columns and of none
    #: alone, with those columns (every term stays; a law with all of them is collinear)
    combined: dict[str, list[str]] = field(default_factory=dict)
    summary: str = ""

    def representative(self, name: str) -> str:
        """The term that stands for ``name`` (itself unless merged)."""
        for group in self.groups:
            if name in group:
                return group[0]
        return name

    def collinear(self, law: Law) -> str | None:
        """The first term of ``law`` whose column is (within noise) a combination of the
        law's other columns, or None: such a law has no unique coefficients here."""
        idx = [self.names.index(t.name) for t in law.terms if t.name in self.names]
        for k, j in enumerate(idx):
            others = idx[:k] + idx[k + 1 :]
            if others and self.merged(j, others):
                return self.names[j]
        return None

    def merged(self, j: int, others: Sequence[int]) -> bool:
        """Whether column ``j`` adds nothing distinguishable to ``others``: what is its
        own no coefficient its prior allows makes visible above the force noise, or is
        rounding, or (for a column almost wholly theirs) is what position noise puts
        into it. Noise counts only against a column almost wholly theirs: an estimate
        of position noise that is too high (a coarse ADC's steps) must not merge
        columns that are plainly their own."""
        own = _residual(self.gram, j, others)
        seen = float(self.floor[j]) if self.floor.size else 0.0
        if own <= max(seen, COLLINEAR * self.gram[j, j]):
            return True
        return own <= MOSTLY * self.gram[j, j] and own <= NOISE_RATIO * self.noise[j] * self.n

    def reduce(self, laws: Sequence[Law]) -> list[Law]:
        """The candidate laws the recording can tell apart: unexcited terms taken out,
        merged terms replaced by their representative, laws whose columns are then
        collinear dropped, duplicates dropped (the first kept)."""
        out: dict[str, Law] = {}
        # every candidate has a damping term; where damping is one column with others
        # (an offset at constant speed), the law without that column is a candidate too:
        # a spring alone must not be made to carry the offset its damping became
        damping = self.representative("xdot")
        shared = damping != "xdot" or any("xdot" in g for g in self.groups)
        for law in laws:
            names = [t.name for t in law.terms if t.name not in self.unexcited]
            names = list(dict.fromkeys(self.representative(n) for n in names))
            variants = [names]
            if shared and damping in names:
                variants.append([n for n in names if n != damping])
            for variant in variants:
                if not any(n in ("x", "x^3") for n in variant):
                    continue
                reduced = Law.of(variant)
                if self.collinear(reduced) is None:
                    out.setdefault(reduced.name, reduced)
        return list(out.values()) or list(laws)


def examine(
    kin: Kinematics,
    x_full: Array,
    sigma_x: float = 0.0,
    columns: dict[str, Array] | None = None,
    names: Sequence[str] = PREFERENCE,
    scales: MotionScales | None = None,
) -> Design:
    """Examine the candidate terms' columns on one recording.

    Parameters
    ----------
    kin : Kinematics
        The filtered kinematics the fit uses.
    x_full : ndarray, shape (n,)
        Position on the raw grid, m.
    sigma_x : float
        Position noise SD, m: what noise alone puts into each column.
    columns : dict, optional
        Columns already formed, by :func:`~tissuecli.identify.design.column_key`
        (filled in for the fit to reuse).
    names : sequence of str
        The terms to examine, in the order merged groups keep them.
    scales : MotionScales, optional
        The priors' yardsticks: a column is told apart from others only if what is its
        own, at the largest coefficient its prior allows, moves the force by more than
        :data:`DETECT_SDS` noise SDs over the session's effective samples. Without them
        only rounding merges columns.

    Returns
    -------
    Design
    """
    terms: list[Term] = [Law.of([n]).terms[0] for n in names]
    if not terms:  # laws of shaped terms alone (contact): nothing here to examine
        return Design([], np.zeros((0, 0)), np.zeros(0), kin.force.size)
    cols = np.column_stack([term_column(t, kin, x_full, sigma_x, columns) for t in terms])
    n = cols.shape[0]
    gram = cols.T @ cols
    noise = np.zeros(len(terms))
    if sigma_x > 0:
        for j, t in enumerate(terms):
            k, slope = term_noise_path(t, kin, x_full, sigma_x=sigma_x)
            noise[j] = sigma_x**2 * float(k @ k) * float(np.mean(slope**2))
    design = Design(list(names), gram, noise, n)
    if scales is not None and n > len(terms):
        # the force noise from the fit of every column at once, and the samples it
        # counts for through the smoothing filter
        y = kin.force
        d = np.linalg.norm(cols, axis=0)
        d[d == 0] = 1.0
        beta = np.linalg.lstsq(cols / d, y, rcond=None)[0] / d
        r = y - cols @ beta
        var = float(r @ r) / n
        weight = kin.stride / filter_tau(kin.kernels[0])  # a kept row stands for stride
        prior = np.array([scales.force / t.typical(scales) for t in terms])
        design.floor = DETECT_SDS**2 * var / (weight * np.maximum(prior, 1e-300) ** 2)
    # the kinematics' own RMS: a term's column is not its variable (x^3 in um^3 dwarfs
    # the closure, sign(xdot) is no speed), and read as one it called speed unexcited
    rms = {v: float(np.sqrt(np.mean(np.square(u)))) if u.size else 0.0
           for v, u in (("x", kin.x), ("v", kin.v), ("a", kin.a))}  # fmt: skip
    dt = kin.dt
    below = {"a": "v", "v": "x"}
    for j, t in enumerate(terms):
        ms = gram[j, j] / max(n, 1)
        lower = below.get(t.variable)
        rounding = lower is not None and rms[t.variable] * dt <= ROUNDING * rms[lower]
        if ms <= NOISE_RATIO * noise[j] or rounding or not ms > 0:
            design.unexcited.append(t.name)
    live = [j for j in range(len(terms)) if terms[j].name not in design.unexcited]
    # groups: each column tested against the ones kept before it. It is one column with
    # a kept column it cannot be told from on its own; a column that only a combination
    # of kept columns carries makes no two of them one (friction at speeds about its
    # smoothing speed is S and S2 together, and S and S2 stay apart): it stays, and
    # only the laws that hold it beside all of its partners are collinear
    kept: list[int] = []
    for j in live:
        if not kept or not design.merged(j, kept):
            kept.append(j)
            continue
        single = [p for p in kept if design.merged(j, [p])]
        if not single:
            partners = _partners(gram, j, kept)
            if not design.merged(j, partners):  # the small coefficients mattered
                partners = list(kept)
            design.combined[names[j]] = [names[p] for p in partners]
            continue
        partner = names[single[0]]
        group = next((g for g in design.groups if partner in g), None)
        if group is None:
            design.groups.append([partner, names[j]])
        else:
            group.append(names[j])
    design.summary = _summary(design)
    return design


def _residual(gram: Array, j: int, others: Sequence[int]) -> float:
    """Residual sum of squares of column ``j`` regressed on ``others`` (from the Gram
    matrix, on unit-norm columns so that rounding stays at the precision of 1)."""
    idx = list(others)
    d = np.sqrt(np.clip(np.diag(gram), 1e-300, None))
    g = gram / np.outer(d, d)
    sub = g[np.ix_(idx, idx)]
    rhs = g[idx, j]
    coef = np.linalg.lstsq(sub, rhs, rcond=1e-12)[0]
    return max(1.0 - float(coef @ rhs), 0.0) * float(gram[j, j])


def _partners(gram: Array, j: int, kept: Sequence[int]) -> list[int]:
    """The kept columns that carry column ``j``: those whose removal from the
    regression leaves a residual above the floor (the first kept if none does alone)."""
    d = np.sqrt(np.clip(np.diag(gram), 1e-300, None))
    g = gram / np.outer(d, d)
    idx = list(kept)
    coef = np.linalg.lstsq(g[np.ix_(idx, idx)], g[idx, j], rcond=1e-12)[0]
    big = [idx[i] for i in np.flatnonzero(np.abs(coef) > 0.1 * np.max(np.abs(coef)))]
    return big or [idx[0]]


def _summary(design: Design) -> str:
    """One line: what the recording is, which terms are one column, which not excited."""
    parts = []
    order = list(WORDS)
    for group in design.groups:
        words = [WORDS.get(n, n) for n in sorted(group, key=lambda n: order.index(n)
                                                  if n in order else len(order))]  # fmt: skip
        listed = ", ".join(words[:-1]) + " and " + words[-1]
        parts.append(f"{listed} are one column")
    for name, partners in design.combined.items():
        words = [WORDS.get(n, n) for n in partners]
        parts.append(f"{WORDS.get(name, name)} is {', '.join(words[:-1])} and {words[-1]} "
                     "together")  # fmt: skip
    if design.unexcited:
        words = [WORDS.get(n, n) for n in design.unexcited]
        listed = ", ".join(words[:-1]) + " and " + words[-1] if len(words) > 1 else words[0]
        parts.append(f"{listed} not excited")
    if not parts:
        return ""
    merged = {n for g in design.groups for n in g}
    if {"xdot", "offset"} <= merged and design.representative("offset") == design.representative(
        "xdot"
    ):
        what = "constant speed"
    elif {"xdot", "sign(xdot)"} <= merged:
        what = "one speed wherever it moves"
    else:
        what = "on this recording"
    return f"{what}: " + "; ".join(parts)
