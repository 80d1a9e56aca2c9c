"""The structure search as strategy objects: the greedy steps on a scoring callable, the
exhaustive enumeration, a new strategy as one class, and the registry they read."""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator

import pytest

from tissuecli.core.errors import FitError
from tissuecli.core.terms import TERMS, Law, Maxwell, register, searched, unregister
from tissuecli.identify import BayesianFit
from tissuecli.identify.scoring import ModelResult
from tissuecli.identify.search import (
    SEARCHES,
    ExhaustiveSearch,
    GreedySearch,
    Scope,
    Search,
    search_strategy,
)
from tissuecli.identify.search import register as register_search
from tissuecli.sim.families import FAMILIES
from tissuecli.sim.scenes import FAMILIES as FAMILIES_OF_SCENES
from tissuecli.sim.scenes import random_scene
from tissuecli.sim.synth import random_session

STEM = Law.of(["x", "xdot", "xddot"])


@pytest.fixture(scope="module")
def one_branch() -> object:
    """A short session of one relaxation branch (it resolves time constants from 0.03
    to 1.9 s: room for three branches) and the scope a search sees on it."""
    s, _ = random_session(FAMILIES["one branch"], rate_hz=500.0, seed=1, duration_s=6.0, bits=12)
    kin = BayesianFit().prepare(s).kinematics
    return s, Scope(kin, None, kin.force.size)


def _linear(law: Law, ln_evidence: float) -> ModelResult:
    return ModelResult(model=law, ln_evidence=ln_evidence, residual_rms=1.0)


class _Scorer:
    """A scoring callable with made-up evidence: each relaxation branch is worth
    ``gains[k]`` nats, contact ``contact`` nats; it counts the calls per law."""

    def __init__(
        self, gains: list[float], contact: float = -50.0, bonus: dict[str, float] | None = None
    ) -> None:
        self.gains, self.contact, self.calls = gains, contact, Counter[str]()
        self.bonus = bonus or {}

    def __call__(self, law: Law) -> ModelResult:
        self.calls[law.name] += 1
        names = [t.name for t in law.terms]
        k = names.count("maxwell")
        ln_z = sum(self.gains[:k]) + (self.contact if "contact" in names else 0.0)
        ln_z -= 5.0 * sum(n in ("offset", "x^3") for n in names)  # what pruning removes
        ln_z += sum(self.bonus.get(n, 0.0) for n in names)
        return ModelResult(model=law, family=law, ln_evidence=ln_z, residual_rms=1.0)


def test_greedy_grows_while_each_branch_raises_the_evidence_and_scores_each_law_once(one_branch):
    _, scope = one_branch
    score = _Scorer(gains=[30.0, 4.0, -2.0])
    tried, notes = GreedySearch().run([_linear(STEM, 0.0)], score, scope)
    assert notes == []
    assert max(score.calls.values()) == 1
    names = [r.name for r in tried]
    # contact first, then one branch, a second, and a third that does not pay
    assert names[0].startswith("contact")
    assert names[1:] == [
        "x+maxwell+xdot+xddot",
        "x+maxwell+maxwell+xdot+xddot",
        "x+maxwell+maxwell+maxwell+xdot+xddot",
    ]
    assert max(tried, key=lambda r: r.ln_evidence).name == "x+maxwell+maxwell+xdot+xddot"


def test_greedy_prunes_what_a_branch_makes_redundant(one_branch):
    _, scope = one_branch
    score = _Scorer(gains=[30.0, -1.0])
    stem = Law.of(["x", "x^3", "xdot", "xddot", "offset"])
    tried, _ = GreedySearch().run([_linear(stem, -10.0)], score, scope)
    best = max(tried, key=lambda r: r.ln_evidence)
    assert best.name == "x+maxwell+xdot+xddot"


def test_greedy_grows_branches_on_the_stem_too_when_its_contact_law_leads(one_branch):
    """A contact law's curvature and contact point stand in for a branch on a grasp's
    rise: a nat or two ahead of the stem, it once took every branch, and the spring
    with a branch (the truth) was never scored."""
    _, scope = one_branch
    score = _Scorer(gains=[30.0, -1.0], contact=2.0)
    tried, _ = GreedySearch().run([_linear(STEM, 0.0)], score, scope)
    names = [r.name for r in tried]
    assert "x+maxwell+xdot+xddot" in names
    assert any(n.startswith("contact") and "maxwell" in n for n in names)
    assert max(score.calls.values()) == 1


def test_greedy_grows_branches_on_a_stem_of_another_stiffness(one_branch):
    """Relaxation the linear laws cannot follow may make a hardening spring the best of
    them by evidence and by Schwarz's criterion; pruning keeps a stiffness, so the
    branches grown on it never reached the linear spring with a branch."""
    _, scope = one_branch
    score = _Scorer(gains=[30.0, -1.0], bonus={"x": 10.0})
    cubic = _linear(Law.of(["x^3", "xdot", "xddot"]), 0.0)
    spring = _linear(STEM, -5.0)
    tried, _ = GreedySearch().run([cubic, spring], score, scope)
    best = max(tried, key=lambda r: r.ln_evidence)
    assert best.name == "x+maxwell+xdot+xddot"
    assert max(score.calls.values()) == 1


class _Bounded(_Scorer):
    """As :class:`_Scorer`, but a law with fewer than ``needs`` branches has no evidence
    within its positivity bounds (a negative mass standing in for relaxation)."""

    def __init__(self, needs: int, **kwargs: object) -> None:
        super().__init__(**kwargs)  # type: ignore[arg-type]
        self.needs = needs

    def __call__(self, law: Law) -> ModelResult:
        r = super().__call__(law)
        if [t.name for t in law.terms].count("maxwell") < self.needs:
            r.ln_evidence = float("-inf")
        return r


def test_greedy_goes_on_through_laws_without_evidence_to_one_with_it(one_branch):
    _, scope = one_branch
    score = _Bounded(needs=2, gains=[30.0, 4.0, -2.0], contact=-500.0)
    stem = Law.of(["x", "x^3", "xdot", "xddot", "offset"])
    tried, _ = GreedySearch().run([_linear(stem, float("-inf"))], score, scope)
    best = max(tried, key=lambda r: r.ln_evidence)
    assert best.name == "x+maxwell+maxwell+xdot+xddot"


def test_searches_say_when_the_session_is_too_short_for_more_branches(one_branch):
    s, _ = one_branch
    short = s.replace(s.time[:400], s.force[:400], s.position[:400])  # 0.02-0.2 s
    kin = BayesianFit().prepare(short).kinematics
    scope = Scope(kin, None, kin.force.size)
    for search in (GreedySearch(), ExhaustiveSearch()):
        score = _Scorer(gains=[30.0, 4.0])
        tried, notes = search.run([_linear(STEM, 0.0)], score, scope)
        assert max(r.name.count("maxwell") for r in tried) == 1
        assert len(notes) == 1 and notes[0].startswith("relaxation branch 2 not searched")


def test_exhaustive_scores_every_law_greedy_reaches_within_its_branches(one_branch):
    _, scope = one_branch
    stem = Law.of(["x", "x^3", "xdot", "xddot"])
    greedy, exhaustive = _Scorer([30.0, 4.0, -2.0]), _Scorer([30.0, 4.0, -2.0])
    g_tried, _ = GreedySearch().run([_linear(stem, 0.0)], greedy, scope)
    e_tried, _ = ExhaustiveSearch(max_branches=2).run([_linear(stem, 0.0)], exhaustive, scope)
    assert max(exhaustive.calls.values()) == 1
    within = {r.name for r in g_tried if r.name.count("maxwell") <= 2}
    assert within <= {r.name for r in e_tried}
    # stiffness x, x^3 or both, times 1 or 2 branches; contact with 0 or 1
    assert len(e_tried) == 3 * 2 + 2
    assert all(r.name.count("maxwell") <= 2 for r in e_tried)
    best = max(e_tried, key=lambda r: r.ln_evidence)
    assert best.ln_evidence >= max(r.ln_evidence for r in g_tried if r.name in within)


def test_a_search_reads_its_terms_from_the_registry():
    for kind in ("replace", "grow", "prune"):
        assert Search().terms(kind) == searched(kind)
    no_contact = {n: t for n, t in TERMS.items() if t.search != "replace"}
    assert Search(registry=no_contact).terms("replace") == []
    assert Search(registry=no_contact).terms("grow") == searched("grow")


def test_strategies_by_name_or_instance_and_an_unknown_name_is_refused():
    assert isinstance(search_strategy("greedy"), GreedySearch)
    assert isinstance(search_strategy("exhaustive"), ExhaustiveSearch)
    mine = ExhaustiveSearch(max_branches=1)
    assert search_strategy(mine) is mine
    with pytest.raises(FitError, match="unknown search 'beam'.*greedy.*exhaustive"):
        search_strategy("beam")


class OneBranch(Search):
    """A new strategy in one class: the best linear law with one of each ``grow`` term."""

    name = "one-branch"

    def explore(self, linear, score, scope, notes):  # type: ignore[no-untyped-def]
        best = max(linear, key=lambda r: r.ln_evidence)
        for grow in self.terms("grow"):
            score([*(t.name for t in best.model.terms), grow])


@pytest.fixture
def one_branch_search() -> Iterator[type[Search]]:
    register_search(OneBranch)
    try:
        yield OneBranch
    finally:
        SEARCHES.pop(OneBranch.name, None)


def test_a_new_search_is_one_class_registered_or_passed(one_branch, one_branch_search):
    s, _ = one_branch
    by_name = BayesianFit(search="one-branch").fit(s)
    by_instance = BayesianFit(search=OneBranch()).fit(s)
    for est in (by_name, by_instance):
        shaped = [r.name for r in est.results_ + est.not_evaluated_ if r.model.shape_names]
        # the one law the strategy built, the best linear law and a branch, and beside
        # it only the laws smaller than it the fit scores below its choice
        built = max(shaped, key=lambda n: n.count("+"))
        assert built.count("maxwell") == 1
        assert all(set(n.split("+")) < set(built.split("+")) for n in shaped if n != built)
        assert est.best_.name in shaped and est.best_.name.count("maxwell") == 1
        assert est.law_.shape["tau1"] == pytest.approx(0.5, rel=0.2)
    assert by_name.best_.ln_evidence == by_instance.best_.ln_evidence
    with pytest.raises(FitError, match="unknown search 'nope'.*one-branch"):
        BayesianFit(search="nope").fit(s)


def test_a_search_without_a_name_is_not_registered():
    class Nameless(Search):
        pass

    with pytest.raises(FitError, match="Nameless has no name"):
        register_search(Nameless)


@pytest.mark.slow
def test_exhaustive_fit_finds_at_least_the_evidence_greedy_finds(one_branch):
    s, _ = one_branch
    greedy = BayesianFit().fit(s)
    every = BayesianFit(search=ExhaustiveSearch(max_branches=2)).fit(s)
    assert every.best_.ln_evidence >= greedy.best_.ln_evidence - 1e-6
    assert every.best_.name.count("maxwell") == 1
    assert len(every.results_) + len(every.not_evaluated_) > len(greedy.results_)


class Creep(Maxwell):
    """A grown term that a law may hold twice."""

    name, max_count = "creep", 2


@pytest.fixture
def creep() -> Iterator[dict[str, object]]:
    register(Creep)
    try:
        yield {n: t for n, t in TERMS.items() if n != "maxwell"}
    finally:
        unregister("creep")


def test_a_grown_term_is_added_no_more_times_than_a_law_may_hold_it(one_branch, creep):
    _, scope = one_branch
    for search in (GreedySearch(registry=creep), ExhaustiveSearch(registry=creep)):  # type: ignore[arg-type]
        assert search.terms("grow") == ["creep"]
        # creep worth 10 nats: a greedy search would take another if a law could hold it
        score = _Scorer(gains=[], bonus={"creep": 10.0})
        tried, _ = search.run([_linear(STEM, 0.0)], score, scope)
        assert "x+creep+creep+xdot+xddot" in {r.name for r in tried}
        assert all(r.name.count("creep") <= 2 for r in tried)


def test_smaller_laws_keep_a_stiffness_and_what_a_term_requires():
    names = ["contact", "maxwell", "contact*xdot", "xddot", "offset"]
    fewer = {"+".join(f) for f in GreedySearch().smaller(names)}
    # contact goes with contact damping, and gives way to what it equals at n = 1, a
    # spring (the offset is there already); the branch to what it equals never
    # relaxing, a spring and an offset
    assert fewer == {
        "maxwell+xddot+offset+x",
        "contact+contact*xdot+xddot+offset+x",
        "contact+contact*xdot+xddot+offset",
        "contact+maxwell+xddot+offset",
        "contact+maxwell+contact*xdot+offset",
        "contact+maxwell+contact*xdot+xddot",
    }
    assert GreedySearch().smaller(["x", "maxwell", "maxwell"]) == [
        ["x", "maxwell", "offset"],
        ["x", "maxwell"],
    ]
    assert GreedySearch().smaller(["x", "maxwell", "xdot"]) == [
        ["x", "xdot", "offset"],
        ["x", "xdot"],
        ["x", "maxwell"],
    ]


def test_a_contact_law_gives_way_to_the_laws_it_nests():
    # contact at n = 1 is Kc (x - x0): a spring and an offset, or a spring alone
    assert GreedySearch().smaller(["contact"]) == [["x", "offset"], ["x"]]
    fewer = {Law.of(f).name for f in GreedySearch().smaller(["contact", "contact*xdot", "xddot"])}
    assert fewer == {"x+xddot+offset", "x+xddot", "contact+xddot", "contact+contact*xdot"}


def test_smaller_laws_of_a_linear_law_lose_only_what_pruning_takes_out():
    # damping and inertia stay: the linear laws enumerate them already
    fewer = GreedySearch().smaller(["x", "x^3", "xdot", "sign(xdot)", "xddot", "offset"])
    assert {"+".join(f) for f in fewer} == {
        "x^3+xdot+sign(xdot)+xddot+offset",
        "x+xdot+sign(xdot)+xddot+offset",
        "x+x^3+xdot+xddot+offset",
        "x+x^3+xdot+sign(xdot)+xddot",
    }
    assert GreedySearch().smaller(["x", "xdot"]) == []


def test_descent_scores_the_sub_laws_of_the_choice_while_it_moves_to_one():
    # additive made-up evidence: the truth x+maxwell; damping and inertia cost 2 nats
    worth = {"x": 0.0, "maxwell": 12.0, "xdot": -2.0, "xddot": -2.0, "offset": -5.0}
    scored: dict[str, ModelResult] = {}

    def score(law: Law | list[str]) -> ModelResult:
        law = law if isinstance(law, Law) else Law.of(list(law))
        if law.name not in scored:
            ln_z = sum(worth[t.name] for t in law.terms)
            scored[law.name] = ModelResult(model=law, family=law, ln_evidence=ln_z,
                                           residual_rms=1.0)  # fmt: skip
        return scored[law.name]

    start = score(["x", "maxwell", "xdot", "xddot"])
    calls: list[str] = []

    def choose() -> list[ModelResult]:
        best = max(scored.values(), key=lambda r: r.ln_evidence)
        calls.append(best.name)
        return [best]

    GreedySearch().descend(choose, score)
    assert max(scored.values(), key=lambda r: r.ln_evidence).name == "x+maxwell"
    # each law named once, then the choice stays: x+maxwell's own sub-law (x) is scored
    assert calls[-1] == calls[-2] == "x+maxwell"
    assert "x" in scored and start.name in scored
    # only the sub-laws of the laws named, nothing bigger: an offset only beside the
    # spring in the branch's place (a branch that never relaxes is Km (x - x(0)))
    assert all("maxwell" not in n for n in scored if "offset" in n)
    assert len(scored) <= 1 + 4 + 3 + 2


def test_a_stem_with_evidence_looks_two_branches_further_when_one_has_none() -> None:
    """Two branches of far apart time constants (0.11 and 2.0 s; 262 Hz grasps, 24 s):
    with either alone the spring or the mass is driven far below zero, so no one-branch
    law has evidence within its positivity bounds, while the stem that took an offset
    of -7 N in their place has. Stopping there chose x+xdot+offset at P = 1.0 and
    predicted the held-out part at 16 times the noise floor; looking one branch further
    finds both branches (the true law's ln Z is 108 above the stem's)."""
    others = [f for f in FAMILIES_OF_SCENES if not f.startswith("paper")]
    scene = random_scene(6120738, families=others, max_samples=10_000)
    s = scene.session
    n = int(0.7 * s.time.size)
    est = BayesianFit().fit(s.replace(s.time[:n], s.force[:n], s.position[:n]))
    names = [t.name for t in est.best_.model.terms]
    assert names.count("maxwell") == 2
    assert "offset" not in names
