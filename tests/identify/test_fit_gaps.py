"""fit says what it knows: time gaps anywhere, of any length, fit or are refused with a
reason; the noise integral works whatever the residual; incomplete and lossy recordings
are warned about and recorded in the parameter file."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tissuecli.cli import cli
from tissuecli.core.errors import TissueError
from tissuecli.core.session import Session
from tissuecli.core.tissue import DEFAULT_TISSUE
from tissuecli.formats.params import document
from tissuecli.formats.sessions import write_session
from tissuecli.identify import fit_session
from tissuecli.identify.outcome import recording_state, session_warnings
from tissuecli.identify.posterior import ExactPosterior, Prior, SufficientStats
from tissuecli.sim.synth import random_session

RATE = 1000.0
N = 5000  # 5 s: where a noise-free session used to crash for most gap positions


def _clean_session() -> Session:
    """Noise-free: the force is the law of a smooth closure (derivatives by differences),
    so the filtered residual is rounding, far below the noise prior's 1e-12 N floor."""
    t = np.arange(N) / RATE
    x = 0.005 * (1 - np.cos(2 * np.pi * 0.7 * t)) + 0.001 * np.sin(2 * np.pi * 2.3 * t)
    v = np.gradient(x, t)
    a = np.gradient(v, t)
    return Session(t, 350.0 * x + 3.0 * v + 0.05 * a, x, name="clean")


CLEAN = _clean_session()
NOISY = random_session(DEFAULT_TISSUE, rate_hz=RATE, seed=3, duration_s=N / RATE)[0]


@settings(
    max_examples=120,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow],
)
@given(
    st.sampled_from(["clean", "noisy"]),
    st.integers(1, N - 1),
    st.floats(-3.5, 1.5),  # gap of 0.3 ms (within a period's jitter) to 30 s
    st.booleans(),  # on the sample grid or off it
    st.sampled_from(["bayes", "pinv", "both"]),
)
def test_one_time_gap_anywhere_fits_or_is_refused_with_a_reason(
    which, pos, log_gap, on_grid, method
):
    base = CLEAN if which == "clean" else NOISY
    gap = 10**log_gap
    if on_grid:
        gap = round(gap * RATE) / RATE
    t = base.time.copy()
    t[pos:] += gap
    session = Session(t, base.force, base.position, meta=base.meta, adc=base.adc)
    try:
        out = fit_session(session, forms="x,xdot", method=method)
    except TissueError as exc:  # FitError or InputError: one line with the reason
        assert "\n" not in str(exc)
        return
    if out.bayes is not None:
        post = out.bayes.best_.posterior
        assert np.all(np.isfinite(post.mean)) and np.all(np.isfinite(post.ci95))
        if which == "noisy":
            # an honest posterior: K within 5 SDs of the truth whatever was cut out
            assert abs(post.mean[0] - 350.0) < 5 * post.sd[0], (pos, gap, post.mean, post.sd)
        else:
            # differences for v and a are not the filter's derivatives: K to 0.1 %
            assert abs(post.mean[0] / 350.0 - 1) < 1e-3, (pos, gap, post.mean)
    if out.pinv is not None:
        assert np.all(np.isfinite(out.pinv.params_))


def test_the_noise_integral_works_below_and_above_the_priors_range():
    """The root cause: a least-squares noise level outside [sigma_lo, sigma_hi] gave a
    quadrature grid that ran backwards, NaN weights and an einsum error."""
    rng = np.random.default_rng(0)
    A = rng.normal(size=(500, 3)) * 1e-6
    beta = np.array([1.0, 2.0, 3.0])
    prior = Prior(np.array([10.0, 10.0, 10.0]))
    exact = ExactPosterior(SufficientStats.from_data(A, A @ beta), prior)  # residual ~1e-22 N
    assert np.all(np.isfinite(exact.weights))
    post = exact.summary(rng)
    np.testing.assert_allclose(post.mean, beta, rtol=1e-6)
    assert prior.sigma_lo <= post.sigma_mean < 2 * prior.sigma_lo
    loud = rng.normal(0.0, 1e12, 500)  # residual 1e12 N, above the 1e9 N ceiling
    post = ExactPosterior(SufficientStats.from_data(A, loud), prior).summary(rng)
    assert np.all(np.isfinite(post.mean)) and post.sigma_mean <= prior.sigma_hi


def test_a_noise_free_session_is_said_to_be_one():
    t = CLEAN.time.copy()
    t[2500:] += 0.5
    out = fit_session(Session(t, CLEAN.force, CLEAN.position), forms="x,xdot")
    assert any("looks noise-free" in w for w in out.warnings), out.warnings


# --------------------------------------------------------------------------- recordings


def _recorded(meta: dict) -> Session:
    s = random_session(DEFAULT_TISSUE, rate_hz=RATE, seed=1, duration_s=3.0)[0]
    return Session(s.time, s.force, s.position, name="rec", meta=meta, adc=s.adc)


def test_incomplete_and_lossy_sessions_are_warned_about_and_recorded():
    meta = {"complete": np.bool_(False), "frames_lost": np.int64(12), "frames_bad": 3}
    meta["stop_reason"] = "x" * 500
    out = fit_session(_recorded(meta), forms="x,xdot")
    warnings = out.warnings
    assert warnings[0].startswith("session 'rec' is incomplete: its recording never closed")
    assert len(warnings[0]) < 300  # a long stop reason is cut short
    assert warnings[1].startswith("the recording lost 12 frame(s) and rejected 3 corrupt")
    doc = document(out)
    assert doc["warnings"][:2] == warnings[:2]
    assert {k: doc["data"][k] for k in ("complete", "frames_lost", "frames_bad")} == {
        "complete": False,
        "frames_lost": 12,
        "frames_bad": 3,
    }
    json.dumps(doc, allow_nan=False)


@pytest.mark.parametrize(
    ("meta", "complete"),
    [({"complete": True, "frames_lost": 0, "frames_bad": 0}, True), ({}, None)],
)
def test_complete_clean_and_unknown_sessions_get_no_recording_warning(meta, complete):
    session = _recorded(meta)
    assert session_warnings(session) == []
    assert recording_state(session) == {
        "complete": complete,
        "frames_lost": 0,
        "frames_bad": 0,
        "stop_reason": "",
    }


def test_fit_command_warns_about_a_crashed_recording(tmp_path: Path):
    h5, out = tmp_path / "grasp.h5", tmp_path / "fit.json"
    write_session(h5, _recorded({"tissue": "liver"}))
    with h5py.File(h5, "r+") as f:  # what a recorder killed mid-session leaves
        f["sessions/rec"].attrs["complete"] = False
        f["sessions/rec"].attrs["frames_lost"] = 4
    result = CliRunner().invoke(cli, ["fit", str(h5), "--forms", "x,xdot", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "warning: session 'rec' is incomplete" in result.output
    assert "warning: the recording lost 4 frame(s)" in result.output
    data = json.loads(out.read_text())["data"]
    assert data["complete"] is False and data["frames_lost"] == 4


# --------------------------------------------------------------------------- adaptive logging


class _RampHold:
    """Raised-cosine ramps of ``ramp_s`` to each level, each held ``hold_s``: a tensile
    or relaxation test."""

    def __init__(self, levels: list[float], ramp_s: float, hold_s: float) -> None:
        self.levels, self.ramp_s, self.hold_s = np.asarray(levels), ramp_s, hold_s

    def ramping(self, t: np.ndarray) -> np.ndarray:
        return np.mod(t, self.ramp_s + self.hold_s) < self.ramp_s

    def kinematics(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = np.asarray(t, float)
        i = np.minimum((t // (self.ramp_s + self.hold_s)).astype(int), self.levels.size - 1)
        u, r = t - i * (self.ramp_s + self.hold_s), self.ramp_s
        start = np.concatenate([[0.5e-3], self.levels[:-1]])[i]
        d = self.levels[i] - start
        phase = np.pi * np.minimum(u, r) / r
        on = u < r
        x = start + d * (1 - np.cos(phase)) / 2
        v = np.where(on, d * np.pi / (2 * r) * np.sin(phase), 0.0)
        a = np.where(on, d * np.pi**2 / (2 * r**2) * np.cos(phase), 0.0)
        return x, v, a


def _adaptive(hold_s: float, jitter_s: float, seed: int) -> Session:
    """A relaxing tissue logged every 10 ms while the jaws move and every 100 ms while
    they hold, as event-driven loggers do; stamps jittered by up to ``jitter_s``."""
    from tissuecli.sim.families import FAMILIES
    from tissuecli.sim.synth import ForcepsModel, Sensors, synthesize

    op = _RampHold([2e-3, 4e-3, 6e-3, 3e-3], 1.0, hold_s)
    model = ForcepsModel(
        tissue=FAMILIES["one branch"], operator=op, seed=seed, sensors=Sensors(bits=12)
    )
    s, _ = synthesize(model, 4 * (1.0 + hold_s))
    keep, last = [], -1.0
    for i, ti in enumerate(s.time):
        if ti - last >= (0.01 if op.ramping(ti) else 0.1) - 1e-9:
            keep.append(i)
            last = ti
    k = np.array(keep)
    t = s.time[k] + np.random.default_rng(seed).uniform(0, jitter_s, k.size)
    return Session(np.round(t, 4), s.force[k], s.position[k], name="adaptive")


@pytest.mark.parametrize(
    ("hold_s", "jitter_s"),
    [(4.0, 0.0), (10.0, 1e-3)],  # ramps or holds the most samples; a clock or PC stamps
)
def test_slowly_logged_holds_are_resampled_not_dropped(hold_s: float, jitter_s: float) -> None:
    """Half the samples, and all the relaxation, were left out as gaps; now the holds
    are fitted, and the posterior is honest (every coefficient within 4 SDs)."""
    session = _adaptive(hold_s, jitter_s, seed=1)
    out = fit_session(session, forms="x+maxwell+xdot+xddot", hold_out=0.3)
    est = out.bayes
    t = est.kinematics_.time
    covered = np.ptp(t) / np.ptp(session.time)
    assert covered > 0.65, covered  # 70 % fitted, less the filter's edges
    holes = 1.0 - t.size / (np.ptp(t) / np.median(np.diff(t)) + 1)
    assert holes < 0.02, holes  # the filtered samples run through the holds
    assert any("logged slowly" in w for w in out.warnings), out.warnings
    post = est.best_.posterior
    z = np.abs(post.mean - np.array([300.0, 150.0 + 50.0, 2.0, 0.05])) / post.sd
    assert np.all(z <= 4.0), (post.mean, post.sd)
    assert out.validation is not None and out.validation.r2_held_out > 0.99


def test_a_burst_of_lost_frames_is_still_a_gap() -> None:
    """Lost frames are a hole, whatever their number; only a rhythm of slow steps is a
    stretch logged slowly."""
    from tissuecli.identify.prepare import on_grid, slow_steps

    assert not slow_steps(np.array([1, 1, 40, 1, 1, 2, 1, 1.0])).any()
    assert slow_steps(np.array([1, 1, 10, 10, 10, 11, 1, 1.0]))[2:6].all()
    t = NOISY.time.copy()
    t[2000:] += 0.5
    grid = on_grid(Session(t, NOISY.force, NOISY.position))
    assert grid is not None and not grid.slow.any() and (~grid.measured).sum() == 500
