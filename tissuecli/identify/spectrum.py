"""Signal-processing primitives of identification, in NumPy alone: a Welch power spectrum
and the 'valid' part of a long convolution by FFT overlap-add.

SciPy has both (``scipy.signal.welch``, ``scipy.signal.oaconvolve``), and the tests hold
these to them to 1e-12; importing ``scipy.signal`` costs about 0.4 s, twice the rest of
``tissuecli fit``'s start-up, for some twenty lines.
"""

from __future__ import annotations

import threading

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray

Array = NDArray[np.float64]

#: most samples transformed in one batch of blocks (bounds the memory of long records)
BATCH_SAMPLES = 1 << 20

#: kernel spectra kept (a fit filters hundreds of columns through its few kernels)
KERNEL_SPECTRA = 16
_spectra: dict[tuple[bytes, int], Array] = {}
_spectra_lock = threading.Lock()


def _kernel_spectrum(k: Array, nfft: int) -> Array:
    """``np.fft.rfft(k, nfft)``, kept for the last :data:`KERNEL_SPECTRA` kernels and
    lengths (by value, so a new kernel is never given an old one's spectrum)."""
    key = (k.tobytes(), nfft)
    found = _spectra.get(key)
    if found is None:
        found = np.fft.rfft(k, nfft)
        found.flags.writeable = False
        with _spectra_lock:
            while len(_spectra) >= KERNEL_SPECTRA:
                _spectra.pop(next(iter(_spectra)))
            _spectra[key] = found
    return found


def power_spectrum(
    x: Array, fs: float, nperseg: int, valid: NDArray[np.bool_] | None = None
) -> tuple[Array, Array]:
    """Welch's one-sided power spectral density of ``x``, units^2/Hz.

    Periodic Hann windows of ``nperseg`` samples overlapping by half, each segment's
    mean removed, periodograms averaged: ``scipy.signal.welch(x, fs, nperseg=nperseg)``.
    With ``valid``, only the segments made wholly of valid samples are averaged.

    Parameters
    ----------
    x : ndarray, shape (n,)
        The record; ``n >= nperseg``.
    fs : float
        Sample rate, Hz.
    nperseg : int
        Segment length, samples.
    valid : ndarray of bool, shape (n,), optional
        The samples to trust; at least one segment must be wholly valid.

    Returns
    -------
    freqs : ndarray, shape (nperseg // 2 + 1,)
        Hz.
    psd : ndarray, same shape
        Power spectral density.
    """
    x = np.asarray(x, dtype=float)
    step = nperseg - nperseg // 2
    segments = sliding_window_view(x, nperseg)[::step]
    if valid is not None:
        whole = np.min(sliding_window_view(np.asarray(valid, bool), nperseg)[::step], axis=1)
        if not np.any(whole):
            raise ValueError(f"no segment of {nperseg} samples is wholly valid")
        segments = segments[whole]
    window = 0.5 - 0.5 * np.cos(2 * np.pi * np.arange(nperseg) / nperseg)
    spectra = np.fft.rfft((segments - segments.mean(axis=1, keepdims=True)) * window, axis=1)
    psd = np.mean(spectra.real**2 + spectra.imag**2, axis=0) / (fs * np.sum(window**2))
    psd[1 : nperseg // 2 + (nperseg % 2)] *= 2  # one-sided: all but DC (and Nyquist) twice
    return np.fft.rfftfreq(nperseg, 1.0 / fs), psd


def valid_spectrum(
    x: Array, fs: float, nperseg: int, valid: NDArray[np.bool_] | None, least: int = 7
) -> tuple[Array, Array]:
    """Welch's spectrum of ``x`` (:func:`power_spectrum`) over the segments made wholly of
    ``valid`` samples, their length halved from ``nperseg`` (down to 256 samples) until
    at least ``least`` of them are.

    Clipped or interpolated samples are not the signal: a record clipped at one end of
    its ADC is flat and noiseless there, with a kink where it enters the clip. Left in,
    they lower the noise floor and spread the signal's band. When no segment of 256
    samples is wholly valid, or ``valid`` is None or all True, the whole record is used.
    """
    x = np.asarray(x, dtype=float)
    nperseg = min(nperseg, x.size)
    if valid is None or np.all(valid):
        return power_spectrum(x, fs, nperseg)
    valid = np.asarray(valid, bool)
    size = nperseg
    while True:
        step = size - size // 2
        whole = np.min(sliding_window_view(valid, size)[::step], axis=1)
        count = int(np.count_nonzero(whole))
        if count >= least or size // 2 < min(256, nperseg):
            break
        size //= 2
    if count == 0:
        return power_spectrum(x, fs, nperseg)
    return power_spectrum(x, fs, size, valid)


def convolve_valid(u: Array, kernel: Array) -> Array:
    """``np.convolve(u, kernel, "valid")`` by FFT overlap-add, in bounded memory.

    Parameters
    ----------
    u : ndarray, shape (n,)
    kernel : ndarray, shape (m,), m <= n

    Returns
    -------
    ndarray, shape (n - m + 1,)
    """
    u = np.asarray(u, dtype=float)
    k = np.asarray(kernel, dtype=float)
    n, m = u.size, k.size
    if m > n:
        raise ValueError(f"kernel of {m} taps is longer than the {n} samples")
    if m * min(n, 64) <= 4096:  # short: direct convolution is faster than any FFT
        return np.convolve(u, k, mode="valid")
    nfft = 1 << int(np.ceil(np.log2(n + m - 1)))
    if nfft <= 8 * (1 << int(np.ceil(np.log2(m)))):
        # one transform of the whole record
        full = np.fft.irfft(np.fft.rfft(u, nfft) * _kernel_spectrum(k, nfft), nfft)
        return full[m - 1 : n]
    nfft = 8 * (1 << int(np.ceil(np.log2(m))))  # blocks about 7 kernel lengths long
    block = nfft - m + 1
    kf = _kernel_spectrum(k, nfft)
    nb = -(-n // block)
    per_batch = max(1, BATCH_SAMPLES // nfft)
    if nb <= per_batch:
        # one batch (a record of up to a million samples): each block's spill added in
        # place to the next block's head, the same sums without an accumulator
        padded = np.zeros(nb * block)
        padded[:n] = u
        y = np.fft.irfft(np.fft.rfft(padded.reshape(nb, block), nfft, axis=1) * kf, nfft, axis=1)
        y[1:, : m - 1] += y[:-1, block : block + m - 1]
        return y[:, :block].reshape(-1)[m - 1 : n]
    full = np.zeros((nb + 1) * block)
    padded = np.zeros(nb * block)
    padded[:n] = u
    blocks = padded.reshape(nb, block)
    for b0 in range(0, nb, per_batch):
        b1 = min(nb, b0 + per_batch)
        y = np.fft.irfft(np.fft.rfft(blocks[b0:b1], nfft, axis=1) * kf, nfft, axis=1)
        # each block's first `block` outputs are its own; its last m - 1 spill into the next
        full[b0 * block : b1 * block] += y[:, :block].ravel()
        spill = full[(b0 + 1) * block : (b1 + 1) * block].reshape(b1 - b0, block)
        spill[:, : m - 1] += y[:, block : block + m - 1]
    return full[m - 1 : n]


def convolve_valid_every(u: Array, kernel: Array, step: int) -> Array:
    """Every ``step``-th output of :func:`convolve_valid`, ``convolve_valid(u,
    kernel)[::step]``, at about ``1/step`` of the cost of all of them.

    The kernel and the record are cut into phases of ``step`` samples, so that each
    output is a sum over whole blocks: one matrix product of the record's blocks with
    the kernel's, ``(n/step, step) @ (step, m/step)``, whose diagonals add up to the
    outputs. The same sums as :func:`convolve_valid`, in another order (rounding apart).

    Parameters
    ----------
    u : ndarray, shape (n,)
    kernel : ndarray, shape (m,), m <= n
    step : int, >= 1

    Returns
    -------
    ndarray, shape ((n - m) // step + 1,)
    """
    u = np.asarray(u, dtype=float)
    k = np.asarray(kernel, dtype=float)
    n, m = u.size, k.size
    if step <= 1:
        return convolve_valid(u, k)
    if m > n:
        raise ValueError(f"kernel of {m} taps is longer than the {n} samples")
    out, rows = every_layout(n, m, step)
    padded = np.zeros(rows * step)
    used = min(n, padded.size)
    padded[:used] = u[:used]
    return convolve_padded_every(padded, k, step, out)


def every_layout(n: int, m: int, step: int) -> tuple[int, int]:
    """The outputs of :func:`convolve_valid_every` of ``n`` samples through ``m`` taps
    at ``step``, and the rows of ``step`` samples its padded input is cut into (the
    record, then zeros: ``rows * step`` samples)."""
    out = (n - m) // step + 1
    return out, out - 1 + -(-m // step)


def convolve_padded_every(padded: Array, kernel: Array, step: int, out: int) -> Array:
    """:func:`convolve_valid_every` of a record already laid out as its padded input
    (:func:`every_layout`: the record, then zeros to ``rows * step`` samples), ``out``
    outputs: the same numbers, for a caller that writes the record there directly."""
    k = np.asarray(kernel, dtype=float)
    m = k.size
    q = -(-m // step)  # the kernel's blocks
    kr = np.zeros(q * step)
    kr[:m] = k[::-1]  # output i is sum_j kr[j] u[i + j]
    rows = out - 1 + q
    # (q, rows): each block of taps against every row, a row of the product apiece, so
    # that the sums below read contiguous memory (each entry the same dot product of
    # ``step`` terms as in the product's transpose)
    blocks = kr.reshape(q, step) @ padded.reshape(rows, step).T
    y = np.zeros(out)
    for j in range(q):
        y += blocks[j, j : j + out]
    return y


def white_noise_sd(y: NDArray[np.float64]) -> float:
    """SD of white noise on a sampled signal ``y`` (shape (n,), its units), from its
    second differences (robust median): ``y[i+1] - 2 y[i] + y[i-1]`` carries ``6 sigma^2``
    of noise and, unlike a first difference, next to nothing of a slow change (a squeeze
    sampled slowly, a grasp's force at 1 kHz). 0 for fewer than three samples."""
    d2 = np.diff(np.asarray(y, float), 2)
    if d2.size == 0:
        return 0.0
    return 1.4826 * float(np.median(np.abs(d2 - np.median(d2)))) / np.sqrt(6.0)
