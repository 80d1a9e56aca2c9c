"""The coarser grid a long session's laws are scored on.

The fit's columns are outputs of the smoothing filter, whose band (about 11 Hz at
10 kHz) is a small fraction of the sampling's: neighbouring outputs carry nearly the
same numbers, and the data weight already counts one sample per filter correlation
time ``tau_g`` (:func:`~tissuecli.identify.noise.filter_tau`). On a long session every
``stride``-th filtered output (:meth:`~tissuecli.identify.derivatives.Kinematics.every`)
gives the same sufficient statistics, scaled by ``1/stride``, for a ``stride`` times
smaller cost of forming each column:

- every kept row is an exact output of the full-rate kernels, so each row's expected
  products (signal, force noise, and the position noise the errors-in-variables
  correction takes off, through the same full-rate kernels) are unchanged, and sums
  over the kept rows are ``1/stride`` of the full sums in expectation;
- the sums of products of signals band-limited below the coarse grid's Nyquist
  frequency are the full sums exactly (Poisson summation: the product's spectrum at
  multiples of the coarse rate is all a sampled sum adds), so the stride is the
  largest one whose Nyquist band holds all but :data:`ALIAS_TOLERANCE` of each
  kernel's energy;
- the likelihood is tempered by ``stride / tau_g`` rather than ``1 / tau_g``: the
  kept rows are correlated over ``tau_g / stride`` of them, the effective samples
  ``n / tau_g`` stay what they were, and so do the likelihood and the evidence, in
  expectation. The stride is kept to at most ``tau_g /`` :data:`ROWS_PER_TAU`, so the
  kept rows still resolve the filter's correlation (and a residual's autocorrelation
  time, read on them, is not clipped at one row).

Sessions of at most :data:`DECIMATE_ABOVE` filtered samples are scored on every one.
"""

from __future__ import annotations

import numpy as np

from .derivatives import Kinematics
from .noise import filter_tau

#: filtered samples up to which every one is scored (above the measured recordings a
#: user fits in seconds, and above a 10 s session at 1 kHz)
DECIMATE_ABOVE = 50_000

#: most of a kernel's energy that may lie above the coarse grid's Nyquist frequency
ALIAS_TOLERANCE = 1e-12

#: fewest kept rows per correlation time of the smoothing filter
ROWS_PER_TAU = 8


def fit_stride(kin: Kinematics) -> int:
    """The stride at which a session's laws are scored: 1 (every filtered sample) for
    sessions of at most :data:`DECIMATE_ABOVE` filtered samples or kernels that are
    not band-limited; else the largest stride whose coarse grid keeps each kernel's
    band (:data:`ALIAS_TOLERANCE`) and :data:`ROWS_PER_TAU` rows per filter correlation
    time."""
    if kin.force.size <= DECIMATE_ABOVE or kin.stride > 1:
        return 1
    k0 = kin.kernels[0]
    most = int(filter_tau(k0) // ROWS_PER_TAU)
    if most < 2:
        return 1
    nfft = 1 << int(np.ceil(np.log2(16 * k0.size)))
    freq = np.fft.rfftfreq(nfft)  # cycles per sample
    energy = [np.abs(np.fft.rfft(k, nfft)) ** 2 for k in kin.kernels]
    for stride in range(most, 1, -1):
        above = freq > 0.5 / stride
        if all(e[above].sum() <= ALIAS_TOLERANCE * e.sum() for e in energy):
            return stride
    return 1
