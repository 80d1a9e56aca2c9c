"""A stored session longer than memory allows is fitted from streamed sums, and says so."""

from __future__ import annotations

import json

import pytest

from tissuecli.app import fit as fit_app
from tissuecli.formats.sessions import write_session
from tissuecli.sim.synth import ForcepsModel, synthesize


def test_a_long_session_is_streamed_and_written(tmp_path, monkeypatch) -> None:
    session, _ = synthesize(ForcepsModel(seed=5), 40.0)
    session.name = "long"
    path = tmp_path / "long.h5"
    write_session(path, session)
    monkeypatch.setattr(fit_app, "STREAM_ABOVE", 20_000)
    monkeypatch.setattr(fit_app, "STREAM_PILOT", 15_000)
    monkeypatch.setattr(fit_app, "STREAM_BLOCK", 10_000)
    out = tmp_path / "tissue.json"
    outcome = fit_app.fit_file(path, out=out, forms="paper", report=tmp_path / "r.html")
    lines = fit_app.summary_lines(outcome)
    assert "40,000 samples" in lines[0] and "streamed block by block" in lines[0]
    assert any("too many to hold" in w for w in outcome.bayes.warnings_)
    params = json.loads(out.read_text())
    assert params["law"]["name"] == outcome.bayes.best_.name
    assert (tmp_path / "r.html").stat().st_size > 0
    # the truth of the simulated forceps (K = 350 N/m) within four posterior SDs
    k = outcome.bayes.best_.model.symbols.index("K")
    post = outcome.bayes.best_.posterior
    assert post.mean[k] == pytest.approx(350.0, abs=4 * post.sd[k])


def test_options_only_the_full_fit_gives_keep_it(tmp_path, monkeypatch) -> None:
    session, _ = synthesize(ForcepsModel(seed=6), 25.0)
    session.name = "s"
    path = tmp_path / "s.h5"
    write_session(path, session)
    monkeypatch.setattr(fit_app, "STREAM_ABOVE", 10_000)
    outcome = fit_app.fit_file(path, forms="paper", hold_out=0.2)
    assert "streamed" not in outcome.session.meta
    assert outcome.validation is not None
