"""Design matrices of the tissue law on filtered kinematics, the errors-in-variables
correction for position noise, and least squares on scaled columns."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..core.tissue import TissueModel
from .derivatives import Kinematics
from .spectrum import power_spectrum

Array = NDArray[np.float64]


def position_noise_sd(x: Array, fs: float) -> float:
    """SD of white noise on position from the flat top of its spectrum (m)."""
    freqs, p = power_spectrum(x - x.mean(), fs, int(min(x.size, 4096)))
    top = p[freqs > fs / 4]
    return float(np.sqrt(np.median(top) * fs / 2)) if top.size else 0.0


def design(model: TissueModel, kin: Kinematics, x_full: Array, sigma_x: float = 0.0) -> Array:
    """Design matrix (m, 3) consistent with the filtered force.

    The stiffness column filters f0 of the raw position, ``g * f0(x)``, which
    matches ``g * F`` for any f0; damping uses :meth:`Kinematics.damping_input` (exact for
    a linear f1) and inertia the filtered acceleration (exact). ``sigma_x`` (m), the
    position noise, removes the mean that noise adds inside curved forms.
    """
    var = sigma_x**2
    return np.column_stack(
        [
            kin.stiffness_input(model.f0, x_full, var),
            kin.damping_input(model.f1, x_full, var),
            kin.a,
        ]
    )


def eiv_correction(model: TissueModel, kin: Kinematics, x_full: Array, sigma_x: float) -> Array:
    """Expected contribution of position noise to A^T A (errors in variables).

    Column j carries noise ``d_j * (k_j * e)`` to first order, with ``d_j`` the
    form's slope and ``k_j`` its kernel, so ``E[noise_i . noise_j] =
    sigma_x^2 (k_i . k_j) sum_n d_i d_j``. Subtracting it removes the
    attenuation bias that noisy derivatives put on M.
    """
    d = np.column_stack(
        [kin.smooth(model.f0.derivative(x_full)), model.f1.derivative(kin.v), np.ones(kin.v.size)]
    )
    K = np.array([kin.kernels[0], kin.kernels[1], kin.kernels[2]])
    return sigma_x**2 * (K @ K.T) * (d.T @ d)


def lstsq_scaled(A: Array, y: Array) -> Array:
    """Least squares on unit-norm columns (x^3 in SI units is 1e6 smaller than x)."""
    d = np.linalg.norm(A, axis=0)
    d[d == 0] = 1.0
    return np.linalg.lstsq(A / d, y, rcond=None)[0] / d
