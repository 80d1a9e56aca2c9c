"""A long recording of another logger, fitted directly, is stored block by block as
`import` stores it and fitted from streamed sums, as a long stored session is."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tissuecli.app import fit as fit_app
from tissuecli.sim.synth import ForcepsModel, synthesize


def _csv(path: Path, seconds: float, seed: int) -> Path:
    session, _ = synthesize(ForcepsModel(seed=seed), seconds)
    rows = np.c_[session.time * 1e3, session.force, session.position * 1e3]
    np.savetxt(path, rows, fmt="%.9g", delimiter=",", header="t_ms,force_N,closure_mm",
               comments="")  # fmt: skip
    return path


def test_a_long_text_table_is_streamed_like_a_stored_session(tmp_path, monkeypatch) -> None:
    csv = _csv(tmp_path / "long.csv", 40.0, seed=5)
    monkeypatch.setattr(fit_app, "STREAM_ABOVE", 20_000)
    monkeypatch.setattr(fit_app, "STREAM_PILOT", 15_000)
    monkeypatch.setattr(fit_app, "STREAM_BLOCK", 10_000)
    outcome = fit_app.fit_file(csv, forms="paper", reading={"units": "time=ms,position=mm"})
    assert any("too many to hold" in w for w in outcome.bayes.warnings_)
    assert outcome.session.meta["file"] == str(csv)
    k = outcome.bayes.best_.model.symbols.index("K")
    post = outcome.bayes.best_.posterior
    assert post.mean[k] == pytest.approx(350.0, abs=4 * post.sd[k])
    assert not list(tmp_path.glob("*.h5"))  # the staged file is not left beside it


def test_a_short_text_table_is_read_whole(tmp_path, monkeypatch) -> None:
    csv = _csv(tmp_path / "short.csv", 5.0, seed=6)
    monkeypatch.setattr(fit_app, "STREAM_ABOVE", 20_000)
    outcome = fit_app.fit_file(csv, forms="paper", reading={"units": "time=ms,position=mm"})
    assert "streamed" not in outcome.session.meta
