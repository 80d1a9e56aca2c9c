"""Design matrices of the tissue law on filtered kinematics, the errors-in-variables
correction for position noise, and least squares on scaled columns."""

from __future__ import annotations

import threading
import weakref
from collections import OrderedDict
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from ..core.terms import Law, Term
from .derivatives import Kinematics
from .spectrum import valid_spectrum

if TYPE_CHECKING:
    from .whiten import ARFilter

Array = NDArray[np.float64]


def position_noise_sd(x: Array, fs: float, valid: NDArray[np.bool_] | None = None) -> float:
    """SD of white noise on position from the flat top of its spectrum (m), over the
    stretches of ``valid`` samples when given (clipped samples carry no noise)."""
    freqs, p = valid_spectrum(x - x.mean(), fs, 4096, valid)
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
    return np.column_stack([term_column(t, kin, x_full, sigma_x, columns) for t in law.terms])


def term_column(
    term: Term,
    kin: Kinematics,
    x_full: Array,
    sigma_x: float = 0.0,
    columns: dict[str, Array] | None = None,
    raw_speed: tuple[float, Array] | None = None,
    keep: bool = True,
) -> Array:
    """One term's column of :func:`design`, shape (m,); kept in ``columns`` (by
    :func:`column_key`) unless the term has shape parameters. ``raw_speed``, the sample
    interval (s) and central-difference speed (m/s) of :func:`raw_speed`, if already
    known. ``keep=False``: a shaped column neither looked up nor kept among the recent
    ones (a shape that will not come back, as a chain's)."""
    var = sigma_x**2
    if term.shapes and not keep:
        return _column(term, kin, x_full, var, raw_speed)
    if term.shapes:  # one column per shape node: only the most recent are kept
        key = ("column", var, column_key(term))
        found = RECENT.get(key, kin, x_full)
        if found is None:
            found = RECENT.put(key, kin, x_full, _column(term, kin, x_full, var, raw_speed))
        return found  # type: ignore[no-any-return]
    if columns is None:
        return _column(term, kin, x_full, var, raw_speed)
    key = column_key(term)
    if key not in columns:
        columns[key] = _column(term, kin, x_full, var)
    return columns[key]


def column_key(term: Term) -> str:
    """What a term's column depends on: its name, symbol and shape parameters."""
    shape = ",".join(f"{k}={v!r}" for k, v in sorted(term.shape.items()))
    return f"{term.name}|{term.symbol}|{shape}"


def held_closure(x: Array, free: NDArray[np.bool_]) -> Array:
    """The closure that drives a term with memory (a relaxation branch), shape (n,), m:
    ``x`` in contact, and across each stretch of free jaws (``free``) ``x`` held from
    below at the lower of the closures at its two edges (the one edge at either end).

    The tissue is indented only in contact: while the jaws are open it relaxes at a
    constant indentation, as if held at the contact closure, and the open jaws' travel
    (away and back) is no strain of it. Driven by the raw closure, a branch of the
    true law predicted the held-out grasps of random scenes 1.1-7 times the force's
    noise floor; held, at the floor. Held from below rather than replaced: where a
    stretch called free is still in contact (a release read early), the closure above
    the edges' still strains the tissue."""
    x = np.asarray(x, dtype=float)
    free = np.asarray(free, dtype=bool)
    if not free.any() or free.all():
        return x
    out = x.copy()
    edges = np.flatnonzero(np.diff(np.concatenate([[0], free.astype(np.int8), [0]])))
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        sides = [x[a - 1]] if a > 0 else []
        sides += [x[b]] if b < x.size else []
        out[a:b] = np.maximum(x[a:b], min(sides))
    return out


def raw_speed(kin: Kinematics, x_full: Array) -> tuple[float, Array]:
    """The sample interval (s) and the central-difference speed on the raw grid (m/s)
    that terms of the closure's history and of closure and speed together are formed
    from."""
    dt = kin.dt
    return dt, np.gradient(x_full, dt)


def _column(
    term: Term,
    kin: Kinematics,
    x_full: Array,
    var: float,
    speed: tuple[float, Array] | None = None,
) -> Array:
    """A term's column, the tissue's terms gated by the contact flags on the raw grid
    (:meth:`Kinematics.gated`: zero force on the free samples of an output's window,
    as the filtered force has there) and filtered as the force is; an offset stays with
    the jaws free, but where it holds in contact alone (:attr:`Kinematics.offset_gated`)."""
    if term.variable == "x":
        return kin.stiffness_input(term, x_full, var)
    if term.variable == "v":
        return kin.damping_input(term, x_full, var)
    if term.variable == "a":
        return kin.acceleration_input(term, x_full)
    if term.variable in ("xv", "h"):
        # terms of closure and speed together (contact damping) or of the closure's
        # history (relaxation) are formed on the raw grid and filtered as the force is;
        # the central-difference speed's noise is uncorrelated with the closure at the
        # same sample, so the product carries no noise bias
        drive = x_full
        if term.memory and kin.drive is not None:
            drive = kin.drive  # the tissue is not indented while the jaws are free
        dt, v_full = speed or raw_speed(kin, x_full)
        if term.memory:
            if kin.touching is not None:
                # gated on the raw grid as the tissue's force is: the windows across a
                # grasp's edge see the branch's force in contact and none beside it.
                # (Gated at each output's own sample, the filtered branch carried its
                # force onto the free side of an edge and left half of it out on the
                # other: a bias along the edges that put Km, tau, S and M of random
                # relaxation grasp sessions two posterior SDs off together.)
                series = term.series(dt, drive, v_full, np.zeros_like(x_full))
                return kin.smooth(kin.gated(series))
            # ungated, a branch's recursion commutes with the filter
            recursion = term.recursion(kin.dt) if kin.stride > 1 else None
            if recursion is not None:  # on a long session's coarse grid: the same column
                return kin.smooth_recursion(*recursion, drive)
            return kin.smooth(term.series(dt, drive, v_full, np.zeros_like(x_full)))
        if term.closure_factor(x_full[:1]) is not None:
            if kin.stride > 1:
                return kin.smooth_pointwise(term.closure_factor, x_full, v_full)  # type: ignore[arg-type]
            # f(x) xdot with f formed once per ADC level (Kinematics.pointwise): the same
            # products, at the cost of indexing where it was a power of every sample
            return kin.smooth(kin.gated(kin.pointwise(term.closure_factor, x_full) * v_full))  # type: ignore[arg-type]
        return kin.smooth(kin.gated(term.series(dt, drive, v_full, np.zeros_like(x_full))))
    if kin.offset_gated and kin.touching is not None:
        return kin.smooth(kin.touching.astype(float))
    return term(np.ones(kin.time.size))


def eiv_correction(
    law: Law,
    kin: Kinematics,
    x_full: Array,
    sigma_x: float,
    paths: dict[str, tuple[Array, Array]] | None = None,
    whiten: ARFilter | None = None,
) -> Array:
    """Expected contribution of position noise to A^T A (errors in variables).

    Column j carries noise ``d_j * (k_j * e)`` to first order, with ``d_j`` the
    term's slope and ``k_j`` its kernel (none for an offset), so
    ``E[noise_i . noise_j] = sigma_x^2 (k_i . k_j) sum_n d_i d_j``. Subtracting it
    removes the attenuation bias that noisy derivatives put on M. ``paths``, if
    given, keeps each term's :func:`noise_path` by name, as ``columns`` does in
    :func:`design`. ``whiten``: the correction of the columns passed through that
    filter (each kernel convolved with its taps; the slopes, slow beside the noise,
    taken as constant over its span).
    """
    parts = [term_noise_path(t, kin, x_full, paths, sigma_x) for t in law.terms]
    K = np.array([k for k, _ in parts])
    d = np.column_stack([slope for _, slope in parts])
    if whiten is not None:
        K, d = whiten.kernels(K, kin.stride), d[whiten.span :]
    return sigma_x**2 * (K @ K.T) * (d.T @ d)


def term_noise_path(
    term: Term,
    kin: Kinematics,
    x_full: Array,
    paths: dict[str, tuple[Array, Array]] | None = None,
    sigma_x: float = 0.0,
) -> tuple[Array, Array]:
    """:func:`noise_path`, kept in ``paths`` (by :func:`column_key`) unless the term has
    shape parameters: every law with the term shares it, as its column (one fit, one
    ``sigma_x``)."""
    if paths is None or term.shapes:
        return noise_path(term, kin, x_full, sigma_x)
    key = column_key(term)
    if key not in paths:
        paths[key] = noise_path(term, kin, x_full, sigma_x)
    return paths[key]


def noise_path(
    term: Term, kin: Kinematics, x_full: Array, sigma_x: float = 0.0, keep: bool = True
) -> tuple[Array, Array]:
    """How position noise of SD ``sigma_x`` (m) reaches a term's column
    (:func:`eiv_correction`): the kernel it passes through, shape (w,), and the
    column's slope at each fitted sample, shape (m,) (a term with shape parameters:
    kept among the most recent, as its column is). Only a :attr:`~Term.step` term's
    slope depends on ``sigma_x`` (:meth:`Kinematics.damping_slope`); ``keep`` as in
    :func:`term_column`."""
    if not term.shapes or not keep:
        return _noise_path(term, kin, x_full, sigma_x)
    key = ("path", sigma_x**2 if term.step else 0.0, column_key(term))
    found = RECENT.get(key, kin, x_full)
    if found is None:
        found = RECENT.put(key, kin, x_full, _noise_path(term, kin, x_full, sigma_x))
    return found  # type: ignore[no-any-return]


def _noise_path(term: Term, kin: Kinematics, x_full: Array, sigma_x: float) -> tuple[Array, Array]:
    # the slopes of the tissue's terms are gated as their columns are (design's
    # _column): on the raw grid where the half kernels allow, else by the share of
    # each output's filter weight in contact
    if term.variable == "x":
        if term.shapes:  # many shapes on one closure: filtered once per level
            return kin.kernels[0], kin.smooth_pointwise(term.derivative, x_full)
        return kin.kernels[0], kin.smooth(kin.gated(kin.pointwise(term.derivative, x_full)))
    if term.variable == "v":
        return kin.kernels[1], kin.damping_slope(term, x_full, sigma_x**2)
    if term.variable == "a":
        slope = term.derivative(kin.a)
        weight = kin.contact_weight
        return kin.kernels[2], slope if weight is None else slope * weight
    # a constant, or a history filtered from the raw closure, carries none to first order
    return np.zeros_like(kin.kernels[0]), np.zeros(kin.v.size)


class RecentColumns:
    """The columns and noise paths of terms with shape parameters computed last, by
    session and shape: a structure search scores sibling laws (with and without an
    offset, say) on one grid of shapes, and each node's columns cost a filter pass
    apiece. At most ``max_bytes`` are held, the least recently used dropped first; an
    entry answers only for the very kinematics and closure it was computed from (held
    by weak reference, so a finished fit's are never matched by a new one's). Callers
    must not write to what they are given."""

    def __init__(self, max_bytes: int = 32 << 20) -> None:
        self.max_bytes = max_bytes
        self._items: OrderedDict[tuple[Any, ...], tuple[Any, Any, Any, int]] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    def get(self, key: tuple[Any, ...], kin: Kinematics, x_full: Array) -> Any:
        """What was kept for ``key`` on these kinematics and closure, else None."""
        full = (*key, id(kin), id(x_full))
        with self._lock:
            item = self._items.get(full)
            if item is None or item[0]() is not kin or item[1]() is not x_full:
                return None
            self._items.move_to_end(full)
            return item[2]

    def put(self, key: tuple[Any, ...], kin: Kinematics, x_full: Array, value: Any) -> Any:
        """Keep ``value`` (an array or a tuple of arrays) for ``key``; returns it."""
        parts = value if isinstance(value, tuple) else (value,)
        size = int(sum(np.asarray(v).nbytes for v in parts))
        full = (*key, id(kin), id(x_full))
        with self._lock:
            if self._items and next(reversed(self._items.values()))[0]() is not kin:
                self._drop_dead()  # a new fit: what finished fits left is of no use
            old = self._items.pop(full, None)
            if old is not None:
                self._bytes -= old[3]
            if size <= self.max_bytes:
                self._items[full] = (weakref.ref(kin), weakref.ref(x_full), value, size)
                self._bytes += size
            while self._bytes > self.max_bytes:
                self._bytes -= self._items.popitem(last=False)[1][3]
        return value

    @property
    def nbytes(self) -> int:
        """Bytes held."""
        return self._bytes

    def _drop_dead(self) -> None:
        for key in [k for k, v in self._items.items() if v[0]() is None or v[1]() is None]:
            self._bytes -= self._items.pop(key)[3]

    def clear(self) -> None:
        with self._lock:
            self._items.clear()
            self._bytes = 0


#: the shaped columns of the fits in this process (a few tens of MB at most)
RECENT = RecentColumns()


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
