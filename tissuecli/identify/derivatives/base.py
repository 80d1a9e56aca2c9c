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

import math
import threading
import weakref
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from ...core.errors import FitError
from ...core.terms import Term
from ..spectrum import (
    convolve_padded_every,
    convolve_valid,
    convolve_valid_every,
    every_layout,
    valid_spectrum,
)

Array = NDArray[np.float64]


class _Recent:
    """The values last computed for the very objects (held by weak reference, so that
    a finished fit's are never matched by a new one's) and plain keys they were
    computed from: what a fit asks about hundreds of times for one closure, kept
    ``size`` at a time, the newest first. Thread-safe; callers must not write to what
    they are given."""

    def __init__(self, size: int = 1) -> None:
        self._size = size
        self._lock = threading.Lock()
        self._items: list[tuple[tuple[weakref.ref[Any], ...], tuple[Any, ...], Any]] = []

    def get(self, objects: tuple[Any, ...], plain: tuple[Any, ...] = ()) -> tuple[bool, Any]:
        """Whether a value is kept for ``objects`` (by identity) and ``plain`` (by
        equality), and that value (None if not)."""
        with self._lock:
            for refs, keys, value in self._items:
                if keys == plain and all(r() is o for r, o in zip(refs, objects, strict=True)):
                    return True, value
        return False, None

    def put(self, objects: tuple[Any, ...], plain: tuple[Any, ...], value: Any) -> Any:
        """Keep ``value`` for ``objects`` and ``plain``, dropping the oldest beyond the
        size; returns it."""
        refs = tuple(weakref.ref(o) for o in objects)
        with self._lock:
            self._items[:] = [(refs, plain, value), *self._items[: self._size - 1]]
        return value


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
    #: the closure's low end (2nd percentile, m) over the whole session, free jaw motion
    #: included, where the outputs keep to the grasps; None where they fit every sample
    x_floor: float | None = None
    #: untrimmed, one flag per raw sample: the jaws hold the tissue. Where a fit keeps
    #: to the grasps (its outputs' windows may reach free jaws beside a grasp) or also
    #: reads free jaws (the force sensor's offset alone), the tissue's force is zero on
    #: the free samples: each tissue column is formed on the raw grid times these flags
    #: and filtered as the force is (:meth:`gated`); None: all in contact
    touching: NDArray[np.bool_] | None = None
    #: the law's offset holds in contact alone (its column gated as the tissue's are):
    #: the free samples of a window across a grasp's edge read the free jaws' own level,
    #: taken off the filtered force (:func:`~tissuecli.identify.prepare.fit_grasps`)
    offset_gated: bool = False

    @property
    def gate(self) -> Array | None:
        """1.0 at the outputs in contact and 0.0 at those of free jaws, shape (m,); None
        when every output is in contact."""
        if self.touching is None:
            return None
        return self.touching[self.keep].astype(float)

    @property
    def contact_weight(self) -> Array | None:
        """The share of each output's filter weight on samples in contact, shape (m,):
        1 inside a grasp, falling to 0 across its edges; None when every output is in
        contact. How far position noise reaches a gated column (its slope's factor)."""
        if self.touching is None:
            return None
        return self.smooth(self.touching.astype(float))

    def gated(self, u: Array, offset: int = 0) -> Array:
        """``u`` (a series on the raw grid, or on a filter's valid outputs starting
        ``offset`` samples into it) times the contact flags at its samples: the
        tissue's force is zero while the jaws are free. ``u`` itself when every sample
        is in contact."""
        if self.touching is None:
            return u
        return u * self.touching[offset : offset + u.size]

    def _half_gated(self, u: Array) -> Array:
        """:meth:`gated` for a series on the half window's valid outputs."""
        assert self.half is not None
        return self.gated(u, self.half[0].size // 2)

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

    def smooth_recursion(self, a: float, b: float, x_full: Array) -> Array:
        """:meth:`smooth` of the first-order recursion ``r_k = a r_{k-1} + b (x_k -
        x_{k-1})`` from rest over the untrimmed closure ``x_full`` (m), shape (m,):
        a relaxation branch's column (:meth:`~tissuecli.core.terms.Term.recursion`).

        Both are linear filters from rest, so they commute: the closure's increments
        are filtered once (:func:`increment_blocks`, kept for the closure last asked
        about) and the recursion runs on them. On the coarse grid (:meth:`every`) only
        the kept outputs are formed, ``stride`` filtered increments at a time: each
        kept output is ``a^stride`` times the one before plus ``b`` times the sum of
        the increments since, weighted ``a^j`` by their age j. Where the weights vary
        by at most a factor e either side of the block's middle, their Taylor series
        in ``ln a`` (to :data:`TAYLOR_TOLERANCE`) weighs the blocks' moments instead,
        a few numbers per block.
        """
        s = self.stride
        blocks, head, moments = increment_blocks(x_full, self.kernels[0], s)
        lam = -math.log(a) if a > 0 else math.inf
        half = lam * (s - 1) / 2  # the largest |ln| of a weight over the middle one's
        if half <= 1.0:
            # a^(s-1-j) = a^((s-1)/2) sum_k (-lam d_j)^k / k!, d_j = (s-1)/2 - j
            coef, bound = [1.0], 1.0  # bound: half^k / k!, the k-th term's largest share
            while len(coef) < moments.shape[1] and bound > TAYLOR_TOLERANCE:
                bound *= half / len(coef)
                coef.append(coef[-1] * -lam / len(coef))
            sums = math.exp(-half) * (moments[:, : len(coef)] @ np.array(coef))
        else:
            sums = blocks @ (a ** np.arange(s - 1, -1, -1, dtype=float))  # a^(s-1-j)
        y = first_order(b * sums, a**s)[head:]
        return y if self.rows is None else y[self.rows // s]

    def smooth_pointwise(
        self, fn: Callable[[Array], Array], x_full: Array, speed: Array | None = None
    ) -> Array:
        """:meth:`smooth` of ``fn(x_full)`` (:meth:`pointwise`), or of ``fn(x_full) *
        speed`` for a term of closure and speed, ``speed`` being the raw closure's
        central-difference speed ``np.gradient(x_full, self.dt)`` (m/s).

        On the coarse grid (:meth:`every`) of a closure on few ADC levels, the
        filtered indicator of each level (times the speed) is formed once
        (:func:`level_basis`), and each function's column is their sum weighted by its
        values at the levels: a product of a (rows, levels) matrix where each column
        was a filter pass over the record. The same sums in another order.
        """
        # the contact flags (:meth:`gated`) multiply every branch: the level basis holds
        # them, the strided filter's input takes them as it takes the speed
        basis = level_basis(self, x_full, speed is not None) if self.stride > 1 else None
        if basis is not None:
            values = fn(basis.levels)
            if np.all(np.isfinite(values)):
                return basis.weigh(values)
        if self.stride > 1 and x_full.size >= self.window:
            laid = padded_levels(x_full, self.window, self.stride)
            if laid is not None:  # read straight into the strided filter's input
                levels, index, out = laid
                # np.take: the same gather as indexing, a fifth faster on 6e5 samples
                u = np.take(np.append(np.asarray(fn(levels), dtype=float), 0.0), index)
                if speed is not None:
                    used = min(speed.size, u.size)  # beyond: the padding's zeros
                    np.multiply(u[:used], speed[:used], out=u[:used])
                if self.touching is not None:
                    used = min(self.touching.size, u.size)
                    np.multiply(u[:used], self.touching[:used], out=u[:used])
                assert self.rows is not None
                kept = convolve_padded_every(u, self.kernels[0], self.stride, out)
                return kept[self.rows // self.stride]
        u = self.pointwise(fn, x_full)
        return self.smooth(self.gated(u if speed is None else u * speed))

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
        return replace(self.outputs(kept), stride=stride, step_s=self.dt)

    def outputs(self, kept: NDArray[np.intp]) -> Kinematics:
        """These kinematics at their outputs numbered ``kept`` (in time order)."""
        rows = np.arange(self.time.size) if self.rows is None else self.rows
        return replace(
            self,
            time=self.time[kept],
            x_raw=self.x_raw[kept],
            x=self.x[kept],
            v=self.v[kept],
            a=self.a[kept],
            force=self.force[kept],
            force_raw=self.force_raw[kept],
            keep=rows[kept] + self.window // 2,  # type: ignore[arg-type]
            rows=rows[kept],
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

        if term.shapes:  # many shapes on one closure: filtered once per level
            return self.smooth_pointwise(r, x_full)
        return self.smooth(self.gated(self.pointwise(r, x_full)))

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
            return self._row_gated(term(self.v))
        if self.touching is not None:
            v, spread, n_v, share = self._contact_speed(x_full, noise_var)
            return self._half_smooth(share * term.expected(v, spread - n_v), x_full)
        v, spread, n_v = self._half_speed(x_full, noise_var)
        return self._half_smooth(term.expected(v, spread - n_v), x_full)

    def _contact_speed(self, x_full: Array, noise_var: float) -> tuple[Array, Array, float, Array]:
        """:meth:`_half_speed` over the samples in contact alone, and each half window's
        share of weight in contact ``m_h = g_h * touching``, on the half window's valid
        outputs: the speed ``g_h * (touching * x') / m_h`` and the spread ``s^2
        a^2`` of the acceleration formed alike, from the raw grid's central
        differences. ``g_h * (m_h * E[r](v, spread - n_v))`` is then the gated column
        (:meth:`gated`): exact for a linear r, ``g * (touching * x')``; the half
        window's own speed would carry the free jaws' approach, faster than the
        tissue lets them close, into each grasp's first samples and take damping's
        force for less than it is."""
        assert self.half is not None and self.touching is not None
        gh, gh1, _, s2 = self.half
        n_v = noise_var * float(gh1 @ gh1)
        m = self.touching.astype(float)
        speed = np.gradient(x_full, self.dt)
        share = convolve_valid(m, gh)
        some = share > 1e-9
        safe = np.where(some, share, 1.0)
        v = np.where(some, convolve_valid(m * speed, gh) / safe, 0.0)
        a = np.where(some, convolve_valid(m * np.gradient(speed, self.dt), gh) / safe, 0.0)
        return v, s2 * a * a, n_v, np.where(some, share, 0.0)

    def acceleration_input(self, term: Term, x_full: Array) -> Array:
        """The column ``~ g * r(a)`` of an acceleration term: ``r(a)`` where every output
        is in contact; otherwise with half kernels ``g_h * (touching * r(a_h))``, the
        acceleration ``a_h = g_h'' * x`` of the half window gated on the raw grid as the
        tissue's force is (:meth:`gated`). (Over the samples in contact alone, as the
        speed is, from the raw grid's second differences, its noise put more intervals
        of M off their truth on random grasp sessions.)"""
        if self.touching is None:
            return term(self.a)
        if self.half is None:
            return self._row_gated(term(self.a))
        if _proportional(term):
            return term(self._half_smooth(self._gated_acceleration(x_full), x_full))
        return self._half_smooth(
            self._half_gated(term(convolve_valid(x_full, self.half[2]))), x_full
        )

    def _gated_acceleration(self, x_full: Array) -> Array:
        """``g_h * (touching * x'')`` on the half window's valid outputs (m/s^2), by
        parts: ``g_h'' * (touching * x)`` less each grasp edge's terms, which read the
        closure on the two samples either side of it from a polynomial through the half
        window's span about it (the jaws move smoothly through the touch; a single
        sample's closure, over ``dt^2``, would carry its noise into the column).
        Gating the half window's own acceleration ``g_h'' * x`` instead smooths the
        step of the flags once too few: at 3.7 kHz its column was off by 19 % of its
        RMS within a quarter window of the edges, where a relaxation branch took up the misfit."""
        assert self.half is not None and self.touching is not None
        gh, _, gh2, _ = self.half
        m = self.touching[: x_full.size].astype(float)
        inner = convolve_valid(m * x_full, gh2)
        step = np.diff(m)  # +1 where a grasp starts after sample k, -1 where it ends
        edges = np.flatnonzero(step)
        if edges.size == 0:
            return inner
        # m D2(x) = D2(m x) - c: c reads x beside each edge alone (summation by parts)
        near = _edge_closures(x_full, edges, gh.size // 2)
        c = np.zeros(x_full.size)
        np.add.at(c, edges, step[edges] * near[:, 1])
        np.add.at(c, edges + 1, -step[edges] * near[:, 0])
        return inner - convolve_valid(c / (self.dt * self.dt), gh)

    def _row_gated(self, column: Array) -> Array:
        """A column without half kernels to gate it on the raw grid: zero at the outputs
        whose own sample is free (exact where every window lies wholly in or out of
        contact)."""
        gate = self.gate
        return column if gate is None else column * gate

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
            return self._weighted(term.derivative(self.v))
        if self.half is None:
            k1 = self.kernels[1]
            return self._row_gated(term.expected_slope(self.v, noise_var * float(k1 @ k1)))
        if self.touching is not None:
            v, spread, n_v, share = self._contact_speed(x_full, noise_var)
            slope = term.expected_slope(v, np.maximum(spread - n_v, 0.0) + n_v)
            return self._half_smooth(share * slope, x_full)
        v, spread, n_v = self._half_speed(x_full, noise_var)
        # the column's own spread (less the noise's, at least none) and the noise's
        slope = term.expected_slope(v, np.maximum(spread - n_v, 0.0) + n_v)
        return self._half_smooth(slope, x_full)

    def _weighted(self, slope: Array) -> Array:
        """A slope at the outputs times their share of contact (:attr:`contact_weight`):
        the noise that reaches a gated column, the slope slow beside the noise."""
        weight = self.contact_weight
        return slope if weight is None else slope * weight

    def _half_speed(self, x_full: Array, noise_var: float) -> tuple[Array, Array, float]:
        """The half window's speed (m/s), the other half's spread of speeds about it
        (m^2/s^2) and its noise's variance (m^2/s^2), on the raw grid's valid outputs."""
        assert self.half is not None
        _, gh1, gh2, s2 = self.half
        n_v = noise_var * float(gh1 @ gh1)
        found, kept = _HALF.get((x_full, gh1))  # a long session's speed terms share them
        if found:
            return (*kept, n_v)
        a = convolve_valid(x_full, gh2)
        v, spread = convolve_valid(x_full, gh1), s2 * a * a
        if self.stride > 1:
            _HALF.put((x_full, gh1), (), (v, spread))
        return v, spread, n_v

    def _half_smooth(self, u: Array, x_full: Array) -> Array:
        """``g_h * u`` for ``u`` on the half window's outputs, on the fitted samples."""
        assert self.half is not None
        trim = (u.size - self.half[0].size + 1 - (x_full.size - self.window + 1)) // 2
        if self.stride > 1:  # only the kept outputs, from the full filter's first
            assert self.rows is not None
            kept = convolve_valid_every(u[trim:], self.half[0], self.stride)
            return kept[self.rows // self.stride]
        col = convolve_valid(u, self.half[0])
        return self._rows(col[trim : col.size - trim])  # to the full filter's outputs


#: the half window's speed and spread for the last closure (see every())
_HALF = _Recent()


def _proportional(term: Term) -> bool:
    """Whether ``term`` is ``c u`` for some constant c (it then commutes with filters)."""
    probe = np.array([0.0, 1.0, 2.0, -1.0])
    r = term(probe)
    return bool(np.allclose(r, probe * r[1], rtol=1e-12, atol=0.0))


#: the degree of the polynomial that reads the closure either side of a grasp's edge
#: (:func:`_edge_closures`): a cubic's slope at the middle of its span is off by the
#: fifth derivative times the span's fourth power, a quintic's by the seventh times the
#: sixth; at 6.6 kHz the cubic read the jaws' speed at the touch 0.3 % low and high at
#: every edge alike, a misfit along the edges that an offset took up
EDGE_DEGREE = 5


def _edge_closures(x: Array, edges: NDArray[np.intp], span: int) -> Array:
    """The closure (m) at samples ``k`` and ``k + 1`` for each ``k`` of ``edges``, shape
    (e, 2), from a least-squares polynomial of degree :data:`EDGE_DEGREE` through the
    ``span`` samples either side (fewer at a session's ends; a cubic where fewer than
    twice its coefficients are there, the samples themselves where fewer than 8)."""
    out = np.column_stack([x[edges], x[edges + 1]]).astype(float)
    cache: dict[tuple[int, int], Array] = {}
    for i, k in enumerate(edges):
        lo, hi = max(0, k - span), min(x.size, k + span + 2)
        if hi - lo < 8:
            continue
        key = (lo - k, hi - k)
        weights = cache.get(key)
        if weights is None:
            terms = EDGE_DEGREE + 1 if hi - lo >= 2 * (EDGE_DEGREE + 1) else 4
            t = np.arange(lo - k, hi - k, dtype=float) / max(span, 1)
            basis = np.vander(t, terms, increasing=True)
            at = np.vander(np.array([0.0, 1.0]) / max(span, 1), terms, increasing=True)
            weights = cache[key] = at @ np.linalg.pinv(basis)
        out[i] = weights @ x[lo:hi]
    return out


def first_order(u: Array, a: float) -> Array:
    """The recursion ``y_k = a y_{k-1} + u_k`` from rest, shape (n,), for ``0 <= a <=
    1``, by doubling: after the pass with shift d each ``y_k`` sums the last 2d
    inputs, ``a^(k-i) u_i``; log2(n) vector passes, the sums added pairwise."""
    y = np.array(u, dtype=float)
    d, p = 1, a
    while d < y.size and p != 0.0:
        y[d:] += p * y[:-d]  # the product is formed before the sum is written
        d, p = 2 * d, p * p
    return y


#: the terms of a Taylor series :meth:`Kinematics.smooth_recursion` keeps: those of
#: more than this fraction of the block's sum of absolute filtered increments
TAYLOR_TOLERANCE = 1e-18

#: the moments kept of each block (the series' terms at ``|ln| = 1``: 1/20! = 4e-19)
MOMENTS = 21

#: the filtered increments of the last closure, kernel and stride
_INCREMENTS = _Recent()


def increment_blocks(x: Array, kernel: Array, stride: int) -> tuple[Array, int, Array]:
    """The closure's increments ``x_k - x_{k-1}`` (0 at the first sample) through the
    causal filter ``kernel`` from rest, ``w = np.convolve(dx, kernel)[:n]``, with zeros
    in front and cut into rows of ``stride``, shape (r, stride), so that the filtered
    output i * stride of ``np.convolve(., kernel, "valid")`` sits at the end of row
    ``head + i``; ``head``; and the rows' moments about their middle, ``sum_j w_j
    d_j^k`` with ``d_j = (stride - 1) / 2 - j``, k < :data:`MOMENTS`, shape (r,
    MOMENTS), each column contiguous. Kept for the last closure, kernel and stride
    asked about (a fit asks about one, for each shape of its relaxation branches)."""
    found, kept = _INCREMENTS.get((x, kernel), (stride,))
    if found:
        return kept  # type: ignore[no-any-return]
    m = kernel.size
    count = (x.size - m) // stride + 1  # filtered outputs on the stride's grid
    dx = np.diff(x, prepend=x[:1])
    w = convolve_valid(np.concatenate([np.zeros(m - 1), dx]), kernel)
    pad = (-m) % stride  # the recursion at rest before the record
    blocks = np.concatenate([np.zeros(pad), w[: m + stride * (count - 1)]]).reshape(-1, stride)
    head = (pad + m) // stride - 1
    d = (stride - 1) / 2 - np.arange(stride, dtype=float)
    moments = np.asfortranarray(blocks @ (d[:, None] ** np.arange(MOMENTS)))
    return _INCREMENTS.put((x, kernel), (stride,), (blocks, head, moments))  # type: ignore[no-any-return]


#: largest level basis built (bytes, its entries while they are summed)
BASIS_BYTES = 64 << 20

#: a level basis is built where a column from it costs at most this fraction of the
#: multiply-adds of a filter pass over the record
BASIS_COST = 0.25


@dataclass(frozen=True, eq=False)
class LevelBasis:
    """The filtered indicators of a closure's levels on a coarse grid
    (:func:`level_basis`): ``levels`` (L,) in m, and the (rows, L) matrix B, held
    dense or, where each output's window holds few of the levels, as its nonzero
    entries ``(row, col, data)``."""

    levels: Array
    dense: Array | None
    row: NDArray[np.intp]
    col: NDArray[np.intp]
    data: Array
    size: int

    def weigh(self, values: Array) -> Array:
        """``B @ values``, shape (rows,): the filtered column of a function whose
        values at the levels are ``values`` (L,)."""
        if self.dense is not None:
            return self.dense @ values
        return np.bincount(self.row, weights=self.data * values[self.col], minlength=self.size)


#: the level bases of the last two kinematics, closures and speed flags
_BASES = _Recent(size=2)


def level_basis(kin: Kinematics, x: Array, speed: bool = False) -> LevelBasis | None:
    """The closure's levels (:func:`_levels`) and the coarse grid's
    (:meth:`Kinematics.every`) filtered indicators of each, ``B[:, l] =
    kin.smooth((x == levels[l]) * u)`` with ``u`` 1, or with ``speed`` the closure's
    central-difference speed ``np.gradient(x, kin.dt)`` (m/s); None where a column
    from them would not cost much less than filtering it (:data:`BASIS_COST`) or
    they would take too much memory (:data:`BASIS_BYTES`). Kept for the last two
    kinematics, closure and ``speed`` asked about.

    Output i sums ``kernel[::-1][j] u[i * stride + j]``. Cut into rows of ``stride``
    samples, a row of the record holds few levels: each (row, level) pair's samples
    are summed against each block of ``stride`` taps at once (one matrix product),
    and each sum is added to the output that block of taps reaches."""
    known, found = _BASES.get((kin, x), (speed,))
    if known:
        return found  # type: ignore[no-any-return]
    return _BASES.put((kin, x), (speed,), _level_basis(kin, x, speed))  # type: ignore[no-any-return]


def _level_basis(kin: Kinematics, x: Array, speed: bool) -> LevelBasis | None:
    found = _levels(x)
    k0 = kin.kernels[0]
    s, m = kin.stride, k0.size
    if found is None or s <= 1 or x.size < m:
        return None
    levels, index = found
    count = (x.size - m) // s + 1  # filtered outputs on the stride's grid
    L = levels.size
    q = -(-m // s)  # the kernel's blocks of taps
    taps = np.zeros(q * s)
    taps[:m] = k0[::-1]
    rows = count - 1 + q  # output i reads rows i ... i + q - 1 (taps beyond m are 0)
    used = min(x.size, rows * s)
    level = np.zeros(rows * s, dtype=np.intp)
    level[:used] = index[:used]
    pairs, pair_of = np.unique(np.repeat(np.arange(rows) * L, s) + level, return_inverse=True)
    entries = pairs.size * q  # at most, before those of one output and level are summed
    direct = count * m  # a filter pass's multiply-adds
    if min(count * L, 4 * entries) > BASIS_COST * direct or 16 * entries > BASIS_BYTES:
        return None
    # each pair's samples by their place in the row: 1 (or the speed) where it is there
    Z = np.zeros((pairs.size, s))
    u = np.ones(used) if not speed else np.gradient(x, kin.dt)[:used]
    if kin.touching is not None:  # the tissue's force is zero while the jaws are free
        u = u * kin.touching[:used]
    Z[pair_of[:used], np.arange(used) % s] = u
    P = Z @ taps.reshape(q, s).T  # (pairs, q): each pair against each block of taps
    del Z
    out = (pairs // L)[:, None] - np.arange(q)  # the output a pair's block c reaches
    ok = (out >= 0) & (out < count)
    bins = (out * L + (pairs % L)[:, None])[ok]
    weights = P[ok]
    del P, out, ok
    kept = np.arange(count) if kin.rows is None else kin.rows // s
    if count * L <= 4 * bins.size and 8 * count * L <= BASIS_BYTES:
        B = np.bincount(bins, weights=weights, minlength=count * L).reshape(count, L)
        return LevelBasis(levels, B[kept], *_EMPTY, kept.size)
    keys, where = np.unique(bins, return_inverse=True)
    data = np.bincount(where, weights=weights)
    position = np.full(count, -1)
    position[kept] = np.arange(kept.size)
    row = position[keys // L]
    on = row >= 0
    return LevelBasis(levels, None, row[on], (keys % L)[on], data[on], kept.size)


_EMPTY = (np.zeros(0, dtype=np.intp), np.zeros(0, dtype=np.intp), np.zeros(0))


#: the padded layout of the last closure, window and stride
_PADDED = _Recent()


def padded_levels(x: Array, m: int, stride: int) -> tuple[Array, NDArray[np.intp], int] | None:
    """The closure's levels (:func:`_levels`), each sample's level laid out as the padded
    input of the strided filter (:func:`~tissuecli.identify.spectrum.every_layout`: the
    record's samples, then the index one past the last level, whose value is 0), and
    the filter's outputs; None where the closure is not on few levels. A function's
    values at the levels, with a 0 appended, read at that index are the padded input
    itself: a long session's closure columns skip the record-long function values and
    their copy into the padded input. Kept for the last closure, window and stride."""
    known, found = _PADDED.get((x,), (m, stride))
    if known:
        return found  # type: ignore[no-any-return]
    levelled = _levels(x)
    if levelled is None:
        return None
    levels, index = levelled
    out, rows = every_layout(x.size, m, stride)
    used = min(x.size, rows * stride)
    laid = np.full(rows * stride, levels.size, dtype=np.intp)
    laid[:used] = index[:used]
    return _PADDED.put((x,), (m, stride), (levels, laid, out))  # type: ignore[no-any-return]


#: fewest samples per distinct closure level for :meth:`Kinematics.pointwise` to use them
SAMPLES_PER_LEVEL = 8

#: the levels of the last closure (None: not on few levels)
_LEVELS = _Recent()


def _levels(x: Array) -> tuple[Array, NDArray[np.intp]] | None:
    """The distinct values of ``x`` and each sample's index among them, if there are at
    most one per :data:`SAMPLES_PER_LEVEL` samples; kept for the last closure asked
    about (a fit asks about one, hundreds of times)."""
    known, found = _LEVELS.get((x,))
    if known:
        return found  # type: ignore[no-any-return]
    levels, index = np.unique(x, return_inverse=True)
    found = (levels, index.ravel()) if levels.size * SAMPLES_PER_LEVEL <= x.size else None
    return _LEVELS.put((x,), (), found)  # type: ignore[no-any-return]


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
