"""The tissue law ``K f0(x) + S f1(xdot) + M xddot = F``: a choice of forms
(:class:`TissueModel`) and a model with values (:class:`Tissue`), in SI units."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import InputError
from .forms import FORCE_SCALE, FORMS, TYPICAL, Form, form

Array = NDArray[np.float64]


PARAMETERS = ("K", "S", "M")


@dataclass(frozen=True)
class TissueModel:
    """A choice of forms: ``K f0(x) + S f1(xdot) + M xddot = F``."""

    f0: Form
    f1: Form

    @classmethod
    def from_names(cls, f0: str = "x", f1: str = "xdot") -> TissueModel:
        return cls(form("stiffness", f0), form("damping", f1))

    @property
    def name(self) -> str:
        return f"{self.f0.name},{self.f1.name}"

    def prior_scales(self, force_scale: float = FORCE_SCALE) -> NDArray[np.float64]:
        """Half-normal prior scales of (K, S, M) in SI, for terms reaching ``force_scale`` N."""
        return np.array(
            [
                self.f0.prior_scale(force_scale),
                self.f1.prior_scale(force_scale),
                force_scale / TYPICAL["inertia"],
            ]
        )

    @property
    def units(self) -> dict[str, str]:
        """SI unit of each parameter."""
        return {"K": self.f0.unit, "S": self.f1.unit, "M": "kg"}

    def regressors(self, x: ArrayLike, v: ArrayLike, a: ArrayLike) -> Array:
        """The law's columns at exact kinematics, shape (n, 3): f0(x), f1(xdot), xddot."""
        x, v, a = (np.asarray(z, dtype=float) for z in (x, v, a))
        return np.column_stack([self.f0(x), self.f1(v), a])

    def force(self, p: ArrayLike, x: ArrayLike, v: ArrayLike, a: ArrayLike) -> Array:
        """F = K f0(x) + S f1(xdot) + M xddot for p = (K, S, M); shape (n,) in N."""
        return self.regressors(x, v, a) @ np.asarray(p, dtype=float)


def all_models() -> list[TissueModel]:
    """Every registered combination of stiffness and damping forms."""
    return [
        TissueModel(f0, f1)
        for f0 in FORMS["stiffness"].values()
        for f1 in FORMS["damping"].values()
    ]


@dataclass(frozen=True)
class Tissue:
    """A model with parameter values (SI): what ``simulate``, ``fit`` and ``play`` share."""

    model: TissueModel
    K: float
    S: float
    M: float

    @property
    def p(self) -> Array:
        return np.array([self.K, self.S, self.M])

    def force(self, x: ArrayLike, v: ArrayLike, a: ArrayLike) -> Array:
        return self.model.force(self.p, x, v, a)

    def validate(self) -> Tissue:
        """Raise :class:`InputError` unless the parameters are finite and non-negative."""
        for name in PARAMETERS:
            value = getattr(self, name)
            if not np.isfinite(value) or value < 0:
                raise InputError(
                    f"parameter {name} = {value} {self.model.units[name]} must be finite and >= 0"
                )
        return self


DEFAULT_TISSUE = Tissue(TissueModel.from_names("x", "xdot"), K=350.0, S=3.0, M=0.05)
"""A liver-like default: 350 N/m, 3 N s/m, 50 g moving mass (field notes, section 2)."""
