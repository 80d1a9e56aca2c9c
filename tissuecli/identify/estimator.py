"""What the estimators share: a differentiator and a grasp choice, the preparation of a
session as they fit it, and prediction and scoring on the fitted session or another."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from ..core.session import Session
from ..core.terms import Law
from .derivatives import Differentiator, Frozen, Gaussian, Kinematics, differentiator
from .design import design
from .prepare import Prepared, prepare

Array = NDArray[np.float64]


class Estimator:
    """Base of :class:`~tissuecli.identify.bayes.BayesianFit` and
    :class:`~tissuecli.identify.pinv.WindowedPinv`.

    Subclasses set ``differentiator`` and ``grasps`` in ``__init__``, and after
    ``fit`` the attributes ``session_``, ``kinematics_`` and what
    :meth:`_coefficients` and :meth:`_position_noise_sd` read.
    """

    differentiator: str | Differentiator | None
    grasps: str | Sequence[int]
    session_: Session
    kinematics_: Kinematics

    def _diff(self) -> Differentiator:
        d = self.differentiator
        return differentiator(d) if isinstance(d, str) else (d or Gaussian())

    def prepare(self, session: Session) -> Prepared:
        """``session`` on its grid, filtered and cut to the chosen grasps, as this
        estimator fits it (see :func:`~tissuecli.identify.prepare.prepare`); once
        fitted, with the very filter of the fit, so predictions compare like with like."""
        fitted = getattr(self, "kinematics_", None)
        diff = Frozen(fitted) if fitted is not None else self._diff()
        # chosen grasp numbers belong to the fitted session: another is cut to its own
        grasps = self.grasps if fitted is None or isinstance(self.grasps, str) else "all"
        return prepare(session, diff, grasps)

    def _coefficients(self) -> tuple[Law, Array]:
        """The fitted law and its coefficients (SI)."""
        raise NotImplementedError

    def _position_noise_sd(self) -> float:
        return 0.0

    def predict(self, session: Session | None = None, *, filtered: bool = False) -> Array:
        """The force (N) the fitted law predicts.

        Without ``session``: the filtered force at the fitted samples
        (``kinematics_.time``), shape (m,), as the fit saw it.

        For another ``session``: one value per sample of it, shape (n,), a prediction
        of the force itself, the law on the best estimate of each sample's kinematics
        (:func:`~tissuecli.identify.predict.predict_band`), NaN where it cannot (inside
        a gap). A session that continues the fitted one (its first sample within
        three periods after the fitted last, as a held-out end is) is predicted with
        the fitted part as its history, so a law with memory enters it with the state
        it has there rather than from rest. ``filtered=True`` gives instead the
        filtered force at the samples this estimator would fit
        (``self.prepare(session).kinematics.time``), shape (m,).
        """
        if session is None or filtered:
            return self._predict_filtered(session)
        from ..core.tissue import Tissue
        from .predict import predict_band

        law, coef = self._coefficients()
        tissue = Tissue(law, *coef)
        before = self.session_
        dt = float(np.median(np.diff(before.time)))
        lead = float(session.time[0] - before.time[-1])
        if 0.0 < lead <= 3.0 * dt:
            whole = session.replace(
                np.concatenate([before.time, session.time]),
                np.concatenate([before.force, session.force]),
                np.concatenate([before.position, session.position]),
            )
            return predict_band(tissue, whole).predicted[len(before) :]
        return predict_band(tissue, session).predicted

    def _predict_filtered(self, session: Session | None = None) -> Array:
        """Filtered force (N) at the fitted samples, or at the samples of another
        ``session`` this estimator would fit; shape (m,)."""
        if session is None:
            kin, position = self.kinematics_, self.session_.position
        else:
            ready = self.prepare(session)
            kin, position = ready.kinematics, ready.session.position
        law, coef = self._coefficients()
        return design(law, kin, position, self._position_noise_sd()) @ coef

    def score(self, session: Session | None = None) -> float:
        """Coefficient of determination R^2 of the predicted filtered force, on the fitted
        session or another: 1 is perfect, 0 no better than the force's mean."""
        kin = self.kinematics_ if session is None else self.prepare(session).kinematics
        resid = kin.force - self._predict_filtered(session)
        total = kin.force - np.mean(kin.force)
        return 1.0 - float(resid @ resid) / max(float(total @ total), 1e-300)
