"""Position noise of a quantised closure: analog noise beside an ADC staircase.

A closure read through an ADC of step ``q`` is ``Q(s + eta)``: the true closure ``s``,
analog noise ``eta`` of SD ``sigma`` and rounding to the grid. Its error ``e = Q(s +
eta) - s`` is white only when the analog noise dithers the steps (``sigma`` about
``q / 2`` or more, Widrow's condition). Below that it is a staircase: a function of the
closure, constant while the jaws rest and one jump of ``q`` at each crossing of a
grid line. Through a derivative filter such a jump leaves a spike that white noise of
the step's variance ``q^2 / 12`` does not have, and through a smoother a constant error
that white noise averages away. So how the rounding reaches a column depends on how
fast the jaws cross the steps.

For a closure moving at ``c = |v| dt / q`` steps a sample, with the grid's phase
uniform (the crossings fall anywhere between samples), the rounding error is
stationary with autocovariance (the Fourier series of the sawtooth; Gray 1990,
"Quantization noise spectra")::

    R(0) = sigma^2 + q^2 / 12
    R(l) = q^2 sum_k exp(-4 pi^2 k^2 sigma^2 / q^2) cos(2 pi k c l) / (2 pi^2 k^2),  l != 0

(analog and rounding errors are uncorrelated once the phase is uniform). At ``sigma =
0`` the sum is ``q^2 B_2(frac(c l)) / 2``, Bernoulli's polynomial: ``q^2 / 12`` at every
lag for jaws at rest, the white ``q^2 / 12`` when ``c`` is large and irregular, and at
``sigma >~ q / 2`` the sum vanishes, leaving white noise of ``sigma^2 + q^2 / 12``. Two
filter outputs ``k_a * e`` and ``k_b * e`` then covary by ``sum_l R(l) X_ab(l)``,
``X_ab`` the kernels' cross-correlation: the errors-in-variables correction takes that
at each sample's own speed instead of ``sigma_x^2 (k_a . k_b)``.
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

#: harmonics of the sawtooth summed (their energy beyond is 1e-5 of q^2 / 12)
HARMONICS = 4096
#: points of the tabulated periodic part of the autocovariance over one step
PHASES = 8192
#: speeds (steps a sample) the covariances are tabulated at: from one crossing in 500
#: windows to a twentieth of a step a sample in steps of 4 %, then up to several steps a
#: sample in steps of 1 %, fine enough that a session's own spread of speeds averages
#: the resonances where a multiple of the speed is a whole step a sample (crossings that
#: repeat every sample or every other sample), instead of an assumed spread
SLOW_STEP, FAST_STEP, FAST_FROM, FASTEST = 1.04, 1.01, 0.05, 4.0
#: analog noise at or above this share of the step dithers it: the white model is exact
#: (the sawtooth's first harmonic keeps exp(-4 pi^2 0.75^2) = 2e-10 of its energy)
DITHERED = 0.75


def _periodic(ratio: float) -> Array:
    """``g(f) = sum_k exp(-4 pi^2 k^2 ratio^2) cos(2 pi k f) / (2 pi^2 k^2)`` on
    :data:`PHASES` points of ``f`` in [0, 1) (``ratio = sigma / q``): the rounding's
    autocovariance over ``q^2`` at a lag that moves the closure ``f`` steps."""
    k = np.arange(1, HARMONICS + 1, dtype=float)
    coef = np.exp(-4.0 * np.pi**2 * k**2 * ratio**2) / (2.0 * np.pi**2 * k**2)
    spec = np.zeros(PHASES // 2 + 1)
    spec[1 : min(HARMONICS, PHASES // 2) + 1] = coef[: PHASES // 2]
    return np.fft.irfft(spec, PHASES) * PHASES / 2.0  # sum_k coef_k 2 cos(.) / 2


def dither_share(ratio: float) -> float:
    """``g(0) * 12``: the share of the rounding's variance ``q^2 / 12`` that is not white
    (1 for no analog noise, 0 once it dithers the steps)."""
    k = np.arange(1, HARMONICS + 1, dtype=float)
    return float(np.sum(np.exp(-4.0 * np.pi**2 * k**2 * ratio**2) / k**2) * 6.0 / np.pi**2)


def analog_sd(measured: float, step: float) -> float:
    """The analog noise SD (m) behind a position noise ``measured`` (m) read from the
    flat top of the spectrum, for an ADC of ``step`` (m).

    The flat top sees the white part of the error, ``sigma^2 + (q^2 / 12)(1 - s)``, with
    ``s`` the :func:`dither_share` of ``sigma / q``: the staircase's correlated part does
    not reach the top of the spectrum. Solved for ``sigma`` (0 at ``measured = 0``)."""
    if step <= 0:
        return max(measured, 0.0)
    if measured <= 0:
        return 0.0
    from scipy.optimize import brentq  # only a quantised closure needs it

    def white(sd: float) -> float:
        return sd**2 + step**2 / 12.0 * (1.0 - dither_share(sd / step)) - measured**2

    if white(measured) <= 0:  # rounding's white part negligible at this noise
        return measured
    if white(0.0) >= 0:  # the rounding's own white part makes up the reading
        return 0.0
    return float(brentq(white, 0.0, measured, xtol=1e-6 * step))


class PositionNoise(float):
    """Position noise (m) of a quantised closure: a float, the SD of white noise of the
    same variance at one sample (``sqrt(analog^2 + step^2 / 12)``), which every use of a
    plain noise SD keeps; and the analog SD and ADC step (m) that the
    errors-in-variables correction reads the staircase from
    (:func:`staircase_covariances`)."""

    analog: float
    step: float

    def __new__(cls, analog: float, step: float) -> PositionNoise:
        self = super().__new__(cls, math.sqrt(analog**2 + step**2 / 12.0))
        self.analog = float(analog)
        self.step = float(step)
        return self

    def __reduce__(self) -> tuple[type, tuple[float, float]]:
        return (PositionNoise, (self.analog, self.step))

    def __repr__(self) -> str:
        return f"PositionNoise(analog={self.analog!r}, step={self.step!r})"

    @property
    def staircase(self) -> bool:
        """Whether the rounding is coarse beside the analog noise (not dithered)."""
        return self.step > 0 and self.analog < DITHERED * self.step


def is_staircase(sigma_x: float) -> bool:
    """Whether ``sigma_x`` is a :class:`PositionNoise` whose rounding is a staircase."""
    return isinstance(sigma_x, PositionNoise) and sigma_x.staircase


@dataclass(frozen=True)
class Staircase:
    """Covariances of the rounding error through a set of filter kernels, tabulated
    over the closure's speed in steps a sample.

    Attributes
    ----------
    speeds : ndarray, shape (s,)
        Nodes, steps a sample; 0 first.
    table : ndarray, shape (s, r, r)
        Covariance of the kernels' outputs at each node, in the kernels' units squared
        times m^2.
    """

    speeds: Array
    table: Array

    @classmethod
    def of(cls, kernels: list[Array], noise: PositionNoise) -> Staircase:
        """Tabulate for ``kernels`` (each shape (w,), the same w) and ``noise``: each
        pair's covariance ``sum_l R(l) X_ab(l)``, ``X_ab`` the pair's cross-correlation
        (kept by pair: the laws of a fit ask for different sets of the same kernels)."""
        r = len(kernels)
        speeds, _ = _autocovariances(kernels[0].size, noise)
        table = np.empty((speeds.size, r, r))
        for a in range(r):
            for b in range(a, r):
                table[:, a, b] = table[:, b, a] = _pair(kernels[a], kernels[b], noise)
        return cls(speeds, table)

    def at(self, speed: Array) -> Array:
        """Covariances at each sample's speed (steps a sample), shape (m, r, r): linear
        between nodes (a mixture of two covariances is one), the last beyond them."""
        j, t = _between(self.speeds, speed)
        t = t[:, None, None]
        return self.table[j] * (1 - t) + self.table[j + 1] * t

    def mean_at(self, speed: Array) -> Array:
        """The mean of :meth:`at` over the samples, shape (r, r)."""
        return np.tensordot(node_weights(self.speeds, speed), self.table, axes=1)


def _between(nodes: Array, speed: Array) -> tuple[NDArray[np.intp], Array]:
    """Each speed's node below and its share of the way to the next."""
    c = np.clip(np.abs(speed), 0.0, nodes[-1])
    j = np.clip(np.searchsorted(nodes, c, side="right") - 1, 0, nodes.size - 2)
    return j, (c - nodes[j]) / (nodes[j + 1] - nodes[j])


def node_weights(nodes: Array, speed: Array) -> Array:
    """How much of the samples' mean falls on each node, shape (s,), summing to 1."""
    j, t = _between(nodes, speed)
    w = np.bincount(j, 1 - t, nodes.size) + np.bincount(j + 1, t, nodes.size)
    return w / max(speed.size, 1)


def staircase_correction(
    kernels: list[Array],
    slopes: Array,
    speed: Array,
    dt: float,
    noise: PositionNoise,
) -> Array:
    """Expected share of the rounding error in ``A^T A`` (the columns' units squared):
    ``C_ij = sum_n d_i(n) d_j(n) cov(k_i * e, k_j * e)(n)`` at each sample's speed.

    Parameters
    ----------
    kernels : list of ndarray, each shape (w,)
        Each column's kernel (zeros for a column that carries no position noise).
    slopes : ndarray, shape (m, p)
        Each column's slope at each fitted sample.
    speed : ndarray, shape (m,)
        The filtered speed at those samples, m/s.
    dt : float
        Sample interval, s.
    noise : PositionNoise

    Returns
    -------
    ndarray, shape (p, p)
    """
    return staircase_cross(kernels, slopes, kernels, slopes, speed, dt, noise)


def staircase_cross(
    kernels_a: list[Array],
    slopes_a: Array,
    kernels_b: list[Array],
    slopes_b: Array,
    speed: Array,
    dt: float,
    noise: PositionNoise,
) -> Array:
    """:func:`staircase_correction` between two sets of columns, shape (pa, pb): the
    block of the correction a fit with columns of fixed and of moving shape assembles."""
    distinct: list[Array] = []

    def index(kernels: list[Array]) -> list[int]:
        out = []
        for k in kernels:
            if not np.any(k):
                out.append(-1)  # a constant, or a history: no noise to first order
                continue
            for i, seen in enumerate(distinct):
                if seen is k or (seen.shape == k.shape and np.array_equal(seen, k)):
                    out.append(i)
                    break
            else:
                out.append(len(distinct))
                distinct.append(k)
        return out

    ta, tb = np.array(index(kernels_a), int), np.array(index(kernels_b), int)
    C = np.zeros((len(kernels_a), len(kernels_b)))
    if not distinct:
        return C
    cov = _covariances(distinct, noise, speed, dt)  # (m, r, r)
    for u in range(len(distinct)):
        ia = np.flatnonzero(ta == u)
        if not ia.size:
            continue
        for v in range(len(distinct)):
            ib = np.flatnonzero(tb == v)
            if ib.size:
                C[np.ix_(ia, ib)] = slopes_a[:, ia].T @ (cov[:, u, v, None] * slopes_b[:, ib])
    return C


_TABLES: dict[tuple[object, ...], Staircase] = {}


def _tabulated(kernels: list[Array], noise: PositionNoise) -> Staircase:
    """:meth:`Staircase.of`, kept for the last few kernel sets and noises (every law of
    a fit shares them)."""
    key = (tuple(hash(k.tobytes()) for k in kernels), noise.analog, noise.step)
    found = _TABLES.get(key)
    if found is None:
        if len(_TABLES) >= 16:
            _TABLES.pop(next(iter(_TABLES)))
        found = _TABLES[key] = Staircase.of(kernels, noise)
    return found


#: the fourth difference: a closure's own motion leaves ``x'''' dt^4`` in it, far below
#: the noise at any rate that samples the motion
FOURTH = np.array([1.0, -4.0, 6.0, -4.0, 1.0])


def staircase_analog_sd(d4: Array, speed: Array, step: float) -> float:
    """The analog noise SD (m) beside a staircase, from the closure's fourth differences.

    The flat top of the spectrum cannot tell it apart: the staircase's harmonics reach
    it and read as white noise of about a tenth of a step whatever the analog noise
    below. The mean energy of the fourth differences can: the covariances that the
    errors-in-variables correction uses predict it at each sample's speed for any analog
    SD, rising with it, so the SD is where prediction and measurement meet (0 if the
    staircase alone makes up the measurement).

    Parameters
    ----------
    d4 : ndarray, shape (m,)
        The raw closure's fourth differences (:data:`FOURTH`) at the fitted samples, m.
    speed : ndarray, shape (m,)
        The speed at those samples, steps a sample.
    step : float
        The ADC step, m.
    """
    ok = np.isfinite(d4) & np.isfinite(speed)
    if step <= 0 or np.count_nonzero(ok) < 16:
        return 0.0
    measured = float(np.mean(d4[ok] ** 2))
    nodes, _ = _autocovariances(FOURTH.size, PositionNoise(0.0, step))
    weights = node_weights(nodes, speed[ok])  # the same nodes at every analog SD

    def excess(sd: float) -> float:
        table = Staircase.of([FOURTH], PositionNoise(sd, step))
        return float(weights @ table.table[:, 0, 0]) - measured

    from scipy.optimize import brentq  # only a quantised closure needs it

    top = float(np.sqrt(measured / float(FOURTH @ FOURTH)))  # all of it analog noise
    if excess(0.0) >= 0:
        return 0.0
    if excess(top) <= 0:
        return top
    return float(brentq(excess, 0.0, top, xtol=1e-3 * step))


_COVARIANCES: dict[tuple[object, ...], tuple[weakref.ref[Array], Array]] = {}


def _covariances(kernels: list[Array], noise: PositionNoise, speed: Array, dt: float) -> Array:
    """The covariances at each sample's speed, shape (m, r, r), kept while ``speed``
    lives: every law of a fit, and every shape of a law, asks for the same."""
    key = (id(speed), tuple(hash(k.tobytes()) for k in kernels), noise.analog, noise.step, dt)
    found = _COVARIANCES.get(key)
    if found is not None and found[0]() is speed:
        return found[1]
    cov = _tabulated(kernels, noise).at(np.abs(speed) * dt / noise.step)
    for old in [k for k, v in _COVARIANCES.items() if v[0]() is None]:
        del _COVARIANCES[old]
    while len(_COVARIANCES) >= 8:
        _COVARIANCES.pop(next(iter(_COVARIANCES)))
    _COVARIANCES[key] = (weakref.ref(speed), cov)
    return cov


_AUTOCOVARIANCES: dict[tuple[object, ...], tuple[Array, Array]] = {}
_PAIRS: dict[tuple[object, ...], Array] = {}


def _autocovariances(w: int, noise: PositionNoise) -> tuple[Array, Array]:
    """The speed nodes, shape (s,), and the rounding's autocovariance at lags
    ``-(w-1) .. w-1`` at each, shape (s, 2w-1), m^2."""
    key = (w, noise.analog, noise.step)
    found = _AUTOCOVARIANCES.get(key)
    if found is not None:
        return found
    q, sigma = noise.step, noise.analog
    lags = np.arange(-(w - 1), w)
    g = _periodic(sigma / q)
    slow = min(0.002 / w, FAST_FROM / SLOW_STEP)
    speeds = np.concatenate([
        [0.0],
        np.exp(np.arange(np.log(slow), np.log(FAST_FROM), np.log(SLOW_STEP))),
        np.exp(np.arange(np.log(FAST_FROM), np.log(FASTEST) + 1e-9, np.log(FAST_STEP))),
    ])  # fmt: skip
    f = np.mod(np.outer(speeds, lags), 1.0) * PHASES
    j = np.floor(f).astype(int)
    frac = f - j
    R = q**2 * (g[j % PHASES] * (1 - frac) + g[(j + 1) % PHASES] * frac)
    R[:, w - 1] = sigma**2 + q**2 / 12.0  # R(0): analog and rounding variance
    while len(_AUTOCOVARIANCES) >= 3:  # a fit's few filter widths: they are large
        _AUTOCOVARIANCES.pop(next(iter(_AUTOCOVARIANCES)))
    _AUTOCOVARIANCES[key] = (speeds, R)
    return speeds, R


def _pair(ka: Array, kb: Array, noise: PositionNoise) -> Array:
    """One pair's covariance at each speed node, shape (s,)."""
    key = (hash(ka.tobytes()), hash(kb.tobytes()), noise.analog, noise.step)
    found = _PAIRS.get(key)
    if found is None:
        from scipy.signal import correlate  # only a quantised closure needs it

        _, R = _autocovariances(ka.size, noise)
        found = R @ correlate(kb, ka, mode="full")  # X_ab(l) at lags -(w-1) .. w-1
        while len(_PAIRS) >= 32:
            _PAIRS.pop(next(iter(_PAIRS)))
        _PAIRS[key] = found
    return found
