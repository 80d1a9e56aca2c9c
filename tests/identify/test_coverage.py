"""The 95 % intervals hold the truth at their nominal rate, over fixed seeds.

Each test counts the intervals that miss the true coefficient over independent
sessions. A calibrated 95 % interval misses a binomial count, n = sessions and p = 0.05;
the tests allow up to the count that a calibrated interval exceeds with probability
1e-4 (:func:`allowed_misses`), so they fail at random about once in ten thousand runs
and with 100 sessions fail intervals that hold the truth 80 % of the time in
nine runs of ten.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.stats import binom

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

import protocols as prot  # noqa: E402
from continuous_contact import noisy_contact_truth  # noqa: E402

from tissuecli.core.terms import Law  # noqa: E402
from tissuecli.core.tissue import Tissue  # noqa: E402
from tissuecli.identify import BayesianFit  # noqa: E402
from tissuecli.sim.protocols import random_protocol  # noqa: E402
from tissuecli.sim.scenes import FAMILIES, random_scene  # noqa: E402
from tissuecli.sim.synth import ForcepsModel, Sensors, synthesize  # noqa: E402

#: chance that calibrated intervals fail a test here
FALSE_ALARM = 1e-4

PAPER = [
    Tissue(Law.paper("x", "xdot"), 350.0, 3.0, 0.05),
    Tissue(Law.paper("x^3", "xdot"), 8e6, 3.0, 0.05),
    Tissue(Law.paper("x", "xdot^2"), 350.0, 60.0, 0.05),
    Tissue(Law.paper("x^3", "xdot^2"), 8e6, 60.0, 0.05),
]

#: the protocols the stability bounds are stated for (constant-speed ramps, triangle
#: cycles, ramp-and-hold of a standard linear solid)
PROTOCOLS = ["ramp linear", "ramp offset", "ramp stiffening", "triangle viscoelastic",
             "ramp-hold SLS"]  # fmt: skip


def allowed_misses(n: int, level: float = 0.95) -> int:
    """Most misses of ``n`` calibrated ``level`` intervals short of a 1e-4 tail."""
    return int(binom.ppf(1.0 - FALSE_ALARM, n, 1.0 - level))


def test_the_tolerance_is_binomial() -> None:
    assert allowed_misses(100) == 15  # 5 expected, SD 2.2: 4.6 SD above
    assert binom.sf(allowed_misses(100), 100, 0.05) < FALSE_ALARM


def _paper_misses(tissue: Tissue, seeds: range, **sensors: float) -> np.ndarray:
    """Misses of each coefficient's interval, the true form fitted, over ``seeds``."""
    misses = np.zeros(len(tissue.coef), int)
    for seed in seeds:
        model = ForcepsModel(tissue=tissue, seed=seed, sensors=Sensors(bits=12, **sensors))
        session, _ = synthesize(model, 10.0)
        post = BayesianFit(forms=tissue.law.name, seed=0).fit(session).best_.posterior
        lo, hi = post.ci95.T
        misses += (tissue.coef < lo) | (tissue.coef > hi)
    return misses


@pytest.mark.parametrize("tissue", [PAPER[0], PAPER[1]], ids=lambda t: t.law.name)
def test_position_noise_does_not_narrow_the_intervals(tissue: Tissue) -> None:
    """20 um of position noise on a 12-bit session: the errors-in-variables correction
    takes its bias off the coefficients, and its spread must stay in their intervals
    (before, the cubic stiffness's held the truth in 59 of 100 sessions, and the linear
    law's K, S and M in 84-88)."""
    misses = _paper_misses(tissue, range(200, 300), position_noise_m=20e-6)
    assert np.all(misses <= allowed_misses(100)), misses


@pytest.mark.slow
@pytest.mark.parametrize("tissue", PAPER, ids=lambda t: t.law.name)
def test_paper_forms_cover_at_the_nominal_rate(tissue: Tissue) -> None:
    """The paper's four forms on 12-bit sessions at the simulator's sensor noise, 100
    sessions each."""
    misses = _paper_misses(tissue, range(200, 300))
    assert np.all(misses <= allowed_misses(100)), misses


def _protocol_misses(name: str, seeds: range) -> tuple[int, int]:
    """Misses and intervals of the truth's coefficients, the truth's law fitted, over
    draws of one protocol (``max_samples`` 2000 keeps each fit short)."""
    misses = total = 0
    for seed in seeds:
        scene = random_protocol(seed, name, max_samples=2000)
        law = scene.tissue.law
        best = BayesianFit(grasps="none", forms=law.name, seed=0).fit(scene.session).best_
        assert np.all(np.isfinite([best.ln_evidence])), (seed, name)
        lo, hi = best.posterior.ci95.T
        truth = np.asarray(scene.coefficients, float)
        misses += int(np.count_nonzero((truth < lo) | (truth > hi)))
        total += truth.size
    return misses, total


def _default_search(name: str, seed: int, terms: bool) -> None:
    """The default search on a random draw of a protocol (units, rates, quantisation and
    noise from the stress space): never refused, every ln Z finite and within 20 nats a
    sample, and (``terms``) the chosen law written with the truth's terms, columns the
    design cannot tell apart counted as one."""
    outcome = prot.fit_protocol(random_protocol(seed, name, max_samples=2000))
    assert not outcome.refused, outcome.refused
    assert not outcome.evidence, outcome.evidence
    if terms:
        assert outcome.within, (outcome.law, outcome.scene.tissue.law.name)


@settings(max_examples=2, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])  # fmt: skip
@given(name=st.sampled_from(PROTOCOLS), seed=st.integers(0, 2**20))
def test_random_protocols_give_finite_evidence(name: str, seed: int) -> None:
    _default_search(name, seed, terms=False)


@pytest.mark.slow
@settings(max_examples=15, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])  # fmt: skip
@given(name=st.sampled_from(PROTOCOLS), seed=st.integers(0, 2**20))
def test_random_protocols_give_finite_evidence_and_the_truth_or_its_indistinct_terms(
    name: str, seed: int
) -> None:
    _default_search(name, seed, terms=True)


@settings(max_examples=5, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])  # fmt: skip
@given(name=st.sampled_from(PROTOCOLS), first=st.integers(0, 2**20))
def test_random_protocols_cover_their_truth(name: str, first: int) -> None:
    """A small slice of the slow test below: 10 draws of one protocol."""
    misses, total = _protocol_misses(name, range(first, first + 10))
    assert misses <= allowed_misses(total), (name, misses, total)


@pytest.mark.slow
@pytest.mark.parametrize("name", PROTOCOLS)
def test_protocols_cover_their_truth_over_many_seeds(name: str) -> None:
    """100 draws of each protocol, the truth's law fitted: its intervals hold the
    truth at the nominal rate whatever the units, rate, quantisation and noise."""
    misses, total = _protocol_misses(name, range(100))
    assert misses <= allowed_misses(total), (name, misses, total)


#: the paper's four forms among the random scenes' families
PAPER_FAMILIES = [name for name in FAMILIES if name.startswith("paper")]


def _scene_misses(seeds: range, contact: str) -> tuple[int, int]:
    """Misses and intervals of random paper-form scenes (``random_scene``: 250 Hz-10 kHz,
    8-16 bits, 0.5-10 % noise, cut at 20,000 samples), the truth's form fitted with grasp
    detection, as ``tissuecli fit --forms FORM`` does."""
    misses = total = 0
    for seed in seeds:
        scene = random_scene(seed, families=PAPER_FAMILIES, max_samples=20_000, contact=contact)
        est = BayesianFit(forms=scene.tissue.law.name, seed=0).fit(scene.session)
        lo, hi = est.best_.posterior.ci95.T
        truth = np.asarray(scene.coefficients, float)
        misses += int(np.count_nonzero((truth < lo) | (truth > hi)))
        total += truth.size
    return misses, total


def test_random_paper_form_grasps_cover_their_truth() -> None:
    """Grasps with free jaws between them: the jaws held still between grasps read as
    free, not fitted as tissue. Before, 21 of these 40 scenes were read as one contact
    (the open jaws' zero force fitted by the law) and 26 of the 120 intervals missed;
    now 9 are, and 17 miss (17 allowed)."""
    misses, total = _scene_misses(range(40), "grasps")
    assert misses <= allowed_misses(total), (misses, total)


def test_noisy_continuous_contact_covers_its_truth() -> None:
    """Paper-form x^3 sessions in contact throughout, 8-bit, up to 10 % noise."""
    misses = total = 0
    for seed in range(500, 530):
        session, tissue = noisy_contact_truth(seed)
        post = BayesianFit(forms=tissue.law.name, seed=0).fit(session).best_.posterior
        lo, hi = post.ci95.T
        misses += int(np.count_nonzero((tissue.coef < lo) | (tissue.coef > hi)))
        total += tissue.coef.size
    assert misses <= allowed_misses(total), (misses, total)
