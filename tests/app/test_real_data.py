"""Every recording of data/ imports and fits with the commands docs/real-data.md gives
(data/recordings.json), and what that page says of each fit holds."""

from __future__ import annotations

import multiprocessing
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

import real_data  # noqa: E402

ENTRIES = {e["file"]: e for e in real_data.manifest()}


def _run_in(work: Path, entry: dict[str, Any]) -> dict[str, Any]:
    """One recording's import and fit in a folder of its own (its params.json too)."""
    where = work / Path(entry["file"]).stem
    where.mkdir()
    return real_data.run(entry, where)


@pytest.fixture(scope="module")
def fitted(tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict[str, Any]]:
    """Every recording imported and fitted as the page says, two at a time: the fits
    are independent and each keeps one core busy, so a 2-core machine halves the wait."""
    work = tmp_path_factory.mktemp("real")
    spawn = multiprocessing.get_context("spawn")  # no fork of this process's threads
    with ProcessPoolExecutor(max_workers=2, mp_context=spawn) as pool:
        docs = pool.map(_run_in, [work] * len(ENTRIES), ENTRIES.values())
        return dict(zip(ENTRIES, docs, strict=True))


def test_every_file_in_data_has_commands_and_a_note() -> None:
    data = real_data.DATA
    recordings = {
        p.name for p in data.iterdir() if p.suffix.lower() in (".txt", ".csv", ".tsv", ".mat")
    }
    assert recordings == set(ENTRIES)
    for name, entry in ENTRIES.items():
        note = data / (Path(name).stem + ".md")
        assert note.exists(), f"{name} has no provenance note"
        assert entry["measured"] == ("## Licence" in note.read_text()), name


@pytest.mark.parametrize("name", [n for n, e in ENTRIES.items() if not e["measured"]])
def test_simulated_recordings_give_back_their_truth(fitted, name: str) -> None:
    """The posterior mean within 4 posterior SDs of the truth (P = 6e-5 each if calibrated)."""
    doc, truth = fitted[name], ENTRIES[name]["truth"]
    assert doc["law"]["name"] == truth["law"]
    for term in doc["law"]["terms"]:
        z = abs(term["mean"] - truth[term["symbol"]]) / term["sd"]
        assert z <= 4.0, (term["symbol"], term["mean"], truth[term["symbol"]])
    assert doc["validation"]["r2_held_out"] > 0.99


def test_every_fit_reports_finite_figures(fitted) -> None:
    for name, doc in fitted.items():
        v = doc["validation"]
        assert all(np.isfinite([v["r2_fitted"], v["r2_held_out"], v["rms_N"]])), name
        assert all(np.isfinite(t["mean"]) and t["sd"] > 0 for t in doc["law"]["terms"]), name
        assert "Traceback" not in doc["output"]


def test_the_da_vinci_rig_is_explained_by_friction_and_preload(fitted) -> None:
    doc = fitted["davinci_instrument_L4_45_first10s.TXT"]
    terms = {t["symbol"]: t for t in doc["law"]["terms"]}
    assert doc["validation"]["r2_held_out"] > 0.9
    assert terms["Fc"]["mean"] > 3 * terms["Fc"]["sd"]  # dry friction, resolved
    assert terms["F0"]["mean"] > 3 * terms["F0"]["sd"]  # the preload


def test_the_phantom_law_fits_its_range_and_does_not_extrapolate(fitted) -> None:
    v = fitted["phantom_EF30_0T_A1.csv"]["validation"]
    assert v["r2_fitted"] > 0.99 and v["r2_held_out"] < 0.5


@pytest.mark.parametrize("name", ["meniscus_punch_slow_1824.txt", "paper_punch_slow_1819.txt"])
def test_a_cutting_punch_is_not_a_tissue_law(fitted, name: str) -> None:
    """Finger force on a punch's handle while it cuts: the law explains little of it, and
    the fit says so (R^2 well below 1, worse on held-out cuts)."""
    doc = fitted[name]
    v = doc["validation"]
    assert v["r2_fitted"] < 0.5 and v["r2_held_out"] < v["r2_fitted"]
    # the held-out cuts are predicted worse than by their own mean force...
    assert v["rms_N"] > v["force_sd_N"]
    # ...and the fit does not hide it: the force noise it infers is of the order of the
    # force's own spread, not a sensor's floor
    assert doc["noise"]["sd"] > 0.5 * v["force_sd_N"]
    # The fitted R^2 is not bounded below by 0: it is scored against the force's mean,
    # which a law without an offset does not have. F = K x is the meniscus's choice once
    # relaxation branches are held across free jaws: no branch then fits the cuts, the
    # residuals of the best law left leave 13 effective samples, and no richer law earns
    # its place (dry friction and an offset are 0.8 nats behind). At its least-squares K
    # it is at R^2
    # -0.55 (K = 0 is at -6.1) and predicts the held-out cuts better than the old law
    # (RMS 1.34 N against 1.68 N). Coefficients that did not belong to the bound law's
    # shape put the fitted R^2 at -1.5: keep above -1.
    assert v["r2_fitted"] > -1.0
