"""What a fit says about its own choice: coefficients the data do not pin down, a
blocked cross-validation score beside the evidence (and a warning where the two
disagree), force samples the noise model does not explain, and the residual SD the
chosen law expects."""

from __future__ import annotations

import itertools
import math

import numpy as np
from numpy.typing import NDArray

from ..core.terms import Term
from .derivatives import Kinematics
from .design import design
from .scoring import NOT_EVALUATED, Context, ModelResult

Array = NDArray[np.float64]


#: half-width of a Gaussian's central 95 % interval, in SDs
Z95 = 1.959963984540054

#: a coefficient whose 95 % interval is wider than a Gaussian's with this SD, in prior
#: scales, is not much narrower than its prior: not identified
VAGUE = 0.3

#: a passive coefficient with more than this share of its posterior below zero, the
#: positivity bound set aside, has a 95 % interval that reaches zero: the data do not
#: tell the term from none (a Gaussian posterior's when its SD exceeds 0.51 of its mean)
BELOW_ZERO = 0.025

#: a passive coefficient whose 95 % interval [lo, hi] has lo at or below this share of hi
#: spans more than a factor of 50: not identified (where the mass below zero is not
#: known, also what tells a term from none: a Gaussian's lo is 0.02 hi at an SD of
#: 0.49 of its mean)
REACHES_ZERO = 0.02

#: a passive coefficient whose 95 % interval is wider than a Gaussian's with an SD of
#: this share of its mean (lo below 0.34 hi; :func:`spread`) is poorly identified
POOR = 0.25


def spread(lo: float, hi: float) -> float:
    """The SD relative to the mean of the Gaussian whose central 95 % interval is
    ``[lo, hi]``: ``(hi - lo) / (Z95 (hi + lo))`` (infinite if ``hi + lo <= 0``)."""
    return (hi - lo) / (Z95 * (hi + lo)) if hi + lo > 0 else float("inf")


def identifiability(r: ModelResult) -> list[str]:
    """Flags for coefficients the data do not pin down, judged on posterior quantiles.

    Not identified: the 95 % interval is wider than a Gaussian's with an SD of
    :data:`VAGUE` prior scales (the prior put it there), or, for a passive
    coefficient, it reaches zero (more than :data:`BELOW_ZERO` of the posterior lies
    below zero once the positivity bound is set aside: the data do not tell the term
    from none) or spans more than a factor of 50 (``lo <= REACHES_ZERO hi``). Poorly
    identified: a passive coefficient's interval wider than a Gaussian's with an SD
    of :data:`POOR` of its mean (:func:`spread`).

    For a Gaussian posterior these are the thresholds its SD would give. They read no
    SD: a coefficient's posterior with its shape marginalised (a relaxation branch
    whose time constant may lie far out, where its stiffness is many times larger) is
    heavy-tailed, and its SD over a few hundred of the shape chain's draws moved from
    19 % to 145 % of its mean from one chain to the next, while its 2.5 % quantile
    moved by 2 % and its mass below zero stays 0. The mass below zero is the closed
    form's (exact for a fixed shape; over a chain's shape draws, their mean).

    A coefficient whose unit hangs on its term's shape (a contact stiffness in N/m^n)
    is judged given the shape the law is bound at: across shapes its value changes
    unit, and its spread there spans decades even where the force it gives is pinned.
    The prior's scale is that at that shape too."""
    flags = []
    post = r.posterior
    assert post is not None and r.prior is not None
    scales = r.prior.scales
    at = post.diagnostics.get("at_shape")
    ci = np.array(post.ci95, float)
    below = None if post.below_zero is None else np.array(post.below_zero, float)
    for j, t in enumerate(r.model.terms):
        if at is not None and t.unit_by_shape:
            ci[j] = at["ci95"][j]
            if below is not None and "below_zero" in at:
                below[j] = at["below_zero"][j]
    for j, t in enumerate(r.model.terms):
        lo, hi = ci[j]
        vague = hi - lo > 2 * Z95 * VAGUE * scales[j]
        loose = lo <= REACHES_ZERO * max(hi, 1e-300)
        if below is not None:
            loose = loose or below[j] > BELOW_ZERO
        if vague or (t.passive and loose):
            what = (
                "too little acceleration content"
                if t.role == "inertia"
                else "too little excitation"
            )
            # where the bound alone keeps the interval off zero, say so
            cut = (
                f", {100 * below[j]:.0f} % of its posterior below zero without the positivity bound"
                if below is not None and not vague and lo > REACHES_ZERO * hi
                else ""
            )
            flags.append(
                f"{t.symbol} not identified ({what}): 95 % interval [{lo:.3g}, {hi:.3g}] "
                f"{t.unit}{cut}"
            )
        elif loose_shape := _loose_shapes(r, t):
            flags.append(f"{t.symbol} not identified (its shape is not: {loose_shape})")
        elif t.passive and spread(lo, hi) > POOR:
            flags.append(
                f"{t.symbol} poorly identified: 95 % interval [{lo:.3g}, {hi:.3g}] {t.unit}, "
                f"±{100 * (hi - lo) / (hi + lo):.0f} % of its centre"
            )
    return flags


#: a shape parameter whose 95 % interval covers this much of its prior's range (in the
#: coordinate the prior is uniform in) is where the prior put it: not identified (a
#: posterior equal to the prior covers 0.95 of it)
SHAPE_FILLS = 0.9


def _loose_shapes(r: ModelResult, t: Term) -> str:
    """What the data leave of ``t``'s shape parameters where the prior put them (their
    95 % intervals and prior ranges), or "" if each is pinned. A coefficient judged at
    its shape means nothing if the shape itself is not identified."""
    post, ranges = r.shape_posterior, r.shape_ranges
    if not t.shapes or post is None or ranges is None:
        return ""
    out = []
    for name in t.shapes:
        if name not in post or name not in ranges:
            continue
        p = t.shape_parameter(name)
        lo, hi = ranges[name]
        a, b = post[name]["ci95"]
        width = p.to_u(hi) - p.to_u(lo) if min(lo, a) > 0 or not p.log else 0.0
        if width > 0 and p.to_u(b) - p.to_u(a) >= SHAPE_FILLS * width:
            out.append(
                f"{name} 95 % interval [{a:.3g}, {b:.3g}] of its prior's [{lo:.3g}, {hi:.3g}]"
            )
    return "; ".join(out)


def unidentified(r: ModelResult) -> set[int]:
    """Indices of the terms whose coefficient :func:`identifiability` calls not
    identified."""
    out = set()
    for j, t in enumerate(r.model.terms):
        if any(f.startswith(f"{t.symbol} not identified") for f in r.flags):
            out.add(j)
    return out


#: contiguous blocks of the blocked cross-validation reported beside the evidence
CV_BLOCKS = 5


#: a law predicting held-out blocks this much better than the chosen one is reported
CV_MARGIN = 1.1


def blocked_cv_rms(A: Array, y: Array, blocks: int = CV_BLOCKS) -> float:
    """RMS of what each of ``blocks`` contiguous blocks leaves to the least-squares fit
    of the others (N): a prediction score of a law on data its coefficients never saw,
    from the Gram matrix of each block, formed once.

    Parameters
    ----------
    A : ndarray, shape (m, p)
        The law's design matrix at the fitted samples.
    y : ndarray, shape (m,)
        The filtered force, N.
    """
    m = y.size
    if m < 2 * blocks * max(A.shape[1], 1):
        return float("nan")
    edges = np.linspace(0, m, blocks + 1).astype(int)
    d = np.linalg.norm(A, axis=0)
    d[d == 0] = 1.0
    As = A / d
    parts = [(As[a:b].T @ As[a:b], As[a:b].T @ y[a:b]) for a, b in itertools.pairwise(edges)]
    G = sum(g for g, _ in parts)
    c = sum(v for _, v in parts)
    ss = 0.0
    for (a, b), (g, v) in zip(itertools.pairwise(edges), parts, strict=True):
        beta = np.linalg.lstsq(G - g, c - v, rcond=1e-12)[0]
        r = y[a:b] - As[a:b] @ beta
        ss += float(r @ r)
    return math.sqrt(ss / m)


def cv_scores(results: list[ModelResult], fit: Context) -> None:
    """Set ``cv_rms`` (:func:`blocked_cv_rms`) of every evaluated law that has none yet."""
    for r in results:
        if r.status == NOT_EVALUATED or math.isfinite(r.cv_rms):
            continue
        A = design(r.model, fit.kin, fit.x_full, fit.sigma_x, fit.columns)
        r.cv_rms = blocked_cv_rms(A, fit.y)


def predictive_guard(results: list[ModelResult], fit: Context) -> list[str]:
    """Score each evaluated law by blocked cross-validation (``cv_rms``) and say when a
    law predicts the held-out blocks clearly better than the chosen one: evidence and
    prediction then disagree, and the choice rests on the priors."""
    cv_scores(results, fit)
    best = results[0]
    scored = [r for r in results if math.isfinite(r.cv_rms)]
    if not scored or not math.isfinite(best.cv_rms):
        return []
    top = min(scored, key=lambda r: r.cv_rms)
    if top is best or best.cv_rms <= CV_MARGIN * top.cv_rms:
        return []
    return [
        f"{top.name} predicts held-out blocks better than the chosen {best.name} "
        f"(blocked cross-validation RMS {top.cv_rms:.3g} N against {best.cv_rms:.3g} N): "
        "evidence and prediction disagree"
    ]


def outlier_warnings(kin: Kinematics, fitted: Array, z: float = 8.0) -> list[str]:
    """Raw force samples beyond ``z`` noise SDs of the fit: glitches (ADC spikes, a knock)
    the Gaussian noise model does not explain, and which pull every parameter.

    Raw, not filtered, residuals: filtering smears a spike over the kernel, and at
    high rates with a coarse position ADC the filtered residual carries the
    quantisation of position (plateaus of K q / 2 at every turn of the jaw), which is
    not a glitch but stood at 50 filtered-noise SDs.
    """
    r = kin.force_raw - fitted
    scale = 1.4826 * float(np.median(np.abs(r - np.median(r))))  # robust SD
    if not scale > 0:
        return []
    bad = np.flatnonzero(np.abs(r) > z * scale)
    if bad.size == 0:
        return []
    t = kin.time[bad]
    return [
        f"{bad.size} force sample(s) lie beyond {z:g} noise SDs of the fit, first at "
        f"t = {t[0]:.3f} s: a glitching sensor or a knock; the parameters absorb it, so "
        "inspect the residuals in the report and fit a clean stretch"
    ]


def expected_residual_sd(best: ModelResult, sigma_x: float, n: int) -> float:
    """Residual SD the best form expects (N): force noise plus position noise through the law.

    The posterior noise SD is that of the raw residual about the law (the evidence is
    scored on it, :func:`~tissuecli.identify.scoring.law_stats`): force noise and
    position noise through the design columns together, ``beta^T C beta / n`` of its
    variance the latter (C: the correction subtracted from A^T A). ``sigma_x`` and
    ``n`` are kept for callers; the posterior already holds both parts.
    """
    post = best.posterior
    assert post is not None
    return float(post.sigma_mean)
