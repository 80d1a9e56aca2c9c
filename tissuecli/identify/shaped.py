"""Laws with shape parameters (time constants, contact exponents and points): their
evidence and posterior with the shape marginalised over the prior each term declares,
by a quadrature grid, a Laplace approximation at the peak and Gauss-Hermite nodes, or
(beyond :data:`MAX_GRID_SHAPES` parameters) a Laplace estimate whose shape posterior
emcee samples later; and the first pass of a law at many shapes, its shape-free
columns formed once."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..core.errors import FitError
from ..core.terms import Law
from .design import noise_path, raw_speed, term_column, term_noise_path
from .posterior import CHECK_NATS, ExactPosterior, Posterior, _by_node, _matrix_roots
from .reduced import ReducedPass
from .scoring import (
    CUT_THRESHOLD,
    Context,
    FirstPass,
    ModelResult,
    first_pass,
    law_stats,
    not_evaluated,
    result_of,
)
from .shapes import (
    MIX_DRAWS,
    Peak,
    ShapeGrid,
    continuous_mixture,
    edge_peak,
    hermite_nodes,
    kept,
    laplace,
    mix,
    shape_grid,
    shape_summary,
)

Array = NDArray[np.float64]

#: shape parameters up to which a grid (and a Laplace approximation) marginalises the
#: shape; beyond, emcee samples it
MAX_GRID_SHAPES = 2


#: draws of the shape's chain at which the coefficients' conditional posterior is formed,
#: at most (the chain keeps about 450 at 30 autocorrelation times of 8 walkers, thinned
#: by half an autocorrelation time: about 220 independent, and 256 of them carry nearly
#: all they hold at half the cost); their pooled draws are the coefficients' posterior
#: with the shape marginalised, and its quantiles judge identification
SHAPE_DRAWS = 256

#: coefficient proposals drawn from each of those conditional posteriors; those the
#: positivity bounds keep are kept (rejection: each shape then counts by the mass the
#: bounds keep of its posterior, as in the bounded posterior over shape and coefficients)
PROPOSALS = 16

#: pooled draws the coefficients' marginal posterior is summarised from at least (more
#: proposals are drawn where the bounds reject many)
MARGINAL_DRAWS = 4000

#: noise levels of the closed form at a shape node scanned for its evidence alone (the
#: grid, the climbs, a shape chain): 101 over ln sigma give the evidence of the full
#: grid's 401 to rounding (2e-13 nats at most over a fit's 176 laws and nodes) for its
#: near-Gaussian posterior, at a quarter of the cost; a node whose truncation, posterior
#: or checks are wanted is formed again on the full grid
SCAN_NODES = 101

#: every shape node takes its orthant mass to the lattice's looser target (ln P to about
#: 0.01) first; a node then found to carry more than this share of the law's evidence is
#: taken to the full one. The law's ln Z is the log of a weighted sum, each node's error
#: entering at its share: independent errors of 0.01 on shares of at most 0.1 add in
#: quadrature to at most 0.01 sqrt(0.1) = 3e-3 nats
TIGHT_SHARE = 0.1

#: the fewest draws a component of a mixture over shape nodes takes under the positivity
#: bounds (:func:`mixed_posterior`): its mean and covariance come from them
COMPONENT_DRAWS = 200

#: a quadrature node holding more of the posterior than this: the grid does not resolve
#: it (:func:`~tissuecli.identify.shapes.edge_peak`)
ONE_NODE = 0.9

#: bytes of shaped columns a batch of grid nodes holds at once (:meth:`ShapedPass.many`)
BATCH_BYTES = 8 << 20


def exact_shaped(law: Law, fit: Context) -> ModelResult:
    """A law with shape parameters: its exact evidence at every node of the shape's
    quadrature grid, weighted by the prior's masses. Where the posterior is sharper
    than the grid (most sessions: thousands of samples pin a time constant to a few
    per cent), Newton steps find its peak and a Laplace approximation gives the
    evidence, and three Gauss-Hermite nodes per parameter carry the shape's
    uncertainty into the coefficients; elsewhere the grid's heaviest nodes do.

    With more than :data:`MAX_GRID_SHAPES` shape parameters the grid is coarse and
    only seeds the peak; the evidence is still the Laplace approximation (or the
    grid's sum), and the shape's posterior is left to the result's ``sample_shape``
    (emcee), which the fit runs only if the law is not decisively behind the best.
    """
    many = len(law.shape_names) > MAX_GRID_SHAPES
    grid = shape_grid(law, fit.kin, coarse=many)
    light = ShapedPass(law, fit)
    cache: dict[tuple[float, ...], tuple[float, tuple[Any, ...]]] = {}

    def parts(node: dict[str, float], nodes: int = SCAN_NODES) -> tuple[float, tuple[Any, ...]]:
        """ln evidence given the shape without the positivity bounds' orthant mass
        (the costly part, and nearly constant over a peak), and the fit's parts (the
        closed form on ``nodes`` noise levels: :func:`exact_at` has it on the full grid)."""
        bound = law.bind(node)
        key = (law.name, tuple(node[n] for n in grid.names))
        fp = fit.shaped_passes.get(key)
        if fp is None:
            fp = fit.shaped_passes[key] = light(node, bound)
        st, prior, corr, flags = law_stats(bound, fp, fit)
        exact = ExactPosterior(st, prior, nodes=nodes)
        return exact.ln_z_untruncated, (fp, st, prior, corr, flags, exact)

    def parts_many(nodes: list[dict[str, float]]) -> list[float]:
        """:func:`parts`' ln evidence at many shapes, the same numbers: the first passes
        not yet known formed together (:meth:`ShapedPass.many`)."""
        bounds = [law.bind(node) for node in nodes]
        keys = [(law.name, tuple(node[n] for n in grid.names)) for node in nodes]
        todo = [i for i, key in enumerate(keys) if key not in fit.shaped_passes]
        fps = light.many([bounds[i] for i in todo], keep=False)
        for i, fp in zip(todo, fps, strict=True):
            fit.shaped_passes[keys[i]] = fp
        out = []
        for bound, key in zip(bounds, keys, strict=True):
            st, prior, _, _ = law_stats(bound, fit.shaped_passes[key], fit)
            out.append(ExactPosterior(st, prior, nodes=SCAN_NODES).ln_z_untruncated)
        return out

    def evaluate(node: dict[str, float]) -> tuple[float, tuple[Any, ...]]:
        key = tuple(node[n] for n in grid.names)
        if key not in cache:
            cache[key] = parts(node)
        return cache[key]

    fine: dict[tuple[float, ...], ExactPosterior] = {}

    def exact_at(node: dict[str, float]) -> ExactPosterior:
        """The closed form at ``node`` on the full grid of noise levels: what its
        truncation, posterior and checks are taken from."""
        key = tuple(node[n] for n in grid.names)
        if key not in fine:
            _, (_, st, prior, *_) = evaluate(node)
            fine[key] = ExactPosterior(st, prior)
        return fine[key]

    def evaluate_fine(node: dict[str, float]) -> tuple[float, tuple[Any, ...]]:
        """:func:`evaluate` with the closed form of :func:`exact_at`."""
        ln_z, (fp, st, prior, corr, flags, _) = evaluate(node)
        return ln_z, (fp, st, prior, corr, flags, exact_at(node))

    def truncation(node: dict[str, float]) -> float:
        """ln of what the positivity bounds keep of the closed form's evidence."""
        exact = exact_at(node)
        return exact.ln_evidence() - exact.ln_z_untruncated

    # the grid's first passes in batches; the climbs' nodes come one at a time
    keys = [(law.name, tuple(node[n] for n in grid.names)) for node in grid.nodes]
    todo = [i for i, key in enumerate(keys) if key not in fit.shaped_passes]
    for i, fp in zip(todo, light.many([law.bind(grid.nodes[i]) for i in todo]), strict=True):
        fit.shaped_passes[keys[i]] = fp
    ln_z = np.array([evaluate(node)[0] for node in grid.nodes])
    untruncated = ln_z.copy()
    # the bounds matter only where the evidence does: the nodes near the top (more
    # join them if the bounds pull the top down)
    done = np.zeros(ln_z.size, bool)
    # nodes whose truncation only its closed-form upper bound gives (posterior.FAR_NATS):
    # the lattice runs on them only if that bound leaves them near a node known exactly
    rough = np.zeros(ln_z.size, bool)
    while True:
        near = np.flatnonzero(~done & (ln_z > ln_z[done].max(initial=ln_z.max()) - 30.0))
        if not near.size:
            top = ln_z[done & ~rough].max(initial=-np.inf)
            near = np.flatnonzero(rough & (ln_z > top - 30.0)) if np.isfinite(top) else near
            if not near.size:
                break
            for i in near:
                exact = exact_at(grid.nodes[i])
                exact.refine()
                ln_z[i] = untruncated[i] + truncation(grid.nodes[i])
            rough[near] = False
            continue
        # each mass to the lattice's looser target first (TIGHT_SHARE), where the full
        # one cost up to 64 times the points: on a session whose data weight leaves the
        # shape's posterior flat, every node of the grid is near the top
        for i in near:
            exact = exact_at(grid.nodes[i])
            exact.loosen()
            ln_z[i] += truncation(grid.nodes[i])
            rough[i] = exact.bound_only
        done[near] = True
    # the nodes that carry a large share of the evidence, to the full target
    log_post = ln_z + grid.log_weight
    share = np.exp(log_post - _logsumexp(log_post))
    for i in np.flatnonzero(done & ~rough & (share > TIGHT_SHARE)):
        exact = exact_at(grid.nodes[i])
        exact.tighten()
        ln_z[i] = untruncated[i] + truncation(grid.nodes[i])
    log_post = ln_z + grid.log_weight
    tops = np.argsort(-log_post)[:3]
    starts = [grid.to_u(grid.nodes[i]) for i in tops]
    hint = fit.spans.get(("peak", *grid.names))
    peak = laplace(lambda u: evaluate(grid.from_u(u))[0], grid, starts, hint)
    sharp = peak is not None and bool(np.all(peak.sd < grid.spacing))
    if sharp:  # where sibling laws may start (:func:`~tissuecli.identify.shapes.laplace`)
        fit.spans[("peak", *grid.names)] = peak
    hermite: tuple[list[Array], Array, Peak] | None = None  # the nodes a posterior is mixed over
    piled = False
    if sharp:
        assert peak is not None
        d = peak.u.size
        ln_evidence = (
            peak.log_z
            + truncation(grid.from_u(peak.u))
            + grid.log_density
            + 0.5 * d * np.log(2 * np.pi)
            + 0.5 * float(np.linalg.slogdet(peak.cov)[1])
        )
        point = grid.from_u(peak.u)
        if many:  # the chain will carry the shape's uncertainty, if it runs
            post = exact_at(point).bounded(fit.rng, CUT_THRESHOLD)
            hermite = None
        else:
            nodes_u, w = hermite_nodes(peak)
            post = hermite_posterior(nodes_u, w, peak, grid, exact_at, fit.rng)
            if post is None:  # no node inside the prior (never at a peak inside it)
                post = exact_at(point).bounded(fit.rng, CUT_THRESHOLD)
            hermite = (nodes_u, w, peak)
        draws = fit.rng.multivariate_normal(peak.u, peak.cov, size=4000)
        inside_prior = grid.inside_many(draws)
        if np.count_nonzero(inside_prior) >= draws.shape[0] // 4:
            draws = draws[inside_prior]  # the shape's posterior is cut by its prior too
        shape_post = _shape_draws(grid, draws)
        how = (
            f"Laplace approximation at the peak over the shape, after a {len(grid.nodes)}-"
            f"node grid and {len(cache) - len(grid.nodes)} Newton evaluations"
        )
        start, start_cov = peak.u, peak.cov
    else:
        ln_evidence = float(_logsumexp(log_post))
        heavy = kept(log_post)
        weights = np.exp(log_post[heavy] - log_post[heavy[0]])
        post = mixed_posterior([exact_at(grid.nodes[i]) for i in heavy], weights, fit.rng)
        shape_post, point = shape_summary(grid, log_post)
        how = f"quadrature over {len(grid.nodes)} shape nodes"
        start, start_cov = grid.to_u(grid.nodes[heavy[0]]), np.diag((grid.spacing / 4) ** 2)
        # the posterior sharper than the grid but piled against the prior's edge (an
        # exponent at its largest): one node holds it all, and its intervals are that
        # node, zero wide. For the chosen law, the peak's Gaussian where the law is
        # defined, cut to the prior's support, carries the shape instead (``refine``)
        piled = not many and float(np.exp(log_post[heavy[0]] - ln_evidence)) > ONE_NODE
    post.ln_evidence = float(ln_evidence)
    ls_key, ls_value = min(cache.items(), key=lambda kv: kv[1][1][0].rss)
    ls_law = law.bind(dict(zip(grid.names, ls_key, strict=True)))
    ls_rms = float(np.sqrt(ls_value[1][0].rss / fit.rows))
    ranges = ", ".join(f"{k} {lo:.3g}-{hi:.3g}" for k, (lo, hi) in grid.ranges.items())
    res = shaped_result(law, point, post, evaluate_fine, fit)
    res.reason = f"{how} ({ranges})"
    # the evidence is trusted only if the node it rests on is, and if it stays
    # below the likelihood's maximum over every shape evaluated
    why = exact_at(point).untrusted()
    top = max(entry[1][1].max_log_likelihood() for entry in cache.values())
    if not why and not ln_evidence <= top + CHECK_NATS:
        why = (
            f"its ln evidence ({ln_evidence:.4g}) exceeds the likelihood's maximum "
            f"({top:.4g}): a numerical failure"
        )
    res.shape_posterior = shape_post
    res.shape_ranges = grid.ranges
    res.least_squares = (ls_law, ls_rms)

    def redrawn(
        nodes: tuple[list[Array], Array, Peak], at: dict[str, float]
    ) -> Callable[[np.random.Generator, float], Posterior | None]:
        """The posterior over ``nodes`` drawn again, every node's draws exact under the
        positivity bounds down to an acceptance (what the chosen law is given where the
        bounds cut a node too deeply for the search's draws), the shape still
        marginalised; None if a node's bound keeps less than that."""

        def redraw(rng: np.random.Generator, min_acceptance: float) -> Posterior | None:
            nodes_u, w, peak_ = nodes

            def component(e: ExactPosterior, k: int) -> Posterior | None:
                return e.truncated(rng, draws=max(k, COMPONENT_DRAWS), intervals=False,
                                   min_acceptance=min_acceptance)  # fmt: skip

            again = hermite_posterior(nodes_u, w, peak_, grid, exact_at, rng, component)
            if again is None:
                return None
            out = shaped_result(law, at, again, evaluate_fine, fit).posterior
            mid = exact_at(at).truncated(rng, intervals=False, min_acceptance=min_acceptance)
            if out is not None and mid is not None:  # the mean at the point, exact too
                out.mean = mid.mean
            return out

        return redraw

    if hermite is not None:
        res.redraw = redrawn(hermite, point)
    if not sharp and piled:

        def refine(rng: np.random.Generator) -> None:
            """The shape of a posterior piled against the prior's edge as the Gaussian at
            the peak beyond it, cut to the prior (:func:`edge_peak`); left as the grid
            gave it if no such peak is found."""
            edge = edge_peak(lambda u: evaluate(grid.from_u(u))[0], grid, start)
            if edge is None:
                return
            nodes_u, w = hermite_nodes(edge)
            cut = hermite_posterior(nodes_u, w, edge, grid, exact_at, rng)
            draws = rng.multivariate_normal(edge.u, edge.cov, size=4000)
            draws = draws[grid.inside_many(draws)]
            if cut is None or "continuous_shape_draws" not in cut.diagnostics or (
                draws.shape[0] < 400
            ):
                return
            at = grid.from_u(draws.mean(axis=0))
            cut.ln_evidence = res.ln_evidence
            new = shaped_result(law, at, cut, evaluate_fine, fit)
            for name in ("model", "posterior", "cond", "cond_scaled", "residual_rms",
                         "gram", "correction", "stats", "prior", "flags"):  # fmt: skip
                setattr(res, name, getattr(new, name))
            res.shape_posterior = _shape_draws(grid, draws)
            res.redraw = redrawn((nodes_u, w, edge), at)
            res.reason += "; the shape piled on the prior's edge: the Gaussian at the peak "
            res.reason += "beyond it, cut to the prior"

        res.refine = refine

    if many:
        res.shape_sampler = {"status": "pending", "evidence": how}

        def sample() -> None:
            """emcee over the shape, started at the peak; the evidence stays the
            estimate above (a chain gives none)."""
            from .sampling import sample_shapes  # emcee, only when a shape is sampled

            def target(u: Array) -> float:
                # uniform prior in u inside the support
                return parts(grid.from_u(u))[0]

            def target_many(us: Array) -> list[float]:
                # the walkers' proposals of one move together: their first passes are
                # one batch, the same numbers as one at a time
                return parts_many([grid.from_u(u) for u in us])

            try:
                draws, diag = sample_shapes(
                    target, grid.interior(start), start_cov, grid.inside, fit.rng,
                    progress=fit.chain_progress(res.name), log_post_many=target_many,
                )  # fmt: skip
            except FitError as e:  # keep the Laplace summary, and say why
                res.shape_sampler = {"status": "failed", "reason": str(e), "evidence": how}
                res.reason += f"; shape not sampled: {e}"
                res.flags.append(f"shape not sampled ({e}): its intervals are Laplace's")
                return
            summary = _shape_draws(grid, draws)
            for j, name in enumerate(grid.names):
                summary[name]["method"] = "emcee"
                summary[name]["tau_steps"] = diag["tau"][j]
            mixed = marginal_posterior(law, grid, draws, light, fit)
            mixed.ln_evidence = res.ln_evidence
            median = np.median(draws, axis=0)
            centre = grid.from_u(median) if grid.inside(median) else grid.from_u(draws[0])
            new = shaped_result(law, centre, mixed, evaluate_fine, fit)
            for name in ("model", "posterior", "cond", "cond_scaled", "residual_rms",
                         "gram", "correction", "stats", "prior", "flags"):  # fmt: skip
                setattr(res, name, getattr(new, name))
            res.shape_posterior = summary
            diag.update(status="sampled", evidence=how)
            res.shape_sampler = diag
            mixed.diagnostics["shape_emcee"] = diag
            res.reason += (
                f"; shape sampled by emcee ({diag['walkers']} walkers, {diag['steps']} "
                f"steps, tau {max(diag['tau']):.0f}, acceptance {diag['acceptance']:.2f})"
            )
            if not diag["converged"]:
                res.flags.append(
                    f"shape chain stopped at {diag['steps']} steps, shorter than "
                    f"{diag['times']:g} autocorrelation times "
                    f"({diag['times'] * max(diag['tau']):.0f}): its intervals "
                    "are rough"
                )

        res.sample_shape = sample
    if why:
        not_evaluated(res, why)
    else:
        fit.lead = max(fit.lead, res.ln_evidence)
    fit.scored(law.name)
    return res


def hermite_posterior(
    nodes_u: list[Array],
    weights: Array,
    peak: Peak,
    grid: ShapeGrid,
    exact_at: Callable[[dict[str, float]], ExactPosterior],
    rng: np.random.Generator,
    component: Callable[[ExactPosterior, int], Posterior | None] | None = None,
) -> Any:
    """The coefficients' posterior with a sharp shape marginalised over the peak's
    Gaussian: the mixture of :func:`~tissuecli.identify.shapes.hermite_nodes`'
    conditional posteriors inside the prior (``exact_at`` gives a node's), its
    intervals and draws over the continuous Gaussian
    (:func:`~tissuecli.identify.shapes.continuous_mixture`); nodes beyond the prior's
    edge shape the interpolant only (where the law is defined there), their draws
    dropped. ``component(exact, draws)``: a node's posterior, None where it cannot be
    drawn exactly (then None is returned); by default :meth:`ExactPosterior.bounded`."""
    inside = [i for i, u in enumerate(nodes_u) if grid.inside(u)]
    if not inside:
        return None
    exacts = [exact_at(grid.from_u(nodes_u[i])) for i in inside]
    if component is None:
        post, comps = mixed_posterior(exacts, weights[inside], rng, parts=True)
    else:
        w = np.asarray(weights[inside], dtype=float) / float(np.sum(weights[inside]))
        counts = rng.multinomial(MIX_DRAWS, w)
        drawn = [component(e, int(k)) for e, k in zip(exacts, counts, strict=True)]
        if any(q is None for q in drawn):
            return None
        comps = [q for q in drawn if q is not None]
        post = mix(comps, w, rng, counts)
        post.diagnostics["exact"] = True
    outside = [i for i in range(len(nodes_u)) if i not in inside]
    if len(inside) == 1:
        return post  # a posterior sharper than the nodes' spread: left as it is
    if outside:
        if not all(_allowed(grid, nodes_u[i]) for i in outside):
            return post
        draw = component or (lambda e, k: e.bounded(rng, CUT_THRESHOLD, intervals=False,
                                                     draws=k))  # fmt: skip
        extra = {i: draw(exact_at(grid.from_u(nodes_u[i])), COMPONENT_DRAWS) for i in outside}
        if any(q is None for q in extra.values()):
            return post
        given = dict(zip(inside, comps, strict=True))
        comps = [given[i] if i in given else extra[i] for i in range(len(nodes_u))]
    return continuous_mixture(post, comps, peak, grid, exacts[0].prior.bounded, rng,
                              truncated=bool(outside))  # fmt: skip


def _allowed(grid: ShapeGrid, u: Array) -> bool:
    """Whether the shape at ``u`` lies within every parameter's limits (where the law is
    defined, inside the prior's support or not)."""
    node = grid.from_u(u)
    return all(grid.params[n].limits[0] <= v <= grid.params[n].limits[1]
               for n, v in node.items())  # fmt: skip


def mixed_posterior(
    exacts: list[ExactPosterior],
    weights: Array,
    rng: np.random.Generator,
    parts: bool = False,
) -> Any:
    """The posterior of a law whose shape is marginalised over several nodes: the
    mixture (:func:`~tissuecli.identify.shapes.mix`) of each node's bounded posterior
    (:meth:`ExactPosterior.bounded`). Each component draws only what the mixture takes
    of it (its share of :data:`~tissuecli.identify.shapes.MIX_DRAWS` by weight), and at
    least :data:`COMPONENT_DRAWS` for its own mean and covariance where those come from
    draws: a mixture of twelve nodes drew 48,000 draws under the bounds where it keeps
    4,000. A single node's posterior is that node's, intervals and all. ``parts``:
    return the components' posteriors too, as ``(posterior, components)``."""
    if len(exacts) == 1:
        one = exacts[0].bounded(rng, CUT_THRESHOLD)
        return (one, [one]) if parts else one
    w = np.asarray(weights, dtype=float) / float(np.sum(weights))
    counts = rng.multinomial(MIX_DRAWS, w)
    posts = [
        e.bounded(rng, CUT_THRESHOLD, intervals=False, draws=max(int(k), COMPONENT_DRAWS))
        for e, k in zip(exacts, counts, strict=True)
    ]
    mixed = mix(posts, w, rng, counts)
    return (mixed, posts) if parts else mixed


def marginal_posterior(
    law: Law, grid: ShapeGrid, draws: Array, light: ShapedPass, fit: Context
) -> Posterior:
    """The coefficients' posterior with the shape marginalised over the chain's draws.

    At each of the chain's draws of the shape (:data:`SHAPE_DRAWS` of them at most,
    picked at random) the exact conditional posterior of the coefficients and noise
    level is formed, and :data:`PROPOSALS` draws are taken from it, kept where the
    positivity bounds hold; the pooled draws (at least :data:`MARGINAL_DRAWS`) are
    draws of the bounded joint posterior. Their quantiles carry the Monte Carlo error
    of the chain's independent draws of the shape (a 2.5 % quantile's about
    ``2.7 / sqrt(k)`` posterior SDs for ``k`` of them, 0.18 SD at 224), not that of a
    handful of shapes; the mass below zero without the bounds is the mean of the
    closed form's over the same draws. The verdict on identification reads both
    (:func:`~tissuecli.identify.diagnostics.identifiability`).

    Parameters
    ----------
    law : Law
        The law with its shape parameters free.
    grid : ShapeGrid
        The shape's grid (its coordinates ``u``).
    draws : ndarray, shape (k, d)
        The chain's draws of the shape, in ``u``.
    light : ShapedPass
        The law's first pass at any shape.
    fit : Context

    Returns
    -------
    Posterior
        Mean, SD, covariance and 95 % intervals of the pooled draws, SI;
        ``diagnostics["shape_nodes"]`` the shapes pooled, ``["draws"]`` the draws.
    """
    rng = fit.rng
    rows = np.arange(draws.shape[0])
    if rows.size > SHAPE_DRAWS:
        rows = np.sort(rng.choice(rows, size=SHAPE_DRAWS, replace=False))
    parts = []
    below = np.zeros(len(law.terms))
    bounded: NDArray[np.bool_] | None = None
    for i in rows:
        node = grid.from_u(draws[i])
        bound = law.bind(node)
        st, prior, _, _ = law_stats(bound, light(node, bound), fit)
        exact = ExactPosterior(st, prior, nodes=101)
        w, mus, covs, idx = exact.mixture()
        parts.append((w, mus, _matrix_roots(covs), np.exp(exact.u[idx])))
        # the chain draws the shape from the posterior without the bounds: their mean
        # is the unbounded marginal's mass below zero
        below += exact.below_zero() / rows.size
        bounded = prior.bounded
    assert bounded is not None
    kept: list[Array] = []
    have, proposed, each = 0, 0, PROPOSALS
    while True:
        for w, mus, roots, sig in parts:
            counts = rng.multinomial(each, w)
            z = rng.standard_normal((each, mus.shape[1]))
            beta = _by_node(counts, z, mus, roots)
            ok = np.all(beta[:, bounded] >= 0, axis=1)
            kept.append(np.column_stack([beta[ok], np.repeat(sig, counts)[ok]]))
            have += int(ok.sum())
        proposed += each * len(parts)
        if have >= MARGINAL_DRAWS or proposed >= MAX_PROPOSALS:
            break
        # the bounds reject many: propose what the acceptance so far asks for
        need = (MARGINAL_DRAWS - have) * proposed / max(have, 1)
        each = int(min(max(np.ceil(need / len(parts)), 1), MAX_PROPOSALS // len(parts)))
    samples = np.concatenate(kept)
    if samples.shape[0] < 2:
        raise FitError(
            "the positivity bounds keep almost none of the posterior over the chain's shapes"
        )
    beta, sigma = samples[:, :-1], samples[:, -1]
    ci = np.percentile(samples, [2.5, 97.5], axis=0).T
    return Posterior(
        mean=beta.mean(axis=0),
        sd=beta.std(axis=0, ddof=1),
        ci95=ci[:-1],
        cov=np.atleast_2d(np.cov(beta, rowvar=False)),
        sigma_mean=float(sigma.mean()),
        sigma_ci95=(float(ci[-1, 0]), float(ci[-1, 1])),
        ln_evidence=float("nan"),
        outside=1.0 - have / proposed,
        method="exact draws over the shape chain's draws",
        samples=samples,
        diagnostics={
            "shape_nodes": int(rows.size),
            "draws": int(samples.shape[0]),
            "acceptance": have / proposed,
            "exact": True,
        },
        below_zero=below,
    )


#: most coefficient proposals :func:`marginal_posterior` draws in all
MAX_PROPOSALS = 4_000_000


def shaped_result(
    law: Law,
    point: dict[str, float],
    post: Posterior,
    evaluate: Callable[[dict[str, float]], tuple[float, tuple[Any, ...]]],
    fit: Context,
) -> ModelResult:
    """The result of a law with shape parameters, bound at ``point``.

    Its coefficients' means are those given the shape at ``point``: a coefficient's
    meaning can hang on the shape (a contact stiffness is in N/m^n), so an average
    over shapes would not predict the force the bound law gives. Their SDs and
    intervals stay those of ``post``, which carry the shape's uncertainty; those given
    the shape at ``point`` are kept beside them (``diagnostics["at_shape"]``), to judge
    a coefficient whose unit hangs on the shape where it has a meaning.
    """
    fp, st, prior, corr, flags, exact = evaluate(point)[1]
    if post.diagnostics.get("shape_nodes", 1) > 1:
        post.diagnostics["mean_over_shapes"] = [float(v) for v in post.mean]
        at = exact.bounded(fit.rng, CUT_THRESHOLD)
        post.mean = at.mean
        post.diagnostics["at_shape"] = {
            "sd": [float(v) for v in at.sd],
            "ci95": [[float(lo), float(hi)] for lo, hi in at.ci95],
            "below_zero": [float(v) for v in exact.below_zero()],
        }
    return result_of(law.bind(point), post, fp, fit, st, prior, corr, list(flags), law)


class ShapedPass:
    """:func:`first_pass` of one law at many values of its shape parameters.

    The columns without shape parameters, their products with each other and with the
    force, and their noise paths do not change from one shape to the next: they are
    formed once, so that each shape costs only its own columns and their products
    (what makes sampling the shape affordable).
    """

    def __init__(self, law: Law, fit: Context) -> None:
        self.law, self.fit = law, fit
        terms = law.terms
        self.fixed = [j for j, t in enumerate(terms) if not t.shapes]
        self.moving = [j for j, t in enumerate(terms) if t.shapes]
        fixed, moving = self.fixed, self.moving
        self._blocks = (np.ix_(fixed, fixed), np.ix_(moving, fixed), np.ix_(fixed, moving),
                        np.ix_(moving, moving))  # fmt: skip
        kin, x, sx = fit.kin, fit.x_full, fit.sigma_x
        cols = [term_column(terms[j], kin, x, sx, fit.columns) for j in self.fixed]
        self.F = self._white(np.column_stack(cols) if cols else np.zeros((fit.y.size, 0)))
        y = fit.target
        self.G_ff = self.F.T @ self.F
        self.b_f = self.F.T @ y
        self.yy = float(y @ y)
        if "raw speed" not in fit.spans:  # one pass over the record for every law
            fit.spans["raw speed"] = raw_speed(kin, x)
        self.speed = fit.spans["raw speed"]
        if sx > 0:
            paths = [term_noise_path(terms[j], kin, x, fit.paths, sx) for j in self.fixed]
            width = kin.kernels[0].size
            self.K_f = self._kernels(np.array([k for k, _ in paths]).reshape(len(paths), width))
            D_f = np.column_stack([d for _, d in paths]) if paths else np.zeros((fit.y.size, 0))
            self.D_f = self._white_rows(D_f)
            self.DtD_f = self.D_f.T @ self.D_f
        self.reduced = ReducedPass(self)

    def _white(self, X: Array) -> Array:
        """Columns (first axis: rows) through the prewhitening filter, if the fit has one."""
        w = self.fit.whiten
        return X if w is None else w.transform(X)

    def _white_rows(self, D: Array) -> Array:
        """Slopes at the rows the filter keeps (slow beside the noise: not filtered)."""
        w = self.fit.whiten
        return D if w is None else D[w.span :]

    def _kernels(self, K: Array) -> Array:
        """Noise kernels as the filtered columns see them."""
        w = self.fit.whiten
        return K if w is None else w.kernels(K, self.fit.kin.stride)

    def __call__(self, node: dict[str, float], bound: Law | None = None) -> FirstPass:
        """The first pass at ``node`` (``bound``: the law bound there, if at hand)."""
        fit, bound = self.fit, bound if bound is not None else self.law.bind(node)
        fp = self.reduced(bound) if self.reduced.usable else None
        if fp is not None:
            return fp
        p, fixed, moving = len(bound.terms), self.fixed, self.moving
        S = self._white(np.column_stack(
            [term_column(bound.terms[j], fit.kin, fit.x_full, fit.sigma_x,
                         raw_speed=self.speed) for j in moving]
        ))  # fmt: skip
        y = fit.target
        gram = self._assemble(self.G_ff, S.T @ self.F, S.T @ S)
        b = np.empty(p)
        b[fixed] = self.b_f
        b[moving] = S.T @ y
        d = np.sqrt(np.maximum(gram.diagonal(), 1e-300))
        scaled = gram / (d[:, None] * d)  # np.outer's numbers, formed once
        lam_s = np.linalg.eigvalsh(scaled)
        cond_scaled = float(np.sqrt(lam_s[-1] / lam_s[0])) if lam_s[0] > 0 else float("inf")
        if cond_scaled >= 1e5:  # too ill-conditioned for the normal equations
            return first_pass(bound, fit.kin, fit.x_full, fit.y, fit.sigma_x, fit.columns,
                              fit.paths, fit.whiten)  # fmt: skip
        beta = np.linalg.solve(scaled, b / d) / d
        # from the residuals themselves: yy - 2 beta.b + beta.G.beta cancels to zero (or
        # below) when the law explains all but a millionth of yy, and a zero residual
        # lets the evidence grow without bound as the noise level goes to zero
        r = y - self.F @ beta[fixed] - S @ beta[moving]
        rss = float(r @ r)
        lam = np.linalg.eigvalsh(gram)
        cond = float(np.sqrt(lam[-1] / lam[0])) if lam[0] > 0 else float("inf")
        correction = None
        if fit.sigma_x > 0:
            paths = [noise_path(bound.terms[j], fit.kin, fit.x_full, fit.sigma_x) for j in moving]
            K = np.empty((p, self.K_f.shape[1]))
            K[fixed] = self.K_f
            K[moving] = self._kernels(np.array([k for k, _ in paths]))
            D = self._white_rows(np.column_stack([dd for _, dd in paths]))
            DtD = self._assemble(self.DtD_f, D.T @ self.D_f, D.T @ D)
            correction = fit.sigma_x**2 * (K @ K.T) * DtD
        return FirstPass(gram, b, self.yy, beta, rss, cond, cond_scaled, correction)

    def many(self, bounds: list[Law], keep: bool = True) -> list[FirstPass]:
        """:meth:`__call__` at many shapes (``bounds``: the law bound at each), the same
        numbers: the nodes' columns stacked so that their products, eigenvalues and
        solves are one call each (the same LAPACK and BLAS routine per node), in
        batches of about :data:`BATCH_BYTES` of columns. ``keep=False`` leaves the
        columns out of the recent ones (:data:`~tissuecli.identify.design.RECENT`): a
        chain's shapes never come back, and keeping each cost as much as a filter pass
        on a short session."""
        m = self.fit.rows
        per = max(1, BATCH_BYTES // max(8 * m * len(self.moving), 1))
        out: list[FirstPass] = []
        for start in range(0, len(bounds), per):
            out += self._batch(bounds[start : start + per], keep)
        return out

    def _batch(self, bounds: list[Law], keep: bool = True) -> list[FirstPass]:
        if self.reduced.usable:  # each from the spans, the rest as below
            found = [self.reduced(bound) for bound in bounds]
            rest = [i for i, fp in enumerate(found) if fp is None]
            for i, fp in zip(rest, self._filtered([bounds[i] for i in rest], keep), strict=True):
                found[i] = fp
            return found  # type: ignore[return-value]
        return self._filtered(bounds, keep)

    def _filtered(self, bounds: list[Law], keep: bool = True) -> list[FirstPass]:
        """:meth:`_batch` with every column formed by its filter pass."""
        if not bounds:
            return []
        fit, fixed, moving = self.fit, self.fixed, self.moving
        kin, x, sx = fit.kin, fit.x_full, fit.sigma_x
        n, p = len(bounds), len(fixed) + len(moving)
        S = np.empty((n, fit.rows, len(moving)))
        for i, bound in enumerate(bounds):
            for c, j in enumerate(moving):
                t = bound.terms[j]
                S[i, :, c] = self._white(
                    term_column(t, kin, x, sx, raw_speed=self.speed, keep=keep)
                )
        y = fit.target
        St = S.transpose(0, 2, 1)
        gram = self._assemble_many(self.G_ff, St @ self.F, St @ S)
        b = np.empty((n, p))
        b[:, fixed] = self.b_f
        b[:, moving] = St @ y
        d = np.sqrt(np.clip(np.diagonal(gram, axis1=1, axis2=2), 1e-300, None))
        scaled = gram / (d[:, :, None] * d[:, None, :])
        lam_s = np.linalg.eigvalsh(scaled)
        with np.errstate(divide="ignore", invalid="ignore"):
            cond_s = np.where(lam_s[:, 0] > 0, np.sqrt(lam_s[:, -1] / lam_s[:, 0]), np.inf)
        good = np.flatnonzero(cond_s < 1e5)  # the rest: too ill-conditioned for this
        beta = np.zeros((n, p))
        if good.size:
            beta[good] = np.linalg.solve(scaled[good], (b[good] / d[good])[..., None])[..., 0]
            beta[good] /= d[good]
        # the residuals node by node, as :meth:`__call__` forms them: stacked, their
        # temporaries (several of nodes by rows) cost three times the products
        rss = np.empty(n)
        for i in range(n):
            r = y - self.F @ beta[i, fixed] - S[i] @ beta[i, moving]
            rss[i] = r @ r
        lam = np.linalg.eigvalsh(gram)
        with np.errstate(divide="ignore", invalid="ignore"):
            cond = np.where(lam[:, 0] > 0, np.sqrt(lam[:, -1] / lam[:, 0]), np.inf)
        corrections: Array | None = None
        if sx > 0:
            D = S  # the columns are done with: their slopes take their place
            K = np.empty((n, p, self.K_f.shape[1]))
            K[:, fixed] = self.K_f
            for i, bound in enumerate(bounds):
                for c, j in enumerate(moving):
                    t = bound.terms[j]
                    k, slope = noise_path(t, kin, x, sx, keep=keep)
                    K[i, j], D[i, :, c] = self._kernels(k[None])[0], self._white_rows(slope)
            Dt = D.transpose(0, 2, 1)
            DtD = self._assemble_many(self.DtD_f, Dt @ self.D_f, Dt @ D)
            corrections = sx**2 * (K @ K.transpose(0, 2, 1)) * DtD
        out = []
        for i, bound in enumerate(bounds):
            if cond_s[i] >= 1e5:
                out.append(first_pass(bound, kin, x, fit.y, sx, fit.columns, fit.paths,
                                      fit.whiten))  # fmt: skip
                continue
            out.append(FirstPass(gram[i], b[i], self.yy, beta[i], float(rss[i]), float(cond[i]),
                                 float(cond_s[i]),
                                 None if corrections is None else corrections[i]))  # fmt: skip
        return out

    def _assemble_many(self, ff: Array, mf: Array, mm: Array) -> Array:
        """:meth:`_assemble` of a stack of nodes: ``mf`` (n, k, f), ``mm`` (n, k, k)."""
        p = len(self.fixed) + len(self.moving)
        out = np.empty((mf.shape[0], p, p))
        ff_at, mf_at, fm_at, mm_at = self._blocks
        out[:, ff_at[0], ff_at[1]] = ff
        out[:, mf_at[0], mf_at[1]] = mf
        out[:, fm_at[0], fm_at[1]] = mf.transpose(0, 2, 1)
        out[:, mm_at[0], mm_at[1]] = mm
        return out

    def _assemble(self, ff: Array, mf: Array, mm: Array) -> Array:
        """A (p, p) matrix of products from its blocks: fixed with fixed, moving with
        fixed, moving with moving."""
        p = len(self.fixed) + len(self.moving)
        out = np.empty((p, p))
        ff_at, mf_at, fm_at, mm_at = self._blocks
        out[ff_at] = ff
        out[mf_at] = mf
        out[fm_at] = mf.T
        out[mm_at] = mm
        return out


def _shape_draws(grid: ShapeGrid, draws: Array) -> dict[str, dict[str, Any]]:
    """Mean, SD and central 95 % interval (SI) of each shape parameter from draws in
    ``u`` (parameters of log-uniform prior, such as time constants, drawn in their
    logarithm)."""
    out: dict[str, dict[str, Any]] = {}
    for j, name in enumerate(grid.names):
        v = np.exp(draws[:, j]) if grid.log(name) else draws[:, j]
        out[name] = {
            "mean": float(np.mean(v)),
            "sd": float(np.std(v, ddof=1)),
            "ci95": [float(q) for q in np.percentile(v, [2.5, 97.5])],
        }
    return out


def _logsumexp(a: Array) -> float:
    top = float(np.max(a))
    return top + float(np.log(np.sum(np.exp(a - top)))) if np.isfinite(top) else top
