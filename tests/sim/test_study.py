"""The simulated study: its labels, its names and its truth's spread as designed."""

from __future__ import annotations

import numpy as np

from tissuecli.sim.study import GROUPS, StudyDesign, study_sessions


def test_sessions_carry_labels_and_truth() -> None:
    design = StudyDesign(specimens=2, sessions=3, duration_s=0.5, seed=4)
    drawn = list(study_sessions(design))
    assert len(drawn) == design.size == 4 * 2 * 3
    names = [d.session.name for d in drawn]
    assert len(set(names)) == len(names) and names[0] == "fat-01-01"
    for d in drawn:
        meta = d.session.meta
        assert meta["tissue"] in GROUPS
        assert meta["specimen"].startswith(meta["tissue"] + "-")
        assert meta["operator"].startswith("operator-")
        assert d.truth.law == GROUPS[meta["tissue"]].law
        assert d.truth.M == GROUPS[meta["tissue"]].M  # the forceps' mass is shared
    # the same seed draws the same study
    again = list(study_sessions(design))
    np.testing.assert_array_equal(drawn[5].session.force, again[5].session.force)


def test_truth_spreads_as_designed() -> None:
    """ln K of specimens about their group, and of sessions about their specimen, have
    the designed SDs (n = 200 and 400: within 4 chi-square SDs, sqrt(2/n) relative)."""
    design = StudyDesign(specimens=50, sessions=2, duration_s=0.05, seed=9)
    spec, sess = [], []
    for d in study_sessions(design):
        group = GROUPS[d.session.meta["tissue"]]
        if d.session.name.endswith("-01"):
            spec.append(np.log(d.specimen_truth.K / group.K))
        sess.append(np.log(d.truth.K / d.specimen_truth.K))
    for values, sd in ((spec, design.specimen_sd), (sess, design.session_sd)):
        n = len(values)
        ratio = np.sqrt(np.mean(np.square(values))) / sd
        assert abs(ratio - 1) < 4 * np.sqrt(1 / (2 * n)), (n, ratio)
