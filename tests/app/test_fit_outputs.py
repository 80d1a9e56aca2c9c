"""What a fit exports besides its parameter file: the chosen law's posterior draws and
the structure probabilities (CSV, for pandas and ArviZ), the report's plots as files,
and a notebook's view of the result."""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from tissuecli.app.fit import fit_file
from tissuecli.core.errors import InputError
from tissuecli.formats.sessions import write_session
from tissuecli.sim.synth import ForcepsModel, synthesize

from ..conftest import assert_clean_error, tissuecli_here

MAGIC = {"png": b"\x89PNG\r\n\x1a\n", "pdf": b"%PDF-", "svg": b"<?xml"}


@pytest.fixture(scope="module")
def grasp(tmp_path_factory: pytest.TempPathFactory) -> Path:
    s, _ = synthesize(ForcepsModel(seed=8), 4.0)
    s.name = "s"
    path = tmp_path_factory.mktemp("g") / "g.h5"
    write_session(path, s)
    return path


@pytest.fixture(scope="module")
def exported(grasp: Path, tmp_path_factory: pytest.TempPathFactory):
    root = tmp_path_factory.mktemp("out")
    outcome = fit_file(grasp, draws=root / "draws.csv", plots=root / "plots",
                       plot_format="svg")  # fmt: skip
    return outcome, root


def test_the_draws_are_the_chosen_laws_posterior_with_units(exported) -> None:
    outcome, root = exported
    best = outcome.bayes.best_
    frame = pd.read_csv(root / "draws.csv")
    symbols = [f"{t.symbol} [{t.unit}]" for t in best.model.terms]
    assert list(frame.columns) == ["chain", "draw", *symbols, "sigma [N]"]
    draws = frame[[*symbols, "sigma [N]"]].to_numpy()
    np.testing.assert_array_equal(draws, best.posterior.samples)  # every digit kept
    # their means are the posterior's, within a few Monte Carlo errors
    se = best.posterior.sd / np.sqrt(len(frame))
    assert np.all(np.abs(draws[:, :-1].mean(axis=0) - best.posterior.mean) < 5 * se + 1e-12)
    assert (frame["draw"] == np.arange(len(frame))).all()


def test_the_structure_probabilities_sum_to_one_and_name_the_chosen_law(exported) -> None:
    outcome, root = exported
    table = pd.read_csv(root / "draws.structures.csv")
    assert list(table["law"]) == [r.name for r in outcome.bayes.results_]
    assert table["probability"].sum() == pytest.approx(1.0, abs=1e-9)
    assert list(table.loc[table["chosen"] == "yes", "law"]) == [outcome.bayes.best_.name]
    assert set(table["method"]) <= {"exact", "emcee", "skipped"}


def test_the_plots_are_written_as_files_in_the_format_asked(exported) -> None:
    _, root = exported
    files = sorted((root / "plots").iterdir())
    names = [f.name for f in files]
    assert {"plot-time.svg", "plot-loop.svg", "plot-residuals.svg", "plot-corner.svg"} <= set(names)
    for f in files:
        assert f.read_bytes().startswith(MAGIC["svg"]), f


@pytest.mark.parametrize("fmt", ["png", "pdf"])
def test_plot_format_alone_puts_the_plots_beside_the_report(grasp, tmp_path, fmt) -> None:
    result = tissuecli_here("fit", str(grasp), "--report", str(tmp_path / "r.html"),
                       "--plot-format", fmt, "--forms", "paper")  # fmt: skip
    assert result.returncode == 0, result.stderr
    folder = tmp_path / "r_plots"
    assert f"plots written to {folder}" in result.stdout
    time_plot = folder / f"plot-time.{fmt}"
    assert time_plot.read_bytes().startswith(MAGIC[fmt])


def test_exports_never_overwrite_and_are_checked_before_the_fit(grasp, tmp_path) -> None:
    (tmp_path / "d.structures.csv").write_text("mine\n")
    result = tissuecli_here("fit", str(grasp), "--draws", str(tmp_path / "d.csv"))
    assert_clean_error(result, "--draws", "d.structures.csv exists")
    assert (tmp_path / "d.structures.csv").read_text() == "mine\n"
    assert not (tmp_path / "d.csv").exists()
    (tmp_path / "p").mkdir()
    (tmp_path / "p" / "plot-loop.png").write_text("mine\n")
    result = tissuecli_here("fit", str(grasp), "--plots", str(tmp_path / "p"))
    assert_clean_error(result, "plot-loop.png exists")
    result = tissuecli_here("fit", str(grasp), "--plot-format", "svg")
    assert_clean_error(result, "--plot-format needs --plots DIR or --report FILE")
    with pytest.raises(InputError, match="--draws needs the Bayesian fit"):
        fit_file(grasp, draws=tmp_path / "x.csv", method="pinv", forms="x,xdot")
    assert not (tmp_path / "x.csv").exists()


def test_the_notebook_view_shows_the_law_its_coefficients_and_warnings(exported) -> None:
    outcome, _ = exported
    view = outcome._repr_html_()
    best = outcome.bayes.best_
    assert f"<b>{html.escape(best.name)}</b>" in view
    for j, t in enumerate(best.model.terms):
        assert f"<td>{t.symbol}</td>" in view and f"{best.posterior.mean[j]:.6g}" in view
    for w in outcome.warnings:
        assert html.escape(w) in view
    assert "<script" not in view
