"""Sessions recorded in contact throughout, noisy and coarsely quantised, with a law
whose force is near zero at small closure, are never refused: grasp and clipping
detection that finds too little to fit falls back to fitting every sample, with a note.

A soft ``x^3`` law rests near zero force at the smallest closures, where it looks like
free jaws; what tells it apart is that its force follows the closure speed (the
damping term) and dips below that level while the jaws open, which free jaws never do.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from tissuecli.core.tissue import DEFAULT_TISSUE
from tissuecli.identify import BayesianFit, fit_session
from tissuecli.identify.contact import find_contact
from tissuecli.identify.derivatives import Gaussian
from tissuecli.identify.prepare import prepare
from tissuecli.sim.families import FAMILIES
from tissuecli.sim.synth import ForcepsModel, Operator, Sensors, random_session, synthesize

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from continuous_contact import noisy_contact  # noqa: E402

# seeds on which the grasp detector, reading the resting force at small closure as free
# jaws, kept 6-38 % of the samples, the rest "out of contact"
MISREAD = [2, 33, 89]


@pytest.mark.parametrize("seed", MISREAD)
def test_noisy_continuous_contact_is_one_contact(seed: int) -> None:
    session = noisy_contact(seed)
    assert find_contact(session).all_contact
    ready = prepare(session, Gaussian())
    assert ready.kinematics.time.size > 0.9 * len(session)


def test_detection_reads_continuous_contact_over_many_sessions() -> None:
    """Over 60 random sessions at most 1 in 20 is cut into grasps (7 were, keeping as
    little as 6 % of the samples), and a session cut keeps most of its samples: a soft
    law resting near zero force at small closure looks like free jaws there."""
    shares = [float(np.mean(find_contact(noisy_contact(s)).mask)) for s in range(60)]
    cut = [round(sh, 2) for sh in shares if sh < 1.0]
    assert len(cut) <= 3 and min(shares) > 0.5, cut


def test_grasps_of_a_tissue_that_pulls_on_release_are_found() -> None:
    """A damped tissue pulls on jaws that open faster than it recovers: the force dips
    below the free-jaw level at each release, and the jaws are still opening fast when
    it lets go. Those dips are no sign of continuous contact: of 40 random grasp sessions
    of laws whose force rises with the closure from the contact point on (no soft
    x^3 law, which rests at zero force like free jaws), at most half read as one contact
    (38 did when any dip below the level meant contact), and where grasps are found
    the free jaws are read as free."""
    from tissuecli.sim.scenes import random_scene

    families = ["paper x+xdot", "paper x+xdot|xdot|", "friction", "offset", "hardening"]
    whole, free_read_free = 0, []
    for seed in range(40):
        scene = random_scene(seed, families=families, max_samples=20000, contact="grasps")
        found = find_contact(scene.session)
        if found.all_contact:
            whole += 1
            continue
        free = scene.x <= 0
        free_read_free.append(float(np.mean(~found.mask[free])))
    assert whole <= 20, whole
    assert min(free_read_free) > 0.9, free_read_free


def test_free_jaws_held_still_between_grasps_are_free() -> None:
    """Paper-form grasp sessions whose jaws rest open between grasps: the stretches at the
    free-jaw level take in the first and last few noise SDs of the grasps beside them,
    and a damped tissue pulls the force below that level at each release; neither makes
    the held jaws tissue; nor does a closure quantised coarser than its noise, where the
    jaws resting again and again at their most open closure, at one force level, tell
    free jaws from a slow turn. Of 40 such sessions 21 were read as one contact, then 9,
    now none (the limit leaves room for 2: 1 of 100 other seeds is)."""
    from tissuecli.sim.scenes import FAMILIES as SCENE_FAMILIES
    from tissuecli.sim.scenes import random_scene

    paper = [name for name in SCENE_FAMILIES if name.startswith("paper")]
    whole = sum(
        find_contact(
            random_scene(seed, families=paper, max_samples=20000, contact="grasps").session
        ).all_contact
        for seed in range(40)
    )
    assert whole <= 2, whole


@settings(
    max_examples=25,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow],
)
@given(
    st.integers(0, 2**32 - 1),
    st.floats(250.0, 2000.0),
    st.floats(0.0, 0.1),
    st.floats(3.0, 8.0),
)
# noiseless 8-bit force at 250 Hz: successive differences of the squeeze itself once
# passed for noise, and a third of the contact read as free jaws
@example(seed=11124518, rate_hz=250.0, noise_fraction=0.0, duration_s=3.0)
def test_noisy_continuous_contact_is_never_refused(
    seed: int, rate_hz: float, noise_fraction: float, duration_s: float
) -> None:
    session = noisy_contact(
        seed, rate_hz=rate_hz, noise_fraction=noise_fraction, duration_s=duration_s
    )
    est = BayesianFit("paper").fit(session)
    assert est.kinematics_.time.size > 0.5 * len(session)


def test_a_session_mostly_at_the_adc_ends_is_fitted_with_a_note() -> None:
    """A force sensor whose range the noise keeps crossing: scattered clipped samples in
    every filter window left nothing to fit; now every sample is fitted, and said so."""
    session, _ = random_session(
        DEFAULT_TISSUE,
        seed=1,
        within_range=False,
        bits=8,
        force_noise_n=0.4,
        force_range_n=(-0.3, 1.0),
    )
    est = BayesianFit("x+xdot+xddot").fit(session)
    assert est.kinematics_.time.size > 0.9 * len(session)
    assert any("fitted every sample, clipped ones included" in w for w in est.warnings_)


@dataclass(frozen=True)
class _Taps:
    """Short taps: 0.12 s grasps between 1.5 s of open jaws (closure -1 mm)."""

    squeeze: Operator

    def kinematics(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        x, v, a = self.squeeze.kinematics(t)
        on = np.mod(t, 1.62) >= 1.5
        return np.where(on, x, -1e-3), np.where(on, v, 0.0), np.where(on, a, 0.0)


def test_grasps_too_short_to_filter_fall_back_to_every_sample() -> None:
    model = ForcepsModel(
        operator=_Taps(Operator()),
        rate_hz=250.0,
        seed=2,
        sensors=Sensors(position_range_m=(-3e-3, 15e-3), force_offset_n=0.3),
    )
    session, _ = synthesize(model, 20.0)
    contact = find_contact(session)
    assert contact.grasps and not contact.all_contact  # the premise
    out = fit_session(session, forms="x+xdot+xddot+offset")
    assert any("fitted every sample, contact or not" in w for w in out.warnings)
    assert out.fitted_grasps == [] and not out.contact.kept_to_grasps


class _SqueezeThenHold:
    """A squeeze, then the jaws held still from ``hold_s`` on."""

    def __init__(self, squeeze: Operator, hold_s: float) -> None:
        self.squeeze, self.hold_s = squeeze, hold_s

    def kinematics(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = np.asarray(t, float)
        x, v, a = self.squeeze.kinematics(np.minimum(t, self.hold_s))
        after = t >= self.hold_s
        return x, np.where(after, 0.0, v), np.where(after, 0.0, a)


def test_a_held_out_hold_at_constant_position_is_scored_by_a_law_with_memory() -> None:
    """The held-out part is a hold: the jaws do not move, but the force relaxes, and the
    law's branch, carried over from the fitted part, predicts it."""
    tissue = FAMILIES["one branch"]
    operator = _SqueezeThenHold(Operator.random(np.random.default_rng(4)), 7.0)
    sensors = Sensors(bits=12, position_noise_m=0.0)  # a machine that holds still
    model = ForcepsModel(tissue=tissue, operator=operator, seed=4, sensors=sensors)
    session, _ = synthesize(model, 10.0)
    assert np.ptp(session.position[session.time >= 7.0]) == 0.0  # the premise
    v = fit_session(session, forms="x+maxwell+xdot+xddot", hold_out=0.3).validation
    assert v is not None and v.samples > 2000
    assert v.r2_held_out > 0.95, v.describe()
