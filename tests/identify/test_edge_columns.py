"""The inertia column at a grasp's edges: the filtered force holds ``g * (touching *
M x'')``, the acceleration gated on the raw grid before the filter, and the column must
hold the same there, or the misfit at every edge is taken up by whatever term can bend
to it (a fast relaxation branch, on the paper-form session below)."""

from __future__ import annotations

import numpy as np

from tissuecli.core.terms import Inertia
from tissuecli.identify import BayesianFit
from tissuecli.sim.scenes import FAMILIES, random_scene

PAPER = [f for f in FAMILIES if f.startswith("paper")]


def _scene_and_fit():
    # x+xdot+xddot, 3.7 kHz, 10 bits, 3 % noise, slow squeeze: grasps with free jaws
    scene = random_scene(5520311, families=PAPER, max_samples=10_000)
    s = scene.session
    n = int(0.7 * s.time.size)
    ready = BayesianFit().prepare(s.replace(s.time[:n], s.force[:n], s.position[:n]))
    return scene, n, ready


def test_the_inertia_column_is_the_gated_acceleration_filtered_at_the_edges() -> None:
    """With the true (noise-free) closure, the column at the outputs within a quarter
    window of an edge equals the filtered gated true acceleration to 5 % of its RMS
    there (the sampled Gaussian's second derivative against the second difference;
    gating the half window's own acceleration was off by 19 %), and where the whole
    window is in contact the column is the plain ``g'' * x`` to rounding."""
    scene, n, ready = _scene_and_fit()
    kin = ready.kinematics
    assert kin.touching is not None and kin.half is not None
    touching = kin.touching[:n].astype(float)
    column = kin.acceleration_input(Inertia(), scene.x[:n])
    truth = kin.smooth(touching * scene.a[:n])
    edges = np.flatnonzero(np.diff(touching))
    assert edges.size >= 3
    centre = np.arange(n)[kin.keep]
    gap = np.min(np.abs(centre[:, None] - edges[None, :]), axis=1)
    near = gap < kin.window // 4
    assert near.sum() > 100
    err = np.sqrt(np.mean((column[near] - truth[near]) ** 2))
    assert err < 0.05 * np.sqrt(np.mean(truth[near] ** 2))
    # whole windows in contact: the kinematics' own ``g'' * x`` of the measured closure
    inside = (gap > kin.window // 2 + 1) & (touching[centre] > 0)
    assert inside.sum() > 1000
    measured = kin.acceleration_input(Inertia(), ready.session.position)
    scale = np.sqrt(np.mean(kin.a[inside] ** 2))
    assert np.max(np.abs(measured[inside] - kin.a[inside])) < 1e-3 * scale


def test_a_paper_form_with_edges_gets_no_relaxation_branch() -> None:
    """The session's law x+xdot+xddot: with the edges' misfit the search added a fast
    relaxation branch at P = 0.79; without it the truth is chosen."""
    scene, n, ready = _scene_and_fit()
    s = scene.session
    est = BayesianFit().fit(s.replace(s.time[:n], s.force[:n], s.position[:n]))
    assert est.best_.model.name == "x+xdot+xddot"
    assert est.best_.probability > 0.9
