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


def _on_true_closure(scene, n: int, kin, edges_at_least: int):  # type: ignore[no-untyped-def]
    """The inertia column from the true closure, the filtered gated true acceleration,
    the contact flags, each output's distance to the nearest edge (samples) and the
    centre of each output's window."""
    assert kin.touching is not None and kin.half is not None
    touching = kin.touching[:n].astype(float)
    column = kin.acceleration_input(Inertia(), scene.x[:n])
    truth = kin.smooth(touching * scene.a[:n])
    edges = np.flatnonzero(np.diff(touching))
    assert edges.size >= edges_at_least
    centre = np.arange(n)[kin.keep]
    gap = np.min(np.abs(centre[:, None] - edges[None, :]), axis=1)
    return column, truth, touching, gap, centre


def test_the_inertia_column_is_the_gated_acceleration_filtered_at_the_edges() -> None:
    """With the true (noise-free) closure, the column at the outputs within a quarter
    window of an edge equals the filtered gated true acceleration to 5 % of its RMS
    there (the sampled Gaussian's second derivative against the second difference;
    gating the half window's own acceleration was off by 19 %), and where the whole
    window is in contact the column is the plain ``g'' * x`` to rounding."""
    scene, n, ready = _scene_and_fit()
    kin = ready.kinematics
    column, truth, touching, gap, centre = _on_true_closure(scene, n, kin, 3)
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


def _grasps_at_6_6_khz(noise_seed: int | None = None):
    # x+xdot+xddot, 6.6 kHz, 15 bits, 0.6 % noise, slow squeeze: grasps whose jaws meet
    # the tissue at 0.24 m/s, the edge's speed term 1/dt times the column's scale
    scene = random_scene(9260004, families=PAPER, max_samples=10_000, noise_seed=noise_seed)
    s = scene.session
    n = int(0.7 * s.time.size)
    return scene, n, s.replace(s.time[:n], s.force[:n], s.position[:n])


def test_the_edge_terms_leave_no_mean_misfit_along_the_edges() -> None:
    """The edges' terms read the closure either side of each edge from a polynomial
    through the half window's span: a cubic's slope there was biased by 0.3 % of the
    jaws' speed, and with the true closure the column's mean over the outputs within a
    quarter window of the edges was 0.46 % of its RMS off the filtered gated true
    acceleration, the same sign at every edge. The bias of a quintic is the sixth power
    of the span over the motion's time scale, below 0.1 % here."""
    scene, n, head = _grasps_at_6_6_khz()
    kin = BayesianFit().prepare(head).kinematics
    column, truth, _, gap, _ = _on_true_closure(scene, n, kin, 4)
    near = gap < kin.window // 4
    rms = np.sqrt(np.mean(truth[near] ** 2))
    assert abs(np.mean(column[near] - truth[near])) < 1e-3 * rms


def test_no_offset_stands_in_for_the_edges_misfit() -> None:
    """Across noise draws of the same session, the offset of x+xdot+xddot+offset (the
    truth has none) lies off zero by its posterior SD times a standard normal: the mean
    of 8 draws' z within 3 / sqrt(8) (0.3 % of such means lie beyond). With the edges'
    misfit every draw put it 0.3-4.5 SDs below zero (mean -2.6), and one chose it."""
    zs = []
    for k in range(8):
        _, _, head = _grasps_at_6_6_khz(noise_seed=None if k == 0 else 1000 + k)
        est = BayesianFit().fit(head)
        with_offset = next(r for r in est.results_ if r.name == "x+xdot+xddot+offset")
        post = with_offset.posterior
        assert post is not None
        i = list(with_offset.model.symbols).index("F0")
        zs.append(post.mean[i] / post.sd[i])
        if k == 0:
            assert est.best_.model.name == "x+xdot+xddot"
    assert abs(np.mean(zs)) < 3 / np.sqrt(8), zs
