"""What the estimators share: a differentiator and a grasp choice, hyperparameters read
and set in the scikit-learn manner, the preparation of a session as they fit it, one
vocabulary for what a fit found, and prediction and scoring on the fitted session or
another."""

from __future__ import annotations

import inspect
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..core.errors import FitError
from ..core.session import Session
from ..core.terms import Law
from ..core.tissue import Tissue
from .derivatives import Differentiator, Frozen, Gaussian, Kinematics, differentiator
from .design import design
from .prepare import Prepared, prepare

Array = NDArray[np.float64]


class Estimator:
    """Base of :class:`~tissuecli.identify.bayes.BayesianFit` and
    :class:`~tissuecli.identify.pinv.WindowedPinv`.

    Subclasses take their hyperparameters as keyword arguments of ``__init__`` and store
    each under its own name, unchanged (so :meth:`get_params` and :meth:`set_params`
    read and set them, as in scikit-learn); among them ``differentiator``, ``grasps``
    and ``closure`` (:func:`~tissuecli.identify.prepare.prepare`). After ``fit`` they
    set ``session_``, ``kinematics_``, ``closure_`` (the closure the kinematics are
    formed from, m; ``rebuilt_`` says whether it is a rebuilt staircase), ``contact_``
    and ``warnings_``, and what :meth:`_coefficients`,
    :meth:`_uncertainty` and :meth:`_position_noise_sd` read.

    Every fitted estimator then answers in one vocabulary: ``law_`` (the law chosen or
    given), ``coef_`` (its coefficients, SI), ``coef_sd_`` and ``coef_ci95_`` (their
    uncertainty), ``tissue_`` (law and coefficients as a
    :class:`~tissuecli.core.tissue.Tissue`), :meth:`predict` and :meth:`score`.
    """

    differentiator: str | Differentiator | None
    grasps: str | Sequence[int]
    closure: str
    session_: Session
    kinematics_: Kinematics
    closure_: Array

    @classmethod
    def _param_names(cls) -> list[str]:
        """The hyperparameters: the keyword arguments of ``__init__``."""
        kinds = (inspect.Parameter.KEYWORD_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)
        sig = inspect.signature(cls.__init__)
        return [p.name for p in sig.parameters.values() if p.name != "self" and p.kind in kinds]

    def get_params(self, deep: bool = True) -> dict[str, Any]:
        """The estimator's hyperparameters by name (``deep`` is accepted for scikit-learn's
        sake: no hyperparameter is itself an estimator)."""
        return {name: getattr(self, name) for name in self._param_names()}

    def set_params(self, **params: Any) -> Estimator:
        """Set hyperparameters by name; returns self. A fit already made stands until
        the next ``fit``.

        Raises
        ------
        FitError
            Naming a parameter the estimator does not have.
        """
        names = self._param_names()
        for key, value in params.items():
            if key not in names:
                raise FitError(
                    f"{type(self).__name__} has no parameter {key[:30]!r}; "
                    f"choose among: {', '.join(names)}"
                )
            setattr(self, key, value)
        return self

    def __repr__(self) -> str:
        sig = inspect.signature(type(self).__init__)
        changed = [
            f"{k}={v!r}" for k, v in self.get_params().items()
            if sig.parameters[k].default is inspect.Parameter.empty
            or not _same(v, sig.parameters[k].default)
        ]  # fmt: skip
        return f"{type(self).__name__}({', '.join(changed)})"

    # one vocabulary for what any estimator found

    @property
    def law_(self) -> Law:
        """The law fitted (chosen, for a model choice), its shape parameters bound."""
        return self._coefficients()[0]

    @property
    def coef_(self) -> Array:
        """Its coefficients, SI, shape (p,), in the order of ``law_.terms``."""
        return np.asarray(self._coefficients()[1], dtype=float)

    @property
    def coef_sd_(self) -> Array:
        """Each coefficient's uncertainty as an SD, SI, shape (p,)."""
        return self._uncertainty()[0]

    @property
    def coef_ci95_(self) -> Array:
        """Each coefficient's central 95 % interval, SI, shape (p, 2)."""
        return self._uncertainty()[1]

    @property
    def rebuilt_(self) -> bool:
        """Whether the fit formed its columns from a staircase closure rebuilt through
        its level crossings (``closure="rebuilt"`` on a coarse ADC's closure)."""
        return not np.array_equal(self.closure_, self.session_.position)

    @property
    def tissue_(self) -> Tissue:
        """The law and its coefficients as a tissue (what ``simulate`` and ``play`` take)."""
        law, coef = self._coefficients()
        return Tissue(law, *(float(c) for c in coef))

    def _uncertainty(self) -> tuple[Array, Array]:
        """SD (p,) and 95 % interval (p, 2) of the coefficients, SI."""
        raise NotImplementedError

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
        return prepare(session, diff, grasps, closure=getattr(self, "closure", "read"))

    def _coefficients(self) -> tuple[Law, Array]:
        """The fitted law and its coefficients (SI)."""
        raise NotImplementedError

    def _position_noise_sd(self) -> float:
        return 0.0

    def _fitted(self) -> None:
        if not hasattr(self, "kinematics_"):
            raise FitError(f"this {type(self).__name__} is not fitted yet: call fit(session) first")

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
        self._fitted()
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
            # the smoothing is chosen on the fitted part's force, never the new part's
            fitted = np.arange(len(whole)) < len(before)
            return predict_band(tissue, whole, tune=fitted).predicted[len(before) :]
        return predict_band(tissue, session).predicted

    def _predict_filtered(self, session: Session | None = None) -> Array:
        """Filtered force (N) at the fitted samples, or at the samples of another
        ``session`` this estimator would fit; shape (m,)."""
        if session is None:
            kin, position = self.kinematics_, self.closure_
        else:
            ready = self.prepare(session)
            kin, position = ready.kinematics, ready.closure
        law, coef = self._coefficients()
        return design(law, kin, position, self._position_noise_sd()) @ coef

    def score(self, session: Session | None = None) -> float:
        """Coefficient of determination R^2 of the predicted filtered force, on the fitted
        session or another: 1 is perfect, 0 no better than the force's mean."""
        self._fitted()
        kin = self.kinematics_ if session is None else self.prepare(session).kinematics
        resid = kin.force - self._predict_filtered(session)
        total = kin.force - np.mean(kin.force)
        return 1.0 - float(resid @ resid) / max(float(total @ total), 1e-300)


def _same(a: Any, b: Any) -> bool:
    try:
        return bool(a == b)
    except (TypeError, ValueError):  # arrays compare element by element
        return a is b
