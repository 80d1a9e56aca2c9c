"""Laws with nonlinear (shape) parameters: relaxation time constants, a contact's
exponent and contact point, or any a term declares. Given the shape the law is linear in
its coefficients, so its exact evidence is known; the shape is marginalised by
quadrature over a grid that covers only what the session can resolve, and the posterior
is the mixture of the grid's conditional posteriors.

Priors come from the terms: each declares its shape parameters
(:class:`~tissuecli.core.terms.ShapeParameter`) with the coordinate the prior is
uniform in and its support for a session. For the built-in terms: a time constant is
log-uniform between what the filter can resolve and a third of the fitted stretch (and
within 10 ms to 100 s); several branches' time constants are ordered, tau1 < tau2,
uniform over that triangle; the Hunt-Crossley exponent n is uniform on [1, 2.5]; the
contact point x0 uniform from a quarter of the closure's span below its lowest fitted
value (or from the lowest closure of the whole session, where the fit keeps to the
grasps, or from where the force across the closures lets the steepest exponent touch:
:meth:`~tissuecli.core.terms.ContactPoint.reach`) to half the span above it.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from types import SimpleNamespace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..core.terms import TIME_CONSTANT, Law, SessionSpan, ShapeParameter
from .derivatives import Kinematics
from .posterior import Posterior, central95

Array = NDArray[np.float64]

#: evaluations per shape parameter after which the search for the peak checks whether
#: it is heading for the prior's edge
EDGE_CHECK = 25
#: evaluations per shape parameter a climb's best point may stay on the prior's edge
#: before the climb stops there, if the posterior falls away from the edge inwards
EDGE_SETTLE = 6
#: where, in grid steps from the edge, the posterior must fall away for a climb to end
INWARD = (1 / 32, 1 / 8, 1 / 2, 1.0)
#: nodes holding this much of the posterior are summarised (at most MAX_KEPT of them)
KEPT_MASS, MAX_KEPT = 0.999, 12
#: draws of a mixture over shape nodes, shared out among its components by weight
MIX_DRAWS = 4000


@dataclass
class ShapeGrid:
    """Quadrature nodes over a law's shape parameters.

    The prior is uniform in the coordinates ``u`` (each parameter's
    :meth:`~tissuecli.core.terms.ShapeParameter.to_u`: ln tau for a time constant, the
    value itself for n and x0), over the box of ``ranges`` (the parameters of a
    repeated term ordered).

    Attributes
    ----------
    nodes : list of dict
        Shape values (SI) by name.
    log_weight : ndarray, shape (k,)
        ln of each node's prior mass (they sum to 1).
    ranges : dict
        The range searched for each parameter (SI).
    spacing : ndarray, shape (d,)
        The nodes' spacing in ``u``, per parameter.
    log_density : float
        ln of the prior density in ``u`` inside the ranges.
    params : dict
        Each parameter's declaration, by name.
    ordered : list of list of str
        Groups of parameters held in increasing order (a repeated term's).
    """

    nodes: list[dict[str, float]]
    log_weight: Array
    ranges: dict[str, tuple[float, float]] = field(default_factory=dict)
    spacing: Array = field(default_factory=lambda: np.zeros(0))
    log_density: float = 0.0
    params: dict[str, ShapeParameter] = field(default_factory=dict)
    ordered: list[list[str]] = field(default_factory=list)

    @property
    def names(self) -> list[str]:
        return list(self.nodes[0])

    def log(self, name: str) -> bool:
        """Whether the prior of ``name`` is uniform in its logarithm."""
        return self.params[name].log

    def to_u(self, node: dict[str, float]) -> Array:
        return np.array([self.params[n].to_u(node[n]) for n in self.names])

    def from_u(self, u: Array) -> dict[str, float]:
        return {n: self.params[n].from_u(float(v)) for n, v in zip(self.names, u, strict=True)}

    def inside(self, u: Array) -> bool:
        """Whether ``u`` lies in the prior's support (ordered groups in order)."""
        at = dict(zip(self.names, u, strict=True))
        for n, v in at.items():
            lo, hi = (self.params[n].to_u(b) for b in self.ranges[n])
            if not lo <= v <= hi:
                return False
        return all(at[a] < at[b] for group in self.ordered for a, b in itertools.pairwise(group))

    def inside_many(self, us: Array) -> NDArray[np.bool_]:
        """:meth:`inside` of each row of ``us`` (k, d), at once."""
        us = np.atleast_2d(np.asarray(us, dtype=float))
        ok = np.ones(us.shape[0], bool)
        for j, n in enumerate(self.names):
            lo, hi = (self.params[n].to_u(b) for b in self.ranges[n])
            ok &= (us[:, j] >= lo) & (us[:, j] <= hi)
        index = {n: j for j, n in enumerate(self.names)}
        for group in self.ordered:
            for a, b in itertools.pairwise(group):
                ok &= us[:, index[a]] < us[:, index[b]]
        return ok

    def interior(self, u: Array) -> Array:
        """``u`` moved inside the box by a millionth of a grid step: a node on the
        box's edge may fall outside it after a round trip through ln and exp."""
        out = np.array(u, dtype=float)
        for i, (n, h) in enumerate(zip(self.names, self.spacing, strict=True)):
            lo, hi = (self.params[n].to_u(b) for b in self.ranges[n])
            out[i] = min(max(out[i], lo + 1e-6 * h), hi - 1e-6 * h)
        return out


def session_span(kin: Kinematics, closure: bool = True) -> SessionSpan:
    """What a session lets the shape parameters' priors span (see
    :class:`~tissuecli.core.terms.SessionSpan`); without ``closure`` the closure's low
    end and span are NaN (a pass over every sample saved where only times matter)."""
    gate = kin.gate
    x = kin.x_raw if gate is None else kin.x_raw[gate > 0]  # the closures in contact
    x = x if x.size else kin.x_raw
    ratio, ends = _force_ratio(kin) if closure else (math.nan, (math.nan, math.nan))
    return SessionSpan(
        dt=kin.dt,
        cutoff_hz=float(kin.cutoff_hz),
        duration_s=float(kin.time[-1] - kin.time[0]),
        x_low=float(np.percentile(x, 2)) if closure else math.nan,
        x_span=float(np.ptp(x)) if closure else math.nan,
        x_floor=kin.x_floor if closure and kin.x_floor is not None else math.nan,
        f_ratio=ratio,
        x_ends=ends,
    )


def _force_ratio(kin: Kinematics) -> tuple[float, tuple[float, float]]:
    """The filtered force at the fitted closure's low end over that at its high end
    (medians over the outputs in contact of the lowest and the highest twentieth of the
    closures), and those twentieths' median closures (m): NaN where too few outputs."""
    gate = kin.gate
    inside = np.ones(kin.x.size, dtype=bool) if gate is None else gate > 0
    x, f = kin.x[inside], kin.force[inside]
    if x.size < 20:
        return math.nan, (math.nan, math.nan)
    a, b = np.percentile(x, [5.0, 95.0])
    low, high = x <= a, x >= b
    f_hi = float(np.median(f[high]))
    if not f_hi > 0:
        return math.nan, (math.nan, math.nan)
    return float(np.median(f[low])) / f_hi, (float(np.median(x[low])), float(np.median(x[high])))


def tau_range(kin: Kinematics) -> tuple[float, float]:
    """The time constants a fit can tell apart, s (a relaxation branch's prior:
    :class:`~tissuecli.core.terms.TimeConstant`)."""
    return TIME_CONSTANT.prior_range(session_span(kin, closure=False))


def resolvable(kin: Kinematics) -> bool:
    """Whether the session resolves any time constant (a range of at least a factor 4)."""
    lo, hi = tau_range(kin)
    return hi > 4.0 * lo


def _groups(law: Law) -> list[list[str]]:
    """The law's shape parameters in groups: those of a repeated term (one parameter each,
    exchangeable, so held in order) first, then each other parameter alone, in the
    law's order."""
    repeated: dict[type, list[str]] = {}
    singles: list[str] = []
    seen: set[str] = set()
    for t in law.terms:
        for name in t.shapes:
            if name in seen:
                continue  # shared (contact and its damping share n and x0)
            seen.add(name)
            if t.max_count > 1 and len(t.shapes) == 1:
                repeated.setdefault(type(t), []).append(name)
            else:
                singles.append(name)
    return [*repeated.values(), *([n] for n in singles)]


def shape_grid(law: Law, kin: Kinematics, coarse: bool = False) -> ShapeGrid:
    """The quadrature nodes and prior masses for ``law``'s shape parameters; ``coarse``:
    each parameter's coarse node count, a seed for a sampler rather than a quadrature."""
    span = session_span(kin)
    axes: list[tuple[list[str], Array, Array]] = []  # names, values (k, d), ln weights (k,)
    ranges: dict[str, tuple[float, float]] = {}
    params: dict[str, ShapeParameter] = {}
    ordered: list[list[str]] = []
    spacing: list[float] = []
    log_density = 0.0
    for group in _groups(law):
        spec = law.shape_parameter(group[0])
        lo, hi = spec.prior_range(span)
        u_lo = spec.to_u(lo)
        width = spec.to_u(max(hi, lo * 1.0001)) - u_lo if spec.log else hi - lo
        k = spec.nodes_for(len(group), coarse)
        u, w = _trapezoid(u_lo, u_lo + width, max(k, len(group)))
        combos = np.array(list(itertools.combinations(range(u.size), len(group))))
        values = np.array([[spec.from_u(float(v)) for v in row] for row in u[combos]])
        lw = np.sum(np.log(w[combos]), axis=1)
        axes.append((group, values, lw - _logsumexp(lw)))
        for name in group:
            ranges[name] = (lo, hi)
            params[name] = spec
        if len(group) > 1:
            ordered.append(group)
        spacing += [float(u[1] - u[0])] * len(group)
        # uniform over the ordered simplex of the box: k! / width^k
        log_density += math.lgamma(len(group) + 1) - len(group) * math.log(width)
    nodes: list[dict[str, float]] = []
    log_weight: list[float] = []
    for parts in itertools.product(*(range(len(a[1])) for a in axes)):
        node: dict[str, float] = {}
        lw = 0.0
        for (axis_names, values, weights), i in zip(axes, parts, strict=True):
            node.update(zip(axis_names, (float(v) for v in values[i]), strict=True))
            lw += float(weights[i])
        nodes.append(node)
        log_weight.append(lw)
    return ShapeGrid(nodes, np.array(log_weight), ranges, np.array(spacing), log_density,
                     params, ordered)  # fmt: skip


@dataclass
class Peak:
    """A sharp posterior over the shape, found by Newton steps on finite differences of
    the log evidence in ``u``: its mode, the log evidence there, and the covariance
    of the Gaussian (Laplace) approximation."""

    u: Array
    log_z: float
    cov: Array

    @property
    def sd(self) -> Array:
        return np.sqrt(np.diag(self.cov))

    @property
    def axes(self) -> Array:
        """The Gaussian's principal axes (:func:`principal_axes`)."""
        return principal_axes(self.cov)


def principal_axes(cov: Array) -> Array:
    """The principal axes of a Gaussian of covariance ``cov`` (d, d), shape (d, d):
    each column one SD long."""
    lam, vec = np.linalg.eigh(cov)
    return np.asarray(vec * np.sqrt(np.clip(lam, 0.0, None)))


def laplace(
    log_z: Callable[[Array], float],
    grid: ShapeGrid,
    starts: list[Array],
    hint: Peak | None = None,
) -> Peak | None:
    """The peak of ``log_z`` (ln evidence given the shape, as a function of ``u``) and
    the Laplace approximation there; None when the surface is not concave at the peak
    (a broad or multimodal posterior, which the grid integrates better).

    The log evidence is often far sharper than the grid (a drop of 50 within a tenth
    of a grid step) and its peak may lie on a curved ridge (a contact's exponent and
    contact point trade off), so the peak is found by Nelder-Mead from each of
    ``starts`` (the best grid nodes), which needs no derivative, then polished by
    Newton steps whose curvature comes from central differences along the posterior's
    own axes, at its own scale (:func:`_polish`)."""
    from scipy.optimize import minimize  # only for laws with shape parameters

    def cost(u: Array) -> float:
        value = log_z(u) if grid.inside(u) else -math.inf
        return -value if math.isfinite(value) else 1e300

    # the climb runs in grid steps: Nelder-Mead's moves do not depend on the coordinates'
    # scales, but its stopping rule does (one tolerance for every coordinate), and in
    # ``u`` it held an exponent to a thousandth of the contact point's grid step
    scale = grid.spacing

    def climb(start: Array, maxfev: int, step: Array) -> Any:
        simplex = np.vstack([start, start + np.diag(step)]) / scale
        options = {
            "initial_simplex": simplex,
            "xatol": 1e-3,
            "fatol": 0.01,
            "maxfev": maxfev,
        }
        # the simplex's best point is the best evaluated so far: once it has stayed on
        # the edge a while and the posterior falls away inwards, the climb ends there
        # (what the rest of it did, at the cost of most of a law's evaluations)
        best: list[Any] = [math.inf, None, 0]  # cost, point, evaluations on the edge

        def watched(u: Array) -> float:
            c = cost(u)
            if c < best[0]:
                best[0], best[1] = c, np.array(u, dtype=float)
            if best[0] < 1e300 and _at_edge(grid, best[1]):
                best[2] += 1
                if best[2] >= EDGE_SETTLE * start.size:
                    if _falls_away(cost, grid, best[1], best[0]):
                        raise _OnEdge
                    best[2] = 0
            else:
                best[2] = 0
            return c

        try:
            found = minimize(lambda w: watched(w * scale), start / scale, method="Nelder-Mead",
                             options=options)  # fmt: skip
            final = found.final_simplex[0] * scale
            spread = np.max(np.abs(final - final[0]), axis=0)
            return SimpleNamespace(x=found.x * scale, fun=found.fun, success=found.success,
                                   spread=spread)  # fmt: skip
        except _OnEdge:
            return SimpleNamespace(x=best[1], fun=best[0], success=False, spread=None)

    if hint is not None and hint.u.size == grid.spacing.size and grid.inside(hint.u):
        # a sibling law's peak (the same shape parameters, one term more or less): where
        # it stands above every start, Newton steps from it at its own scale find this
        # law's peak without a climb; else the climbs below
        if log_z(hint.u) > max(log_z(u) for u in starts) and not _at_edge(grid, hint.u):
            h = np.clip(hint.sd, 1e-6 * grid.spacing, grid.spacing / 50.0)
            peak = _polish(log_z, grid, hint.u, h)
            if peak is not None and not _at_edge(grid, peak.u):
                return peak
    for start in starts:  # the next start only if the peak from the last is not one
        # a first short climb: one that ends against the prior's edge has found no
        # Gaussian peak, and the grid integrates a posterior piled on an edge. This is
        # where a law with nothing to relax or to contact ends, so stopping there (and
        # skipping the other starts) saves most of the search's time on such sessions
        found = climb(start, EDGE_CHECK * start.size, grid.spacing / 2.0)
        if found.fun < 1e300 and _at_edge(grid, np.asarray(found.x, dtype=float)):
            return None
        if not found.success and found.fun < 1e300:  # not there yet: climb on
            found = climb(np.asarray(found.x, dtype=float), 80 * start.size, grid.spacing / 8.0)
        if found.fun < 1e300:
            u = np.asarray(found.x, dtype=float)
            if _at_edge(grid, u):
                return None
            # the first differences as far apart as the climb's last simplex (where the
            # peak is sharp, a fiftieth of a grid step is tens of its SDs)
            h = None if found.spread is None else np.clip(found.spread, 1e-6 * grid.spacing,
                                                          grid.spacing / 50.0)  # fmt: skip
            peak = _polish(log_z, grid, u, h)
            if peak is not None:
                return peak
    return None


def edge_peak(log_z: Callable[[Array], float], grid: ShapeGrid, start: Array) -> Peak | None:
    """The peak of ``log_z`` near ``start`` (``u``) with the shape free to every
    parameter's limits (where the law is defined), beyond the prior's box: where the
    posterior is sharper than the grid and piled against the box's edge, the Gaussian at
    that peak, cut to the box, is its shape. None if no concave peak is found there."""
    limits = {n: grid.params[n].limits for n in grid.names}
    open_grid = replace(grid, ranges=limits, ordered=grid.ordered)
    peak = laplace(log_z, open_grid, [np.asarray(start, dtype=float)])
    if peak is None or not np.all(np.isfinite(peak.cov)):
        return None
    return peak


class _OnEdge(Exception):
    """A climb's best point has settled on the prior's edge."""


def _falls_away(cost: Callable[[Array], float], grid: ShapeGrid, u: Array, c: float) -> bool:
    """Whether ``u`` (of cost ``c``) lies on an edge of the prior's box and the cost
    rises from it inwards: at :data:`INWARD` grid steps in, along each parameter at its
    bound (a peak more than a sixty-fourth of a step inside is nearer the first of them
    than the edge is, so a posterior falling off on both sides of it costs less there).
    False on the edge where two ordered parameters meet (no single step leads inwards
    there)."""
    edges = 0
    for i, (n, h) in enumerate(zip(grid.names, grid.spacing, strict=True)):
        lo, hi = (grid.params[n].to_u(b) for b in grid.ranges[n])
        if u[i] - lo < 0.05 * h:
            inward = h
        elif hi - u[i] < 0.05 * h:
            inward = -h
        else:
            continue
        edges += 1
        for f in INWARD:
            v = np.array(u, dtype=float)
            v[i] += f * inward
            if not grid.inside(v) or not cost(v) > c:
                return False
    return edges > 0


def _at_edge(grid: ShapeGrid, u: Array) -> bool:
    """Whether ``u`` lies within a twentieth of a grid step of the prior's support's
    edge (the box, or two time constants meeting)."""
    for i, h in enumerate(grid.spacing):
        e = np.zeros(u.size)
        e[i] = 0.05 * h
        if not (grid.inside(u + e) and grid.inside(u - e)):
            return True
    return False


def _polish(
    log_z: Callable[[Array], float], grid: ShapeGrid, u: Array, h: Array | None = None
) -> Peak | None:
    """Newton steps to the peak near ``u``, and its curvature; None if not concave. The
    first central differences are ``h`` apart (a fiftieth of a grid step if None), the
    next the last step's SDs; the peak is taken once they are and the step is under a
    hundredth of them, its curvature then measured again along its own axes where its
    parameters trade off (:func:`_on_axes`)."""
    h = grid.spacing / 50.0 if h is None else h
    for _ in range(12):
        newton = _newton(log_z, u, np.diag(h), grid)
        if newton is None:
            return None
        f0, _, cov, step = newton
        sd = np.sqrt(np.diag(cov))
        # at most three SDs at a time, and never out of the prior's support
        step *= min(1.0, 3.0 / max(float(np.max(np.abs(step) / sd)), 1e-300))
        converged = bool(np.all(np.abs(step) < 0.01 * sd)) and bool(np.all(h <= 1.01 * sd))
        if converged:
            return _on_axes(log_z, grid, Peak(u, f0, cov))
        if grid.inside(u + step):
            u = u + step
        h = np.clip(sd, 1e-7, grid.spacing / 2.0)
    return None


#: shape parameters correlated beyond this have their peak's curvature measured along
#: its principal axes (:func:`_on_axes`): a step of one marginal SD along a coordinate
#: lies ``1 / sqrt(1 - rho^2)`` of the conditional SDs across the ridge, 2.3 at 0.9
RIDGE_CORRELATION = 0.9

#: the longest a difference frame's axis may be at the peak, in the posterior's SDs
#: along it (each axis is the previous step's, measured anew)
FRAME_SD = 1.05


def _on_axes(log_z: Callable[[Array], float], grid: ShapeGrid, peak: Peak) -> Peak:
    """``peak`` with its curvature from central differences along its own principal
    axes, one SD each (Newton steps on them, at most three), where two of its
    parameters are correlated beyond :data:`RIDGE_CORRELATION`; ``peak`` as it is
    otherwise, or where those differences are not concave or leave the prior.

    Along the coordinates, the curvature along a ridge where two parameters trade off
    (a contact's exponent and contact point) is the small difference of the large
    curvatures across it, measured far off the ridge: on a 15-bit Hunt-Crossley
    session the ln evidence fell 0.11 at one SD along the ridge, not 0.5, and the
    exponent's interval came out 2.2 times too narrow."""
    sd = peak.sd
    corr = peak.cov / np.outer(sd, sd)
    if peak.u.size < 2 or np.max(np.abs(corr - np.eye(sd.size))) <= RIDGE_CORRELATION:
        return peak
    u, cov = peak.u, peak.cov
    for _ in range(3):
        frame = _frame(cov, grid)
        newton = _newton(log_z, u, frame, grid)
        if newton is None:
            return peak
        f0, H, cov, step = newton
        # each axis of the frame in the posterior's SDs along it
        lengths = np.sqrt(np.maximum(np.einsum("ik,ij,jk->k", frame, -H, frame), 0.0))
        if np.all(np.abs(step) < 0.01 * np.sqrt(np.diag(cov))) and np.all(lengths <= FRAME_SD):
            return Peak(u, f0, cov)
        if not grid.inside(u + step):
            return peak
        u = u + step
    return peak


def _newton(
    log_z: Callable[[Array], float], u: Array, frame: Array, grid: ShapeGrid
) -> tuple[float, Array, Array, Array] | None:
    """``log_z`` at ``u``, its Hessian H by central differences along ``frame``'s
    columns (:func:`_stencil`), the covariance ``(-H)^-1`` and the Newton step to its
    peak; None where the stencil leaves the prior or the curvature is not concave."""
    f0, g, H = _stencil(log_z, u, frame, grid)
    if H is None or not np.all(np.linalg.eigvalsh(H) < 0):
        return None
    cov = np.linalg.inv(-H)
    return f0, H, cov, cov @ g


def _frame(cov: Array, grid: ShapeGrid) -> Array:
    """The principal axes of ``cov`` (:func:`principal_axes`), but no longer than half
    a grid step in any coordinate and no shorter than 1e-7 in all."""
    frame = principal_axes(cov)
    reach = np.max(np.abs(frame) / (grid.spacing[:, None] / 2.0), axis=0)
    frame = frame / np.maximum(reach, 1.0)
    size = np.max(np.abs(frame), axis=0)
    return frame * np.maximum(1e-7 / np.maximum(size, 1e-300), 1.0)


def _stencil(
    f: Callable[[Array], float], u: Array, frame: Array, grid: ShapeGrid
) -> tuple[float, Array, Array | None]:
    """Value, gradient and Hessian of ``f`` at ``u`` in ``u``'s coordinates, from
    central differences along the columns of ``frame`` (None if the stencil leaves the
    prior's support)."""
    d = u.size
    f0 = f(u)
    g = np.zeros(d)
    H = np.zeros((d, d))
    for i in range(d):
        e = frame[:, i]
        if not (grid.inside(u + e) and grid.inside(u - e)):
            return f0, g, None
        fp, fm = f(u + e), f(u - e)
        g[i] = 0.5 * (fp - fm)
        H[i, i] = fp - 2 * f0 + fm
        for j in range(i):
            e2 = frame[:, j]
            pts = [u + e + e2, u - e - e2, u + e - e2, u - e + e2]
            if not all(grid.inside(p) for p in pts):
                return f0, g, None
            fpp, fmm, fpm, fmp = (f(p) for p in pts)
            H[i, j] = H[j, i] = 0.25 * (fpp + fmm - fpm - fmp)
    # from the frame's coordinates w (u = u0 + frame w) to u's
    inv = np.linalg.inv(frame)
    return f0, inv.T @ g, inv.T @ H @ inv


def hermite_nodes(peak: Peak) -> tuple[list[Array], Array]:
    """Three-point Gauss-Hermite nodes per dimension of the peak's Gaussian (along its
    principal axes) and their weights: enough to carry the shape's uncertainty into
    the coefficients' posterior."""
    scale = peak.axes
    z1, w1 = np.array([-math.sqrt(3.0), 0.0, math.sqrt(3.0)]), np.array([1, 4, 1]) / 6.0
    nodes, weights = [], []
    for idx in itertools.product(range(3), repeat=peak.u.size):
        z = z1[list(idx)]
        nodes.append(peak.u + scale @ z)
        weights.append(float(np.prod(w1[list(idx)])))
    return nodes, np.array(weights)


#: the three Gauss-Hermite abscissae of :func:`hermite_nodes`, in standard deviations
HERMITE_Z = (-math.sqrt(3.0), 0.0, math.sqrt(3.0))


def hermite_interpolant(values: Array, z: Array) -> Array:
    """The polynomial through :func:`hermite_nodes`' values, at standard-normal points.

    ``values`` (3^d, ...) hold a quantity at each node, in the nodes' order; the
    interpolant is the tensor product of the Hermite polynomials 1, ``z`` and ``z^2 - 1``
    in each principal direction, so its mean and variance over the peak's Gaussian are
    the nodes' weighted mean and variance (the three-point rule integrates it and its
    square exactly). Returns it at ``z`` (k, d), shape (k, ...).
    """
    z = np.atleast_2d(np.asarray(z, dtype=float))
    d = z.shape[1]
    nodes = np.array(list(itertools.product(HERMITE_Z, repeat=d)))

    def basis(q: Array) -> Array:
        per = np.stack([np.ones_like(q), q, q**2 - 1.0], axis=-1)  # (k, d, 3)
        out = np.ones((q.shape[0], 1))
        for j in range(d):
            out = (out[:, :, None] * per[:, j, None, :]).reshape(q.shape[0], -1)
        return out

    vals = np.asarray(values, dtype=float)
    coef = np.linalg.solve(basis(nodes), vals.reshape(vals.shape[0], -1))
    return np.asarray((basis(z) @ coef).reshape((z.shape[0], *vals.shape[1:])))


def continuous_mixture(
    post: Posterior,
    components: list[Posterior],
    peak: Peak,
    grid: ShapeGrid,
    bounded: NDArray[np.bool_],
    rng: np.random.Generator,
    truncated: bool = False,
) -> Posterior:
    """``post``, the mixture of :func:`hermite_nodes`' conditional posteriors, with its
    intervals and draws taken over the shape's continuous Gaussian rather than its nine
    (or three) nodes.

    The three-point rule carries the shape's uncertainty into the coefficients' mean and
    variance exactly, but a mixture of a few narrow components has the quantiles of a
    few points: where the shape's uncertainty dominates a coefficient (a contact
    stiffness in N/m^n moves with n), its 2.5 % quantile sat on the outer node at
    sqrt(3) = 1.73 SDs, not 1.96, and the interval held the truth in about nine cases in
    ten. Here each draw takes a shape from the peak's Gaussian, the coefficients' mean
    there from the nodes' means (:func:`hermite_interpolant`), and a deviation from the
    nearest node's draws about its mean; draws the prior's support over the shape
    (``grid``) or the positivity bounds (``bounded``, per coefficient) exclude are
    dropped. Mean, covariance and everything else stay ``post``'s, unless ``truncated``:
    some of the nodes lie outside the prior's support (``components`` holds every node
    all the same, for the interpolant), so ``post`` is a mixture of the nodes inside
    alone, and the draws give the mean and covariance too. A posterior near the edge
    of the prior (an exponent near its largest) lost its outer nodes there, and the
    mixture of those left was lopsided: the interval missed a truth 0.7 SDs from the
    mean.
    """
    d = peak.u.size
    if len(components) != 3**d or any(q.samples.shape[0] == 0 for q in components):
        return post
    k = max(int(post.samples.shape[0]), MIX_DRAWS)
    z = rng.standard_normal((k, d))
    inside = grid.inside_many(peak.u + z @ peak.axes.T)  # the axes of :func:`hermite_nodes`
    means = np.array([np.append(q.mean, q.sigma_mean) for q in components])
    centre = hermite_interpolant(means, z)
    # the nearest node along each principal direction: its index in the nodes' order
    digit = np.digitize(z, [-0.5 * math.sqrt(3.0), 0.5 * math.sqrt(3.0)])
    nearest = digit @ (3 ** np.arange(d - 1, -1, -1))
    draws = np.empty((k, means.shape[1]))
    for i, q in enumerate(components):
        rows = np.flatnonzero(nearest == i)
        if rows.size:
            pick = rng.integers(0, q.samples.shape[0], rows.size)
            draws[rows] = centre[rows] + q.samples[pick] - means[i]
    ok = inside & np.all(draws[:, :-1][:, bounded] >= 0, axis=1) & (draws[:, -1] > 0)
    if np.count_nonzero(ok) < k // 4:
        # the bounds keep too little of the Gaussian over the shape for its quantiles:
        # the nodes' mixture stands
        return post
    draws = draws[ok]
    post.samples = draws
    post.ci95 = central95(draws[:, :-1])
    sig = central95(draws[:, -1:])[0]
    post.sigma_ci95 = (float(sig[0]), float(sig[1]))
    post.diagnostics["continuous_shape_draws"] = int(draws.shape[0])
    if truncated:
        beta = draws[:, :-1]
        post.mean = beta.mean(axis=0)
        post.cov = np.atleast_2d(np.cov(beta, rowvar=False))
        post.sd = np.sqrt(np.clip(np.diag(post.cov), 0.0, None))
        post.sigma_mean = float(draws[:, -1].mean())
    return post


def _trapezoid(lo: float, hi: float, k: int) -> tuple[Array, Array]:
    """``k`` equally spaced nodes on [lo, hi] and trapezoid weights summing to 1."""
    u = np.linspace(lo, hi, k)
    w = np.full(k, 1.0)
    w[[0, -1]] = 0.5
    return u, w / w.sum()


def _logsumexp(a: Array) -> float:
    top = float(np.max(a))
    return top + math.log(float(np.sum(np.exp(a - top)))) if math.isfinite(top) else top


def kept(log_post: Array) -> NDArray[np.intp]:
    """The nodes that hold :data:`KEPT_MASS` of the posterior (at most :data:`MAX_KEPT`),
    heaviest first."""
    order = np.argsort(-log_post)
    p = np.exp(log_post[order] - _logsumexp(log_post))
    count = int(np.searchsorted(np.cumsum(p), KEPT_MASS) + 1)
    return order[: min(count, MAX_KEPT, order.size)]


def shape_summary(
    grid: ShapeGrid, log_post: Array
) -> tuple[dict[str, dict[str, float | list[float]]], dict[str, float]]:
    """The shape parameters' posterior from the grid's weights: mean, SD and central 95 %
    interval of each (SI), and a point to bind the law at (parameters of log-uniform
    prior, such as time constants, at their geometric mean, the others at their mean)."""
    p = np.exp(log_post - _logsumexp(log_post))
    out: dict[str, dict[str, float | list[float]]] = {}
    point: dict[str, float] = {}
    for name in grid.nodes[0]:
        v = np.array([node[name] for node in grid.nodes])
        mean = float(p @ v)
        sd = float(math.sqrt(max(float(p @ (v - mean) ** 2), 0.0)))
        order = np.argsort(v)
        cdf = np.cumsum(p[order])
        ci = [float(np.interp(q, cdf, v[order])) for q in (0.025, 0.975)]
        out[name] = {"mean": mean, "sd": sd, "ci95": ci}
        point[name] = float(np.exp(p @ np.log(v))) if grid.log(name) else mean
    return out, point


def mix(
    posteriors: list[Posterior],
    weights: Array,
    rng: np.random.Generator,
    counts: NDArray[np.intp] | None = None,
) -> Posterior:
    """One posterior from the conditional posteriors of several shape nodes: the
    mixture's mean and covariance (law of total variance), its intervals from draws
    taken in proportion to the weights: ``counts[i]`` of component ``i``'s draws (its
    first ones; drawn here, multinomially from the weights, if not given), each
    component's drawn again with replacement where it has too few."""
    w = np.asarray(weights, dtype=float) / float(np.sum(weights))
    if len(posteriors) == 1:
        return posteriors[0]
    means = np.array([q.mean for q in posteriors])
    mean = w @ means
    second = sum(
        wi * (q.cov + np.outer(q.mean, q.mean)) for wi, q in zip(w, posteriors, strict=True)
    )
    cov = second - np.outer(mean, mean)
    if counts is None:
        counts = rng.multinomial(MIX_DRAWS, w)
    parts = []
    for k, q in zip(counts, posteriors, strict=True):
        have = q.samples.shape[0]
        if k and have:
            parts.append(q.samples[:k] if have >= k else q.samples[rng.integers(0, have, k)])
    samples = np.vstack(parts) if parts else np.zeros((0, mean.size + 1))
    beta = samples[:, :-1]
    # np.percentile's numbers (linear interpolation), from one sort of each column
    ci = central95(beta) if beta.shape[0] else np.column_stack([mean, mean])
    sig = samples[:, -1] if samples.shape[0] else np.array([posteriors[0].sigma_mean])
    sig_ci = central95(sig[:, None])[0]
    return Posterior(
        mean=mean,
        sd=np.sqrt(np.clip(np.diag(cov), 0.0, None)),
        ci95=ci,
        cov=cov,
        sigma_mean=float(w @ np.array([q.sigma_mean for q in posteriors])),
        sigma_ci95=(float(sig_ci[0]), float(sig_ci[1])),
        ln_evidence=float("nan"),
        outside=float(w @ np.array([q.outside for q in posteriors])),
        method="+".join(sorted({q.method for q in posteriors})) + " (mixture over the shape)",
        samples=samples,
        diagnostics={
            "shape_nodes": len(posteriors),
            "exact": all(q.diagnostics.get("exact", False) for q in posteriors),
        },
        below_zero=(
            w @ np.array([q.below_zero for q in posteriors])
            if all(q.below_zero is not None for q in posteriors)
            else None
        ),
    )
