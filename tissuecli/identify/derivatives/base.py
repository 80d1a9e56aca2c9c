"""What every differentiator shares: the :class:`Kinematics` it returns, the
:class:`Differentiator` base (trimming, holes, noise gains, the force filter), the
registry, and the position spectrum's signal band.

Each differentiator returns smoothed position, velocity and acceleration and the
force passed through the *same* filter, so that for the linear parts of the model
``filt(F) = K filt(x) + S filt(x)' + M filt(x)''`` holds exactly and the filter adds
no bias. Edges, where a filter has only one side, are trimmed, and so is every
output whose filter window touches an input sample marked invalid (lost or
clipped): a filter cannot see across a hole.
"""

from __future__ import annotations

import threading
import weakref
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import ClassVar

import numpy as np
from numpy.typing import NDArray

from ...core.errors import FitError
from ...core.terms import Term
from ..spectrum import convolve_valid, convolve_valid_every, valid_spectrum

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Kinematics:
    """Output of a differentiator, all arrays of shape (m,) after trimming.

    Attributes
    ----------
    time, x_raw, x, v, a, force : ndarray
        s, m (unfiltered), m, m/s, m/s^2, N (filtered like x).
    kernels : tuple of ndarray
        Convolution kernels giving x, v and a (the last two include 1/dt, 1/dt^2).
    keep : slice or ndarray of int
        Which input samples the outputs sit on: a slice after the edge trim alone,
        indices when invalid input samples removed outputs too.
    force_raw : ndarray
        The unfiltered force at those samples (N).
    noise_gain : tuple of float
        Output SD over input SD for white input noise: position, velocity (1/s)
        and acceleration (1/s^2).
    cutoff_hz : float
        The filter's -3 dB frequency (nan if it does not smooth).
    method : str
        What was used, for reports.
    """

    time: Array
    x_raw: Array
    x: Array
    v: Array
    a: Array
    force: Array
    kernels: tuple[Array, Array, Array]
    keep: slice
    noise_gain: tuple[float, float, float]
    cutoff_hz: float
    method: str
    force_raw: Array
    half: tuple[Array, Array, Array, float] | None = None
    rows: NDArray[np.intp] | None = None  # outputs kept after the edge trim; None: all
    #: the untrimmed closure (m) that drives terms with memory where it is not the raw
    #: closure: held across free jaw motion (:func:`~tissuecli.identify.design.held_closure`)
    drive: Array | None = None
    #: every ``stride``-th filtered output is kept (:meth:`every`); 1: all of them
    stride: int = 1
    #: the raw grid's sample interval (s), where the kept outputs no longer show it
    step_s: float | None = None

    @property
    def window(self) -> int:
        return int(self.kernels[0].size)

    @property
    def dt(self) -> float:
        """The raw grid's sample interval (s)."""
        if self.step_s is not None:
            return self.step_s
        return float(np.median(np.diff(self.time))) if self.time.size > 1 else 1.0

    def _rows(self, u: Array) -> Array:
        return u if self.rows is None else u[self.rows]

    def smooth(self, u: Array) -> Array:
        """Filter an untrimmed series of the same session like x (for position columns)."""
        if self.stride > 1:  # only the kept outputs are formed
            assert self.rows is not None
            return convolve_valid_every(u, self.kernels[0], self.stride)[self.rows // self.stride]
        return self._rows(convolve_valid(u, self.kernels[0]))

    def every(self, stride: int) -> Kinematics:
        """These kinematics at the filtered outputs whose index (counted from the first
        output of the whole record) is a multiple of ``stride``: the same values, exact
        outputs of the same kernels, at a ``stride`` times coarser grid. Columns formed
        on it (:meth:`smooth`) cost about ``1/stride`` of the full ones."""
        if stride <= 1:
            return self
        rows = np.arange(self.x_raw.size) if self.rows is None else self.rows
        stride *= self.stride
        kept = np.flatnonzero(rows % stride == 0)
        h = self.window // 2
        return replace(
            self,
            time=self.time[kept],
            x_raw=self.x_raw[kept],
            x=self.x[kept],
            v=self.v[kept],
            a=self.a[kept],
            force=self.force[kept],
            force_raw=self.force_raw[kept],
            keep=rows[kept] + h,  # type: ignore[arg-type]
            rows=rows[kept],
            stride=stride,
            step_s=self.dt,
        )

    def stiffness_input(self, term: Term, x_full: Array, noise_var: float = 0.0) -> Array:
        """The column ``g * r(x)`` of a position term from the untrimmed raw position.

        Position noise of variance ``noise_var`` (m^2) inside a curved r adds
        ``r'' noise_var / 2`` on average (``3 x noise_var`` for x^3): that much is
        taken off, so the column matches ``g * F`` to second order.
        """

        def r(x: Array) -> Array:
            u = term(x)
            return u - 0.5 * term.curvature(x) * noise_var if noise_var > 0 else u

        return self.smooth(self.pointwise(r, x_full))

    def pointwise(self, fn: Callable[[Array], Array], x_full: Array) -> Array:
        """``fn(x_full)`` for a function of each sample's value alone (a term of the
        closure, its slope or curvature). Where an ADC has put the closure on few levels
        (at most one per :data:`SAMPLES_PER_LEVEL` samples: 96 levels in the 10,000
        samples of the simulated forceps' 8 bits), ``fn`` runs on the levels and is read
        back at each sample: the same numbers, for the cost of indexing where it was
        that of a power of every sample."""
        found = _levels(x_full)
        if found is not None:
            levels, index = found
            return fn(levels)[index]
        return fn(x_full)

    def damping_input(self, term: Term, x_full: Array, noise_var: float = 0.0) -> Array:
        """The column ``~ g * r(v)`` of a speed term from the untrimmed position.

        With half kernels ``g_h * E[r](v_h, s^2 a_h^2 - n_v)`` (:meth:`Term.expected`),
        where ``v_h = g_h' * x``, ``a_h = g_h'' * x``, ``s`` is g_h's SD and ``n_v`` the
        variance position noise of ``noise_var`` (m^2) gives v_h: the spread
        ``s^2 a_h^2`` is the other half window's smoothing inside the nonlinearity
        (``g_h * r(v) = E[r](g_h * v, Var)``) and ``- n_v`` removes the same effect of
        noise. For a smooth r, ``E[r](u, var) = r(u) + r''(u) var / 2``; exact for a
        linear r. Without half kernels: ``r(v)``.
        """
        if self.half is None:
            return term(self.v)
        v, spread, n_v = self._half_speed(x_full, noise_var)
        return self._half_smooth(term.expected(v, spread - n_v), x_full)

    def damping_slope(self, term: Term, x_full: Array, noise_var: float = 0.0) -> Array:
        """How position noise moves a speed term's column (:meth:`damping_input`): its
        slope in the filtered speed at each fitted sample, (m,), for the
        errors-in-variables correction (the noise then passes the speed kernel).

        A smooth regressor's own slope at the filtered speed. For a :attr:`Term.step`
        (dry friction) the slope of the same mean its column is,
        ``g_h * E[r]'(v_h, max(s^2 a_h^2 - n_v, 0) + n_v)`` (:meth:`Term.expected_slope`):
        the column's spread and the noise's together, as the column's error sees them.
        For Gaussian noise that mean slope is the exact covariance of the column with
        the speed's error (Bussgang's theorem), where the step's own slope, 1/V_SMOOTH at
        every turn, put a noise there that the column does not carry, and the
        correction took it off the friction's share of the data.
        """
        if not term.step:
            return term.derivative(self.v)
        if self.half is None:
            k1 = self.kernels[1]
            return term.expected_slope(self.v, noise_var * float(k1 @ k1))
        v, spread, n_v = self._half_speed(x_full, noise_var)
        # the column's own spread (less the noise's, at least none) and the noise's
        slope = term.expected_slope(v, np.maximum(spread - n_v, 0.0) + n_v)
        return self._half_smooth(slope, x_full)

    def _half_speed(self, x_full: Array, noise_var: float) -> tuple[Array, Array, float]:
        """The half window's speed (m/s), the other half's spread of speeds about it
        (m^2/s^2) and its noise's variance (m^2/s^2), on the raw grid's valid outputs."""
        assert self.half is not None
        _, gh1, gh2, s2 = self.half
        a = convolve_valid(x_full, gh2)
        return convolve_valid(x_full, gh1), s2 * a * a, noise_var * float(gh1 @ gh1)

    def _half_smooth(self, u: Array, x_full: Array) -> Array:
        """``g_h * u`` for ``u`` on the half window's outputs, on the fitted samples."""
        assert self.half is not None
        col = convolve_valid(u, self.half[0])
        trim = (col.size - (x_full.size - self.window + 1)) // 2  # to the full filter's outputs
        return self._rows(col[trim : col.size - trim])


#: fewest samples per distinct closure level for :meth:`Kinematics.pointwise` to use them
SAMPLES_PER_LEVEL = 8

_levels_lock = threading.Lock()
_levels_of: list[tuple[weakref.ref[Array], tuple[Array, NDArray[np.intp]] | None]] = []


def _levels(x: Array) -> tuple[Array, NDArray[np.intp]] | None:
    """The distinct values of ``x`` and each sample's index among them, if there are at
    most one per :data:`SAMPLES_PER_LEVEL` samples; kept for the last closure asked
    about (a fit asks about one, hundreds of times)."""
    with _levels_lock:
        if _levels_of and _levels_of[0][0]() is x:
            return _levels_of[0][1]
    levels, index = np.unique(x, return_inverse=True)
    found = (levels, index.ravel()) if levels.size * SAMPLES_PER_LEVEL <= x.size else None
    with _levels_lock:
        _levels_of[:] = [(weakref.ref(x), found)]
    return found


class Differentiator(ABC):
    """Estimates x, xdot, xddot and filters F alike, by three convolution kernels.

    Subclasses give the kernels; trimming, noise gains and the force filter are shared.
    """

    name: ClassVar[str]

    @abstractmethod
    def kernels(
        self, x: Array, dt: float, valid: NDArray[np.bool_] | None = None
    ) -> tuple[tuple[Array, Array, Array], float, str]:
        """Kernels for x, v, a (odd length, for ``np.convolve``), cutoff in Hz, description.

        A width chosen from the data reads the spectrum of the ``valid`` samples' stretches.
        """

    def half_kernels(
        self, x: Array, dt: float, valid: NDArray[np.bool_] | None = None
    ) -> tuple[Array, Array, Array, float] | None:
        """Kernels ``g_h, g_h', g_h''`` with ``g_h * g_h = g`` and g_h's variance (s^2), if any."""
        return None

    def __call__(
        self, time: Array, x: Array, force: Array, valid: NDArray[np.bool_] | None = None
    ) -> Kinematics:
        """Differentiate; ``time`` must be uniformly sampled (s).

        ``valid`` (n,) marks the input samples to trust; outputs whose filter
        window holds an invalid one are left out. Invalid samples still need
        finite stand-in values (interpolated, say): they pass through the
        convolution, but nothing that depends on them is kept.
        """
        dt = sample_interval(time)
        (k0, k1, k2), cutoff, method = self.kernels(x, dt, valid)
        if 2 * k0.size > x.size:
            raise FitError(
                f"{x.size} samples are too few for a {k0.size}-sample derivative filter; "
                "record a longer session"
            )
        h = k0.size // 2
        keep: slice | NDArray[np.intp] = slice(h, x.size - h)
        rows = None
        if valid is not None and not np.all(valid):
            bad = convolve_valid((~valid).astype(float), np.ones(k0.size))
            rows = np.flatnonzero(bad < 0.5)
            if rows.size < k0.size:
                raise FitError(
                    f"only {rows.size} filtered samples have a window free of lost, clipped "
                    f"or out-of-contact samples ({k0.size} needed); record a cleaner "
                    "session, or fit every sample with --grasps none"
                )
            keep = rows + h

        def conv(u: Array, k: Array) -> Array:
            out = convolve_valid(u, k)
            return out if rows is None else out[rows]

        half = self.half_kernels(x, dt, valid)
        return Kinematics(
            half=half,
            time=time[keep],
            x_raw=x[keep],
            x=conv(x, k0),
            v=conv(x, k1),
            a=conv(x, k2),
            force=conv(force, k0),
            force_raw=force[keep],
            kernels=(k0, k1, k2),
            keep=keep,
            noise_gain=tuple(float(np.linalg.norm(k)) for k in (k0, k1, k2)),  # type: ignore[arg-type]
            cutoff_hz=cutoff,
            method=method,
            rows=rows,
        )


class Frozen(Differentiator):
    """The filter a fit chose, kept to differentiate other samples alike (to predict
    them with the fitted law, whose inputs must be filtered as the fitted ones were).

    Not registered: it is made from a :class:`Kinematics`, not chosen by name.
    """

    name = "frozen"

    def __init__(self, fitted: Kinematics) -> None:
        self.fitted = fitted
        self.dt = float(np.median(np.diff(fitted.time)))

    def kernels(
        self, x: Array, dt: float, valid: NDArray[np.bool_] | None = None
    ) -> tuple[tuple[Array, Array, Array], float, str]:
        if abs(dt / self.dt - 1.0) > 1e-3:
            raise FitError(
                f"these samples come every {dt * 1e3:.4g} ms, the fitted ones every "
                f"{self.dt * 1e3:.4g} ms: the fitted filter does not apply; resample them"
            )
        k = self.fitted
        return k.kernels, k.cutoff_hz, k.method

    def half_kernels(
        self, x: Array, dt: float, valid: NDArray[np.bool_] | None = None
    ) -> tuple[Array, Array, Array, float] | None:
        return self.fitted.half


def sample_interval(time: Array) -> float:
    """The sample interval in s, refusing data too irregular for a fixed-step filter."""
    steps = np.diff(time)
    dt = float(np.median(steps))
    if not dt > 0:
        raise FitError("time does not increase; cannot differentiate")
    if np.max(np.abs(steps - dt)) > 0.25 * dt:
        worst = int(np.argmax(np.abs(steps - dt)))
        raise FitError(
            f"samples are not evenly spaced (step of {steps[worst] * 1e3:.3g} ms near "
            f"t = {time[worst]:.3f} s against {dt * 1e3:.3g} ms): lost frames or a gap; "
            "fit a gap-free part of the session"
        )
    return dt


def signal_band_hz(
    x: Array, fs: float, snr_db: float = 20.0, valid: NDArray[np.bool_] | None = None
) -> float:
    """Highest frequency at which the position spectrum stands ``snr_db`` above its noise floor.

    The floor is the median of the Welch spectrum between ``min(100 Hz, fs/4)`` and
    ``min(1 kHz, fs/2)``: a hand moves the jaws below about 30 Hz, and higher up
    coarse quantisation leaves a spectrum that falls far below the noise the
    derivatives will see (at 10 kHz, 8 bits, the top half of the band put the
    floor 2x too low and the band edge at 122 Hz instead of 7 Hz).

    Segments are at most 4 s long and at most a quarter of the record, so that
    Welch averages at least 7 of them: with 2 segments (6.6 s at 10 kHz), chance
    peaks of the quantisation noise, which at 8 bits stands 10-12 dB above the
    floor at 10-200 Hz, crossed the 20 dB line in 3 sessions of 20 and put the
    cutoff at 19-65 Hz instead of about 12 Hz, costing M up to 400 Cramer-Rao bounds.

    With ``valid``, only segments made wholly of valid samples count (shorter ones if
    needed, :func:`~tissuecli.identify.spectrum.valid_spectrum`): jaws clipped at an end
    of the ADC between grasps put a kink in the record at each grasp, whose spectrum
    doubled the band (10 to 20 Hz at 1 kHz, 14 to 30 Hz at 10 kHz) and so the
    acceleration's noise.
    """
    n = x.size if valid is None else max(int(np.count_nonzero(valid)), 1)
    longest = 2 ** np.floor(np.log2(max(n / 4, 1)))
    nperseg = int(min(x.size, max(256, min(2 ** np.ceil(np.log2(4 * fs)), longest))))
    f, p = valid_spectrum(x - np.mean(x), fs, nperseg, valid)
    sel = (f >= min(100.0, fs / 4)) & (f <= min(1000.0, fs / 2))
    floor = np.median(p[sel]) if np.any(sel) else np.min(p)
    above = np.flatnonzero((p > floor * 10 ** (snr_db / 10)) & (f > 0))
    if above.size == 0:
        return float(f[1]) if f.size > 1 else fs / 4
    return float(f[above[-1]])


DIFFERENTIATORS: dict[str, type[Differentiator]] = {}


def register(cls: type[Differentiator]) -> type[Differentiator]:
    DIFFERENTIATORS[cls.name] = cls
    return cls


def differentiator(name: str, **kwargs: object) -> Differentiator:
    """Look a differentiator up by name."""
    try:
        return DIFFERENTIATORS[name](**kwargs)  # type: ignore[arg-type]
    except KeyError:
        raise FitError(
            f"unknown differentiator {name!r}; choose one of: {', '.join(DIFFERENTIATORS)}"
        ) from None
