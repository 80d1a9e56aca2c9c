"""A long session's shaped columns from spans of the functions seen: a function's column
is its filter pass's to rounding, a function the span holds costs no pass, and a
shaped law's statistics formed in the spans' coordinates are the filtered ones."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from tissuecli.identify import BayesianFit, bayes, decimate, reduced, shaped
from tissuecli.identify.derivatives import Gaussian
from tissuecli.identify.shapes import shape_grid
from tissuecli.identify.whiten import ARFilter
from tissuecli.sim.families import FAMILIES
from tissuecli.sim.synth import random_session


def _session(seconds: float = 3.0) -> Any:
    # a noisy 12-bit closure in continuous contact, flickering over many levels
    return random_session(FAMILIES["Hunt-Crossley"], rate_hz=10000.0, seed=300,
                          duration_s=seconds, bits=12)[0]  # fmt: skip


def test_a_functions_column_is_its_filter_pass_and_a_seen_one_costs_none() -> None:
    s = _session()
    kin = Gaussian()(s.time, s.position, s.force).every(30)
    x = s.position
    speed = np.gradient(x, kin.dt)
    for v in (None, speed):
        span = reduced.ClosureSpan(kin, x, v)
        fns = [lambda u, n=n, x0=x0: np.maximum(u - x0, 0.0) ** n
               for n in (1.3, 1.5, 2.0) for x0 in (0.0, 1e-3)]  # fmt: skip
        for fn in fns:
            c = span.coordinates(fn(span.levels))
            assert c is not None
            want = kin.smooth_pointwise(fn, x, v)
            # TOLERANCE of the function's energy, rounding of the basis's sums
            assert np.max(np.abs(c @ span.columns - want)) <= 1e-10 * np.max(np.abs(want))
        grown = span.size
        assert grown == span.misses <= len(fns)
        # what the span holds (a function seen, a sum of them) costs no filter pass
        mix = 0.3 * fns[0](span.levels) - 2.0 * fns[4](span.levels)
        for values in (fns[2](span.levels), mix):
            c = span.coordinates(values)
            assert c is not None and span.size == grown
        want = 0.3 * kin.smooth_pointwise(fns[0], x, v) - 2.0 * kin.smooth_pointwise(fns[4], x, v)
        assert np.max(np.abs(c @ span.columns - want)) <= 1e-10 * np.max(np.abs(want))
        # what is not finite is left to the filter pass
        assert span.coordinates(np.full(span.levels.size, np.inf)) is None


@pytest.fixture(scope="module")
def scored() -> list[tuple[Any, Any]]:
    """(law, fit context) of each shaped law a fit of a coarse-grid session scores, the
    spans used wherever they apply."""
    seen: list[tuple[Any, Any]] = []
    original, above, basis = bayes.exact_shaped, decimate.DECIMATE_ABOVE, reduced.level_basis

    def keep(law: Any, fit: Any) -> Any:
        seen.append((law, fit))
        return original(law, fit)

    bayes.exact_shaped, decimate.DECIMATE_ABOVE = keep, 5_000
    reduced.level_basis = lambda *a, **k: None  # the spans even where a basis would pay
    try:
        BayesianFit(forms=["contact+contact*xdot+xddot", "contact+maxwell+contact*xdot+xddot",
                           "contact+xddot+offset"]).fit(_session())  # fmt: skip
    finally:
        bayes.exact_shaped, decimate.DECIMATE_ABOVE = original, above
        reduced.level_basis = basis
    return seen


def test_statistics_in_the_spans_coordinates_are_the_filtered_ones(
    scored: list[tuple[Any, Any]],
) -> None:
    assert {law.name for law, _ in scored} >= {"contact+contact*xdot+xddot",
                                               "contact+maxwell+contact*xdot+xddot"}  # fmt: skip
    for law, fit in scored:
        assert fit.kin.stride > 1
        light = shaped.ShapedPass(law, fit)
        assert light.reduced.usable, law.name
        grid = shape_grid(law, fit.kin, coarse=len(law.shape_names) > 2)
        nodes = grid.nodes[:: max(1, len(grid.nodes) // 12)]
        # and nodes near one another, as a climb's (the span holds most of them)
        u = grid.to_u(grid.nodes[len(grid.nodes) // 2])
        nodes += [grid.from_u(u + 1e-4 * k * grid.spacing) for k in range(1, 6)]
        checked = 0
        for node in nodes:
            bound = law.bind(node)
            got = light.reduced(bound)
            if got is None:  # too ill-conditioned for the normal equations: as before
                continue
            want = light._filtered([bound])[0]
            checked += 1
            for name in ("gram", "b", "correction"):
                a, b = np.asarray(getattr(got, name)), np.asarray(getattr(want, name))
                assert np.max(np.abs(a - b)) <= 1e-9 * np.max(np.abs(b)), (law.name, name)
            np.testing.assert_allclose(got.beta, want.beta, rtol=1e-6, atol=0)
            # the residual's own rounding, about the reference node's
            assert abs(got.rss - want.rss) <= 1e-8 * want.rss, law.name
        assert checked >= len(nodes) // 2, law.name


def test_through_a_prewhitening_filter_too(
    scored: list[tuple[Any, Any]], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(reduced, "level_basis", lambda *a, **k: None)
    law, fit = next((law, fit) for law, fit in scored if law.name == "contact+contact*xdot+xddot")
    y = fit.y
    w = ARFilter(step=3).fit(y - np.convolve(y, np.ones(50) / 50, "same"))
    assert w.order_ >= 1
    white = replace(fit, whiten=w, spans={})
    light = shaped.ShapedPass(law, white)
    assert light.reduced.usable
    grid = shape_grid(law, fit.kin)
    for node in grid.nodes[::5]:
        bound = law.bind(node)
        got, want = light.reduced(bound), light._filtered([bound])[0]
        if got is None:
            continue
        for name in ("gram", "b", "correction"):
            a, b = np.asarray(getattr(got, name)), np.asarray(getattr(want, name))
            assert np.max(np.abs(a - b)) <= 1e-9 * np.max(np.abs(b)), name
        assert abs(got.rss - want.rss) <= 1e-8 * want.rss


def test_a_session_on_every_sample_never_uses_the_spans(scored: list[tuple[Any, Any]]) -> None:
    law, fit = scored[0]
    assert shaped.ShapedPass(law, fit).reduced.usable
    full = replace(fit, kin=replace(fit.kin, stride=1), spans={})
    assert not shaped.ShapedPass(law, full).reduced.usable


def test_a_few_rows_against_many_are_products_row_by_row() -> None:
    rng = np.random.default_rng(7)
    B = rng.standard_normal((40, 3000))
    for rows in (1, 2, 3, 5):
        A = rng.standard_normal((rows, 3000))
        for got, want in ((reduced.product(A, B), A @ B.T), (reduced.product(B, A), B @ A.T)):
            # the same sums, in another order at most: rounding of 3000 terms of size 1
            assert got.shape == want.shape
            assert np.max(np.abs(got - want)) <= 1e-12
        # up to THIN rows, each row the numbers of its own product, whatever rows stand
        # beside it
        one = reduced.product(A, B)
        for i in range(rows if rows <= reduced.THIN else 0):
            assert np.array_equal(one[i], (A[i : i + 1] @ B.T)[0])


def test_a_shape_seen_before_is_not_projected_again(
    scored: list[tuple[Any, Any]], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(reduced, "level_basis", lambda *a, **k: None)
    laws = {law.name: (law, fit) for law, fit in scored}
    law, fit = laws["contact+contact*xdot+xddot"]
    sibling = laws["contact+maxwell+contact*xdot+xddot"][0]
    fresh = replace(fit, spans={})
    calls: list[int] = []
    many, one = reduced.ClosureSpan.coordinates_many, reduced.RowSpan.coordinates
    monkeypatch.setattr(reduced.ClosureSpan, "coordinates_many",
                        lambda self, v, t: calls.append(len(v)) or many(self, v, t))  # fmt: skip
    monkeypatch.setattr(reduced.RowSpan, "coordinates",
                        lambda self, c: calls.append(1) or one(self, c))  # fmt: skip
    node = shape_grid(law, fit.kin).nodes[7]
    first = shaped.ShapedPass(law, fresh).reduced(law.bind(node))
    assert first is not None and calls
    # the sibling at the same contact: only its relaxation branch is new, once per
    # time constant whatever the contact's shape
    light = shaped.ShapedPass(sibling, fresh)
    taus = [1.0, 1.0, 3.0]
    for k, tau in enumerate(taus):
        calls.clear()
        at = {**node, "n": node["n"] + 0.01 * k, "tau1": tau} if k else {**node, "tau1": tau}
        got = light.reduced(sibling.bind(at))
        assert got is not None
        want = light._filtered([sibling.bind(at)])[0]
        for name in ("gram", "b", "correction"):
            a, b = np.asarray(getattr(got, name)), np.asarray(getattr(want, name))
            assert np.max(np.abs(a - b)) <= 1e-9 * np.max(np.abs(b)), name
        new_contact = k > 0
        new_branch = tau not in taus[:k]
        # the contact's stiffness and slope (one call) and contact damping (another)
        assert len(calls) == 2 * new_contact + new_branch, (k, calls)
