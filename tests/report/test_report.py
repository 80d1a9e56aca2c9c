"""The HTML report: one self-contained document with tables, figures and diagnostics."""

from __future__ import annotations

import base64
import html
import re
from pathlib import Path

import numpy as np
import pytest

from tissuecli import __version__
from tissuecli.app.fit import write_report
from tissuecli.core.terms import Law, paper_laws
from tissuecli.core.tissue import Tissue
from tissuecli.identify import FitOutcome, fit_session
from tissuecli.report.figures import MAX_POINTS
from tissuecli.report.figures import envelope as _envelope
from tissuecli.sim.synth import ForcepsModel, Sensors, synthesize

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
IMAGE = re.compile(r'<img\s[^>]*src="data:image/png;base64,([A-Za-z0-9+/=]+)"')


def _session(
    seed: int = 3, duration_s: float = 6.0, tissue: Tissue | None = None, name: str = "liver-1"
):
    model = ForcepsModel(seed=seed) if tissue is None else ForcepsModel(tissue=tissue, seed=seed)
    session, _ = synthesize(model, duration_s)
    session.name = name
    session.meta["tissue"] = "porcine liver"
    return session


def _write(tmp_path: Path, outcome: FitOutcome, name: str = "report.html") -> str:
    path = tmp_path / name
    write_report(path, outcome)
    assert path.is_file()
    return path.read_text(encoding="utf-8")


def _assert_self_contained(text: str) -> None:
    assert text.startswith("<!DOCTYPE html>")
    for tag in ("<html", "<head", "<body", "</html>"):
        assert text.count(tag) == 1, tag
    assert text.rstrip().endswith("</html>")
    plain = re.sub(r"base64,[A-Za-z0-9+/=]+", "base64,", text).lower()
    assert "http" not in plain and "file:" not in plain
    assert "<script" not in plain
    for src in re.findall(r'src\s*=\s*["\']([^"\']*)', text):
        assert src.startswith("data:image/"), src[:40]
    for href in re.findall(r'href\s*=\s*["\']([^"\']*)', text):
        assert href.startswith("#"), href
    assert "<link" not in text.lower()


def _images(text: str) -> list[bytes]:
    return [base64.b64decode(m) for m in IMAGE.findall(text)]


def _formula_numbers(text: str) -> list[float]:
    m = re.search(r'<div class="formula">F = (.*?)</div>', text)
    assert m is not None
    return [float(v) for v in re.findall(r"(\d+(?:\.\d+)?)&#8201;", m.group(1))]


@pytest.fixture(scope="module")
def both(tmp_path_factory: pytest.TempPathFactory) -> tuple[FitOutcome, str]:
    outcome = fit_session(_session(), method="both")
    return outcome, _write(tmp_path_factory.mktemp("both"), outcome)


def test_report_is_one_self_contained_html_document(both: tuple[FitOutcome, str]) -> None:
    _assert_self_contained(both[1])


def test_report_embeds_at_least_five_png_figures(both: tuple[FitOutcome, str]) -> None:
    images = _images(both[1])
    assert len(images) >= 5
    assert all(img.startswith(PNG_MAGIC) for img in images)
    for anchor in ("plot-time", "plot-loop", "plot-residuals", "plot-corner"):
        assert f'id="{anchor}"' in both[1]


def test_report_names_the_best_model_and_its_formula(both: tuple[FitOutcome, str]) -> None:
    outcome, text = both
    best = outcome.bayes.best_
    assert best.name == "x+xdot+xddot"
    assert f"Chosen law: <b>{best.name}</b>" in text
    numbers = _formula_numbers(text)
    assert len(numbers) == 3
    post = best.posterior
    np.testing.assert_allclose(numbers, post.mean, atol=0, rtol=0.01)
    assert np.all(np.abs(np.array(numbers) - post.mean) <= post.sd)


def test_report_has_the_parameter_table(both: tuple[FitOutcome, str]) -> None:
    outcome, text = both
    section = text[text.index("id='parameters'") : text.index("id='plots'")]
    for head in (
        "<th>mean</th>",
        "<th>SD</th>",
        "<th>95 % interval</th>",
        "<th>unit (SI)</th>",
        "convenient units</th>",
    ):
        assert head in section
    for unit in ("N/m<", "N s/m<", "kg<", "N/mm", "N s/mm", " g<", "mN"):
        assert unit in section, unit
    mass_g = outcome.bayes.best_.posterior.mean[2] * 1e3
    assert re.search(rf"{int(mass_g)}\.\d+ \[", section), "mass in grams missing"
    assert "noise SD" in section


def test_report_compares_all_four_forms(both: tuple[FitOutcome, str]) -> None:
    outcome, text = both
    section = text[text.index("id='comparison'") : text.index("id='diagnostics'")]
    names = [m.name for m in paper_laws()]
    assert len(names) == 4
    for name in names:
        assert f"<td><b>{html.escape(name).replace('+', '+<wbr>')}</b></td>" in section
    for head in (
        "ln evidence (exact)",
        "posterior probability",
        "ln BF vs best",
        "method",
        "cond (scaled)",
        "residual RMS (mN)",
    ):
        assert f"<th>{head}</th>" in section
    for r in outcome.bayes.results_:
        assert html.escape(r.reason) in section
    assert section.count('class="best"') == 2  # in the best few and in the full table


def test_both_includes_the_windows_chart_and_comparison(both: tuple[FitOutcome, str]) -> None:
    outcome, text = both
    assert 'id="plot-windows"' in text
    assert "Bayesian mean ± SD" in text
    assert f"chosen window index {outcome.pinv.best_window_}" in text


def test_report_has_diagnostics_and_provenance(both: tuple[FitOutcome, str]) -> None:
    outcome, text = both
    section = text[text.index("id='diagnostics'") :]
    kin = outcome.bayes.kinematics_
    assert html.escape(kin.method) in section
    assert "Effective samples" in section and "autocorrelation" in section
    assert "How to read this report" in text
    footer = text[text.index("<footer>") :]
    assert f"tissuecli {__version__}" in footer


@pytest.fixture(scope="module")
def pinv_only(tmp_path_factory: pytest.TempPathFactory) -> tuple[FitOutcome, str]:
    """The windowed pseudoinverse alone, on a session whose name is markup."""
    outcome = fit_session(_session(name='<b>liver</b> & "co"'), method="pinv", forms="x,xdot")
    return outcome, _write(tmp_path_factory.mktemp("pinv"), outcome)


def test_pinv_only_report(pinv_only: tuple[FitOutcome, str]) -> None:
    outcome, text = pinv_only
    assert outcome.bayes is None
    _assert_self_contained(text)
    assert 'id="plot-windows"' in text and 'id="plot-residuals"' in text
    assert 'id="plot-corner"' not in text
    assert len(_images(text)) == 4
    np.testing.assert_allclose(_formula_numbers(text), outcome.pinv.params_, rtol=1e-3)
    assert "no uncertainty" in text


def test_bayes_only_report_has_no_windows_chart(default_search) -> None:
    """The report over the default search (below), a Bayesian fit alone."""
    outcome, path = default_search
    assert outcome.pinv is None
    text = path.read_text(encoding="utf-8")
    assert 'id="plot-windows"' not in text
    ids = re.findall(r'<figure id="(plot-[a-z-]+)"', text) or re.findall(
        r'id="(plot-[a-z-]+)"', text
    )
    assert set(ids) == {
        "plot-time",
        "plot-loop",
        "plot-residuals",
        "plot-residual-map",
        "plot-elastic",
        "plot-corner",
    }
    assert len(_images(text)) == len(ids)


def test_warnings_are_shown_in_a_box(tmp_path: Path) -> None:
    massless = Tissue(Law.paper("x", "xdot"), K=350.0, S=3.0, M=0.0)
    # the law asked for keeps the mass the tissue does not have (the search would drop it)
    outcome = fit_session(_session(seed=5, duration_s=4.0, tissue=massless), forms="x+xdot+xddot")
    warnings = outcome.warnings
    assert warnings, "a massless tissue should leave M unidentified"
    text = _write(tmp_path, outcome)
    box = re.search(r'<div class="box warn">(.*?)</div>', text, re.S)
    assert box is not None
    for w in warnings:
        assert html.escape(w) in box.group(1)


def test_emcee_fit_reports_chain_and_sampler_evidence(tmp_path: Path) -> None:
    # the paper's four forms, each sampled: a choice among chains, as the default
    # search's 30 laws give, in 6 s of CPU rather than 14
    outcome = fit_session(_session(seed=6, duration_s=4.0), sampler="emcee", forms="paper")
    text = _write(tmp_path, outcome)
    assert "ln evidence (stepping-stone)" in text
    assert "Sampler (emcee)" in text
    diag = outcome.bayes.best_.posterior.diagnostics
    assert f"{diag['steps']:,}" in text
    assert "converged (chain &gt; 50 τ)" in text


def test_text_is_escaped(pinv_only: tuple[FitOutcome, str]) -> None:
    _, text = pinv_only
    assert "<b>liver</b>" not in text
    assert "&lt;b&gt;liver&lt;/b&gt; &amp; &quot;co&quot;" in text


def test_envelope_keeps_extremes_and_bounds_points() -> None:
    t = np.arange(200_001, dtype=float)
    y = np.sin(t / 500.0)
    y[123_457] = 9.0
    y[77_777] = -9.0
    tt, yy = _envelope(t, y)
    assert yy.size <= MAX_POINTS + 2
    assert yy.max() == 9.0 and yy.min() == -9.0
    assert np.all(np.diff(tt) >= 0)


def test_report_on_a_session_with_lost_frames(tmp_path: Path) -> None:
    s = _session()
    keep = np.ones(len(s), bool)
    keep[800:804] = keep[2500:2505] = False  # two gaps too long to bridge
    gappy = type(s)(
        s.time[keep], s.force[keep], s.position[keep], name=s.name, meta=s.meta, adc=s.adc
    )
    text = _write(tmp_path, fit_session(gappy, method="both"))
    _assert_self_contained(text)
    assert "beside lost or clipped samples" in text
    assert "2 gap(s) (9 missing sample(s))" in html.unescape(text)


def test_relaxation_law_report_shows_its_time_constant(tmp_path: Path) -> None:
    law = Law.of(["x", "maxwell", "xdot", "xddot"]).bind({"tau1": 0.5})
    sls = Tissue(law, 300.0, 200.0, 2.0, 0.05)
    # a 16-bit closure: an 8-bit one's staircase biases tau by ~0.5 % (docs/estimators.md)
    model = ForcepsModel(tissue=sls, seed=7, sensors=Sensors(bits=16))
    session, _ = synthesize(model, 8.0)
    outcome = fit_session(session, forms="x+maxwell+xdot+xddot")
    text = _write(tmp_path, outcome)
    _assert_self_contained(text)
    assert 'id="plot-relaxation"' in text
    row = re.search(r"<b>tau1</b>.*?</tr>", text, re.S)
    assert row is not None, "the time constant should have a row in the parameter table"
    interval = re.search(r"\[([0-9.]+), ([0-9.]+)\]", row.group(0))
    assert interval is not None
    lo, hi = float(interval.group(1)), float(interval.group(2))
    assert lo < 0.5 < hi


# -- a report that reads in a minute ------------------------------------------------------


@pytest.fixture(scope="module")
def default_search(tmp_path_factory: pytest.TempPathFactory) -> tuple[FitOutcome, Path]:
    """A report over the default structure search (some 30 laws)."""
    outcome = fit_session(_session())
    path = tmp_path_factory.mktemp("default") / "report.html"
    write_report(path, outcome)
    return outcome, path


def test_the_law_its_parameters_and_the_plots_come_first(default_search) -> None:
    text = default_search[1].read_text(encoding="utf-8")
    order = [text.index(k) for k in ("Chosen law:", "id='parameters'", "id='plots'",
                                     "id='comparison'", "id='diagnostics'")]  # fmt: skip
    assert order == sorted(order)
    # the session's table and the diagnostics are folded, the plots are not
    plots = text[text.index("id='plots'") : text.index("id='comparison'")]
    assert "<details" not in plots
    rest = text[text.index("id='diagnostics'") :]
    assert rest.count("<details>") == 2 and "Effective samples" in rest


def test_the_comparison_shows_the_best_few_with_a_reason_and_folds_the_rest(
    default_search,
) -> None:
    outcome, path = default_search
    text = path.read_text(encoding="utf-8")
    results = outcome.bayes.results_
    assert len(results) > 20
    section = text[text.index("id='comparison'") : text.index("id='diagnostics'")]
    shown, folded = section.split("<details>", 1)
    rows = re.findall(r"<tr( class=\"best\")?><td><b>(.*?)</b></td>(.*?)</tr>", shown, re.S)
    assert 3 <= len(rows) <= 5
    names = [html.unescape(name.replace("<wbr>", "")) for _, name, _ in rows]
    assert names == [r.name for r in results[: len(rows)]]
    assert rows[0][0]  # the best is marked
    for _, _, cells in rows[1:]:
        why = html.unescape(re.findall(r'<td class="why">(.*?)</td>', cells)[0])
        assert "evidence against it: " in why and ("lacks" in why or "adds" in why), why
    # the full table, folded, has every law
    assert f"All {len(results)} laws" in folded
    for r in results:
        assert f"<b>{html.escape(r.name).replace('+', '+<wbr>')}</b>" in folded


def test_a_short_reason_names_what_a_law_adds_or_lacks() -> None:
    from tissuecli.identify.bayes import ModelResult
    from tissuecli.report.sections import short_reason

    best = ModelResult(Law.of(["x", "xdot", "xddot"]), residual_rms=1e-3)
    more = ModelResult(Law.of(["x", "xdot", "xddot", "offset"]), residual_rms=1e-3)
    less = ModelResult(Law.of(["x", "xdot"]), residual_rms=3e-3)
    assert short_reason(best, best, 0.0).startswith("highest evidence")
    assert short_reason(more, best, 2.0) == (
        "adds offset: fits no better, so its extra freedom costs evidence; "
        "evidence against it: substantial"
    )
    assert short_reason(less, best, 40.0) == (
        "lacks xddot: fits worse (residual 3.00 mN against 1.00); evidence against it: decisive"
    )


#: the tallest a report over the default search may be at 1280 px, its details folded
MAX_HEIGHT_PX = 4000


@pytest.mark.slow
def test_the_report_fits_4000_px_at_1280_and_never_scrolls_sideways(default_search, tmp_path):
    """Measured in headless Chromium at 1280 and 1920 px: the page with its details
    folded is at most 4,000 px tall, and no element scrolls sideways, folded or open.
    ``TISSUECLI_SCREENSHOT=1`` writes the screenshots to docs/img/."""
    import os

    from ..browser import Browser, chromium

    if chromium() is None:
        pytest.skip("needs Chromium (apt-get install -y chromium)")
    _, path = default_search
    sideways = (
        "Math.max(0, ...[...document.querySelectorAll('*')]"
        ".map(e => e.scrollWidth - e.clientWidth))"
    )
    browser = Browser(tmp_path / "profile")
    try:
        for width in (1280, 1920):
            browser.set_width(width)
            browser.open(path.as_uri())
            height = browser.evaluate("document.documentElement.scrollHeight")
            assert browser.evaluate(sideways) == 0, width
            if width == 1280:
                assert height <= MAX_HEIGHT_PX, height
            if os.environ.get("TISSUECLI_SCREENSHOT") == "1":
                docs = Path(__file__).resolve().parents[2] / "docs" / "img"
                browser.screenshot(docs / f"report-{width}.png")
            browser.evaluate("document.querySelectorAll('details').forEach(d => d.open = true)")
            assert browser.evaluate(sideways) == 0, f"{width} px, details open"
    finally:
        browser.close()
