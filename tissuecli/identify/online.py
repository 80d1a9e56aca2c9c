"""Online identification: the exact Bayesian fit of :mod:`~tissuecli.identify.bayes`
made recursive, so that a recording shows its tissue law while it runs.

Samples arrive in blocks. A fixed differentiator (a Gaussian of fixed width by
default) is evaluated at the centre of its window once the whole window has arrived,
so the kinematics and the filtered force of a sample are known ``lag_s`` (half the
window) after it, and they are exactly the offline filter's. Each new filtered
sample adds its row of every candidate law's design matrix to one running Gram
matrix of all the laws' columns and the force, ``Z^T Z``; every law's sufficient
statistics ``(A^T A, A^T F, F^T F, n)`` are blocks of it. Before a block is added
the statistics are multiplied by ``exp(-T / forgetting_s)`` (T: the block's
duration), so a sample counts ``exp(-age / forgetting_s)``: after a change of tissue
the old one fades with that time constant. The posterior and evidence of each law
come from the statistics by :class:`~tissuecli.identify.posterior.ExactPosterior`,
the very code of the offline fit; with ``forgetting_s = inf`` the online posterior
is the offline one of the same filtered samples.

Grasps: a sample is in contact while its force, smoothed over the last
:data:`~tissuecli.identify.contact.SMOOTH_S`, stands above the free-jaw baseline by
the thresholds of :mod:`~tissuecli.identify.contact` (entering at 6 noise SDs,
leaving at 3); the baseline is the least smoothed force seen so far and
the noise SD comes from the force's first differences. A filtered sample counts only
if its whole filter window is in contact. docs/estimators.md, "Online
identification", gives the rules and their limits.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..core.errors import FitError, InputError
from ..core.terms import Law, MotionScales
from ..core.tissue import Tissue
from .contact import ENTER_SD, LEAVE_SD, SMOOTH_S
from .derivatives import Differentiator, Gaussian, Kinematics, differentiator
from .design import column_key, design
from .forms import parse_forms
from .posterior import ExactPosterior, SufficientStats
from .priors import law_prior, scales_from
from .spectrum import convolve_valid

Array = NDArray[np.float64]

#: default SD of the Gaussian differentiator, s: a -3 dB cutoff of 13 Hz, above a
#: hand's grasping band (below about 5 Hz) and its faster tremor
DEFAULT_SIGMA_S = 0.01
#: data time between two computations of the estimate, s (at most 20 a second)
ESTIMATE_INTERVAL_S = 0.05
#: the estimate is confident when the central 95 % interval of each coefficient of
#: these roles is at most this fraction of its mean
CONFIDENT_WIDTH = {"stiffness": 0.10, "damping": 0.20}
#: ... and it rests on at least this many effective independent samples per
#: coefficient (fewer, and the noise level behind the intervals is itself uncertain)
CONFIDENT_N_EFF = 10.0
#: quadrature nodes over ln sigma for the online posteriors (the offline fit uses 401;
#: with thousands of samples sigma's posterior is narrow and 101 agree to 1e-6)
NODES = 101


@dataclass(frozen=True)
class OnlineEstimate:
    """The online fit's current answer, SI throughout.

    Attributes
    ----------
    time_s : float
        Time of the newest filtered sample used, s since the first update (the newest
        sample received less the differentiator's lag).
    law : str
        The most probable law, e.g. ``"x+xdot+xddot"``.
    names : tuple of str
        Its coefficients' symbols, e.g. ``("K", "S", "M")``.
    units : tuple of str
        Their SI units.
    mean : ndarray, shape (p,)
        Posterior means.
    ci95 : ndarray, shape (p, 2)
        Central 95 % intervals.
    probabilities : dict
        Law name -> posterior probability among the candidates (sums to 1).
    confident : bool
        Every stiffness and damping coefficient's 95 % interval is within
        :data:`CONFIDENT_WIDTH` of its mean, and ``n_eff`` is at least
        :data:`CONFIDENT_N_EFF` per coefficient.
    samples : float
        Filtered samples behind the estimate, each counted by its forgetting weight.
    n_eff : float
        Effective independent samples: ``samples`` times the filter's data weight.
    model : Law
        The most probable law itself.
    """

    time_s: float
    law: str
    names: tuple[str, ...]
    units: tuple[str, ...]
    mean: Array
    ci95: Array
    probabilities: dict[str, float]
    confident: bool
    samples: float = 0.0
    n_eff: float = 0.0
    model: Law | None = field(default=None, repr=False, compare=False)

    def tissue(self) -> Tissue:
        """The estimate as a renderable :class:`~tissuecli.core.tissue.Tissue` (posterior
        means)."""
        from ..core.terms import parse_law

        law = self.model if self.model is not None else parse_law(self.law)
        return Tissue(law, *(float(c) for c in self.mean))

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready: floats, lists and strings."""
        return {
            "time_s": float(self.time_s),
            "law": self.law,
            "names": list(self.names),
            "units": list(self.units),
            "mean": [float(c) for c in self.mean],
            "ci95": [[float(lo), float(hi)] for lo, hi in self.ci95],
            "probabilities": {k: float(v) for k, v in self.probabilities.items()},
            "confident": bool(self.confident),
            "samples": float(self.samples),
            "n_eff": float(self.n_eff),
        }

    def describe(self) -> str:
        """One line: the law and its coefficients, with +- (half the 95 % interval) once
        confident, or ``identifying...`` before."""
        if not self.confident:
            return f"identifying... ({self.law}, {100 * self.probabilities[self.law]:.0f} %)"
        parts = []
        for name, unit, m, (lo, hi) in zip(
            self.names, self.units, self.mean, self.ci95, strict=True
        ):
            parts.append(f"{name} {m:.4g} +- {(hi - lo) / 2:.2g} {unit}")
        return f"{self.law} ({100 * self.probabilities[self.law]:.0f} %): " + ", ".join(parts)


class _Fixed(Differentiator):
    """A differentiator's kernels fixed once, for a stream (not registered)."""

    name = "fixed"

    def __init__(self, base: Differentiator, dt: float) -> None:
        try:
            # the kernels must not depend on the data, which have not arrived yet
            self._kernels = base.kernels(np.zeros(0), dt)
            self._half = base.half_kernels(np.zeros(0), dt)
        except Exception as exc:  # noqa: BLE001  (whatever a data-driven choice raises)
            raise InputError(
                f"the {base.name} differentiator chooses its width from the data; online "
                "identification needs a fixed one (Gaussian(sigma_s=...) or "
                f"SavitzkyGolay(window=...)): {exc}"
            ) from None

    def kernels(
        self, x: Array, dt: float, valid: NDArray[np.bool_] | None = None
    ) -> tuple[tuple[Array, Array, Array], float, str]:
        return self._kernels

    def half_kernels(
        self, x: Array, dt: float, valid: NDArray[np.bool_] | None = None
    ) -> tuple[Array, Array, Array, float] | None:
        return self._half


class OnlineFit:
    """Recursive exact Bayesian identification with exponential forgetting.

    Parameters
    ----------
    rate_hz : float
        Sample rate of the stream, Hz; samples are taken as evenly spaced.
    forms : str, Law or list of them
        Candidate laws, as :class:`~tissuecli.identify.bayes.BayesianFit` reads them;
        ``"paper"`` (the paper's four) by default. Laws with shape parameters or
        memory are refused.
    forgetting_s : float
        Time constant of the forgetting, s: a sample of age ``t`` counts
        ``exp(-t / forgetting_s)``, so about ``forgetting_s * rate_hz`` samples count
        at once. ``math.inf`` forgets nothing.
    differentiator : Differentiator or str, optional
        With fixed kernels; by default ``Gaussian(sigma_s=DEFAULT_SIGMA_S)``.
    contact : bool
        Fit only samples in contact (see the module's docstring); off, every sample.
    force_scale : float, optional
        N, for the priors, as in :class:`~tissuecli.identify.bayes.BayesianFit`;
        by default five times the largest filtered force counted.
    estimate_interval_s : float
        :meth:`estimate` recomputes at most once per this much data time, s.
    min_samples : int, optional
        Filtered samples in contact needed before any estimate; by default two
        filter windows.

    Attributes
    ----------
    lag_s : float
        Delay of the filtered samples behind the newest sample received, s.
    window : int
        Taps of the differentiator.
    data_weight : float
        What one filtered sample counts, ``1 / tau`` with ``tau = 1 / sum(g^2)`` the
        integrated autocorrelation time of white noise through the smoothing kernel g.
    received, skipped : int
        Samples received, and those not finite (held at the last finite value and
        kept out of every filter window, like a lost sample offline).
    """

    def __init__(
        self,
        *,
        rate_hz: float,
        forms: str | Law | list[str | Law] = "paper",
        forgetting_s: float = 5.0,
        differentiator: Differentiator | str | None = None,
        contact: bool = True,
        force_scale: float | None = None,
        estimate_interval_s: float = ESTIMATE_INTERVAL_S,
        min_samples: int | None = None,
    ) -> None:
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise InputError(
                f"rate_hz must be a positive number of samples a second, got {rate_hz}"
            )
        if not forgetting_s > 0:
            raise InputError(f"forgetting_s must be positive (or inf), got {forgetting_s}")
        self.rate_hz = float(rate_hz)
        self.forgetting_s = float(forgetting_s)
        self.contact = contact
        self.force_scale = force_scale
        self.estimate_interval_s = estimate_interval_s
        self.laws = parse_forms(forms)
        for law in self.laws:
            if law.shape_names or law.memory:
                raise InputError(
                    f"online identification fits laws linear in their coefficients; "
                    f"{law.name} has shape parameters or memory: fit it offline"
                )
        self.dt = 1.0 / self.rate_hz
        base = differentiator or Gaussian(sigma_s=DEFAULT_SIGMA_S)
        base = _named(base) if isinstance(base, str) else base
        self.differentiator = _Fixed(base, self.dt)
        (k0, _, _), self.cutoff_hz, self.method = self.differentiator.kernels(np.zeros(0), self.dt)
        self.window = int(k0.size)
        self.lag_s = (self.window // 2) * self.dt
        self.data_weight = float(k0 @ k0) / float(k0.sum()) ** 2
        self.min_samples = min_samples if min_samples is not None else 2 * self.window
        self.decay = math.exp(-self.dt / self.forgetting_s)  # per sample; 1 for inf
        # the columns every law uses, once each (keys as design() keeps them)
        self._keys: list[str] = []
        self._index: list[list[int]] = []
        for law in self.laws:
            idx = []
            for t in law.terms:
                key = column_key(t)
                if key not in self._keys:
                    self._keys.append(key)
                idx.append(self._keys.index(key))
            self._index.append(idx)
        q = len(self._keys) + 1
        self._gram = np.zeros((q, q))  # [columns..., force]^T W [columns..., force]
        self._count = 0.0  # sum of weights of the rows counted
        self._sq = np.zeros(3)  # weighted sums of x^2, v^2, a^2 over those rows
        self._peak = 0.0  # largest |filtered force| counted, forgotten like the rest
        # the stream: samples not yet at a window's centre, and the last window - 1
        self._x = np.zeros(0)
        self._f = np.zeros(0)
        self._ok = np.zeros(0, bool)  # finite and in contact
        self._done = 0  # filtered samples produced (their centres' index)
        self.received = 0
        self.skipped = 0
        # contact: the running smoothed force, its least value, the noise SD
        self._smooth_n = max(1, int(round(SMOOTH_S * self.rate_hz)))
        self._recent = np.zeros(0)  # last smooth_n - 1 force samples, for the moving mean
        self._baseline = math.inf
        self._diff_sq = 0.0  # forgotten sums of squared first differences of the force
        self._diff_n = 0.0
        self._last_f = math.nan
        self._last_x = math.nan
        self._in_contact = False
        self._t0: float | None = None  # time of the first sample, when times are given
        self._k_last = -1  # grid index of the last sample placed by time
        self._cached: OnlineEstimate | None = None
        self._cached_at = -1
        self._rng = np.random.default_rng(0)

    # -- the stream ---------------------------------------------------------------

    def update(
        self, position: ArrayLike, force: ArrayLike, *, time: ArrayLike | None = None
    ) -> None:
        """Add a block of samples.

        Parameters
        ----------
        position, force : array_like, shape (n,)
            Jaw closure (m) and force (N), evenly spaced at ``rate_hz`` after every
            sample given before. An empty block does nothing; non-finite samples are
            counted in :attr:`skipped` and kept out of the fit.
        time : array_like, shape (n,), optional
            Their times (s). Given, samples lost in between (a gap of more than half a
            sample interval) are filled by holes that no filter window counts across,
            and samples at or before the last one are skipped.

        Raises
        ------
        InputError
            If the arrays are not one-dimensional and of one length.
        """
        x = np.asarray(position, dtype=float)
        f = np.asarray(force, dtype=float)
        if x.ndim != 1 or f.ndim != 1 or x.size != f.size:
            raise InputError(
                f"position and force must be 1-D arrays of one length; got shapes "
                f"{x.shape} and {f.shape}"
            )
        if time is not None:
            x, f = self._regrid(np.asarray(time, dtype=float), x, f)
        if x.size == 0:
            return
        good = np.isfinite(x) & np.isfinite(f)
        if not np.all(good):
            # hold the last finite value: the filter sees no jump, and the windows that
            # hold these samples are left out below
            x, f = _hold(x, good, self._last_x), _hold(f, good, self._last_f)
            self.skipped += int(np.sum(~good))
        if np.all(~good) and not math.isfinite(self._last_x):
            self.received += x.size
            return  # nothing finite yet: nothing to hold, nothing to filter
        self.received += x.size
        ok = good & (self._contact(f, good) if self.contact else True)
        self._last_x, self._last_f = float(x[-1]), float(f[-1])
        self._x = np.concatenate([self._x, x])
        self._f = np.concatenate([self._f, f])
        self._ok = np.concatenate([self._ok, ok])
        # the differentiator wants at least two windows at a time
        if self._x.size >= 2 * self.window:
            self._filter()

    def _regrid(self, t: Array, x: Array, f: Array) -> tuple[Array, Array]:
        """Samples on the stream's grid: holes (NaN) where samples are missing, and
        none that repeat or go back in time."""
        if t.shape != x.shape:
            raise InputError(f"time must have the shape of position {x.shape}, got {t.shape}")
        ok = np.isfinite(t)
        if self._t0 is None:
            if not np.any(ok):
                self.skipped += t.size
                return np.zeros(0), np.zeros(0)
            self._t0 = float(t[ok][0])
        k = np.rint((np.where(ok, t, -np.inf) - self._t0) * self.rate_hz)
        # keep samples strictly after the last, in order (a running maximum)
        last = np.maximum.accumulate(np.concatenate([[self._k_last], k]))[:-1]
        keep = ok & (k > last)
        self.skipped += int(t.size - np.sum(keep))
        if not np.any(keep):
            return np.zeros(0), np.zeros(0)
        k = k[keep].astype(np.int64)
        # holes before each kept sample; a gap longer than a filter window breaks every
        # window as well as a longer one would, so it costs no more than a window
        holes = np.minimum(np.diff(np.concatenate([[self._k_last], k])) - 1, self.window)
        at = np.cumsum(holes + 1) - 1
        out_x = np.full(int(at[-1] + 1), np.nan)
        out_f = out_x.copy()
        out_x[at], out_f[at] = x[keep], f[keep]
        self._k_last = int(k[-1])
        return out_x, out_f

    def _filter(self) -> None:
        """Filter the buffered samples, count the new rows, keep the last window - 1."""
        w = self.window
        t = np.arange(self._x.size) * self.dt
        kin = self.differentiator(t, self._x, self._f)
        m = kin.x.size
        rows = np.flatnonzero(convolve_valid((~self._ok).astype(float), np.ones(w)) < 0.5)
        # each new row is one sample older than the next; the old ones age by m samples
        age = self.decay ** np.arange(m - 1, -1, -1, dtype=float)
        fade = self.decay**m
        self._gram *= fade
        self._count *= fade
        self._sq *= fade
        self._peak *= fade
        if rows.size:
            z = self._columns(kin, self._x)[rows]
            wz = z * age[rows, None]
            self._gram += z.T @ wz
            self._count += float(age[rows].sum())
            self._sq += np.array([kin.x[rows], kin.v[rows], kin.a[rows]]) ** 2 @ age[rows]
            self._peak = max(self._peak, float(np.max(np.abs(kin.force[rows]))))
        self._done += m
        keep = w - 1
        self._x, self._f, self._ok = self._x[-keep:], self._f[-keep:], self._ok[-keep:]

    def _columns(self, kin: Kinematics, x: Array) -> Array:
        """Every law's columns and the filtered force, shape (m, q + 1)."""
        columns: dict[str, Array] = {}
        for law in self.laws:
            design(law, kin, x, 0.0, columns)
        return np.column_stack([*(columns[k] for k in self._keys), kin.force])

    def _contact(self, f: Array, good: NDArray[np.bool_]) -> NDArray[np.bool_]:
        """Whether each sample is in contact (hysteresis on the trailing moving mean of
        the force above the least one seen), updating the running baseline and noise."""
        k = self._smooth_n
        joined = np.concatenate([self._recent, f])
        csum = np.concatenate([[0.0], np.cumsum(joined)])
        # trailing mean over up to k samples (fewer at the very start)
        idx = np.arange(self._recent.size, joined.size) + 1
        lo = np.maximum(idx - k, 0)
        smooth = (csum[idx] - csum[lo]) / (idx - lo)
        self._recent = joined[-(k - 1) :] if k > 1 else np.zeros(0)
        # noise SD from first differences (white noise: var(diff) = 2 var); the signal's
        # own differences at kHz rates are far below the noise of a force sensor
        step = (
            np.diff(np.concatenate([[self._last_f], f]))
            if math.isfinite(self._last_f)
            else np.diff(f)
        )
        step = step[np.isfinite(step)]
        fade = self.decay**f.size
        self._diff_sq = self._diff_sq * fade + float(step @ step)
        self._diff_n = self._diff_n * fade + step.size
        noise = math.sqrt(self._diff_sq / (2 * self._diff_n)) if self._diff_n > 0 else 0.0
        # the least smoothed force seen is the free-jaw baseline (a session that never
        # leaves contact puts it at its least grasping force)
        self._baseline = (
            min(self._baseline, float(np.min(smooth[good]))) if np.any(good) else self._baseline
        )
        above = smooth - self._baseline
        out = np.empty(f.size, bool)
        state = self._in_contact
        enter, leave = ENTER_SD * noise, LEAVE_SD * noise
        # hysteresis: a short loop over the block's samples would cost O(block) in
        # Python; the state only changes where a threshold is crossed
        high, low = above > enter, above < leave
        i = 0
        while i < f.size:
            target = low if state else high
            nxt = np.flatnonzero(target[i:])
            j = f.size if not nxt.size else i + int(nxt[0])
            out[i:j] = state
            if j < f.size:
                state = not state
                out[j] = state
                i = j + 1
            else:
                i = j
        self._in_contact = state
        return out

    # -- the answer ---------------------------------------------------------------

    @property
    def samples(self) -> float:
        """Filtered samples counted, each by its forgetting weight."""
        return self._count

    def scales(self) -> MotionScales:
        """The priors' yardsticks from the counted samples (as
        :func:`~tissuecli.identify.priors.session_scales` computes them offline)."""
        c = max(self._count, 1e-300)
        return scales_from(*(self._sq / c), self._peak, self.force_scale)

    def statistics(self, law: Law | int) -> SufficientStats:
        """The tempered sufficient statistics of one candidate law (by law or index)."""
        j = law if isinstance(law, int) else self.laws.index(law)
        idx = self._index[j]
        g, w = self._gram, self.data_weight
        return SufficientStats(
            w * g[np.ix_(idx, idx)], w * g[idx, -1], float(w * g[-1, -1]), w * self._count
        )

    def posteriors(self) -> list[ExactPosterior]:
        """Each candidate law's exact posterior from the current statistics."""
        scales = self.scales()
        return [
            ExactPosterior(self.statistics(j), law_prior(law, scales), nodes=NODES)
            for j, law in enumerate(self.laws)
        ]

    def estimate(self) -> OnlineEstimate | None:
        """The current estimate, or None before :attr:`min_samples` filtered samples in
        contact; recomputed at most every ``estimate_interval_s`` of data."""
        if self._count < self.min_samples * (1 - 1e-9) and self._cached is None:
            return None
        due = self._cached is None or (
            self._done > self._cached_at
            and (self._done - self._cached_at) * self.dt >= self.estimate_interval_s * (1 - 1e-9)
        )
        if not due:
            return self._cached
        if self._count < 1.0:  # every sample forgotten or none in contact
            return self._cached
        self._cached = self._compute()
        self._cached_at = self._done
        return self._cached

    def _compute(self) -> OnlineEstimate | None:
        try:
            posts = self.posteriors()
            ln_z = np.array([p.ln_evidence() for p in posts])
        except FitError:
            return self._cached  # statistics that floating point cannot hold: keep the last
        prob = np.exp(ln_z - ln_z.max())
        prob /= prob.sum()
        best = int(np.argmax(ln_z))
        law = self.laws[best]
        post = posts[best].summary(self._rng, draws=0)
        confident = self._count * self.data_weight >= CONFIDENT_N_EFF * len(law.terms)
        for t, m, (lo, hi) in zip(law.terms, post.mean, post.ci95, strict=True):
            limit = CONFIDENT_WIDTH.get(t.role)
            if limit is not None and not (m > 0 and hi - lo <= limit * m):
                confident = False
        return OnlineEstimate(
            time_s=(self._done - 1 + self.window // 2) * self.dt,
            law=law.name,
            names=law.symbols,
            units=tuple(t.unit for t in law.terms),
            mean=post.mean,
            ci95=post.ci95,
            probabilities={lw.name: float(p) for lw, p in zip(self.laws, prob, strict=True)},
            confident=confident,
            samples=self._count,
            n_eff=self._count * self.data_weight,
            model=law,
        )


def _named(name: str) -> Differentiator:
    """A differentiator by name; the Gaussian at the online default width."""
    return Gaussian(sigma_s=DEFAULT_SIGMA_S) if name == "gaussian" else differentiator(name)


def _hold(u: Array, good: NDArray[np.bool_], last: float) -> Array:
    """``u`` with every non-finite sample replaced by the last finite one before it."""
    idx = np.where(good, np.arange(u.size), -1)
    np.maximum.accumulate(idx, out=idx)
    first = last if math.isfinite(last) else (float(u[good][0]) if np.any(good) else 0.0)
    return np.where(idx >= 0, u[np.maximum(idx, 0)], first)
