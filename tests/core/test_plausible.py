"""Diagnoses that name the likely cause: a closure of the wrong sign, a unit a thousand
times off either way, a load cell read too slowly; and silence on plausible sessions."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tissuecli.app.fit import fit_file
from tissuecli.core.plausible import unit_warnings
from tissuecli.core.terms import Law
from tissuecli.core.tissue import Tissue
from tissuecli.sim.synth import random_session


def _tissue(k: float, s: float, m: float) -> Tissue:
    return Tissue(Law.paper("x", "xdot"), K=k, S=s, M=m)


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    k=st.floats(100, 1300),
    s=st.floats(0.5, 10),
    m=st.floats(0.0, 0.1),
    bits=st.sampled_from([8, 12, 16]),
)
def test_a_plausible_session_gets_no_diagnosis(seed, k, s, m, bits) -> None:
    session, _ = random_session(
        _tissue(k, s, m), seed=seed, duration_s=4.0, bits=bits, force_range_n=(-1.0, 20.0)
    )
    assert unit_warnings(session) == []


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), k=st.floats(100, 1300))
def test_a_closure_of_the_wrong_sign_is_named(seed, k) -> None:
    session, _ = random_session(
        _tissue(k, 3.0, 0.05), seed=seed, duration_s=4.0, force_range_n=(-1.0, 20.0)
    )
    flipped = session.replace(session.time, session.force, -session.position)
    (warning,) = unit_warnings(flipped)
    assert "the force falls as the jaws close" in warning and "sign reversed" in warning


def test_the_sign_diagnosis_names_the_units_to_pass(tmp_path) -> None:
    """A closure logged in degrees of a jaw angle, read with --units position=-deg:
    the fit finds no stiffness, and the warning says to pass deg."""
    session, _ = random_session(_tissue(350.0, 3.0, 0.05), seed=3, duration_s=6.0, bits=16)
    # the jaw angle of 20 mm jaws whose tips are `closure` closer than at rest
    angle = np.degrees(2 * np.arcsin((10e-3 - session.position) / 40e-3))
    path = tmp_path / "grasp.csv"
    np.savetxt(path, np.column_stack([session.time, session.force, angle]), delimiter=",",
               header="time,force,angle", comments="")  # fmt: skip
    outcome = fit_file(path, reading={"units": "position=-deg", "jaw_length_m": 0.02},
                       forms="paper")  # fmt: skip
    text = "\n".join(outcome.warnings)
    assert "the force falls as the jaws close" in text, text
    assert "pass --units position=deg" in text, text


@pytest.mark.parametrize(
    ("scale", "column", "words"),
    [
        (1e-3, "position", "the jaw closure spans only"),
        (1e-3, "force", "the force varies by only"),
        (1e3, "position", "more than forceps jaws open"),
        (1e3, "force", "more than a grasp"),
    ],
)
def test_a_unit_a_thousand_times_off_is_named(scale, column, words) -> None:
    session, _ = random_session(_tissue(350.0, 3.0, 0.05), seed=5, duration_s=4.0)
    force = session.force * (scale if column == "force" else 1)
    position = session.position * (scale if column == "position" else 1)
    warnings = unit_warnings(session.replace(session.time, force, position))
    assert len(warnings) == 1 and words in warnings[0], warnings
    assert f"--units {column}" in warnings[0]


@pytest.mark.parametrize("every", [2, 3, 4, 10])
def test_a_load_cell_read_slowly_names_its_rate(every: int) -> None:
    session, _ = random_session(_tissue(350.0, 3.0, 0.05), seed=7, duration_s=4.0)
    held = np.repeat(session.force[::every], every)[: len(session)]
    (warning,) = unit_warnings(session.replace(session.time, held, session.position))
    assert f"every {every} samples ({1000 / every:.4g} Hz, against 1000 Hz)" in warning


def test_repeated_samples_of_both_channels_are_not_a_slow_load_cell() -> None:
    session, _ = random_session(_tissue(350.0, 3.0, 0.05), seed=7, duration_s=4.0)
    f = np.repeat(session.force[::4], 4)[: len(session)]
    x = np.repeat(session.position[::4], 4)[: len(session)]
    assert unit_warnings(session.replace(session.time, f, x)) == []
