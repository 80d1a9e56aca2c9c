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
    assert pred.r2 > 0.99
    # the band is the posterior predictive: about 95 % inside. Residuals are correlated
    # over ~30 samples, so ~250 independent draws: 0.90-0.99 holds with P > 0.999
    assert 0.90 <= pred.inside <= 0.99, pred.inside
    assert pred.rms_n < 1.5 * sd


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
