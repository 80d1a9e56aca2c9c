"""A long session's shaped closure columns from a basis that grows as shapes are seen.

On the coarse grid (:mod:`~tissuecli.identify.decimate`) the column of a function of
the closure is ``B v``: ``v`` its values at the closure's L ADC levels, ``B`` (rows, L)
the filtered indicator of each level (times the raw speed, for a term of closure and
speed). Where ``B`` is too dense to hold (a noisy closure flickering over hundreds of
levels in each filter window), every shape node cost a filter pass over the record
per column. But the nodes a climb to a sharp peak evaluates lie close together, and
so do their functions: all but the first few are, to rounding, sums of those before.

:class:`ClosureSpan` keeps an orthonormal basis of the functions seen (``v`` weighted
by each level's share of the record, so that the basis is orthonormal in the column's
own energy) and the filtered column of each basis vector. A new function is projected
on it; where what is left is below :data:`TOLERANCE` of it, its column is the basis
columns weighed by its coordinates, else what is left is filtered (one pass over the
record, as before) and joins the basis. :class:`SpanProducts` keeps the products of
the basis columns with each other, with a law's shape-free columns and with the force,
so that a law's statistics at a new node are formed in the basis's coordinates without
touching a row of the record (:meth:`~tissuecli.identify.shaped.ShapedPass.reduced`).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from ..core.terms import Term
from .derivatives import Kinematics
from .derivatives.base import level_basis, padded_levels

if TYPE_CHECKING:
    from .whiten import ARFilter

Array = NDArray[np.float64]

#: what may be left of a function (in its energy over the record) after its projection
#: on the basis for its column to be the basis columns' weighted sum; the column is then
#: within about this fraction of the one a filter pass gives (rounding: 1e-16)
TOLERANCE = 1e-12

#: :data:`TOLERANCE` for a term's slope, which enters only the errors-in-variables
#: correction ``sigma_x^2 (k . k) sum d d``, a small share of the Gram matrix (9e-9 of
#: the contact's diagonal on the 12-bit Hunt-Crossley session): a slope within 1e-6 of
#: its energy moves it by less than 1e-6 of that share, and seldom needs a filter pass
SLOPE_TOLERANCE = 1e-6

#: bytes of basis columns one span may hold (as a level basis, BASIS_BYTES); beyond, a
#: node's column is filtered as before
MAX_BYTES = 64 << 20


class ClosureSpan:
    """The basis of functions of one closure's levels seen so far and their columns.

    Parameters
    ----------
    kin : Kinematics
        The coarse grid's kinematics (``stride > 1``).
    x_full : ndarray, shape (n,)
        The untrimmed raw closure (m), on few levels.
    speed : ndarray, shape (n,), optional
        The raw speed (m/s) a term of closure and speed multiplies its function by.
    """

    def __init__(self, kin: Kinematics, x_full: Array, speed: Array | None = None) -> None:
        laid = padded_levels(x_full, kin.window, kin.stride)
        if laid is None:
            raise ValueError("the closure is not on few levels")
        self.kin, self.x_full, self.speed = kin, x_full, speed
        self.levels, index, _ = laid
        used = min(x_full.size, index.size)
        # each level's energy in the record: its samples (times the speed squared)
        energy = np.ones(used) if speed is None else np.square(speed[:used])
        power = np.bincount(index[:used], weights=energy, minlength=self.levels.size + 1)
        self.weight = np.sqrt(power[: self.levels.size])
        self.inverse = np.divide(1.0, self.weight, out=np.zeros_like(self.weight),
                                 where=self.weight > 0)  # fmt: skip
        self.rows = kin.force.size
        self.most = int(min(self.levels.size, MAX_BYTES // (8 * max(self.rows, 1))))
        self._Q = np.zeros((0, self.levels.size))  # basis vectors, weighted coordinates
        # their filtered columns, one a row: room for all at once (zeros the system
        # hands out as rows are written), where doubling copied all before
        self._C = np.zeros((self.most, self.rows))
        self.size = 0
        self.misses = 0
        #: coordinates found before, by what the function hangs on (kept by
        #: :class:`ReducedPass`): a node of one law's grid is a node of its siblings'
        self.known: dict[Any, Array] = {}
        self._lock = threading.Lock()

    @property
    def basis(self) -> Array:
        """The basis vectors (weighted by :attr:`weight`), one a row, shape (r, L)."""
        return self._Q[: self.size]

    @property
    def columns(self) -> Array:
        """The basis vectors' filtered columns, one a row, shape (r, rows)."""
        return self._C[: self.size]

    def coordinates(self, values: Array, tolerance: float = TOLERANCE) -> Array | None:
        """Coordinates ``c`` (shape (r,), the basis's size once it has grown) such that
        ``c @`` :attr:`columns` is the filtered column of the function whose values at
        the levels are ``values`` (L,), within ``tolerance`` of its energy; None if they
        are not all finite or the basis is full."""
        values = np.asarray(values, dtype=float)
        if not np.all(np.isfinite(values)):
            return None
        with self._lock:
            c, rest, left = _project(self._Q[: self.size], self.weight * values, tolerance)
            if rest is None:
                return c
            if self.size >= self.most:
                return None
            q = rest / left
            # gated by the contact flags on the raw grid (Kinematics.smooth_pointwise)
            column = self.kin.smooth_pointwise(lambda _: q * self.inverse, self.x_full,
                                               self.speed)  # fmt: skip
            self._Q = _room(self._Q, self.size)
            self._Q[self.size] = q
            self._C[self.size] = column
            self.size += 1
            self.misses += 1
            return np.append(c, left)

    def coordinates_many(
        self, values: list[Array], tolerances: list[float]
    ) -> list[Array | None]:
        """:meth:`coordinates` of several functions, those the basis holds projected
        together (one read of the basis)."""
        V = np.asarray(values, dtype=float) * self.weight
        if not np.all(np.isfinite(V)):
            return [self.coordinates(v, t) for v, t in zip(values, tolerances, strict=True)]
        with self._lock:
            Q = self._Q[: self.size]
            # row by row (matrix-vector products, see :func:`product`)
            c = product(V, Q)
            rest = np.concatenate([V[i : i + 1] - c[i : i + 1] @ Q for i in range(len(V))])
        left = np.sqrt(np.einsum("ij,ij->i", rest, rest))
        norm = np.sqrt(np.einsum("ij,ij->i", V, V))
        return [c[i] if left[i] <= tolerances[i] * norm[i]
                else self.coordinates(values[i], tolerances[i])
                for i in range(len(values))]  # fmt: skip



def _project(Q: Array, v: Array, tolerance: float) -> tuple[Array, Array | None, float]:
    """Coordinates of ``v`` on the orthonormal rows of ``Q``, what is left of it and that
    rest's norm; the rest None where it is within ``tolerance`` of ``v``'s norm. A second
    pass keeps the basis orthonormal to rounding."""
    norm = float(np.sqrt(v @ v))
    c = Q @ v
    rest = v - c @ Q
    if norm == 0.0 or float(np.sqrt(rest @ rest)) <= tolerance * norm:
        return c, None, 0.0
    again = Q @ rest
    rest -= again @ Q
    c += again
    left = float(np.sqrt(rest @ rest))
    return (c, None, left) if left <= tolerance * norm else (c, rest, left)


#: most rows of the thinner stack :func:`product` takes one at a time
THIN = 3


def product(A: Array, B: Array) -> Array:
    """``A @ B.T`` of two stacks of rows, shape (r, s), one matrix-vector product per
    row of the thinner where it has 2 to :data:`THIN` rows. A matrix product of a few
    rows by many packs (copies) the many first, and costs about twice as much as a
    pass over them per row; a stack of one row is already a matrix-vector product, so
    each row's numbers are those of that row's product alone."""
    r, s = A.shape[0], B.shape[0]
    if 1 < r <= THIN and r <= s:
        return np.concatenate([A[i : i + 1] @ B.T for i in range(r)])
    if 1 < s <= THIN:
        return np.concatenate([A @ B[j : j + 1].T for j in range(s)], axis=1)
    return A @ B.T


def _room(stack: Array, size: int) -> Array:
    """``stack`` (rows of which ``size`` are in use) with room for one more: doubled
    (at least 16 rows) when full."""
    if size < stack.shape[0]:
        return stack
    grown = max(16, 2 * size)
    return np.concatenate([stack, np.zeros((grown - size, stack.shape[1]))])


def pad(c: Array, size: int) -> Array:
    """Coordinates taken before the basis grew, with zeros for the vectors added since."""
    return c if c.size == size else np.concatenate([c, np.zeros(size - c.size)])


class Grown:
    """A product ``A @ B.T`` of two stacks of rows that only grow (basis columns, or a
    fixed matrix's columns), extended by the blocks new rows add.

    ``left`` and ``right`` give the stacks as they stand, shape (r, m) and (s, m);
    ``right`` None: the product of ``left`` with itself (symmetric: each new block
    formed once).
    """

    def __init__(
        self,
        left: Callable[[], Array],
        right: Callable[[], Array] | None,
        sizes: Callable[[], tuple[int, int]] | None = None,
    ) -> None:
        self.left, self.right, self.sizes = left, right, sizes
        self.value = np.zeros((0, 0))

    def __call__(self) -> Array:
        if self.sizes is not None and self.sizes() == self.value.shape:
            return self.value  # nothing new (the stacks not even looked at)
        A = self.left()
        B = A if self.right is None else self.right()
        r0, s0 = self.value.shape
        if A.shape[0] == r0 and B.shape[0] == s0:
            return self.value
        out = np.empty((A.shape[0], B.shape[0]))
        out[:r0, :s0] = self.value
        if r0 < A.shape[0]:
            out[r0:, :] = product(A[r0:], B)
        if s0 < B.shape[0]:
            if self.right is None:
                out[:r0, s0:] = out[s0:, :r0].T
            else:
                out[:r0, s0:] = product(A[:r0], B[s0:])
        self.value = out
        return out


class SpanProducts:
    """The basis columns of a fit's spans through its prewhitening filter (if any), and
    their products with each other (kept once per fit and filter) and with the rows a
    law's slopes are read at."""

    def __init__(self, whiten: ARFilter | None) -> None:
        self.whiten = whiten
        self._white: dict[int, tuple[ClosureSpan, int, Array]] = {}
        self._grams: dict[tuple[int, int, str], Grown] = {}

    def white(self, span: ClosureSpan | RowSpan) -> Array:
        """The span's basis columns through the filter, one a row, shape (r, rows')."""
        if self.whiten is None or isinstance(span, RowSpan):  # a row span's are
            return span.columns
        key = id(span)
        have = self._white.get(key)
        done, stack = (0, np.zeros((0, span.rows - self.whiten.span))) if have is None else have[1:]
        if done < span.size:
            if span.size > stack.shape[0]:  # room for twice as many
                room = np.zeros((2 * span.size, stack.shape[1]))
                room[:done] = stack[:done]
                stack = room
            stack[done : span.size] = self.whiten.transform(span.columns[done:].T).T
            done = span.size
            self._white[key] = (span, done, stack)
        return stack[:done]

    def sloped(self, span: ClosureSpan) -> Array:
        """The span's basis columns at the rows slopes are read at (the filter's first
        ``span`` rows left out, not filtered: :meth:`ShapedPass._white_rows`)."""
        skip = self.whiten.span if self.whiten is not None else 0
        return span.columns[:, skip:]

    def gram(
        self, a: ClosureSpan | RowSpan, b: ClosureSpan | RowSpan, kind: str = "white"
    ) -> Array:
        """``Wa @ Wb.T`` of the two spans' columns (``kind`` "white": through the
        filter; "slope": at the slopes' rows, the same rows without a filter)."""
        if kind == "slope" and self.whiten is None:
            kind = "white"
        if id(a) > id(b):  # one product of two spans, read either way
            return self.gram(b, a, kind).T
        key = (id(a), id(b), kind)
        found = self._grams.get(key)
        if found is None:
            get: Callable[[Any], Array] = self.white if kind == "white" else self.sloped
            found = self._grams[key] = Grown(lambda: get(a), None if a is b else lambda: get(b),
                                             lambda: (a.size, b.size))  # fmt: skip
        return found()



class RowSpan:
    """An orthonormal basis (in the sum over rows) of a shaped term's columns as the
    statistics see them (through the prewhitening filter, if any): a column that is
    cheap to form (a relaxation branch's, from the filtered increments) but whose
    products with the other columns would each be a pass over the rows. A new column
    is projected on it; what is left beyond :data:`TOLERANCE` of it joins the basis.
    """

    def __init__(self, rows: int) -> None:
        self.rows = rows
        self.most = int(MAX_BYTES // (8 * max(rows, 1)))
        self._B = np.zeros((self.most, rows))  # as ClosureSpan's columns
        self.size = 0
        self.misses = 0
        #: coordinates found before, by the term and shape of the column (a relaxation
        #: branch's time constant recurs at each node of the other shapes)
        self.known: dict[Any, Array] = {}
        self._lock = threading.Lock()

    @property
    def columns(self) -> Array:
        """The basis, one a row, shape (r, rows)."""
        return self._B[: self.size]

    def coordinates(self, column: Array) -> Array | None:
        """Coordinates ``c`` with ``c @`` :attr:`columns` equal to ``column`` (rows,)
        within :data:`TOLERANCE` of it; None if it is not finite or the basis is full."""
        v = np.asarray(column, dtype=float)
        if not np.all(np.isfinite(v)):
            return None
        with self._lock:
            c, rest, left = _project(self._B[: self.size], v, TOLERANCE)
            if rest is None:
                return c
            if self.size >= self.most:
                return None
            self._B[self.size] = rest / left
            self.size += 1
            self.misses += 1
            return np.append(c, left)


Span = ClosureSpan | RowSpan


def shaped_term(term: Term) -> tuple[str, str, tuple[float, ...]]:
    """What a shaped term's column hangs on, as a key: its kind, name and shape."""
    return (type(term).__qualname__, term.name, tuple(term.shape[n] for n in term.shapes))


def level_span(
    spans: dict[Any, Any], kin: Kinematics, x_full: Array, speed: Array | None
) -> ClosureSpan | None:
    """The fit's span of functions of the closure (times ``speed``, if given), made on
    first use; None where the session is not on a coarse grid, its closure not on few
    levels, or a column from the filtered indicators of its levels is cheap
    (:func:`~tissuecli.identify.derivatives.base.level_basis`: few levels in each
    filter window, as the simulated forceps' 96)."""
    key = ("levels", speed is not None)
    if key not in spans:
        ok = kin.stride > 1 and x_full.size >= kin.window
        ok = ok and padded_levels(x_full, kin.window, kin.stride) is not None
        ok = ok and level_basis(kin, x_full, speed is not None) is None
        spans[key] = ClosureSpan(kin, x_full, speed) if ok else None
    found = spans[key]
    return found if found is None or (found.kin is kin and found.x_full is x_full) else None


def row_span(spans: dict[Any, Any], name: str, whiten: ARFilter | None, rows: int) -> RowSpan:
    """The fit's span of the columns of terms named ``name`` through this filter."""
    key = ("rows", name, id(whiten))
    found = spans.get(key)
    if found is None or found[0] is not whiten:
        found = spans[key] = (whiten, RowSpan(rows))
    return found[1]  # type: ignore[no-any-return]


def products_for(spans: dict[Any, Any], whiten: ARFilter | None) -> SpanProducts:
    """The fit's :class:`SpanProducts` for this prewhitening filter (or none)."""
    key = ("products", id(whiten))
    found = spans.get(key)
    if found is None or found.whiten is not whiten:
        found = spans[key] = SpanProducts(whiten)
    return found  # type: ignore[no-any-return]


def column_function(term: Term, var: float) -> tuple[Callable[[Array], Array], bool] | None:
    """How a term's column on the coarse grid is a function of the closure alone: the
    function (of the levels, m) and whether the raw speed multiplies it, as
    :func:`~tissuecli.identify.design.term_column` forms it (``var``: the position
    noise's variance, m^2); None if it is not one."""
    if term.variable == "x":

        def stiffness(x: Array) -> Array:
            u = term(x)
            return u - 0.5 * term.curvature(x) * var if var > 0 else u

        return stiffness, False
    if term.variable == "xv" and not term.memory:
        factor = term.closure_factor
        if factor(np.zeros(1)) is not None:
            return factor, True  # type: ignore[return-value]
    return None


#: variables of the terms whose noise path is none (:func:`~tissuecli.identify.design.
#: noise_path`): a constant, the closure's history, closure and speed
NO_NOISE_PATH = ("1", "h", "xv")

#: a residual sum of squares formed in the spans' coordinates is kept if it is above this
#: fraction of the largest of the terms it is summed from (their rounding, about 2e-15
#: of it, is then under 1e-9 of it); below, the residual itself is formed
RSS_FLOOR = 1e-5


class ReducedPass:
    """A shaped law's first pass (:class:`~tissuecli.identify.shaped.ShapedPass`) in the
    coordinates of the fit's spans: each moving column a function of the closure
    (:class:`ClosureSpan`) or a column projected on its term's :class:`RowSpan`, its
    products with the shape-free columns, the force and the other moving columns read
    from the spans' products. The same statistics to about :data:`TOLERANCE`.

    The residual sum of squares is summed from products too, about the residual at a
    reference node (the first, and any whose terms come within :data:`RSS_FLOOR` of
    cancelling), so that no rounding of the force's own size is left in it.

    ``owner`` is the :class:`~tissuecli.identify.shaped.ShapedPass` whose shape-free
    statistics (``F``, ``G_ff``, ``b_f``, ``yy``, ``D_f``, ``DtD_f``, ``K_f``) and
    filters it uses. :attr:`usable` is False where a moving term is of neither kind,
    the session is scored on every sample, or no column is a function of the closure.
    """

    def __init__(self, owner: Any) -> None:
        self.owner = owner
        self.usable = False
        fit = owner.fit
        kin = fit.kin
        if kin.stride <= 1 or not owner.moving:
            return
        var = fit.sigma_x**2
        plan: list[tuple[str, int, Span, ClosureSpan | None]] = []
        for j in owner.moving:
            t = owner.law.terms[j]
            how = column_function(t, var)
            span = None
            if how is not None:
                span = level_span(fit.spans, kin, fit.x_full, owner.speed[1] if how[1] else None)
            if span is not None:
                slope = None
                if t.variable not in NO_NOISE_PATH:
                    slope = level_span(fit.spans, kin, fit.x_full, None)
                    if slope is None:
                        return
                plan.append(("level", j, span, slope))
            elif t.variable in NO_NOISE_PATH:
                plan.append(("row", j, row_span(fit.spans, t.name, fit.whiten, fit.rows), None))
            else:
                return
        if not any(kind == "level" for kind, *_ in plan):
            return  # nothing a span saves: each column is cheap to form
        self.plan = plan
        self.products = products_for(fit.spans, fit.whiten)
        self.spans: list[Span] = []
        for _, _, span, _ in plan:
            if not any(span is s for s in self.spans):
                self.spans.append(span)
        self.slot = [next(i for i, s in enumerate(self.spans) if s is span)
                     for _, _, span, _ in plan]  # fmt: skip
        self._with: dict[tuple[int, str], Grown] = {}
        self._K: Array | None = None
        self._ref: tuple[Array, list[Array], float, Array, list[Grown]] | None = None
        self.usable = True

    def _stack(self, span: Span, kind: str = "white") -> Array:
        if kind == "slope":
            assert isinstance(span, ClosureSpan)
            return self.products.sloped(span)
        return self.products.white(span)

    def _against(self, span: Span, what: str) -> Array:
        """The span's basis columns against the law's shape-free columns (``what`` "F"),
        the force ("y") or the shape-free terms' slopes ("D"): (r, f), (r,), (r, f)."""
        key = (id(span), what)
        found = self._with.get(key)
        if found is None:
            o = self.owner
            fixed = {"F": o.F.T, "y": o.fit.target[None, :], "D": o.D_f.T if what == "D"
                     else None}[what]  # fmt: skip
            kind = "slope" if what == "D" else "white"
            width = fixed.shape[0]
            found = self._with[key] = Grown(lambda: self._stack(span, kind), lambda: fixed,
                                            lambda: (span.size, width))  # fmt: skip
        out = found()
        return out[:, 0] if what == "y" else out

    def __call__(self, bound: Any) -> Any:
        """The :class:`~tissuecli.identify.scoring.FirstPass` of ``bound`` (the law at
        one shape), or None where a column does not fit in its span or the columns are
        too ill-conditioned for the normal equations (then formed as before)."""
        from .design import term_column
        from .scoring import FirstPass

        o, fit = self.owner, self.owner.fit
        fixed, moving = o.fixed, o.moving
        var = fit.sigma_x**2
        # each function of the closure a span is asked about, by span: (slot, its key
        # in the span's known coordinates, values, tolerance)
        asked: dict[int, tuple[ClosureSpan, list[tuple[tuple[str, int], Any, Array, float]]]] = {}
        found: dict[tuple[str, int], Array | None] = {}
        for i, (kind, j, span, slope_span) in enumerate(self.plan):
            t = bound.terms[j]
            name = shaped_term(t)
            if kind == "level":
                assert isinstance(span, ClosureSpan)
                key = ("c", name, var)
                if key in span.known:
                    found["c", i] = span.known[key]
                else:
                    how = column_function(t, var)
                    assert how is not None
                    asked.setdefault(id(span), (span, []))[1].append(
                        (("c", i), key, how[0](span.levels), TOLERANCE)
                    )
            else:
                assert isinstance(span, RowSpan)
                got = span.known.get((name, var))
                if got is None:
                    column = term_column(t, fit.kin, fit.x_full, fit.sigma_x, raw_speed=o.speed)
                    got = span.coordinates(o._white(column))
                    if got is not None:
                        span.known[name, var] = got
                found["c", i] = got
            if slope_span is not None and fit.sigma_x > 0:
                key = ("e", name, var)
                if key in slope_span.known:
                    found["e", i] = slope_span.known[key]
                else:
                    values = t.derivative(slope_span.levels)
                    asked.setdefault(id(slope_span), (slope_span, []))[1].append(
                        (("e", i), key, values, SLOPE_TOLERANCE)
                    )
        for span, items in asked.values():
            got = span.coordinates_many([v for *_, v, _ in items], [t for *_, t in items])
            for (slot, key, *_), c in zip(items, got, strict=True):
                found[slot] = c
                if c is not None:
                    span.known[key] = c
        if any(c is None for c in found.values()):
            return None
        coords = [pad(found["c", i], span.size)  # type: ignore[arg-type]
                  for i, (_, _, span, _) in enumerate(self.plan)]  # fmt: skip
        slopes = [found.get(("e", i)) for i in range(len(self.plan))]
        k = len(moving)
        SF = np.empty((k, len(fixed)))
        Sy = np.empty(k)
        for i, (c, (_, _, span, _)) in enumerate(zip(coords, self.plan, strict=True)):
            SF[i] = c @ self._against(span, "F")
            Sy[i] = c @ self._against(span, "y")
        SS = np.empty((k, k))
        for i in range(k):
            for m in range(i + 1):
                a, b = self.plan[i][2], self.plan[m][2]
                SS[i, m] = SS[m, i] = coords[i] @ self.products.gram(a, b) @ coords[m]
        p = len(bound.terms)
        gram = o._assemble(o.G_ff, SF, SS)
        bvec = np.empty(p)
        bvec[fixed] = o.b_f
        bvec[moving] = Sy
        d = np.sqrt(np.clip(np.diag(gram), 1e-300, None))
        lam_s = np.linalg.eigvalsh(gram / np.outer(d, d))
        cond_scaled = float(np.sqrt(lam_s[-1] / lam_s[0])) if lam_s[0] > 0 else float("inf")
        if cond_scaled >= 1e5:
            return None
        beta = np.linalg.solve(gram / np.outer(d, d), bvec / d) / d
        z = [np.zeros(s.size) for s in self.spans]
        for i, c in enumerate(coords):
            z[self.slot[i]] += beta[moving[i]] * c
        rss = self._rss(beta[fixed], z)
        lam = np.linalg.eigvalsh(gram)
        cond = float(np.sqrt(lam[-1] / lam[0])) if lam[0] > 0 else float("inf")
        correction = None
        if fit.sigma_x > 0:
            DmDf = np.zeros((k, len(fixed)))
            DmDm = np.zeros((k, k))
            plain = next((s for *_, s in self.plan if s is not None), None)
            if plain is not None:
                es = [None if e is None else pad(e, plain.size) for e in slopes]
                G = self.products.gram(plain, plain, "slope")
                U = self._against(plain, "D")
                for i, ei in enumerate(es):
                    if ei is None:
                        continue
                    DmDf[i] = ei @ U
                    for m in range(i + 1):
                        em = es[m]
                        if em is not None:
                            DmDm[i, m] = DmDm[m, i] = ei @ G @ em
            DtD = o._assemble(o.DtD_f, DmDf, DmDm)
            K = self._kernels()
            correction = fit.sigma_x**2 * (K @ K.T) * DtD
        return FirstPass(gram, bvec, o.yy, beta, rss, cond, cond_scaled, correction)

    def _rss(self, beta_f: Array, z: list[Array]) -> float:
        """``|y - F beta_f - sum_a z_a @ W_a|^2``, summed from products about the
        reference node's residual; the residual itself where they come near cancelling
        (and that node becomes the reference)."""
        o = self.owner
        if self._ref is not None:
            bf0, z0, r0r0, Fr0, Wr0 = self._ref
            df = beta_f - bf0
            dz = [za - pad(z0a, za.size) for za, z0a in zip(z, z0, strict=True)]
            terms = [r0r0, -2.0 * float(df @ Fr0), float(df @ o.G_ff @ df)]
            for a, span in enumerate(self.spans):
                terms.append(-2.0 * float(dz[a] @ Wr0[a]()[:, 0]))
                terms.append(2.0 * float(dz[a] @ self._against(span, "F") @ df))
                for b, other in enumerate(self.spans):
                    terms.append(float(dz[a] @ self.products.gram(span, other) @ dz[b]))
            rss = math.fsum(terms)
            if rss > RSS_FLOOR * max(abs(t) for t in terms):
                return rss
        r = o.fit.target - o.F @ beta_f
        for za, span in zip(z, self.spans, strict=True):
            r = r - za @ self._stack(span)
        r0r0 = float(r @ r)
        here = r[None, :]
        Wr0 = [Grown(lambda s=span: self._stack(s), lambda: here, lambda s=span: (s.size, 1))
               for span in self.spans]  # fmt: skip
        self._ref = (beta_f.copy(), [za.copy() for za in z], r0r0, o.F.T @ r, Wr0)
        return r0r0

    def _kernels(self) -> Array:
        """The noise kernels of the law's terms as the filtered columns see them: the
        shape-free ones', the position filter's for a moving term of the closure, none
        for the others; the same at every shape."""
        if self._K is None:
            o = self.owner
            K = np.empty((len(o.law.terms), o.K_f.shape[1]))
            K[o.fixed] = o.K_f
            k0 = o.fit.kin.kernels[0]
            moving = [k0 if s is not None else np.zeros_like(k0) for *_, s in self.plan]
            K[o.moving] = o._kernels(np.array(moving))
            self._K = K
        return self._K
