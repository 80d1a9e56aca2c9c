"""The streamed fit of a session too long to hold: every filtered sample summed once,
the same answer as the full fit of the same law, memory set by the block."""

from __future__ import annotations

import numpy as np
import pytest

from tissuecli.core.session import Session
from tissuecli.identify import BayesianFit
from tissuecli.identify.stream import StreamedFit
from tissuecli.sim.synth import ForcepsModel, synthesize


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
