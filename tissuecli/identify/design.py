"""Design matrices of the tissue law on filtered kinematics, the errors-in-variables
correction for position noise, and least squares on scaled columns."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..core.terms import Law, Term
from .derivatives import Kinematics
from .spectrum import power_spectrum

Array = NDArray[np.float64]


def position_noise_sd(x: Array, fs: float) -> float:
    """SD of white noise on position from the flat top of its spectrum (m)."""
    freqs, p = power_spectrum(x - x.mean(), fs, int(min(x.size, 4096)))
    top = p[freqs > fs / 4]
    return float(np.sqrt(np.median(top) * fs / 2)) if top.size else 0.0


def design(
    law: Law,
    kin: Kinematics,
    x_full: Array,
    sigma_x: float = 0.0,
    columns: dict[str, Array] | None = None,
) -> Array:
    """Design matrix (m, p) of a law, consistent with the filtered force.

    A position term filters its function of the raw position, ``g * r(x)``, which
    matches ``g * F`` for any r; a speed term uses :meth:`Kinematics.damping_input`
    (exact for a linear r), inertia the filtered acceleration (exact) and an offset
    ones (the filter keeps a constant). ``sigma_x`` (m), the position noise, removes
    the mean that noise adds inside curved functions. ``columns``, if given, keeps
    each term's column by name, so laws that share terms (every candidate has
    inertia, most an offset) compute them once; a term with shape parameters is
    computed afresh.
    """
    var = sigma_x**2
    if columns is None:
        return np.column_stack([_column(t, kin, x_full, var) for t in law.terms])
    out = []
    for t in law.terms:
        if t.shapes:  # one column per shape node: not worth keeping
            out.append(_column(t, kin, x_full, var))
            continue
        key = column_key(t)
        if key not in columns:
            columns[key] = _column(t, kin, x_full, var)
        out.append(columns[key])
    return np.column_stack(out)


def column_key(term: Term) -> str:
    """What a term's column depends on: its name, symbol and shape parameters."""
    shape = ",".join(f"{k}={v!r}" for k, v in sorted(term.shape.items()))
    return f"{term.name}|{term.symbol}|{shape}"


def _column(term: Term, kin: Kinematics, x_full: Array, var: float) -> Array:
    if term.variable == "x":
        return kin.stiffness_input(term, x_full, var)
    if term.variable == "v":
        return kin.damping_input(term, x_full, var)
    if term.variable == "a":
        return term(kin.a)
    if term.variable in ("xv", "h"):
        # terms of closure and speed together (contact damping) or of the closure's
        # history (relaxation) are formed on the raw grid and filtered as the force is;
        # the central-difference speed's noise is uncorrelated with the closure at the
        # same sample, so the product carries no noise bias
        dt = float(np.median(np.diff(kin.time)))
        v_full = np.gradient(x_full, dt)
        return kin.smooth(term.series(dt, x_full, v_full, np.zeros_like(x_full)))
    return term(np.ones(kin.time.size))


def eiv_correction(law: Law, kin: Kinematics, x_full: Array, sigma_x: float) -> Array:
    """Expected contribution of position noise to A^T A (errors in variables).

    Column j carries noise ``d_j * (k_j * e)`` to first order, with ``d_j`` the
    term's slope and ``k_j`` its kernel (none for an offset), so
    ``E[noise_i . noise_j] = sigma_x^2 (k_i . k_j) sum_n d_i d_j``. Subtracting it
    removes the attenuation bias that noisy derivatives put on M.
    """
    m = kin.v.size
    kernels, slopes = [], []
    for t in law.terms:
        if t.variable == "x":
            kernels.append(kin.kernels[0])
            slopes.append(kin.smooth(t.derivative(x_full)))
        elif t.variable == "v":
            kernels.append(kin.kernels[1])
            slopes.append(t.derivative(kin.v))
        elif t.variable == "a":
            kernels.append(kin.kernels[2])
            slopes.append(t.derivative(kin.a))
        else:  # a constant carries no position noise
            kernels.append(np.zeros_like(kin.kernels[0]))
            slopes.append(np.zeros(m))
    d = np.column_stack(slopes)
    K = np.array(kernels)
    return sigma_x**2 * (K @ K.T) * (d.T @ d)


def lstsq_scaled(A: Array, y: Array) -> Array:
    """Least squares on unit-norm columns (x^3 in SI units is 1e6 smaller than x)."""
    return lstsq_scaled_cond(A, y)[0]


def lstsq_scaled_cond(A: Array, y: Array) -> tuple[Array, float]:
    """:func:`lstsq_scaled` and the condition number of the unit-norm columns, from the
    same singular values."""
    d = np.linalg.norm(A, axis=0)
    d[d == 0] = 1.0
    beta, _, _, sv = np.linalg.lstsq(A / d, y, rcond=None)
    cond = float(sv[0] / sv[-1]) if sv.size and sv[-1] > 0 else float("inf")
    return beta / d, cond
