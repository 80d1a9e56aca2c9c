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

    def predict(self, session: Session | None = None) -> Array:
        """Filtered force (N) the fitted law predicts: at the fitted samples
        (``kinematics_.time``), or at the samples of another ``session`` that this
        estimator would fit (``self.prepare(session).kinematics.time``); shape (m,)."""
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
        resid = kin.force - self.predict(session)
        total = kin.force - np.mean(kin.force)
        return 1.0 - float(resid @ resid) / max(float(total @ total), 1e-300)
