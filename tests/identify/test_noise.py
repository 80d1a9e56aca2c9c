"""The data weight of the errors-in-variables corrected estimator."""

from __future__ import annotations

import numpy as np
import pytest

from tissuecli.identify.noise import data_weight


def _draw(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Independent rows: an exact column and a noisy one (noise variance 1 beside a
    regressor variance of 1), force noise variance 1/4; returns (A, y, C)."""
    t = np.linspace(0.0, 20.0, n)
    w = rng.normal(0.0, 1.0, n)
    A = np.column_stack([np.cos(t), w + rng.normal(0.0, 1.0, n)])
    y = np.cos(t) + w + rng.normal(0.0, 0.5, n)
    C = np.diag([0.0, float(n)])  # E[U^T U]: the noisy column's noise, variance 1 a row
    return A, y, C


def test_weight_matches_the_corrected_estimators_sampling_variance() -> None:
    # The corrected estimator beta_c = (A^T A - C)^-1 A^T y scatters beyond the sandwich
    # s^2 (A^T A - C)^-1 A^T A (A^T A - C)^-1 its posterior reports: by Fuller's (1987,
    # thm 2.2.1) term C beta beta^T C / n (0.4 of the sandwich's middle on the noisy
    # coefficient: 1 / (1.25 * 2)), and as s^2, the least-squares residual variance
    # (0.75), is short of the 1.25 that noise path and force noise give about beta_c.
    # The honest weight is 0.6 / 1.4 = 0.43, where least squares' own variances
    # (jointly Gaussian rows: exact for it) say 1.
    n, reps = 6000, 600
    rng = np.random.default_rng(20261127)
    est, model = [], []
    for _ in range(reps):
        A, y, C = _draw(rng, n)
        G = A.T @ A
        gc_inv = np.linalg.inv(G - C)
        beta = np.linalg.solve(G, A.T @ y)
        r = y - A @ beta
        est.append(gc_inv @ (A.T @ y))
        model.append((r @ r / n) * np.diag(gc_inv @ G @ gc_inv))
    want = float(np.min(np.mean(model, axis=0) / np.var(est, axis=0, ddof=1)))
    assert want == pytest.approx(0.6 / 1.4, rel=0.15)
    A, y, C = _draw(np.random.default_rng(7), n)
    beta = np.linalg.solve(A.T @ A, A.T @ y)
    r = y - A @ beta
    got = data_weight(A, r, 1.0, C, beta)
    # spread: the batch means' variance from n / 5 = 1200 blocks (relative SD
    # sqrt(2 / 1200) = 0.04) and the Monte-Carlo variance from 600 draws (sqrt(2 / 599)
    # = 0.06): 0.07 together, 3.5 of them
    assert got == pytest.approx(want, rel=0.25)
    # least squares' comparison misses it: intervals 1.5x too narrow
    assert data_weight(A, r, 1.0) > 0.9
