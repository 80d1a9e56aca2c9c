"""The structure search: laws beyond the linear ones, built from the terms the registry
declares searchable (``Term.search``: ``"replace"``, ``"grow"``, ``"prune"``) and scored
by exact evidence.

A search is a strategy object: one subclass of :class:`Search` that sets ``name`` and
implements :meth:`Search.explore`, registered with :func:`register`.
:class:`~tissuecli.identify.bayes.BayesianFit` takes one by name or as an instance
(``search="greedy"``, ``"exhaustive"`` or ``MySearch()``). A strategy sees the linear
laws scored, a scoring callable (a law in, its :class:`ModelResult` out, each law
scored once) and what the recording resolves (:class:`Scope`); it never names a term.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import ClassVar

from ..core.errors import FitError
from ..core.terms import MAX_BRANCHES, TERMS, Law, Term, term, term_order
from .derivatives import Kinematics
from .identifiable import Design
from .scoring import ModelResult
from .shapes import resolvable, tau_range

#: each further relaxation branch needs the resolvable range of time constants to
#: span this factor more (k branches: BRANCH_SPREAD**k)
BRANCH_SPREAD = 4.0

#: the roles a stem's terms keep when contact replaces its stiffness and damping
KEPT_ROLES = ("friction", "inertia", "offset")

#: a law, or the names of its terms, scored by exact evidence (each law once)
Score = Callable[[Law | Sequence[str]], ModelResult]

#: most laws :meth:`Search.descend` takes terms out of, one after the other
DESCENT_STEPS = 6


@dataclass(frozen=True)
class Scope:
    """What a search may look at besides the evidence.

    Attributes
    ----------
    kinematics : Kinematics
        The filtered session: which time constants it resolves (:func:`tau_range`).
    design : Design or None
        The columns the recording leaves unexcited or cannot tell apart
        (:func:`~tissuecli.identify.identifiable.examine`).
    samples : int
        Filtered samples fitted (for Schwarz's criterion).
    """

    kinematics: Kinematics
    design: Design | None
    samples: int


class Search:
    """Base of the structure searches.

    A subclass sets ``name`` (as ``BayesianFit(search=NAME)`` gives it) and implements
    :meth:`explore`; hyperparameters are keyword arguments of ``__init__`` stored under
    their own names. The terms come from ``registry`` (by default the registered terms
    of :mod:`tissuecli.core.terms`, read when the search runs, so a term registered
    later is searched as it declares).
    """

    name: ClassVar[str] = ""

    def __init__(self, *, registry: Mapping[str, Term] | None = None) -> None:
        self.registry = registry

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"

    def terms(self, kind: str) -> list[str]:
        """The registry's terms searched as ``kind`` (``"replace"``, ``"grow"`` or
        ``"prune"``), in law order (``prune``: last first, as the search takes them out)."""
        registry = TERMS if self.registry is None else self.registry
        names = [t.name for t in sorted(registry.values(), key=term_order) if t.search == kind]
        return names[::-1] if kind == "prune" else names

    def run(
        self, linear: Sequence[ModelResult], score: Callable[[Law], ModelResult], scope: Scope
    ) -> tuple[list[ModelResult], list[str]]:
        """The laws this search scores beyond ``linear`` (in the order scored, each once)
        and its notes (what it could not search, and why)."""
        tried: list[ModelResult] = []
        seen: dict[str, ModelResult] = {}

        def once(law: Law | Sequence[str]) -> ModelResult:
            law = law if isinstance(law, Law) else Law.of(list(law))
            if law.name not in seen:
                seen[law.name] = score(law)
                tried.append(seen[law.name])
            return seen[law.name]

        notes: list[str] = []
        self.explore(list(linear), once, scope, notes)
        return tried, notes

    def explore(
        self, linear: list[ModelResult], score: Score, scope: Scope, notes: list[str]
    ) -> None:
        """Score the laws of this search with ``score``, appending to ``notes`` what it
        could not search."""
        raise NotImplementedError

    # what the searches share

    def stems(self, linear: Sequence[ModelResult], scope: Scope) -> list[ModelResult]:
        """The linear laws a search starts from: the one the evidence prefers, and the
        one that fits best by Schwarz's criterion (on a misfit's correlated residuals the
        two part, and only the second may be the stem of the law that fits)."""
        n = scope.samples
        stems = {r.name: r for r in (max(linear, key=lambda r: r.ln_evidence),
                                     min(linear, key=lambda r: bic(r, n)))}  # fmt: skip
        return list(stems.values())

    def other_stiffness(
        self, linear: Sequence[ModelResult], stems: Sequence[ModelResult], scope: Scope
    ) -> list[ModelResult]:
        """The linear law that fits best by Schwarz's criterion among those whose
        stiffness terms differ from every stem's (none if there is none): relaxation the
        linear laws cannot follow may make a hardening spring the best of them, and
        branches grown on it never reach a law without it (pruning keeps a stiffness)."""
        held = {_stiffness(r) for r in stems}
        other = [r for r in linear if _stiffness(r) not in held]
        return [min(other, key=lambda r: bic(r, scope.samples))] if other else []

    def replacing(self, scope: Scope) -> list[str]:
        """The ``"replace"`` terms (contact), less those of closure and speed together
        where the recording has one speed (contact damping, ``(x - x0)^n xdot``, is
        then the closure term itself)."""
        design = scope.design
        speed = design is None or (
            "xdot" not in design.unexcited and design.representative("xdot") == "xdot"
        )
        return [n for n in self.terms("replace") if speed or term(n).variable != "xv"]

    def smaller(self, names: Sequence[str]) -> list[list[str]]:
        """The laws one term smaller than the law of ``names``: each term that may go
        taken out in turn (one of a repeated term), with the terms that require it, as
        long as some stiffness remains. From a law the search built (one with a
        ``"replace"`` or ``"grow"`` term) any term may go; from a linear law only its
        ``"prune"`` terms (offset, friction, ``x^3``, ``x``): the linear laws enumerate
        damping and inertia already, and taking damping out of a linear law that
        misfits (a measured recording) trades prediction for evidence.

        A term that equals others at one of its shapes (:attr:`Term.nests`) may also
        give way to them, or to those of them that keep a stiffness (contact: to a
        spring and an offset, or a spring): those laws are its sub-laws too, with
        fewer parameters."""
        built = any(n in self.terms("replace") or n in self.terms("grow") for n in names)
        prune = self.terms("prune")
        out: list[list[str]] = []
        for drop in dict.fromkeys(names):
            if not built and drop not in prune:
                continue
            fewer = list(names)
            fewer.remove(drop)
            fewer = [n for n in fewer if all(r in fewer for r in term(n).requires)]
            nests = [n for n in term(drop).nests if n not in fewer]
            for k in range(len(nests), -1, -1):
                for some in itertools.combinations(nests, k):
                    law = [*fewer, *some]
                    if any(term(n).role == "stiffness" for n in law) and law not in out:
                        out.append(law)
        return out

    def descend(self, choose: Callable[[], Sequence[ModelResult]], score: Score) -> None:
        """Score the laws one term smaller (:meth:`smaller`) than each law ``choose``
        names (called again after each step: the law the fit would choose now), and
        theirs while ``choose`` moves to them (at most :data:`DESCENT_STEPS` steps).

        Every step of a search adds a term or prunes after a step that paid, and every
        linear law carries damping and inertia: a truth such as ``x+maxwell`` or
        ``x+x^3+xdot``, one term short of a law scored, is otherwise never scored, and
        the law with a term the data do not need is chosen. Only the sub-laws of the
        choice are scored, not those of every law near it: where the choice is linear
        they are linear (closed form, milliseconds), and a choice that no sub-law
        beats stays as it was.
        """
        done: set[str] = set()
        for _ in range(DESCENT_STEPS):
            fresh = [r for r in choose() if r.name not in done]
            if not fresh:
                return
            for r in fresh:
                done.add(r.name)
                for fewer in self.smaller([t.name for t in (r.family or r.model).terms]):
                    score(fewer)

    @staticmethod
    def kept(law: Law) -> list[str]:
        """A stem's terms that contact does not replace (friction, inertia, offset)."""
        return [t.name for t in law.terms if t.role in KEPT_ROLES]

    @staticmethod
    def unresolved(scope: Scope) -> str | None:
        """Why the session resolves no relaxation, or None if it resolves some."""
        if resolvable(scope.kinematics):
            return None
        lo, hi = tau_range(scope.kinematics)
        return (
            f"relaxation not searched: the session resolves time constants only between "
            f"{lo:.3g} s and {hi:.3g} s; record longer or with faster motion"
        )

    @staticmethod
    def too_narrow(scope: Scope, k: int) -> str | None:
        """Why the session cannot hold ``k`` distinct relaxation branches (the range of
        time constants it resolves must span ``BRANCH_SPREAD**k``), or None if it can."""
        why = Search.unresolved(scope)
        if why:
            return why
        lo, hi = tau_range(scope.kinematics)
        if hi < BRANCH_SPREAD**k * lo:
            return (
                f"relaxation branch {k} not searched: the session resolves time constants "
                f"only between {lo:.3g} s and {hi:.3g} s, too narrow a range for {k} "
                "distinct ones"
            )
        return None


#: the structure searches by name
SEARCHES: dict[str, type[Search]] = {}


def register(cls: type[Search]) -> type[Search]:
    """Class decorator: make a search available by its ``name``."""
    if not cls.name:
        raise FitError(f"{cls.__name__} has no name: set name = '...' to register it")
    SEARCHES[cls.name] = cls
    return cls


def search_strategy(spec: str | Search) -> Search:
    """A search from its name or itself.

    Raises
    ------
    FitError
        For a name no search is registered under.
    """
    if isinstance(spec, Search):
        return spec
    if isinstance(spec, str) and spec in SEARCHES:
        return SEARCHES[spec]()
    raise FitError(f"unknown search {str(spec)[:30]!r}; choose among: {', '.join(SEARCHES)}")


@register
class GreedySearch(Search):
    """Greedy search by exact evidence (docs/estimators.md), from each stem: the terms
    that declare ``search = "replace"`` (Hunt-Crossley contact) in place of its
    stiffness and damping; then, to the better of the two, the ``"grow"`` terms
    (relaxation branches) one at a time (up to three, one on a contact law, and each no
    more often than a law may hold it) while each raises the evidence; after each,
    ``"prune"`` terms the new one makes redundant are taken out while that raises the
    evidence."""

    name = "greedy"

    def explore(
        self, linear: list[ModelResult], score: Score, scope: Scope, notes: list[str]
    ) -> None:
        stems = self.stems(linear, scope)
        grew = 0
        for stem in stems:
            found = self._grow(stem, score, scope, notes)
            if found is None:
                return
            grew = max(grew, found)
        # once branches have paid, on a stem of another stiffness too, as many as paid
        if grew:
            for stem in self.other_stiffness(linear, stems, scope):
                self._branches(stem, grew, score, scope, notes)

    def _prune(self, res: ModelResult, score: Score) -> ModelResult:
        """Take ``"prune"`` terms out of ``res``'s law while that raises the evidence
        (as long as some stiffness remains)."""
        improved = True
        while improved:
            improved = False
            names = [t.name for t in res.family.terms]  # type: ignore[union-attr]
            for extra in self.terms("prune"):
                fewer = [n for n in names if n != extra]
                stiff = any(term(n).role == "stiffness" for n in fewer)
                if extra not in names or not stiff:
                    continue
                trial = score(fewer)
                if trial.ln_evidence > res.ln_evidence:
                    res, improved = trial, True
                    break
        return res

    def _grow(self, best: ModelResult, score: Score, scope: Scope, notes: list[str]) -> int | None:
        """The search's steps from one linear law: how many branches raised the
        evidence, None if the session resolves no relaxation (no other stem will
        either)."""
        contact = self._prune(score([*self.replacing(scope), *self.kept(best.model)]), score)
        why = self.unresolved(scope)
        if why:
            notes.append(why)
            return None
        # branches grow on the stem whichever of it and its contact law leads: a contact
        # law's curvature and contact point stand in for a branch's relaxation on a
        # grasp's rise, and led the stem by a nat or two where the truth was a spring
        # with a branch, which the stem alone then reaches
        grew = 0
        if contact.ln_evidence > best.ln_evidence:
            grew = self._branches(contact, 1, score, scope, notes)
        return max(self._branches(best, MAX_BRANCHES, score, scope, notes), grew)

    def _branches(
        self, base: ModelResult, most: int, score: Score, scope: Scope, notes: list[str]
    ) -> int:
        """Branches added to ``base`` one at a time while each raises the evidence (at
        most ``most``; a contact law takes one, its exponent and contact point already
        make it the costliest to sample), pruning after each; how many did."""
        current = base
        k = 0
        while k < most:
            k += 1
            why = self.too_narrow(scope, k)
            if why:
                if why not in notes:
                    notes.append(why)
                break
            trial = self._grown(current, score)
            if trial is None:
                break
            if not math.isfinite(trial.ln_evidence):
                # a stem whose missing branches drove a coefficient far below zero (a
                # negative mass or hardening standing in for relaxation) has no evidence
                # within its positivity bounds, and neither may the law with one branch
                # more: pruned of the term it need not hold, or with a further branch, it
                # may; from no evidence to none is no step down, and the search goes on
                trial = self._prune(trial, score)
                if not math.isfinite(trial.ln_evidence):
                    if not math.isfinite(current.ln_evidence):
                        current = trial
                        continue
                    # from a law with evidence to one without, look one branch further
                    # before stopping: two branches of far apart time constants, one
                    # alone drives the spring or the mass below zero (the other's force
                    # unexplained), and a stem that kept an offset in their place has
                    # evidence all the same
                    if k < most and not self.too_narrow(scope, k + 1):
                        deeper = self._grown(trial, score)
                        if deeper is not None and math.isfinite(deeper.ln_evidence):
                            trial, k = deeper, k + 1
            if not trial.ln_evidence > current.ln_evidence:
                break
            current = self._prune(trial, score)
        if current is base or not math.isfinite(current.ln_evidence):
            return 0
        grown = set(self.terms("grow"))

        def count(r: ModelResult) -> int:
            return sum(t.name in grown for t in (r.family or r.model).terms)

        return count(current) - count(base)

    def _grown(self, law: ModelResult, score: Score) -> ModelResult | None:
        """``law`` with the ``"grow"`` term that raises its evidence most (None where no
        more of any may be added)."""
        names = [t.name for t in (law.family or law.model).terms]
        grow = [g for g in self.terms("grow") if names.count(g) < term(g).max_count]
        if not grow:
            return None
        return max((score([*names, g]) for g in grow), key=lambda r: r.ln_evidence)


@register
class ExhaustiveSearch(Search):
    """Every law the greedy search could reach from each stem (and from the stem of
    another stiffness, :meth:`Search.other_stiffness`), each scored: with its
    stiffness and damping kept or replaced by the ``"replace"`` terms, any of its
    ``"prune"`` terms taken out (some stiffness kept), and zero to ``max_branches``
    ``"grow"`` terms (one on a contact law), as far as the session resolves time
    constants. Only laws with a searched term are new (the linear ones are scored
    already). Costlier than greedy; what it checks the greedy choice against.

    Parameters
    ----------
    max_branches : int
        Most ``"grow"`` terms in one law.
    registry : mapping of str to Term, optional
        The terms to search (by default every registered one).
    """

    name = "exhaustive"

    def __init__(
        self, *, max_branches: int = MAX_BRANCHES, registry: Mapping[str, Term] | None = None
    ) -> None:
        super().__init__(registry=registry)
        self.max_branches = max_branches

    def __repr__(self) -> str:
        return f"{type(self).__name__}(max_branches={self.max_branches!r})"

    def explore(
        self, linear: list[ModelResult], score: Score, scope: Scope, notes: list[str]
    ) -> None:
        room = 0
        for k in range(1, self.max_branches + 1):
            why = self.too_narrow(scope, k)
            if why:
                notes.append(why)
                break
            room = k
        grow = self.terms("grow")
        stems = self.stems(linear, scope)
        for stem in [*stems, *self.other_stiffness(linear, stems, scope)]:
            names = [t.name for t in stem.model.terms]
            bases = [(names, room)]
            replace = self.replacing(scope)
            if replace:
                bases.append(([*replace, *self.kept(stem.model)], min(room, 1)))
            for base, most in bases:
                for fewer in self._pruned(base):
                    for k in range(most + 1):
                        for extra in itertools.combinations_with_replacement(grow, k):
                            law = [*fewer, *extra]
                            many = any(law.count(g) > term(g).max_count for g in extra)
                            if not many and any(n in replace or n in grow for n in law):
                                score(law)

    def _pruned(self, names: list[str]) -> Iterable[list[str]]:
        """``names`` with every subset of its ``"prune"`` terms taken out, as long as
        some stiffness remains."""
        present = [n for n in self.terms("prune") if n in names]
        for r in range(len(present) + 1):
            for out in itertools.combinations(present, r):
                fewer = [n for n in names if n not in out]
                if any(term(n).role == "stiffness" for n in fewer):
                    yield fewer


def _stiffness(res: ModelResult) -> frozenset[str]:
    """The names of a law's stiffness terms."""
    return frozenset(t.name for t in res.model.terms if t.role == "stiffness")


def bic(res: ModelResult, n: int) -> float:
    """Schwarz's criterion of a law's least-squares fit over ``n`` samples; its shape
    parameters count as parameters."""
    k = len(res.model.terms) + len(res.model.shape_names)
    rms = res.least_squares[1] if res.least_squares is not None else res.residual_rms
    return n * math.log(max(rms**2, 1e-300)) + k * math.log(n)
