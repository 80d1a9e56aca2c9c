"""Online identification: the recursion against the offline posterior, forgetting,
confidence, bad input, and the live estimate of a recording."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tissuecli.core.errors import InputError
from tissuecli.core.tissue import DEFAULT_TISSUE, Tissue
from tissuecli.identify.bayes import law_prior, session_scales
from tissuecli.identify.design import design
from tissuecli.identify.online import NODES, OnlineEstimate, OnlineFit
from tissuecli.identify.posterior import ExactPosterior, SufficientStats
from tissuecli.sim.synth import ForcepsModel, GraspingOperator, Operator, synthesize


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


def test_forgetting_follows_a_tissue_switch() -> None:
    soft = Tissue(DEFAULT_TISSUE.law, 200.0, 2.0, 0.05)
    a, b = _session(seconds=10.0, seed=5), _session(soft, seconds=10.0, seed=6)
    fit = OnlineFit(rate_hz=1000.0, forgetting_s=1.0)
    _feed(fit, a.position, a.force)
    assert fit.estimate().tissue().K == pytest.approx(350.0, rel=0.02)
    _feed(fit, b.position, b.force)
    est = fit.estimate()
    # ten time constants later the first tissue weighs e^-10 of the second
    assert est.tissue().K == pytest.approx(200.0, rel=0.02)
    assert est.ci95[0, 0] < 200.0 < est.ci95[0, 1]
    # without forgetting the estimate is stuck between the two
    stuck = OnlineFit(rate_hz=1000.0, forgetting_s=math.inf)
    _feed(stuck, a.position, a.force)
    _feed(stuck, b.position, b.force)
    assert 220.0 < stuck.estimate().tissue().K < 330.0


def test_confidence_comes_only_with_enough_data() -> None:
    s = _session(seconds=6.0)
    fit = OnlineFit(rate_hz=1000.0)
    seen = []
    for i in range(0, s.time.size, 50):
        fit.update(s.position[i : i + 50], s.force[i : i + 50])
        est = fit.estimate()
        seen.append(None if est is None else est.confident)
    assert seen[0] is None  # nothing before two filter windows
    first = seen.index(True)
    assert any(c is False for c in seen[:first]), "confidence should not come at once"
    assert all(seen[first:]), "with steady data confidence should stay"
    # the rule itself: K's and S's intervals within their limits once confident
    est = fit.estimate()
    rel = (est.ci95[:, 1] - est.ci95[:, 0]) / est.mean
    assert rel[0] <= 0.10 and rel[1] <= 0.20 and est.n_eff >= 30


def test_grasps_count_only_in_contact() -> None:
    model = ForcepsModel(operator=GraspingOperator(), seed=2)
    s = synthesize(model, 12.0)[0]
    gated, ungated = OnlineFit(rate_hz=1000.0), OnlineFit(rate_hz=1000.0, contact=False)
    _feed(gated, s.position, s.force)
    _feed(ungated, s.position, s.force)
    # free jaw motion (no force whatever the closure) breaks the law: without the gate
    # its misfit swells the noise level and every interval
    good, bad = gated.estimate(), ungated.estimate()
    assert good.confident and not bad.confident
    for true, g, b in zip(DEFAULT_TISSUE.coef, good.ci95, bad.ci95, strict=True):
        assert g[0] < true < g[1]
        assert b[1] - b[0] > 5 * (g[1] - g[0])
    assert gated.samples < 0.9 * ungated.samples


def test_lost_samples_become_holes_when_times_are_given() -> None:
    s = _session(seconds=6.0)
    keep = np.ones(s.time.size, bool)
    keep[2000:2100] = False  # a lost stretch
    kw = {"rate_hz": 1000.0, "forgetting_s": math.inf, "contact": False}
    whole, holed = OnlineFit(**kw), OnlineFit(**kw)
    whole.update(s.position, s.force)
    holed.update(s.position[keep], s.force[keep], time=s.time[keep])
    # the gap and every filter window across it are left out, nothing else
    assert holed.samples == whole.samples - (100 + holed.window - 1)
    assert holed.skipped == 100
    assert holed.estimate().tissue().K == pytest.approx(350.0, rel=0.02)


finite = st.floats(-1e3, 1e3, allow_nan=False)
values = st.one_of(finite, st.just(float("nan")), st.just(float("inf")))


@settings(max_examples=60, deadline=None)
@given(
    blocks=st.lists(
        st.integers(0, 40).flatmap(
            lambda n: st.tuples(st.lists(values, min_size=n, max_size=n),
                                st.lists(values, min_size=n, max_size=n))
        ),
        max_size=30,
    )
)  # fmt: skip
def test_bad_blocks_never_crash(blocks) -> None:
    fit = OnlineFit(rate_hz=1000.0, min_samples=5)
    for x, f in blocks:
        fit.update(np.array(x), np.array(f))
        est = fit.estimate()
        if est is not None:
            assert np.all(np.isfinite(est.mean)) and est.law in est.probabilities
    n_bad = sum(
        int(np.sum(~(np.isfinite(np.array(x, float)) & np.isfinite(np.array(f, float)))))
        for x, f in blocks
    )
    assert fit.skipped == n_bad
    assert fit.received == sum(len(x) for x, _ in blocks)


def test_mismatched_or_malformed_blocks_are_refused() -> None:
    fit = OnlineFit(rate_hz=1000.0)
    with pytest.raises(InputError, match="one length"):
        fit.update(np.zeros(3), np.zeros(4))
    with pytest.raises(InputError, match="1-D"):
        fit.update(np.zeros((2, 2)), np.zeros((2, 2)))
    with pytest.raises(InputError, match="shape"):
        fit.update(np.zeros(3), np.zeros(3), time=np.zeros(2))
    fit.update([], [])  # empty: nothing happens
    fit.update([1e-3], [0.3])  # one sample: kept for the next window
    assert fit.received == 1 and fit.estimate() is None
    with pytest.raises(InputError):
        OnlineFit(rate_hz=0.0)
    with pytest.raises(InputError, match="linear"):
        OnlineFit(rate_hz=1000.0, forms="x+maxwell+xdot+xddot")


def test_record_shows_the_online_estimate(forceps, tmp_path) -> None:
    from tissuecli.app.record import record

    sim = forceps("--seed", "3")
    statuses = []
    res = record(
        str(sim.link), tmp_path / "g.h5", "s1", duration_s=4.0,
        on_status=statuses.append, status_interval_s=0.2,
    )  # fmt: skip
    estimates = [s.estimate for s in statuses if s.estimate is not None]
    assert estimates, "the status should carry an estimate while recording"
    assert res.estimate is not None and res.identify_note == ""
    assert res.estimate.law == DEFAULT_TISSUE.law.name
    assert res.estimate.tissue().K == pytest.approx(350.0, rel=0.05)
    off = record(str(sim.link), tmp_path / "g.h5", "s2", duration_s=0.5, identify=False)
    assert off.estimate is None


def test_record_command_prints_the_estimate(forceps, tmp_path) -> None:
    from click.testing import CliRunner

    from tissuecli.cli import cli

    sim = forceps("--seed", "3")
    out = tmp_path / "g.h5"
    args = ["record", "--port", str(sim.link), "--out", str(out), "--duration", "3"]
    res = CliRunner().invoke(cli, args)
    assert res.exit_code == 0, res.output
    assert "identifying..." in res.output or "K " in res.output  # the status line
    assert "online estimate: x+xdot+xddot" in res.output
    res = CliRunner().invoke(cli, [*args, "--session", "quiet", "--no-identify"])
    assert res.exit_code == 0 and "online estimate" not in res.output
