"""The first pass of a law with shape parameters at many nodes in one batch: the same
numbers, to the last bit, as one node at a time, in batches of any size."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from tissuecli.identify import BayesianFit, bayes, shaped
from tissuecli.identify.blas import one_blas_thread
from tissuecli.identify.shapes import shape_grid
from tissuecli.sim.synth import ForcepsModel, Sensors, synthesize


@pytest.fixture(scope="module")
def scored() -> list[tuple[Any, Any]]:
    """(law, fit context) of each law with shape parameters a short fit scores."""
    seen: list[tuple[Any, Any]] = []
    original = bayes.exact_shaped

    def keep(law: Any, fit: Any) -> Any:
        seen.append((law, fit))
        return original(law, fit)

    session = synthesize(ForcepsModel(seed=3, sensors=Sensors(bits=12)), 2.0)[0]
    bayes.exact_shaped = keep
    try:
        BayesianFit(forms=["x+maxwell+xdot+xddot", "contact+contact*xdot+xddot"]).fit(session)
    finally:
        bayes.exact_shaped = original
    return seen


@pytest.mark.parametrize("batch_bytes", [1, shaped.BATCH_BYTES])
def test_batched_first_passes_equal_one_node_at_a_time(
    scored: list[tuple[Any, Any]], batch_bytes: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(shaped, "BATCH_BYTES", batch_bytes)
    assert {law.name for law, _ in scored} >= {"x+maxwell+xdot+xddot",
                                               "contact+contact*xdot+xddot"}  # fmt: skip
    for law, fit in scored:
        grid = shape_grid(law, fit.kin)
        light = shaped.ShapedPass(law, fit)
        bounds = [law.bind(node) for node in grid.nodes]
        with one_blas_thread():
            many = light.many(bounds)
            one = [light(node, b) for node, b in zip(grid.nodes, bounds, strict=True)]
        assert len(many) == len(one) == len(grid.nodes)
        for a, b in zip(many, one, strict=True):
            for name in ("gram", "b", "beta", "correction"):
                x, y = getattr(a, name), getattr(b, name)
                assert (x is None) == (y is None)
                if x is not None:
                    assert np.array_equal(x, y), (law.name, name)
            for name in ("yy", "rss", "cond", "cond_scaled"):
                assert getattr(a, name) == getattr(b, name), (law.name, name)


def test_shape_nodes_take_the_looser_lattice_at_no_cost_to_the_evidence(monkeypatch):
    """Every node of a shape grid takes its orthant mass to the looser target, and those
    carrying more than a tenth of the law's evidence the full one: each law's ln Z stays
    within 3.2e-3 nats of the full target's everywhere (independent errors of 0.01 on
    shares of at most 0.1: 0.01 sqrt(0.1), 3 standard errors)."""
    from tissuecli.identify import posterior
    from tissuecli.sim.scenes import random_scene

    # a contact law's exponent and contact point on grids of 35 nodes (six laws)
    scene = random_scene(102, families=["Hunt-Crossley"], max_samples=3000)
    calls = []
    tighten = posterior.ExactPosterior.tighten
    monkeypatch.setattr(posterior.ExactPosterior, "tighten",
                        lambda self: (calls.append(1), tighten(self))[1])  # fmt: skip
    light = BayesianFit(seed=0).fit(scene.session)
    tightened = len(calls)
    monkeypatch.setattr(shaped, "TIGHT_SHARE", -1.0)
    full = BayesianFit(seed=0).fit(scene.session)
    assert len(calls) - tightened > 3 * tightened  # the rule is at work on this grid
    assert light.best_.name == full.best_.name
    z_light = {r.name: r.ln_evidence for r in light.results_}
    z_full = {r.name: r.ln_evidence for r in full.results_}
    assert z_light.keys() == z_full.keys()
    worst = max(abs(z_light[k] - z_full[k]) for k in z_full if np.isfinite(z_full[k]))
    assert worst < 3.2e-3, worst
