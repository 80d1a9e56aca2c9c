"""A smoke run of the benchmark: every configuration runs and the report is complete."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import bench  # noqa: E402


def test_quick_benchmark_runs_and_reports(tmp_path, capsys):
    result = bench.main(["--quick", "--out", str(tmp_path)])
    out = capsys.readouterr().out
    summary = result["summary"]
    for name in ("pinv (paper)", "bayes gaussian (default)", "bayes savgol", "bayes + emcee 300"):
        assert name in summary and name in out
    # the default chose the right form on every smoke session
    assert summary["bayes gaussian (default)"][2] == 1.0
    assert result["front"]  # a Pareto front exists and is printed
    assert all(
        (tmp_path / f).stat().st_size > 5000
        for f in ("bench_time_error.png", "bench_time_choice.png", "bench_length.png")
    )
    assert all(np.isfinite(result["per_sample"]))


def test_pareto_front_keeps_only_undominated_rows():
    rows = [
        ("fast-bad", 1.0, 10.0),
        ("slow-good", 10.0, 1.0),
        ("slow-bad", 10.0, 10.0),
        ("same-as-fast", 1.0, 10.0),
    ]
    assert bench.pareto(rows) == {"fast-bad", "slow-good", "same-as-fast"}
