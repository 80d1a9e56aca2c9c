"""What a grasp session's fit reads: the grasps, and the free jaws that measure the
force sensor's offset.

The scenes are :func:`tissuecli.sim.scenes.random_scene` grasp sessions whose sensor has
an offset: the force reads it with the jaws open too, where the tissue's force is zero.
The first 70 % of each is fitted, as the generalisation benchmark does.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tissuecli.core.errors import FitError
from tissuecli.core.terms import Law
from tissuecli.identify import BayesianFit
from tissuecli.identify.design import design
from tissuecli.identify.prepare import _dithered
from tissuecli.sim.scenes import FAMILIES, Scene, random_scene

OTHER = [f for f in FAMILIES if not f.startswith("paper")]
PAPER = [f for f in FAMILIES if f.startswith("paper")]


def _head(seed: int) -> tuple[Scene, int]:
    scene = random_scene(seed, families=OTHER, max_samples=10_000)
    t = scene.session.time
    return scene, int(np.searchsorted(t, t[0] + 0.7 * (t[-1] - t[0])))


def test_open_jaws_are_fitted_with_the_tissue_columns_zero() -> None:
    """Outputs of free jaws are among those fitted (the sensor's offset alone); every one
    of them lies where the jaws are truly open (closure below 0 across its window: the
    jaws are read open only past every closure seen in contact), the tissue's columns
    are zero there and the offset's is one."""
    scene, n = _head(6587724)
    s = scene.session
    ready = BayesianFit().prepare(s.replace(s.time[:n], s.force[:n], s.position[:n]))
    kin = ready.kinematics
    weight = kin.contact_weight
    assert weight is not None
    free = np.flatnonzero(weight == 0)  # whole windows of free jaws
    assert free.size > 100
    h = kin.window // 2
    centres = np.arange(n)[kin.keep][free]
    assert all(np.all(scene.x[c - h : c + h + 1] <= 0) for c in centres)
    A = design(Law.of(["x", "xdot", "sign(xdot)", "xddot", "offset"]), kin, ready.session.position)
    assert np.all(A[free, :4] == 0)
    assert np.all(A[free, 4] == 1)


@pytest.mark.parametrize("seed", [6587724, 8537436])
def test_the_offset_is_found_from_the_open_jaws(seed: int) -> None:
    """friction+offset grasp sessions (8 bits, 654 Hz, 8 % noise, fast taps; 9 bits,
    9.3 kHz, slow squeeze) whose offset stands 8.6-9.6 times its standard error over the
    session, but inside the grasps trades with the spring's intercept: the chosen law
    left it out (P = 0.94 and 1.0), and predicted 4.8-5.2 times the noise floor on the
    held-out part. Fitted with the open jaws, the chosen law has the offset, and its
    95 % interval holds the true one (a 5 % miss each, so both hold 90 % of the time
    for a calibrated posterior; the seeds are fixed)."""
    scene, n = _head(seed)
    s = scene.session
    est = BayesianFit(seed=seed).fit(s.replace(s.time[:n], s.force[:n], s.position[:n]))
    names = [t.name for t in est.law_.terms]
    assert "offset" in names
    j = names.index("offset")
    truth = dict(zip(scene.tissue.law.symbols, scene.coefficients, strict=True))
    lo, hi = est.coef_ci95_[j]
    assert lo <= truth[est.law_.terms[j].symbol] <= hi


def test_damping_is_found_at_the_grasp_edges() -> None:
    """A short fast grasp session (paper form x+xdot|xdot|+xddot, 10 bits, 8.7 kHz,
    1.2 s, slow squeezes): its speed is in each grasp's first and last 20-50 ms, the
    jaws closing onto the tissue and leaving it. Kept to the filtered samples whose
    whole 321-tap window lies inside a grasp, the fit saw a damping force 3000 times
    smaller than in contact and chose x+xddot (P 1.000). Fitted on every window that
    touches a grasp, the tissue's columns gated on the raw grid, the truth is chosen
    and its damping found. S2 is held to 10 % (the posterior SD is 1.6 %, the truth 2.4
    SDs off: the columns' gating inside the half kernel, ``g_h * (touching * r(g_h'
    x))`` for ``g * (touching * r(xdot))``, is exact inside a grasp, an approximation
    across its edges)."""
    scene = random_scene(4455139, families=PAPER, max_samples=10_000)
    s = scene.session
    t = s.time
    n = int(np.searchsorted(t, t[0] + 0.7 * (t[-1] - t[0])))
    est = BayesianFit(seed=4455139).fit(s.replace(s.time[:n], s.force[:n], s.position[:n]))
    assert est.law_.name == scene.tissue.law.name == "x+xdot|xdot|+xddot"
    assert est.best_.probability > 0.9
    truth = dict(zip(scene.tissue.law.symbols, scene.coefficients, strict=True))
    got = dict(zip(est.law_.symbols, est.coef_, strict=True))
    assert got["S2"] == pytest.approx(truth["S2"], rel=0.1)
    lo, hi = est.coef_ci95_[0]
    assert lo <= truth["K"] <= hi


def test_inertia_is_found_at_the_grasp_edges_of_a_coarse_force_adc() -> None:
    """A short fast grasp session (paper form x+xdot+xddot, 8 bits, 8.3 kHz, 1.2 s): its
    inertia's force is in each grasp's first 20 ms, where the jaws close onto the
    tissue. The free jaws' force noise is 1.3 ADC steps: its mean is off by e^-30 of a
    step, dithered. Read as undithered (a noise under two steps), the windows across the
    edges were left out, the fit saw an acceleration 5 times smaller than its own noise
    and chose x+xdot (P 0.999, M "not identified"). Fitted across the edges, the truth is
    chosen and M lies inside its 95 % interval."""
    scene = random_scene(5520330, families=PAPER, max_samples=10_000)
    s = scene.session
    t = s.time
    n = int(np.searchsorted(t, t[0] + 0.7 * (t[-1] - t[0])))
    est = BayesianFit(seed=5520330).fit(s.replace(s.time[:n], s.force[:n], s.position[:n]))
    assert est.grasp_rules_.edges
    assert est.law_.name == scene.tissue.law.name == "x+xdot+xddot"
    truth = dict(zip(scene.tissue.law.symbols, scene.coefficients, strict=True))
    j = list(est.law_.symbols).index("M")
    lo, hi = est.coef_ci95_[j]
    assert lo <= truth["M"] <= hi


@settings(max_examples=60, deadline=None)
@given(
    sd_steps=st.floats(0.0, 3.0),
    level=st.floats(-50.0, 50.0),
    m=st.integers(64, 20_000),
    seed=st.integers(0, 2**32 - 1),
)
def test_a_dithered_level_is_read_within_its_standard_errors(
    sd_steps: float, level: float, m: int, seed: int
) -> None:
    """A steady level read through an ADC of one step with Gaussian noise of any SD:
    where :func:`_dithered` calls it dithered, the mean of what the ADC reads lies within
    4.5 standard errors of the level (its bias is held to a quarter of one; a false
    failure has odds of 1 in 10^5 an example). With no noise at all (a level between
    two steps reads one of them in every sample) it is never called dithered."""
    rng = np.random.default_rng(seed)
    read = np.round(level + sd_steps * rng.standard_normal(m))
    if sd_steps == 0.0 and read[0] != level:
        assert not _dithered(read, 1.0)
    if _dithered(read, 1.0):
        se = max(sd_steps, 1e-12) / np.sqrt(m)
        assert abs(read.mean() - level) <= 4.5 * se


def _speed_error(scene: Scene, n: int, closure: str) -> tuple[float, BayesianFit]:
    """RMS of the fitted speed column less the truth filtered alike, over its RMS."""
    s = scene.session
    est = BayesianFit(closure=closure, forms="x,xdot")
    ready = est.prepare(s.replace(s.time[:n], s.force[:n], s.position[:n]))
    kin = ready.kinematics
    truth = np.convolve(scene.x[:n], kin.kernels[1], mode="valid")
    rows = np.arange(truth.size) if kin.rows is None else kin.rows
    v = truth[rows]
    return float(np.std(kin.v - v) / np.std(v)), est


def test_a_staircase_closure_is_rebuilt_through_its_level_crossings() -> None:
    """A slow 8-bit squeeze in contact throughout (paper form x+xdot+xddot, 1.8 kHz):
    the closure holds each level for 50 samples on average, and where the jaws turn it
    holds one while they move by up to a step, an error the filter passes whole. The
    speed column formed from the closure as read is off by 5 % of its RMS; rebuilt
    through the level crossings, by 2 %. With it read, a relaxation branch followed
    that error (x+maxwell+xdot+xddot, P 0.82); rebuilt, the truth's terms are chosen.
    Read or rebuilt, the filter is the one chosen on the closure as read."""
    scene = random_scene(7730001, families=PAPER, max_samples=10_000)
    t = scene.session.time
    n = int(np.searchsorted(t, t[0] + 0.7 * (t[-1] - t[0])))
    read, _ = _speed_error(scene, n, "read")
    rebuilt, _ = _speed_error(scene, n, "rebuilt")
    assert rebuilt < 0.6 * read
    s = scene.session
    est = BayesianFit(seed=1).fit(s.replace(s.time[:n], s.force[:n], s.position[:n]))
    assert scene.judged_on(n).right(est.law_)
    assert "maxwell" not in est.law_.name
    assert not np.array_equal(est.closure_, est.session_.position)


def test_a_closure_that_is_no_staircase_is_fitted_as_read() -> None:
    """A 16-bit closure steps nearly every sample: nothing to rebuild, and the columns
    are formed from the closure as read, whatever ``closure`` says."""
    scene, n = _head(6587724)
    s = scene.session
    head = s.replace(s.time[:n], s.force[:n], s.position[:n])
    ready = BayesianFit(closure="rebuilt").prepare(head)
    assert ready.rebuilt is None and ready.rebuilt_sd is None
    assert ready.closure is ready.session.position


def test_an_unknown_closure_is_refused_in_one_line() -> None:
    scene, n = _head(6587724)
    with pytest.raises(FitError, match="choose read or rebuilt") as info:
        BayesianFit(closure="smooth").fit(scene.session)
    assert "\n" not in str(info.value)
