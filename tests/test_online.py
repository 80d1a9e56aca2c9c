"""Online identification: the recursion against the offline posterior, forgetting,
confidence, bad input, and the live estimate of a recording."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from tissuecli.core.tissue import DEFAULT_TISSUE, Tissue
from tissuecli.identify.bayes import law_prior, session_scales
from tissuecli.identify.design import design
from tissuecli.identify.online import NODES, OnlineEstimate, OnlineFit
from tissuecli.identify.posterior import ExactPosterior, SufficientStats
from tissuecli.sim.synth import ForcepsModel, Operator, synthesize


def _session(tissue: Tissue = DEFAULT_TISSUE, seconds: float = 6.0, seed: int = 3, **kw):
    model = ForcepsModel(tissue=tissue, operator=Operator(), seed=seed, **kw)
    return synthesize(model, seconds)[0]


def _feed(fit: OnlineFit, x: np.ndarray, f: np.ndarray, sizes=(1, 7, 40, 13, 250)) -> None:
    """Blocks of varied sizes, as a serial stream delivers them."""
    i = k = 0
    while i < x.size:
        n = sizes[k % len(sizes)]
        fit.update(x[i : i + n], f[i : i + n])
        i, k = i + n, k + 1


def test_without_forgetting_the_online_posterior_is_the_offline_one() -> None:
    s = _session()
    fit = OnlineFit(rate_hz=1000.0, forgetting_s=math.inf, contact=False)
    _feed(fit, s.position, s.force)
    # offline: the same filter on the whole record, one design matrix, one posterior
    kin = fit.differentiator(s.time, s.position, s.force)
    done = fit.samples  # rows the online fit has filtered so far
    kin_rows = int(done)
    assert kin_rows > 0.9 * kin.x.size
    scales = None
    for j, law in enumerate(fit.laws):
        A = design(law, kin, s.position)[:kin_rows]
        y = kin.force[:kin_rows]
        stats = SufficientStats.from_data(A, y, weight=fit.data_weight)
        if scales is None:
            r = slice(0, kin_rows)
            scales = session_scales(replace(kin, x=kin.x[r], v=kin.v[r], a=kin.a[r], force=y))
        offline = ExactPosterior(stats, law_prior(law, scales), nodes=NODES)
        online = fit.posteriors()[j]
        on, off = online.stats, offline.stats
        np.testing.assert_allclose(on.G, off.G, rtol=1e-9)
        np.testing.assert_allclose(on.b, off.b, rtol=1e-9)
        assert on.yy == pytest.approx(off.yy, rel=1e-9)
        assert on.n == pytest.approx(off.n, rel=1e-12)
        assert online.ln_evidence() == pytest.approx(offline.ln_evidence(), rel=1e-9)
        p_on = online.summary(np.random.default_rng(0), draws=0)
        p_off = offline.summary(np.random.default_rng(0), draws=0)
        np.testing.assert_allclose(p_on.mean, p_off.mean, rtol=1e-9)
        np.testing.assert_allclose(p_on.ci95, p_off.ci95, rtol=1e-9)


def test_estimate_recovers_the_tissue_and_is_json_ready() -> None:
    s = _session(seconds=8.0)
    fit = OnlineFit(rate_hz=1000.0)
    _feed(fit, s.position, s.force)
    est = fit.estimate()
    assert isinstance(est, OnlineEstimate)
    assert est.law == DEFAULT_TISSUE.law.name
    assert est.names == ("K", "S", "M") and est.units == ("N/m", "N s/m", "kg")
    assert sum(est.probabilities.values()) == pytest.approx(1.0)
    # the truth inside the 95 % intervals (all three: fails 1 - 0.95^3 of the time
    # if intervals were exact; seed fixed)
    for c, (lo, hi) in zip(DEFAULT_TISSUE.coef, est.ci95, strict=True):
        assert lo < c < hi
    assert est.tissue().law == DEFAULT_TISSUE.law
    d = est.as_dict()
    assert d["law"] == est.law and isinstance(d["mean"][0], float)
    assert d["time_s"] == pytest.approx(s.time[-1] - s.time[0] - fit.lag_s, abs=0.2)
