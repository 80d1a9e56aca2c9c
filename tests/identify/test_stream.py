"""The streamed fit of a session too long to hold: every filtered sample summed once,
the same answer as the full fit of the same law, memory set by the block."""

from __future__ import annotations

import numpy as np
import pytest

from tissuecli.core.errors import FitError
from tissuecli.core.session import Session
from tissuecli.identify import BayesianFit
from tissuecli.identify.stream import StreamedFit
from tissuecli.sim.synth import ForcepsModel, GraspingOperator, Sensors, synthesize


@pytest.fixture(scope="module")
def long_session() -> Session:
    session, _ = synthesize(ForcepsModel(seed=3), 90.0)  # 90,000 samples at 1 kHz
    return session


def reader(session: Session, log: list[tuple[int, int]]):
    def read(a: int, b: int) -> Session:
        log.append((a, b))
        return session.replace(session.time[a:b], session.force[a:b], session.position[a:b])

    return read


def test_every_filtered_sample_is_summed_once(long_session: Session) -> None:
    log: list[tuple[int, int]] = []
    fit = StreamedFit(20_000, 7_000, bayes={"forms": "paper"}).fit(
        reader(long_session, log), len(long_session)
    )
    window = fit.pilot_.kinematics_.window
    # the blocks meet without a seam: the filtered samples of the whole session, each
    # once (a gap or an overlap at any of the 13 seams would change the count)
    assert fit.n_samples_ == len(long_session) - window + 1
    assert fit.skipped_blocks_ == 0
    # memory is set by the block: no read but the pilot's is longer than a block and
    # its margins
    blocks = log[1:]
    assert max(b - a for a, b in blocks) <= 7_000 + window


def test_a_short_tail_goes_with_the_block_before_it(long_session: Session) -> None:
    """90,000 rows in blocks of 8,980 leave a tail of 200 rows, shorter than two filter
    windows: it is filtered with the block before it, and nothing is lost."""
    fit = StreamedFit(20_000, 8_980, bayes={"forms": "paper"}).fit(
        reader(long_session, []), len(long_session)
    )
    assert fit.n_samples_ == len(long_session) - fit.pilot_.kinematics_.window + 1
    assert fit.skipped_blocks_ == 0


def test_streamed_sums_give_the_full_fit(long_session: Session) -> None:
    """Same data, same law: the streamed posterior is the full one up to the filter,
    which the pilot chose on a stretch rather than on the whole session. Both estimate
    K from the same samples, so they differ by far less than an SD (a third of one
    allows for the filters' different cut-offs)."""
    law = "x+xdot+xddot"
    full = BayesianFit(forms=law).fit(long_session)
    fit = StreamedFit(30_000, 20_000, bayes={"forms": law}).fit(
        reader(long_session, []), len(long_session)
    )
    a, b = full.best_.posterior, fit.best_.posterior
    assert fit.best_.name == full.best_.name == law
    assert np.all(np.abs(a.mean - b.mean) < 0.35 * a.sd)
    assert np.allclose(a.sd, b.sd, rtol=0.1)
    assert fit.n_eff_ == pytest.approx(full.n_eff_, rel=0.2)
    assert np.isfinite(fit.best_.ln_evidence)


def grasp_session(seconds: float, noise_n: float, offset_n: float, open_m: float, seed: int):
    """Grasps with free jaws between them, read by a 12-bit ADC; ``open_m`` short of
    the tissue, the free jaws lie inside the position range (read open) or at its end
    (clipped)."""
    model = ForcepsModel(
        operator=GraspingOperator(open_m=open_m),
        sensors=Sensors(bits=12, force_noise_n=noise_n, force_offset_n=offset_n),
        seed=seed,
    )
    return synthesize(model, seconds)[0]


@pytest.mark.parametrize(
    ("noise_n", "offset_n", "open_m", "open_fitted"),
    [(0.005, 0.0, 2e-3, False), (0.01, 0.1, 3e-4, True)],
    ids=["edges", "open-jaws"],
)
def test_a_grasp_session_streamed_sums_the_full_fits_rows(
    noise_n: float, offset_n: float, open_m: float, open_fitted: bool
) -> None:
    """A pilot as long as the session reads the full fit's grasp rules; each block's
    grasps, found on it and its margins, are the whole session's, so the streamed sums
    are the full fit's over the very same rows: the grasps' edges with each tissue
    column gated on the raw grid and the free jaws' level taken off the force, and (with
    an offset to read, through a dithered ADC) the open jaws. Only the noise
    correction, shared out over a block's rows, differs (by a few parts in a million
    of the Gram matrix); the sessions are short enough for the full fit to score every
    filtered sample, as the streamed one does."""
    session = grasp_session(40.0, noise_n, offset_n, open_m, seed=7)
    full = BayesianFit(forms="paper").fit(session)
    fit = StreamedFit(100_000, 9_000, bayes={"forms": "paper"}).fit(
        reader(session, []), len(session)
    )
    rules = full.grasp_rules_
    assert rules is not None and rules.edges and rules.open_fitted is open_fitted
    assert fit.pilot_.grasp_rules_ == rules
    assert fit.skipped_blocks_ == 0
    assert fit.n_samples_ == full.kinematics_.time.size < len(session) - 100
    assert fit.best_.name == full.best_.name
    a, b = full.best_.stats, fit.best_.stats
    assert a is not None and b is not None
    np.testing.assert_allclose(b.G, a.G, rtol=1e-4)
    np.testing.assert_allclose(b.b, a.b, rtol=1e-6)
    assert b.yy == pytest.approx(a.yy, rel=1e-9)
    assert fit.best_.ln_evidence == pytest.approx(full.best_.ln_evidence, abs=1e-3)


def test_a_long_grasp_session_streamed_gives_the_full_fits_law() -> None:
    """A pilot of a third of the session: its filter, noise, data weight and grasp rules
    (the least closure in contact, the free jaws' level, where the jaws read open) come
    from its own stretch, the grasps of every block from the block. The law is the full
    fit's, and so are its coefficients, to far less than an SD: both fit nearly the
    same rows with nearly the same filter (summing every sample, contact or not, put
    the spring 9 SDs and the inertia 5 SDs off)."""
    session = grasp_session(90.0, 0.02, 0.05, 2e-3, seed=1)
    full = BayesianFit(forms="paper").fit(session)
    fit = StreamedFit(30_000, 20_000, bayes={"forms": "paper"}).fit(
        reader(session, []), len(session)
    )
    assert fit.pilot_.grasp_rules_ is not None
    assert fit.best_.name == full.best_.name
    a, b = full.best_.posterior, fit.best_.posterior
    assert np.all(np.abs(a.mean - b.mean) < 0.25 * a.sd)
    np.testing.assert_allclose(b.sd, a.sd, rtol=0.1)
    assert fit.n_samples_ == pytest.approx(full.kinematics_.time.size, rel=0.005)


def test_grasps_none_streamed_sums_every_sample() -> None:
    """``--grasps none`` fits every sample in memory, and so streamed: no grasp rules,
    every filtered sample of a grasp session summed once."""
    session = grasp_session(30.0, 0.005, 0.0, 3e-4, seed=2)
    fit = StreamedFit(10_000, 7_000, bayes={"forms": "paper", "grasps": "none"}).fit(
        reader(session, []), len(session)
    )
    assert fit.pilot_.grasp_rules_ is None
    assert fit.n_samples_ == len(session) - fit.pilot_.kinematics_.window + 1


def test_free_jaws_beside_a_pilot_in_contact_throughout_are_named() -> None:
    """A pilot inside one long grasp reads no free-jaw level, so no grasp rules: the
    blocks with free jaws of their own are summed whole, and a warning names them."""
    model = ForcepsModel(
        operator=GraspingOperator(grasp_s=60.0, free_s=2.0, open_m=3e-4),
        sensors=Sensors(bits=12, force_noise_n=0.005),
        seed=4,
    )
    session, _ = synthesize(model, 90.0)
    fit = StreamedFit(10_000, 20_000, bayes={"forms": "paper"}).fit(
        reader(session, []), len(session)
    )
    assert fit.pilot_.contact_.all_contact and fit.pilot_.grasp_rules_ is None
    assert fit.grasp_blocks_ == 2  # the free jaws at 0-2 s and 62-64 s
    assert any("2 block(s) of the session hold free jaw motion" in w for w in fit.warnings_)


def test_grasp_numbers_are_refused_when_streamed(long_session: Session) -> None:
    """Grasps are numbered over the whole session, which a streamed fit never holds."""
    with pytest.raises(FitError, match="grasp numbers"):
        StreamedFit(20_000, 7_000, bayes={"grasps": [1]}).fit(
            reader(long_session, []), len(long_session)
        )


@pytest.mark.slow
def test_a_hundred_million_samples_fit_within_two_gigabytes() -> None:
    """The stored-session benchmark: 1e8 samples written block by block, then
    ``tissuecli fit`` in a child process, whose peak memory must stay under 2 GB."""
    import re
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).parents[2] / "benchmarks" / "long_session.py"
    done = subprocess.run(
        [sys.executable, str(script), "--samples", "1e8", "--stored"],
        capture_output=True,
        text=True,
        check=True,
    )
    found = re.search(r"exit (\d+) in [\d.]+ s; child peak memory (\d+) MB", done.stdout)
    assert found, done.stdout + done.stderr
    assert int(found[1]) == 0, done.stdout
    assert int(found[2]) < 2048, done.stdout
    assert "streamed block by block" in done.stdout
