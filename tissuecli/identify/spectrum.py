"""Signal-processing primitives of identification: a Welch power spectrum and the
'valid' part of a convolution, for long records and kernels of hundreds of taps."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.signal import oaconvolve, welch

Array = NDArray[np.float64]


def power_spectrum(x: Array, fs: float, nperseg: int) -> tuple[Array, Array]:
    """Welch's one-sided power spectral density of ``x`` (units^2/Hz).

    Hann windows of ``nperseg`` samples overlapping by half, each segment's mean
    removed, periodograms averaged.

    Returns
    -------
    freqs : ndarray, shape (nperseg // 2 + 1,)
        Hz.
    psd : ndarray, same shape
        Power spectral density.
    """
    return welch(x, fs=fs, nperseg=nperseg)


def convolve_valid(u: Array, kernel: Array) -> Array:
    """``np.convolve(u, kernel, "valid")``, by FFT overlap-add: shape (n - k + 1,)."""
    return oaconvolve(u, kernel, mode="valid")
