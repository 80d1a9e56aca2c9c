"""The paper's identification: a pseudoinverse on each of m windows of n+1 samples,
keeping the window of smallest residual (paper, section 4)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..core.errors import FitError
from ..core.session import Session
from ..core.terms import Law
from .derivatives import Differentiator
from .design import design, lstsq_scaled
from .estimator import Estimator
from .forms import parse_forms

Array = NDArray[np.float64]


class WindowedPinv(Estimator):
    """The paper's identification: pseudoinverse on m windows of n+1 samples.

    Parameters
    ----------
    forms : str or Law
        One law, e.g. ``"x,xdot"``.
    window_s : float
        Window length in s (n+1 = window_s * rate).
    differentiator : str or Differentiator
    grasps : {"all", "none"} or list of int
    closure : {"rebuilt", "read"}
        As :class:`~tissuecli.identify.bayes.BayesianFit`.

    Attributes
    ----------
    params_ : ndarray, shape (p,)
        The law's coefficients in the window with the smallest residual, SI.
    model_ : Law
        The law fitted.
    windows_ : ndarray, shape (m, p)
        Parameters of every window.
    residuals_ : ndarray, shape (m,)
        RMS residual of each window (N).
    best_window_ : int
    session_ : Session
        What was fitted (see :class:`BayesianFit`).
    cond_, cond_scaled_ : float
        Condition numbers of the best window's design, raw and column-scaled.
    pooled_ : ndarray, shape (p,)
        All windows in one least-squares problem, for comparison.
    law_, coef_, coef_sd_, coef_ci95_, tissue_
        As every estimator (:class:`~tissuecli.identify.estimator.Estimator`): the law,
        ``params_``, and the windows' spread.
    """

    def __init__(
        self,
        forms: str | Law = "x,xdot",
        *,
        window_s: float = 1.0,
        differentiator: str | Differentiator = "gaussian",
        grasps: str | Sequence[int] = "all",
        closure: str = "rebuilt",
    ) -> None:
        self.forms = forms
        self.window_s = window_s
        self.differentiator = differentiator
        self.grasps = grasps
        self.closure = closure

    def fit(self, session: Session) -> WindowedPinv:
        """Fit the form to each window of ``session``; returns self."""
        forms = "x,xdot" if self.forms in ("all", "paper") else self.forms
        models = parse_forms(forms)
        if len(models) != 1:
            raise FitError("the pseudoinverse fits one law; give --forms such as x,xdot")
        (model,) = models
        ready = self.prepare(session)
        session, kin, warnings, contact = (
            ready.session,
            ready.kinematics,
            ready.warnings,
            ready.contact,
        )
        A, y = design(model, kin, ready.closure), kin.force
        n = max(int(round(self.window_s / np.median(np.diff(kin.time)))), 10)
        m = A.shape[0] // n
        if m < 1:
            raise FitError(
                f"session shorter than one {self.window_s:g} s window; "
                "use a shorter --window or a longer session"
            )
        params, resid = np.empty((m, len(model.terms))), np.empty(m)
        for i in range(m):
            Ai, yi = A[i * n : (i + 1) * n], y[i * n : (i + 1) * n]
            params[i] = lstsq_scaled(Ai, yi)
            resid[i] = np.sqrt(np.mean((yi - Ai @ params[i]) ** 2))
        best = int(np.argmin(resid))
        Ab = A[best * n : (best + 1) * n]
        self.session_ = session
        self.closure_ = ready.closure
        self.contact_ = contact
        self.warnings_ = warnings
        self.model_ = model
        self.kinematics_ = kin
        self.windows_, self.residuals_ = params, resid
        self.best_window_ = best
        self.params_ = params[best]
        self.cond_ = float(np.linalg.cond(Ab))
        self.cond_scaled_ = float(np.linalg.cond(Ab / np.linalg.norm(Ab, axis=0)))
        self.pooled_ = lstsq_scaled(A[: m * n], y[: m * n])
        self.window_samples_ = n
        return self

    def _coefficients(self) -> tuple[Law, Array]:
        self._fitted()
        return self.model_, self.params_

    def _uncertainty(self) -> tuple[Array, Array]:
        """The spread of the windows' parameters: their SD and central 95 % (what the
        choice of window would change; one window gives zero)."""
        self._fitted()
        w = self.windows_
        sd = np.std(w, axis=0, ddof=1) if w.shape[0] > 1 else np.zeros(w.shape[1])
        return sd, np.percentile(w, [2.5, 97.5], axis=0).T

    def summary(self) -> dict[str, Any]:
        return {
            "model": self.model_.name,
            "window_samples": self.window_samples_,
            "windows": int(self.windows_.shape[0]),
            "best_window": self.best_window_,
            "best_residual_rms_N": float(self.residuals_[self.best_window_]),
            "cond": self.cond_,
            "cond_scaled": self.cond_scaled_,
        }
