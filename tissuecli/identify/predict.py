"""The force a fitted tissue predicts for a session it did not see, with its 95 %
predictive band: how a researcher validates a law on another grasp."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..core.errors import FitError
from ..core.session import Session
from ..core.tissue import Tissue
from .derivatives import Differentiator, differentiator
from .design import design
from .prepare import prepare

Array = NDArray[np.float64]

#: two-sided 95 % quantile of the normal distribution
Z95 = 1.959963984540054


@dataclass(frozen=True)
class Prediction:
    """Predicted and measured filtered force at a session's fitted samples.

    Attributes
    ----------
    time : ndarray, shape (m,)
        s, on the session's clock.
    force : ndarray, shape (m,)
        The measured force, filtered as in a fit, N.
    predicted, lower, upper : ndarray, shape (m,)
        The law's force (posterior mean) and its 95 % predictive band, N: the
        coefficients' uncertainty carried through the law, plus the residual noise.
    """

    time: Array
    force: Array
    predicted: Array
    lower: Array
    upper: Array

    @property
    def rms_n(self) -> float:
        """RMS of measured minus predicted, N."""
        return float(np.sqrt(np.mean((self.force - self.predicted) ** 2)))

    @property
    def r2(self) -> float:
        """Coefficient of determination of the prediction."""
        total = self.force - np.mean(self.force)
        resid = self.force - self.predicted
        return 1.0 - float(resid @ resid) / max(float(total @ total), 1e-300)

    @property
    def inside(self) -> float:
        """Fraction of measured samples inside the band."""
        return float(np.mean((self.force >= self.lower) & (self.force <= self.upper)))


def predict_band(
    tissue: Tissue,
    session: Session,
    *,
    cov: Array | None = None,
    noise_sd: float | None = None,
    differentiator_name: str | Differentiator = "gaussian",
) -> Prediction:
    """Predict the filtered force of every sample of ``session`` (all of it: grasps
    and free motion alike) with ``tissue``'s law; a law with memory starts from rest
    at the session's first sample.

    Parameters
    ----------
    tissue : Tissue
    session : Session
    cov : ndarray, shape (p, p), optional
        Covariance of the coefficients (SI); none: the band holds the noise alone.
    noise_sd : float, optional
        SD of the filtered force's residual, N; none: the band holds the coefficients'
        uncertainty alone.
    differentiator_name : str or Differentiator
        As the fit used (``gaussian`` by default).

    Raises
    ------
    FitError
        If the session cannot be differentiated (too short, constant).
    """
    d = differentiator_name
    diff = differentiator(d) if isinstance(d, str) else d
    ready = prepare(session, diff, "none")
    kin, x_full = ready.kinematics, ready.session.position
    A = design(tissue.law, kin, x_full)
    predicted = A @ tissue.coef
    var = np.zeros(predicted.size)
    if cov is not None:
        if cov.shape != (A.shape[1], A.shape[1]):
            raise FitError(f"the covariance is {cov.shape}, the law has {A.shape[1]} terms")
        var += np.einsum("ij,jk,ik->i", A, cov, A)
    if noise_sd is not None:
        var += noise_sd**2
    half = Z95 * np.sqrt(np.clip(var, 0.0, None))
    return Prediction(kin.time, kin.force, predicted, predicted - half, predicted + half)
