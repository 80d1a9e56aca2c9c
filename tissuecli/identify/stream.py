"""A session too long to hold in memory, fitted from sums streamed block by block.

The default fit keeps tens of arrays as long as the session (columns, their noise paths,
residuals): about 600 bytes a sample. A session of 1e8 samples (28 hours at 1 kHz)
would need 60 GB. Laws that are linear in their coefficients need only the sums
``A^T A``, ``A^T F``, ``F^T F`` and the sample count to give their exact posterior and
evidence, and those sums add over blocks. So :class:`StreamedFit`

1. fits a *pilot*, a contiguous stretch from the middle of the session, with the full
   :class:`~tissuecli.identify.bayes.BayesianFit`: it chooses the filter, the position
   noise, the data weight (effective samples per sample, from the residuals'
   correlation) and the few laws worth scoring;
2. reads the whole session block by block, each with margins so that every filtered
   sample sees its full window (and a law with memory its history, ten time constants
   back), differentiates it with the pilot's very filter and adds each candidate law's
   sums. Where the pilot kept to the grasps, each block's grasps are found as the full
   fit finds them (:func:`~tissuecli.identify.contact.find_contact`, on the block and a
   margin either side, against the pilot's free-jaw level and noise) and fitted by the pilot's rules
   (:func:`~tissuecli.identify.prepare.fit_grasps`, the full fit's own code): the
   grasps' edges, each tissue column gated on the raw grid by the contact flags, the
   free jaws' level taken off the force there, and the open jaws for the sensor's
   offset; samples at an end of the ADC are holes, as in the full fit;
3. scores the candidates on those sums, exactly as the default fit scores a law.

Memory is set by the block and the pilot, not by the session's length.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..core.errors import FitError
from ..core.progress import Progress, as_progress
from ..core.session import Session
from ..core.terms import Law
from .bayes import CUT_THRESHOLD, BayesianFit, ModelResult, law_prior
from .contact import Contact, find_contact
from .derivatives import Frozen, Kinematics
from .derivatives.staircase import staircase
from .design import design, eiv_correction
from .noise import corrected_curvature
from .posterior import ExactPosterior, SufficientStats, gram_lstsq
from .prepare import GraspRules, adc_ends, fit_grasps

Array = NDArray[np.float64]

#: a law with memory is warmed up on this many of its longest time constants before a
#: block's first counted sample (its history's weight falls to e^-10 = 5e-5)
MEMORY_WARMUP = 10.0
#: a block's grasps are found on it and this much more of the session either side (s),
#: so that a grasp beside a seam is read as the full fit reads it (its onset, its
#: baseline either side), and a whole filter window of samples beyond either way
CONTACT_MARGIN_S = 2.0


@dataclass
class _Sums:
    """One candidate law's streamed sums."""

    law: Law
    G: Array
    b: Array
    yy: float = 0.0
    n: int = 0
    correction: Array | None = None
    #: R of the QR factorisation of [A | y] so far, updated block by block: its last
    #: diagonal element is the least-squares residual's norm, free of the cancellation
    #: that ``yy - b^T G^-1 b`` suffers on nearly collinear columns
    R: Array | None = None

    @classmethod
    def empty(cls, law: Law, corrected: bool) -> _Sums:
        p = len(law.terms)
        return cls(
            law, np.zeros((p, p)), np.zeros(p), correction=np.zeros((p, p)) if corrected else None
        )

    def add(self, A: Array, y: Array) -> None:
        """Add a block's columns (m, p) and filtered forces (m,)."""
        self.G += A.T @ A
        self.b += A.T @ y
        self.yy += float(y @ y)
        self.n += int(y.size)
        block = np.column_stack([A, y])
        stacked = block if self.R is None else np.vstack([self.R, block])
        self.R = np.linalg.qr(stacked, mode="r")

    def rss(self) -> float:
        """The least-squares residual sum of squares, with the noise correction's share
        taken off as :meth:`SufficientStats.from_data` does."""
        assert self.R is not None
        p = len(self.law.terms)
        R = self.R
        rss = float(R[p, p] ** 2) if R.shape[0] > p else 0.0
        if self.correction is not None:
            d = np.linalg.norm(R[:p, :p], axis=0)  # the columns' norms, as in A
            d[d == 0] = 1.0
            beta = np.linalg.lstsq(R[:p, :p] / d, R[:p, p], rcond=None)[0] / d
            beta_c = gram_lstsq(self.G - self.correction, self.b)
            rss = max(rss - float(beta_c @ self.correction @ beta), 0.0)
        return rss


@dataclass
class StreamedFit:
    """The default fit's answer over a session read block by block.

    Parameters
    ----------
    pilot_samples : int
        Length of the pilot stretch fitted in full (samples).
    block_samples : int
        Samples read and differentiated at a time (memory grows with it).
    candidates : int
        How many of the pilot's best laws are scored over the whole session.
    bayes : dict
        Hyperparameters of the pilot's :class:`BayesianFit` (forms, seed, ...).

    Attributes
    ----------
    pilot_ : BayesianFit
        The pilot's fit: its filter, noise and data weight were used throughout.
    pilot_rows_ : tuple of int
        Rows [start, stop) of the pilot in the session.
    results_ : list of ModelResult
        The candidates scored over the whole session, best first.
    best_ : ModelResult
    n_samples_ : int
        Filtered samples summed (each counted once).
    n_eff_ : float
        Effective independent samples (the pilot's weight per sample times n_samples_).
    skipped_blocks_ : int
        Blocks left out because their samples were too irregular for the filter.
    grasp_blocks_ : int
        Blocks whose own grasps the pilot, in contact throughout, could not read: every
        sample of them summed, free jaws included (a warning says so).
    not_evaluated_ : list of (str, str)
        Candidates whose evidence over the whole session cannot be trusted, with the
        reason; never chosen.
    warnings_ : list of str
    """

    pilot_samples: int = 400_000
    block_samples: int = 500_000
    candidates: int = 4
    bayes: dict[str, Any] = field(default_factory=dict)

    def fit(
        self,
        read: Callable[[int, int], Session],
        rows: int,
        progress: Progress | None = None,
    ) -> StreamedFit:
        """Fit a session of ``rows`` rows; ``read(start, stop)`` returns rows
        [start, stop) of it as a :class:`Session` (SI units)."""
        progress = as_progress(progress)
        if not isinstance(self.bayes.get("grasps", "all"), str):
            raise FitError(
                "grasp numbers are not read in a session too long to hold: fit --grasps "
                "all or none, or cut the session to the grasps wanted"
            )
        a = max(0, rows // 2 - self.pilot_samples // 2)
        b = min(rows, a + self.pilot_samples)
        progress.stage(f"the pilot: samples {a:,} to {b:,} fitted in full")
        pilot = BayesianFit(**self.bayes).fit(read(a, b))
        self.pilot_, self.pilot_rows_ = pilot, (a, b)
        # where the pilot's closure is a staircase it fitted rebuilt, each block's is too
        rebuild = pilot.rebuilt_
        kin0 = pilot.kinematics_
        dt = kin0.dt
        frozen = Frozen(kin0)
        weight = pilot.n_eff_ / max(kin0.force.size, 1)
        chosen = [r for r in pilot.results_ if r.posterior is not None and not r.model.shape_names][
            : self.candidates
        ]
        if not chosen:
            raise FitError("the pilot stretch scored no law; fit a shorter session in full")
        sums = [_Sums.empty(r.model, r.correction is not None) for r in chosen]
        rules: GraspRules | None = pilot.grasp_rules_
        half = kin0.window // 2
        # the times over which each term with memory forgets (a branch's tau)
        taus = [
            float(v) for r in chosen for t in r.model.terms if t.memory for v in t.time_scales()
        ]
        step = max(self.block_samples, 4 * kin0.window)
        # a law with memory needs its history; past two blocks of it the read would
        # outgrow the memory the blocks are there to bound, and the branch is slower
        # than the pilot can tell apart from a spring anyway
        warm = half + min(int(np.ceil(MEMORY_WARMUP * max(taus, default=0.0) / dt)), 2 * step)
        # the grasps are found on a margin beyond the samples read for the filter
        margin = 0 if rules is None else max(2 * kin0.window, int(CONTACT_MARGIN_S / dt))
        starts = list(range(0, rows, step))
        if len(starts) > 1 and rows - starts[-1] < 2 * kin0.window:
            starts.pop()  # a tail too short to filter goes with the block before it
        progress.stage("summing the session block by block", len(starts))
        t_first: float | None = None
        self.skipped_blocks_ = 0
        self.grasp_blocks_ = 0
        # a pilot in contact throughout has no free-jaw level to read grasps against:
        # a block that finds grasps of its own is then named, not silently summed whole
        check = rules is None and pilot.contact_.all_contact and self.bayes.get("grasps") != "none"
        for i, s in enumerate(starts):
            e = rows if i == len(starts) - 1 else s + step
            first = max(0, s - warm - margin)
            block = read(first, min(rows, e + half + margin))
            if t_first is None:
                t_first = float(block.time[0])
            lo = float(block.time[s - first])
            hi = float(block.time[e - first]) if e < rows else np.inf  # the next block's
            try:
                kin, gx = self._kinematics(block, frozen, rules, pilot.contact_, dt, t_first,
                                           rebuild)  # fmt: skip
                if check and not find_contact(block).all_contact:
                    self.grasp_blocks_ += 1
            except FitError:
                self.skipped_blocks_ += 1
            else:
                if kin is not None:
                    self._add(kin, gx, pilot.sigma_x_, dt, lo, hi, e >= rows, sums)
            progress.advance(i + 1, len(starts))
        self._score(sums, pilot, weight)
        return self

    @staticmethod
    def _kinematics(
        block: Session,
        frozen: Frozen,
        rules: GraspRules | None,
        levels: Contact,
        dt: float,
        t_first: float,
        rebuild: bool = False,
    ) -> tuple[Kinematics | None, Array]:
        """A block on the whole session's grid (so that blocks meet without a seam),
        filtered as the pilot was: every sample, or by the pilot's grasp ``rules``, its
        grasps found against the pilot's free-jaw level and noise (``levels``); and
        the closure on that grid (m), a staircase rebuilt through its level crossings
        where ``rebuild`` (as the pilot's was). None for kinematics where the block
        holds nothing to fit (no grasp, by the rules).

        Raises
        ------
        FitError
            Where the block's samples are too irregular for the filter.
        """
        t, x, f = block.time, block.position, block.force
        ok = np.isfinite(t) & np.isfinite(x) & np.isfinite(f)
        if np.count_nonzero(ok) < 2:
            raise FitError("block without finite samples")
        t, x, f = t[ok], x[ok], f[ok]
        k0 = int(np.ceil((t[0] - t_first) / dt - 1e-6))
        k1 = int(np.floor((t[-1] - t_first) / dt + 1e-6))
        grid = t_first + dt * np.arange(k0, k1 + 1)
        after = np.clip(np.searchsorted(t, grid, side="right"), 1, t.size - 1)
        valid = (t[after] - t[after - 1]) <= 2.0 * dt + 1e-12
        gx, gf = np.interp(grid, t, x), np.interp(grid, t, f)
        on_grid = block.replace(grid, gf, gx)
        for _, clipped in adc_ends(on_grid):  # a clipped value is not a measurement
            valid &= ~clipped
        formed = on_grid
        # rebuilt from the samples as read (the grid's interpolation leaves the levels)
        stair = staircase(x, dt) if rebuild else None
        if stair is not None:
            gx = np.interp(grid, t, stair[0])
            formed = block.replace(grid, gf, gx)
        if rules is None:
            return frozen(grid, gx, gf, valid), gx
        contact = find_contact(on_grid, levels).mask  # read on the closure as read
        if not (rules.open_fitted or np.any(contact & valid)):
            return None, gx
        try:
            return fit_grasps(rules, frozen, formed, valid, contact, contact), gx
        except FitError:
            return None, gx  # too few outputs touch a grasp to filter

    def _add(
        self,
        kin: Kinematics,
        gx: Array,
        sigma_x: float,
        dt: float,
        lo: float,
        hi: float,
        last: bool,
        sums: list[_Sums],
    ) -> None:
        """Add one block's filtered samples with grid times in [lo, hi) (all to its end
        for the last block) to every candidate's sums."""
        counted = (kin.time >= lo - 0.5 * dt) & ((kin.time < hi - 0.5 * dt) | last)
        if not np.any(counted):
            return
        y = kin.force[counted]
        columns: dict[str, Array] = {}
        for s in sums:
            s.add(design(s.law, kin, gx, sigma_x, columns)[counted], y)
            if s.correction is not None:
                # the noise correction is a sum over samples too; each block's share
                # scales with the samples it counts
                s.correction += eiv_correction(s.law, kin, gx, sigma_x) * (
                    y.size / max(kin.time.size, 1)
                )

    def _score(self, sums: list[_Sums], pilot: BayesianFit, weight: float) -> None:
        rng = np.random.default_rng(pilot.seed)
        results = []
        self.not_evaluated_: list[tuple[str, str]] = []
        for s in sums:
            if s.n <= len(s.law.terms):
                continue
            G, b, yy, rss = s.G, s.b, s.yy, s.rss()
            if s.correction is not None:
                # as in the full fit: the corrected estimator's spread, and the raw
                # residual (force noise and position noise through the law) scored
                p, R = len(s.law.terms), s.R
                rss = float(R[p, p] ** 2) if R is not None and R.shape[0] > p else rss
                G, b, yy = corrected_curvature(s.G, s.b, s.correction, rss, rss)
            st = SufficientStats(weight * G, weight * b, weight * yy, weight * s.n, weight * rss)
            prior = law_prior(s.law, pilot.scales_)
            exact = ExactPosterior(st, prior)
            why = exact.untrusted()
            if why:  # as in the full fit: named, never chosen
                self.not_evaluated_.append((s.law.name, why))
                continue
            post = exact.bounded(rng, CUT_THRESHOLD)
            results.append(
                ModelResult(
                    model=s.law,
                    ln_evidence=post.ln_evidence,
                    posterior=post,
                    cond=float(np.linalg.cond(s.G)),
                    residual_rms=float(np.sqrt(rss / s.n)),
                    gram=s.G,
                    correction=s.correction,
                    stats=st,
                    prior=prior,
                )
            )
        if not results:
            raise FitError("no block of the session could be filtered; fit it in full")
        ln_z = np.array([r.ln_evidence for r in results])
        if not np.all(np.isfinite(ln_z)):
            raise FitError("a streamed evidence is not finite; fit a shorter stretch in full")
        prob = np.exp(ln_z - ln_z.max())
        prob /= prob.sum()
        for r, p in zip(results, prob, strict=True):
            r.probability = float(p)
        results.sort(key=lambda r: (-r.probability, -r.ln_evidence))
        self.results_ = results
        self.best_ = results[0]
        self.n_samples_ = max(s.n for s in sums)
        self.n_eff_ = weight * self.n_samples_
        self.warnings_ = list(pilot.warnings_) + [
            f"{name}: not evaluated over the whole session, so never chosen: {why}"
            for name, why in self.not_evaluated_
        ]
        if self.grasp_blocks_:
            self.warnings_.append(
                f"the pilot stretch is in contact throughout, but {self.grasp_blocks_} "
                "block(s) of the session hold free jaw motion, fitted as contact; fit a "
                "part with grasps (--start, --end) to keep to them"
            )
