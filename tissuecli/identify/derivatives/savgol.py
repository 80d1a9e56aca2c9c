"""Savitzky-Golay smoothing differentiator, for comparison with the Gaussian."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .base import Array, Differentiator, register, signal_band_hz


@register
class SavitzkyGolay(Differentiator):
    """Savitzky-Golay smoothing differentiator (local least-squares polynomial).

    Parameters
    ----------
    window : int, optional
        Length in samples (odd). By default the -3 dB cutoff, from Schafer's
        approximation ``f_c / (fs/2) = (p + 1) / (3.2 h - 4.6)`` for half-width
        ``h`` and order ``p``, is put at ``cutoff_ratio`` times the signal band.
    polyorder : int
        Degree of the local polynomial (>= 2 for acceleration).
    """

    name = "savgol"

    def __init__(
        self, window: int | None = None, polyorder: int = 3, cutoff_ratio: float = 2.5
    ) -> None:
        self.window = window
        self.polyorder = polyorder
        self.cutoff_ratio = cutoff_ratio

    def kernels(
        self, x: Array, dt: float, valid: NDArray[np.bool_] | None = None
    ) -> tuple[tuple[Array, Array, Array], float, str]:
        fs, p = 1.0 / dt, self.polyorder
        if self.window:
            window = self.window | 1
        else:
            fc = min(self.cutoff_ratio * signal_band_hz(x, fs, valid=valid), 0.45 * fs)
            window = 2 * int(np.ceil(((p + 1) * fs / (2 * fc) + 4.6) / 3.2)) + 1
        window = max(window, p + 2 + (p + 1) % 2)
        from scipy.signal import savgol_coeffs  # only when Savitzky-Golay is asked for

        ks = tuple(savgol_coeffs(window, p, deriv=k, delta=dt, use="conv") for k in range(3))
        half = (window - 1) / 2
        cutoff = fs / 2 * min(1.0, (p + 1) / max(3.2 * half - 4.6, 1e-9))
        return ks, cutoff, f"savgol(window={window}, order={p})"  # type: ignore[return-value]
