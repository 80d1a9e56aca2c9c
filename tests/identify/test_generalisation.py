"""A fixed-seed slice of the generalisation benchmark and of the protocol stress suite
(benchmarks/generalisation.py, benchmarks/protocols.py): a few short scenes each.

Bounds that today's fit does not meet are marked ``xfail`` with the failure seen; they
are the bounds the fit must hold, kept here so that they turn green when it does."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.stats import binom

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

import generalisation as gen  # noqa: E402
import protocols as prot  # noqa: E402

from tissuecli.core.errors import FitError  # noqa: E402
from tissuecli.identify import BayesianFit  # noqa: E402
from tissuecli.sim.protocols import random_protocol  # noqa: E402
from tissuecli.sim.scenes import FAMILIES, random_scene  # noqa: E402

PAPER = [f for f in FAMILIES if f.startswith("paper")]


@pytest.fixture(scope="module")
def paper_rows() -> list[gen.Row]:
    """Three short paper-form scenes (continuous contact and grasps), fitted both ways."""
    rows: list[gen.Row] = []
    for seed in (0, 1, 2):
        scene = random_scene(seed, families=PAPER, max_samples=2000, duration_s=4.0)
        rows += gen.run_scene(scene, seed=seed)
    return rows


def test_paper_scenes_are_fitted_and_scored(paper_rows):
    fits = [r for r in paper_rows if r.fit in gen.FITS]
    assert len(fits) == 6
    assert not [r.refused for r in fits if r.refused]
    assert all(np.isfinite(r.ratio) and r.ratio > 0 for r in paper_rows)
    assert not [r.evidence for r in fits if r.evidence]


def test_the_default_is_right_at_least_as_often_as_the_four_form_reference(paper_rows):
    right = {k: sum(r.right for r in paper_rows if r.fit == k) for k in gen.FITS}
    assert right["default"] >= right["paper"], right


def test_the_reference_intervals_cover_at_their_nominal_rate():
    """The four-form reference on the law it chose right: its 95 % intervals hold the
    truth as often as a binomial count of that many intervals at 0.95 does, but for
    one run in a thousand (intervals of one scene are correlated, so this is lenient
    only if anything)."""
    inside: list[bool] = []
    for seed in range(100, 124):
        scene = random_scene(seed, families=PAPER, max_samples=2500, contact="continuous")
        fitted, _, _ = gen.split(scene.session)
        try:
            est = BayesianFit("paper", seed=seed).fit(fitted)
        except FitError:  # a refusal is a failure of its own (see the test below)
            continue
        if scene.right(gen.chosen_law(est)):
            inside += gen.intervals(est, scene)[0]
    n = len(inside)
    assert n >= 45
    lo, hi = binom.ppf(0.0005, n, 0.95), binom.ppf(0.9995, n, 0.95)
    assert lo <= sum(inside) <= hi, (sum(inside), n)


def test_noisy_quantised_continuous_contact_is_never_refused():
    """8 bits, 10 % noise, an x^3 law near zero at small closure, continuous contact."""
    for seed in range(4):
        scene = random_scene(seed, families=["paper x^3+xdot"], bits=8, noise_frac=0.1,
                             rate_hz=250.0 + 500.0 * seed, contact="continuous",
                             max_samples=3000)  # fmt: skip
        BayesianFit(forms="paper").fit(scene.session)


def test_held_out_prediction_comes_within_half_again_the_noise_floor():
    """Friction was 2.1 times the floor (one window for every derivative, and the
    fit's friction column); now 0.42, and one branch 0.53."""
    for seed, family in ((3, "one branch"), (4, "friction")):
        scene = random_scene(seed, families=[family], max_samples=3000, contact="continuous")
        rows = gen.run_scene(scene, fits=("default",), seed=seed)
        assert rows[0].ratio <= 1.5, (family, rows[0].ratio)


@pytest.mark.slow
def test_a_paper_form_grasp_session_is_not_given_terms_that_predict_no_better():
    """A grasp session of x^3+xdot+xddot (8 bits, 1.4 kHz, fast taps) whose grasps are
    found only in part: the evidence put xdot|xdot| plus dry friction 1.7 nats ahead of
    the truth (P 0.76), though that law predicts held-out blocks no better; the smaller
    law it does not beat decisively is chosen."""
    seed = 16691060
    scene = random_scene(seed, families=PAPER, max_samples=20000)
    fitted, _, _ = gen.split(scene.session)
    est = BayesianFit("all", seed=seed).fit(fitted)
    assert scene.right(gen.chosen_law(est)), gen.chosen_law(est).name


def test_a_cubic_law_read_without_a_wrong_sample_is_not_given_an_offset():
    """A grasp session of x^3+xdot+xddot (10 bits, 1.75 kHz, slow squeezes) whose
    grasps are read without one sample wrong: the fit gave it an offset at P 1.00, 27
    nats ahead of the truth, because the position-noise corrected residual was solved
    on the unscaled Gram matrix, where the x^3 column (1e-8 m^3) beside the offset's
    ones fell below the solver's cut-off. The reference chose the truth."""
    seed = 61127002
    scene = random_scene(seed, families=PAPER, max_samples=10000)
    fitted, _, _ = gen.split(scene.session)
    est = BayesianFit("all", seed=seed).fit(fitted)
    assert scene.right(gen.chosen_law(est)), gen.chosen_law(est).name
    assert "offset" not in gen.chosen_law(est).name


def test_a_slow_cubic_squeeze_in_contact_is_not_handed_to_a_law_far_behind():
    """A 1.9 s slow squeeze of x^3+xdot+xddot in contact throughout (9 bits, 5.4 kHz):
    the same unscaled solve gave x+x^3+maxwell+xdot+sign(xdot)+xddot 18 nats it had
    not earned, and the law standing for it without its unidentified terms was
    x+maxwell+xddot, 318 nats behind (P 0.78). Now x^3+xdot: M's force stands below the
    noise there, so the truth's structure with or without it."""
    seed = 61127031
    scene = random_scene(seed, families=PAPER, max_samples=10000)
    fitted, _, _ = gen.split(scene.session)
    est = BayesianFit("all", seed=seed).fit(fitted)
    assert scene.right(gen.chosen_law(est)), gen.chosen_law(est).name


@pytest.mark.parametrize(
    ("seed", "truth"),
    [(16825523, "x+xdot|xdot|+xddot"), (7386467, "x+xdot|xdot|+xddot")],
)
def test_position_noise_through_a_law_earns_it_no_evidence(seed, truth):
    """Grasp sessions sampled at 6.3-7.5 kHz where the closure's noise, through the
    acceleration kernel, is nearly all of the truth's residual. Scored on the force noise
    alone (the residual less the position noise's share), the truth's share was a
    difference of two like numbers: below zero on the 10-bit session, so the truth was
    left uncorrected and x+xdot+xddot chosen (P 0.98, its blocked cross-validation 40 %
    worse); on the 14-bit one x+maxwell+xdot|xdot|+xddot gained 3.6 nats over the truth
    (P 0.95). Scored on the raw residual, as every law's is, each chooses the truth."""
    scene = random_scene(seed, families=PAPER, max_samples=10000)
    fitted, _, _ = gen.split(scene.session)
    est = BayesianFit("all", seed=seed).fit(fitted)
    assert gen.chosen_law(est).name == truth


@pytest.mark.parametrize("seed", [11768711, 11768714])
def test_a_fast_grasp_session_with_short_rests_is_fitted_on_its_grasps(seed):
    """1 s grasp sessions of x+xdot+xddot at 9-10 kHz whose jaws rest open for 20-40 ms
    between grasps: read as one contact (or their grasps merged across a break), the law
    misfitted the open jaws and the default chose contact+contact*xdot (P 0.99) or
    contact+xddot (P 0.41). With the rests found the truth is chosen."""
    scene = random_scene(seed, families=PAPER, max_samples=10000)
    fitted, _, _ = gen.split(scene.session)
    est = BayesianFit("all", seed=seed).fit(fitted)
    assert not est.contact_.all_contact
    assert scene.right(gen.chosen_law(est)), gen.chosen_law(est).name


def test_a_slow_8_bit_squeeze_keeps_its_quadratic_damping():
    """A 2.3 s slow squeeze of x+xdot|xdot|+xddot in contact throughout (8 bits, 4.4
    kHz): friction's column is xdot and xdot|xdot| together there, and that once made K,
    the offset and the three speed terms one column, so no law with xdot|xdot| was
    scored and x+maxwell was chosen (P 1.00, held-out error 160-180 times the noise
    floor). Each term is now merged only with a term it is one column with on its own."""
    seed = 2520607
    scene = random_scene(seed, families=PAPER, max_samples=10000)
    fitted, _, _ = gen.split(scene.session)
    est = BayesianFit("all", seed=seed).fit(fitted)
    assert scene.right(gen.chosen_law(est)), gen.chosen_law(est).name
    assert "xdot|xdot|" in gen.chosen_law(est).name


@pytest.mark.slow
def test_the_law_standing_for_one_with_unidentified_terms_is_followed_to_a_clean_one():
    """A 2.9 s slow squeeze of x^3+xdot+xddot in contact throughout, 5.8 % noise: two
    relaxation branches, neither identified, led by 3.6 nats; the law without them,
    x^3+xdot+xddot, has M not identified, and the law without that, x^3+xdot, was never
    scored, so the two branches were kept (P 0.86). Scored, x^3+xdot has the most
    evidence of all (585.0 against 581.7 nats)."""
    seed = 61127022
    scene = random_scene(seed, families=PAPER, max_samples=10000)
    fitted, _, _ = gen.split(scene.session)
    est = BayesianFit("all", seed=seed).fit(fitted)
    assert scene.right(gen.chosen_law(est)), gen.chosen_law(est).name
    assert "maxwell" not in gen.chosen_law(est).name


# -- protocols -------------------------------------------------------------------------

#: moderate settings: SI units, 200 Hz, 1000 samples, 1 % noise, a 2 mm stroke
MODERATE = {"rate_hz": 200.0, "force_unit": 1.0, "length_unit": 1.0, "noise_frac": 0.01,
            "amplitude_m": 2e-3, "stiffness": 350.0, "quantisation": "float64",
            "max_samples": 1000}  # fmt: skip


def _holds(outcome: prot.Outcome) -> list[str]:
    """The bounds (time apart) that ``outcome``, of a starred protocol, breaks."""
    broken = []
    if outcome.refused:
        return [f"refused: {outcome.refused}"]
    if outcome.evidence:
        broken.append(f"evidence: {outcome.evidence}")
    if not outcome.within:
        broken.append(f"terms beyond the truth: {outcome.law}")
    if not outcome.k_ok:
        broken.append(f"K off by {outcome.k_error:.3g}")
    return broken


def test_a_triangle_cycle_holds_every_bound():
    o = prot.fit_protocol(random_protocol(5, "triangle viscoelastic", **MODERATE))
    assert not _holds(o), _holds(o)


def test_a_sine_sweep_is_recovered():
    o = prot.fit_protocol(random_protocol(6, "sine sweep", **MODERATE))
    assert not _holds(o) and o.right, (o.law, _holds(o))


def test_a_constant_speed_ramp_with_an_offset_holds_every_bound():
    """Its damping column is one with the offset, which the truth has."""
    o = prot.fit_protocol(random_protocol(7, "ramp offset", **MODERATE))
    assert not _holds(o), _holds(o)


@pytest.mark.parametrize("name", ["ramp linear", "ramp stiffening"])
def test_constant_speed_ramps_hold_every_bound(name):
    o = prot.fit_protocol(random_protocol(7, name, **MODERATE))
    assert not _holds(o), _holds(o)


def test_ramp_and_hold_of_a_standard_linear_solid_holds_every_bound():
    o = prot.fit_protocol(random_protocol(8, "ramp-hold SLS", **MODERATE))
    assert not _holds(o), _holds(o)


@pytest.mark.slow
@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**31), name=st.sampled_from(list(prot.PROTOCOLS)))
def test_no_protocol_gives_an_impossible_evidence(seed, name):
    """Over the whole stress space: every ln Z finite and within 20 nats per sample."""
    o = prot.fit_protocol(random_protocol(seed, name, max_samples=4000))
    assert not o.evidence, o.evidence


def test_a_one_branch_squeeze_whose_linear_laws_have_no_evidence_finds_its_branch():
    """A 13 s squeeze of x+maxwell+xdot+xddot in contact throughout (11 bits, 749 Hz):
    the relaxation pushes the inertia of every linear law with xdot far below zero, so
    none has evidence within its positivity bounds, nor has one with one branch and
    x^3 or an offset; the greedy search stopped there and grew its branches on
    xdot|xdot| instead (x+maxwell+maxwell+xdot|xdot|+xddot, P 0.99, held-out error 5.8
    times the noise floor)."""
    others = ["hardening", "friction", "offset", "friction+offset", "Hunt-Crossley",
              "one branch", "two branches"]  # fmt: skip
    seed = 27111522
    scene = random_scene(seed, families=others, max_samples=10000)
    (row,) = [r for r in gen.run_scene(scene, fits=("default",), seed=seed) if r.fit == "default"]
    assert row.right, row.law
    assert row.ratio <= 1.5, row.ratio
