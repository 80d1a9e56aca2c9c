"""The held-out score of a fit (:func:`tissuecli.identify.outcome.held_out`)."""

from __future__ import annotations

import pytest

from tissuecli.identify.outcome import fit_session

from .lab_protocols import relaxation


@pytest.mark.parametrize("grasps", ["all", "none"])
def test_a_relaxation_hold_at_constant_position_is_scored(grasps: str) -> None:
    """Ramped for 1 s and held 9 s: the held-out 3 s lie wholly in the hold, at one
    closure. The law runs over the whole session, so its branch enters the hold with
    its history and the hold is scored (not refused as a constant closure); its error
    is of the order of the filtered noise (10 mN of white noise, filtered)."""
    s, truth = relaxation(1, hold=9.0)
    out = fit_session(s, forms="x+maxwell", grasps=grasps, hold_out=0.3)
    v = out.validation
    assert v is not None and v.samples > 1000
    assert v.rms_n < truth["noise"]
