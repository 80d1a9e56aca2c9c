"""The search for the peak of the evidence over a law's shape parameters: a posterior
piled on the prior's edge has no peak (the grid integrates it), and a sharp peak near
the edge is still found (the climb ends early only on an edge the posterior falls away
from)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tissuecli.core.terms import TIME_CONSTANT
from tissuecli.identify.shapes import EDGE_CHECK, ShapeGrid, laplace


def _grid(k: int = 16) -> ShapeGrid:
    """One time constant, log-uniform over 10 ms to 10 s on ``k`` nodes."""
    lo, hi = 0.01, 10.0
    u = np.linspace(math.log(lo), math.log(hi), k)
    nodes = [{"tau1": float(math.exp(v))} for v in u]
    width = u[-1] - u[0]
    return ShapeGrid(
        nodes, np.full(k, -math.log(k)), {"tau1": (lo, hi)}, np.array([u[1] - u[0]]),
        -math.log(width), {"tau1": TIME_CONSTANT},
    )  # fmt: skip


def _counted(f):  # type: ignore[no-untyped-def]
    calls: list[float] = []

    def log_z(u: np.ndarray) -> float:
        calls.append(float(u[0]))
        return f(float(u[0]))

    return log_z, calls


@pytest.mark.parametrize("slope", [5.0, 200.0])
def test_a_posterior_piled_on_the_edge_ends_the_climb_early(slope: float) -> None:
    """Evidence rising to the prior's upper edge: no peak, within the first climb's
    budget of evaluations."""
    grid = _grid()
    log_z, calls = _counted(lambda u: slope * u)
    start = grid.to_u(grid.nodes[-2])
    assert laplace(log_z, grid, [start]) is None
    assert len(calls) < EDGE_CHECK


@pytest.mark.parametrize("depth", [0.3, 0.6])
def test_a_sharp_peak_near_the_edge_is_still_found(depth: float) -> None:
    """A sharp peak a fraction of a grid step inside the edge, the climb started on the
    edge node: the Laplace approximation is at the peak."""
    grid = _grid()
    h = float(grid.spacing[0])
    top = math.log(10.0) - depth * h
    sd = 0.01 * h
    log_z, _ = _counted(lambda u: -0.5 * ((u - top) / sd) ** 2)
    peak = laplace(log_z, grid, [grid.to_u(grid.nodes[-1])])
    assert peak is not None
    assert abs(float(peak.u[0]) - top) < 0.1 * sd
    assert float(peak.sd[0]) == pytest.approx(sd, rel=1e-3)


def _grid_tau_n() -> tuple[ShapeGrid, np.ndarray, np.ndarray]:
    """A time constant log-uniform over 10 ms to 10 s on 16 nodes by an exponent over
    1-2.5 on 5; with the time constant's nodes (ln s) and the grid's spacing."""
    from tissuecli.core.terms import EXPONENT

    taus = np.linspace(math.log(0.01), math.log(10.0), 16)
    ns = np.linspace(1.0, 2.5, 5)
    nodes = [{"tau1": float(math.exp(a)), "n": float(b)} for a in taus for b in ns]
    h = np.array([taus[1] - taus[0], ns[1] - ns[0]])
    grid = ShapeGrid(
        nodes, np.full(len(nodes), -math.log(len(nodes))),
        {"tau1": (0.01, 10.0), "n": (1.0, 2.5)}, h, 0.0,
        {"tau1": TIME_CONSTANT, "n": EXPONENT},
    )  # fmt: skip
    return grid, taus, h


def test_a_sharp_peak_near_an_edge_in_two_parameters_is_found() -> None:
    """A time constant's sharp peak a tenth of a grid step inside its upper edge, with
    an exponent well inside its range: the climbs from the best grid nodes end at the
    peak, not on the edge."""
    grid, taus, h = _grid_tau_n()
    centre = np.array([taus[-1] - 0.1 * h[0], 1.355])
    sd = np.array([0.052 * h[0], 0.02 * h[1]])
    cov = np.array([[1.0, 0.37], [0.37, 1.0]]) * np.outer(sd, sd)
    precision = np.linalg.inv(cov)

    def log_z(u: np.ndarray) -> float:
        z = u - centre
        return float(-0.5 * z @ precision @ z)

    values = np.array([log_z(grid.to_u(node)) for node in grid.nodes])
    starts = [grid.to_u(grid.nodes[i]) for i in np.argsort(-values)[:3]]
    peak = laplace(log_z, grid, starts)
    assert peak is not None
    # Newton's steps stop within a hundredth of an SD
    np.testing.assert_allclose(peak.u, centre, atol=0.02 * float(np.min(sd)))


def test_the_curvature_along_a_ridge_is_measured_at_its_own_scale() -> None:
    """Two shape parameters that trade off along a narrow ridge (a contact's exponent
    and contact point), the ln evidence falling faster than a parabola away from it:
    the Laplace SD along the ridge is the posterior's (an exact parabola there) to
    1e-6. Measured by central differences along the coordinates, the ridge's curvature
    is the small difference of the large curvatures across it, and the quartic's share
    of those put the SD along the ridge 1.44 times too wide."""
    grid, _, h = _grid_tau_n()
    centre = np.array([math.log(0.3), 1.8])
    along = h / np.linalg.norm(h)  # the ridge, diagonal across the grid
    across = np.array([-along[1], along[0]])
    sd_along = 0.1 * float(np.min(h))
    sd_across = 0.01 * sd_along

    def log_z(u: np.ndarray) -> float:
        a, b = (u - centre) @ across / sd_across, (u - centre) @ along / sd_along
        return float(-0.5 * b * b - 0.5 * a * a - 1e-4 * a**4)

    peak = laplace(log_z, grid, [centre + 0.3 * sd_along * along])
    assert peak is not None
    measured = math.sqrt(float(along @ peak.cov @ along))
    assert measured == pytest.approx(sd_along, rel=1e-6)
