"""``tissuecli predict``: a fitted law's force for a grasp it was not fitted to, with a
95 % predictive band that holds about 95 % of the measured force."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from tissuecli import formats
from tissuecli.cli import cli
from tissuecli.core.session import Session
from tissuecli.core.terms import Law
from tissuecli.core.tissue import DEFAULT_TISSUE, Tissue
from tissuecli.formats.params import read_fitted, tissue_to_dict
from tissuecli.identify import fit_session
from tissuecli.identify.predict import predict_band
from tissuecli.sim.synth import random_session

from ..conftest import assert_clean_error

SLS = Tissue(Law.of(["x", "maxwell", "xdot", "xddot"]).bind({"tau1": 0.5}), 300.0, 200.0, 2.0, 0.05)


def _fitted(tmp_path: Path, tissue: Tissue, forms: str) -> Path:
    s, _ = random_session(tissue, seed=1, duration_s=8.0, bits=12)
    path = tmp_path / "fit.json"
    formats.write_params(path, fit_session(s, forms=forms))
    return path


@pytest.mark.parametrize(
    ("tissue", "forms"), [(DEFAULT_TISSUE, "x+xdot+xddot"), (SLS, "x+maxwell+xdot+xddot")]
)
def test_a_fitted_law_predicts_another_grasp_within_its_band(tmp_path, tissue, forms) -> None:
    params = _fitted(tmp_path, tissue, forms)
    fitted, cov, sd = read_fitted(params)
    assert cov is not None and cov.shape == (len(fitted.law.terms),) * 2 and sd is not None
    other, _ = random_session(tissue, seed=7, duration_s=8.0, bits=12)  # another grasp
    pred = predict_band(fitted, other, cov=cov, noise_sd=sd)
    assert pred.r2 > 0.99 and pred.count == len(other)  # every sample
    np.testing.assert_array_equal(pred.force, other.force)  # as measured
    # the band is the posterior predictive: about 95 % inside (the measured force's
    # noise is white here: 8000 nearly independent draws)
    assert 0.92 <= pred.inside <= 0.98, pred.inside
    # against the force as measured, what is left is its noise: 5 mN and the 12-bit
    # step's 0.42 mN, less what the law's smooth estimate shares of it
    assert pred.rms_n < 1.1 * np.hypot(5e-3, 6.0 / 4096 / np.sqrt(12))
    # filtered as in a fit, the residual is the fit's
    filt = predict_band(fitted, other, cov=cov, noise_sd=sd, filtered=True)
    assert filt.time.size == len(other) and np.isnan(filt.predicted[0])
    assert filt.rms_n < 1.5 * sd and 0.90 <= filt.inside <= 0.99


def test_the_cli_writes_the_band_as_csv_and_refuses_to_destroy(tmp_path: Path) -> None:
    params = _fitted(tmp_path, DEFAULT_TISSUE, "x+xdot+xddot")
    data = tmp_path / "g.h5"
    formats.write_session(data, random_session(DEFAULT_TISSUE, seed=9, duration_s=5.0)[0])
    out = tmp_path / "pred.csv"
    r = CliRunner().invoke(cli, ["predict", str(params), str(data), "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert "inside the 95 % band" in r.output
    lines = out.read_text().splitlines()
    assert lines[0].startswith("# ") and lines[1] == "time,force_pred,force_lo,force_hi,force"
    table = np.loadtxt(out, delimiter=",", skiprows=2)
    assert table.shape == (5000, 5)  # a row per sample
    assert np.all(table[:, 2] <= table[:, 1]) and np.all(table[:, 1] <= table[:, 3])
    before = out.read_bytes()
    assert_clean_error(
        CliRunner().invoke(cli, ["predict", str(params), str(data), "--out", str(out)]),
        "exists",
    )
    assert out.read_bytes() == before
    assert_clean_error(
        CliRunner().invoke(cli, ["predict", str(params), str(data), "--out", str(params)]),
        "input",
    )


def test_a_file_without_uncertainty_gives_the_law_alone(tmp_path: Path) -> None:
    path = tmp_path / "t.json"
    path.write_text(json.dumps(tissue_to_dict(DEFAULT_TISSUE)))
    tissue, cov, sd = read_fitted(path)
    assert cov is None and sd is None
    s, _ = random_session(DEFAULT_TISSUE, seed=3, duration_s=4.0)
    pred = predict_band(tissue, s)
    np.testing.assert_array_equal(pred.lower, pred.predicted)


@pytest.mark.parametrize(
    ("cov", "message"),
    [([[1.0]], "3 x 3 array"), ([[1, 2, 0], [0, 1, 0], [0, 0, 1]], "symmetric"),
     ([[1, 0, 0], [0, "x", 0], [0, 0, 1]], "cov")],
)  # fmt: skip
def test_a_bad_covariance_is_refused_by_name(tmp_path: Path, cov, message: str) -> None:
    doc = tissue_to_dict(DEFAULT_TISSUE)
    doc["law"]["cov"] = cov
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc))
    data = tmp_path / "g.h5"
    formats.write_session(data, random_session(DEFAULT_TISSUE, seed=9, duration_s=3.0)[0])
    r = CliRunner().invoke(cli, ["predict", str(path), str(data), "--out", str(tmp_path / "p")])
    assert_clean_error(r, message)


def test_a_sample_inside_a_gap_is_nan_and_every_other_is_predicted() -> None:
    s, _ = random_session(DEFAULT_TISSUE, seed=4, duration_s=6.0)
    t = s.time.copy()
    t[3000:] += 0.4  # 400 samples missing
    gappy = Session(t, s.force, s.position, name="gappy")
    pred = predict_band(DEFAULT_TISSUE, gappy)
    assert pred.predicted.size == len(gappy)
    lost = ~np.isfinite(pred.predicted)
    # only the samples whose widest smoother window (of the three derivatives', each
    # chosen on the force: here at most 0.3 s) reaches into the gap
    assert 0 < lost.sum() < 300 and np.all((t[lost] > 2.85) & (t[lost] < 3.55))


#: families with the law's coefficients, fitted on one session and predicted on the
#: held-out end of another with a different operator
FLOOR_FAMILIES = ["paper x+xdot", "paper x^3+xdot^2", "Hunt-Crossley", "two branches"]


@pytest.mark.parametrize("family", FLOOR_FAMILIES)
def test_the_prediction_is_as_close_to_the_true_force_as_a_smoother_of_the_measured_one(
    family: str,
) -> None:
    """The measure a user can check: the predicted force against the true (noise-free)
    force, over the held-out part, within 1.5 times the error of a Savitzky-Golay
    smoother of the measured force (its noise floor, with the window the kinematics use).
    The filtered prediction (what predict wrote before) is 4-6 times that floor."""
    from scipy.signal import savgol_filter

    from tissuecli.identify.derivatives import SavitzkyGolay
    from tissuecli.sim.families import FAMILIES

    tissue = FAMILIES[family]
    s, model = random_session(tissue, seed=1, duration_s=10.0, bits=12)
    forms = "+".join(t.name for t in tissue.law.terms)
    best = fit_session(s, forms=forms, hold_out=0.3).bayes.best_
    fitted = Tissue(best.model, *best.posterior.mean)
    truth = model.truth(np.arange(len(s)))[3]
    after = s.time >= s.time[int(0.7 * len(s))]
    pred = predict_band(fitted, s)
    error = np.sqrt(np.mean((pred.predicted[after] - truth[after]) ** 2))
    w = SavitzkyGolay().kernels(s.position, float(np.median(np.diff(s.time))))[0][0].size
    floor = np.sqrt(np.mean((savgol_filter(s.force, w, 3)[after] - truth[after]) ** 2))
    assert error <= 1.5 * floor, (error, floor)
    filtered = predict_band(fitted, s, filtered=True).predicted[after]
    known = np.isfinite(filtered)
    assert np.sqrt(np.mean((filtered[known] - truth[after][known]) ** 2)) > 2 * floor


def test_a_hold_at_constant_position_is_predicted_not_refused() -> None:
    """Jaws held still after a squeeze: nothing to identify, but a law with memory has
    a force to give, the relaxation, and predict gives it, filtered or not."""
    t = np.arange(4000) / 1000.0
    x = np.where(t < 1.0, 4e-3 * np.sin(np.pi * np.minimum(t, 1.0) / 2) ** 2, 4e-3)
    truth = SLS.force(x, np.gradient(x, t), np.gradient(np.gradient(x, t), t), dt=1e-3)
    held = t >= 1.5
    hold = Session(t[held], truth[held], x[held], name="hold")
    assert np.ptp(hold.position) == 0.0  # the premise
    for filtered in (False, True):
        pred = predict_band(SLS, hold, filtered=filtered)
        # filtered, the fit's wide filter trims both edges of the hold
        assert pred.count > (0.5 if filtered else 0.9) * len(hold)


def _savgol_floor(measured: np.ndarray, truth: np.ndarray) -> float:
    """RMS error against ``truth`` of the best cubic Savitzky-Golay smoother of
    ``measured`` (the generalisation benchmark's noise floor)."""
    from scipy.signal import savgol_filter

    top = max(5, measured.size // 3)
    windows = sorted({int(w) | 1 for w in np.geomspace(5, top, 24)} - {1, 3})
    return min(
        float(np.sqrt(np.mean((savgol_filter(measured, w, 3, mode="interp") - truth) ** 2)))
        for w in windows
        if w <= measured.size
    )

def _true_law_held_out(seed: int) -> tuple[float, float]:
    """A random scene of a family beyond the paper's (at most 10,000 samples): the RMS
    error (N) of its true law through ``predict_band`` on the last 30 %, the smoothers
    tuned on the rest, against the true force, and that part's Savitzky-Golay floor."""
    from tissuecli.sim.scenes import FAMILIES, random_scene

    other = [f for f in FAMILIES if not f.startswith("paper")]
    scene = random_scene(seed, families=other, max_samples=10_000)
    s = scene.session
    i0 = int(np.searchsorted(s.time, s.time[0] + 0.7 * (s.time[-1] - s.time[0])))
    tune = np.arange(len(s)) < i0
    predicted = predict_band(scene.tissue, s, tune=tune).predicted[i0:]
    truth = scene.force[i0:]
    rms = float(np.sqrt(np.mean((predicted - truth) ** 2)))
    return rms, _savgol_floor(s.force[i0:], truth)


@pytest.mark.parametrize(("seed", "bound"), [(5150127, 1.5), (5150013, 1.5), (5150018, 2.5)])
def test_the_true_law_predicts_a_held_out_end_that_ends_in_a_grasp(seed: int, bound: float) -> None:
    """Grasp sessions (two branches, hardening, Hunt-Crossley) whose held-out last 30 %
    ends in a grasp cut by the recording, or holds contact too weak or too short for a
    20 ms moving mean: the true law through ``predict_band`` lands within 1.5 times the
    Savitzky-Golay floor of the true force (11-18 times before: the contact read free
    there, and the tissue's force set to zero). The hardening session (9 bits, 8 %
    noise, 8.8 kHz) within 2.5: the foot of each fast release, under 3 noise SDs of
    force, is still read free (2.0 today)."""
    rms, floor = _true_law_held_out(seed)
    assert rms < bound * floor


@pytest.mark.parametrize("degree", [3, 5, 7])
def test_the_ends_carry_no_more_noise_than_the_centred_windows(degree: int) -> None:
    """At either end a window's polynomial is read off-centre, where a high degree
    amplifies noise most. On a quadratic closure every degree is unbiased and Lepski's
    rule at 3 SDs sets the lowest aside about 1 % of the time in all, those samples
    taking a noisier degree: over 400 draws the end samples' acceleration RMS error is
    0.9-1.2 times the centred estimate's noise SD for degrees 3, 5, 7. 40 draws know it
    to some 15 %, so 1.5 times; reading the chosen degree at the edge, as before, gave
    3.4, 4.9 and 8.0 times."""
    from tissuecli.identify.predict import _smoothed

    dt, w, sigma = 1e-3, 101, 1e-6
    t = np.arange(1000) * dt
    x = 2e-3 + 0.5 * 3.0 * (t - 0.4) ** 2  # acceleration 3 m/s^2 throughout
    rng = np.random.default_rng(3)
    end, centre_sd = [], 0.0
    for _ in range(40):
        a, gain = _smoothed(x + rng.normal(0.0, sigma, x.size), w, degree, 2, dt, sigma)
        end.append(np.concatenate([a[: w // 2], a[-(w // 2) :]]) - 3.0)
        centre_sd = sigma * gain
    rms = float(np.sqrt(np.mean(np.square(end))))
    assert rms <= 1.5 * centre_sd, (rms, centre_sd)
    # without position noise the chosen degree is kept: exact on its polynomial
    exact, _ = _smoothed(x, w, degree, 2, dt, 0.0)
    np.testing.assert_allclose(exact, 3.0, rtol=1e-6)


@pytest.mark.parametrize("degree", [3, 5])
def test_a_window_across_a_step_in_acceleration_bends_there(degree: int) -> None:
    """A closure sampled at 10 kHz whose acceleration steps by 20 m/s^2 between two
    samples (a squeeze that starts), under position noise of 10 nm: a centred window
    spreads the step over its width, so the samples within a half window of it miss
    the acceleration by a sixth to a quarter of the step in RMS (a ramp across the
    window). Bent at the break, they miss it by the noise of a hinged window: under
    2 % of the step (the break's place is known to a sample at this noise; its
    ambiguous sample apart). Away from the break the centred estimate stands, sample
    for sample."""
    from tissuecli.identify.predict import _smoothed

    dt, w, jump = 1e-4, 41, 20.0
    t = np.arange(1200) * dt
    tb = 0.06003  # between two samples
    x = 2e-3 + 1e-3 * t + 0.5 * jump * np.clip(t - tb, 0.0, None) ** 2
    a_true = np.where(t < tb, 0.0, jump)
    x = x + np.random.default_rng(5).normal(0.0, 1e-8, x.size)
    near = np.abs(t - tb) < (w // 2) * dt
    near[np.argmin(np.abs(t - tb))] = False  # the sample at the break: either side is right
    centred, _ = _smoothed(x, w, degree, 2, dt, 1e-8)
    bent, _ = _smoothed(x, w, degree, 2, dt, 1e-8, True)

    def rms(a: np.ndarray) -> float:
        return float(np.sqrt(np.mean((a[near] - a_true[near]) ** 2)))

    assert rms(centred) > 0.15 * jump
    assert rms(bent) < 0.02 * jump, rms(bent)
    far = np.abs(t - tb) > w * dt
    np.testing.assert_array_equal(bent[far], centred[far])


@pytest.mark.parametrize(
    ("seed", "was"),
    [(7265007, 1.71), (9820720, 1.62), (9820730, 5.26), (6630410, 2.50), (6630420, 2.34)],
)
def test_the_true_law_predicts_a_held_out_end_within_the_floor(seed: int, was: float) -> None:
    """Sessions whose held-out end was lost to the end windows, to the grasp detector
    or to the motion's breaks (``was``: the true law's held-out error over the
    Savitzky-Golay floor before): inertia at 2.5 and 6 kHz read off a degree-7 window's
    edge; a Hunt-Crossley tissue in contact throughout whose closure dips short of its
    contact point, read free by the detector with the small force past that point; and
    grasps at 6.7 kHz whose squeeze starts and stops with a step of 20 m/s^2 in
    acceleration, spread over the window by a centred one; and two relaxation branches
    in grasps whose loose part the detector reads free (54 % of the samples, where 33 %
    are), where a law with memory kept its tissue's force at zero. The true law through
    ``predict_band`` lands within the 1.5 times the floor the generalisation benchmark
    asks of a fit (0.98, 1.28, 0.12, 1.09 and 0.28 today)."""
    rms, floor = _true_law_held_out(seed)
    assert rms < 1.5 * floor, (rms, was)


@pytest.mark.parametrize(("seed", "was"), [(6630428, 8.95)])
def test_a_coarse_adcs_staircase_is_predicted_from_its_level_crossings(
    seed: int, was: float
) -> None:
    """friction+offset squeeze, 8 bits at 8.4 kHz: the closure holds each level some 12
    samples, a sawtooth no Savitzky-Golay window averages out, and the true law on
    those kinematics was ``was`` times the floor off the true force. Read through the
    level crossings (where that agrees better with the measured force) it lands within
    the 1.5 times the floor the benchmark asks of a fit (1.30 today)."""
    rms, floor = _true_law_held_out(seed)
    assert rms < 1.5 * floor, (rms / floor, was)


@pytest.mark.parametrize(("seed", "was"), [(6587724, 5.66), (6587716, 3.88)])
def test_a_grasps_loose_part_read_free_is_predicted_in_contact(seed: int, was: float) -> None:
    """friction+offset fast taps (8 bits, 654 Hz, 8 % noise) and friction grasps (9
    bits, 7.8 kHz) whose grasps spend much of their time a few noise SDs above the
    free-jaw level: the detector reads only their peaks in contact, and the tissue's
    force was set to the offset's on the rest (``was``: the true law's held-out error
    over the Savitzky-Golay floor). Over the samples read free, the closure past
    which the law's force explains them better than the offset's, by far more than
    noise can, is contact: the true law lands within the 1.5 times the floor the
    generalisation benchmark asks of a fit (0.39 and 1.39 today)."""
    rms, floor = _true_law_held_out(seed)
    assert rms < 1.5 * floor, (rms, was)


def test_a_bend_is_taken_only_where_it_agrees_clearly_better() -> None:
    """Two smoothers whose residuals differ by noise alone: the mean of 20 block means
    of the squared residuals' difference beats twice its standard error 2.8 % of the
    time (Student's t with 19 degrees of freedom), so of 400 such pairs at most 5.6 %
    (three binomial SDs above) may pass; a smoother whose residual is truly smaller
    (by half the noise's SD, one sample in two) passes almost always."""
    from tissuecli.identify.predict import _clearly_better

    rng = np.random.default_rng(11)
    passed = 0
    for _ in range(400):
        noise = rng.normal(0.0, 1.0, 2000)
        a = noise + rng.normal(0.0, 0.1, noise.size)
        b = noise + rng.normal(0.0, 0.1, noise.size)
        passed += _clearly_better(a, b)
    assert passed / 400 <= 0.056, passed
    noise = rng.normal(0.0, 1.0, 2000)
    worse = noise + np.where(np.arange(noise.size) % 2 == 0, 0.5, 0.0)
    assert _clearly_better(noise, worse)
    assert not _clearly_better(worse, noise)
