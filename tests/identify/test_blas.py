"""BLAS runs on one thread while a fit runs, and gets its threads back after it."""

from __future__ import annotations

import numpy as np
import pytest
from threadpoolctl import threadpool_info

from tissuecli.identify import BayesianFit
from tissuecli.identify.blas import one_blas_thread
from tissuecli.sim.synth import ForcepsModel, synthesize

_ = np.linalg  # numpy's BLAS is loaded


def _threads() -> list[int]:
    return [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]


def test_one_thread_inside_and_restored_after() -> None:
    before = _threads()
    if not before:
        pytest.skip("no BLAS that threadpoolctl can see")
    with one_blas_thread():
        assert set(_threads()) == {1}
        with one_blas_thread():  # nested (a batch worker already pinned): still one
            assert set(_threads()) == {1}
        assert set(_threads()) == {1}
    assert _threads() == before


def test_fit_runs_with_one_thread(monkeypatch: pytest.MonkeyPatch) -> None:
    seen: list[list[int]] = []
    original = BayesianFit._fit

    def spy(self: BayesianFit, session):  # type: ignore[no-untyped-def]
        seen.append(_threads())
        return original(self, session)

    monkeypatch.setattr(BayesianFit, "_fit", spy)
    session, _ = synthesize(ForcepsModel(seed=3), 4.0)
    BayesianFit(grasps="none", seed=0).fit(session)
    assert seen and set(seen[0]) <= {1}
