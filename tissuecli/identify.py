"""Identification of ``K f0(x) + S f1(xdot) + M xddot = F`` from a session.

Two estimators with the scikit-learn shape (keyword hyperparameters,
``fit(session)`` returning self, fitted attributes ending in ``_``):

- :class:`WindowedPinv`: the paper's method, a pseudoinverse on each of m
  windows of n+1 samples, keeping the window of smallest residual;
- :class:`BayesianFit`: every model form at once, exact posteriors and
  evidences where they exist, emcee where the positivity bounds cut the
  posterior, posterior model probabilities, and diagnostics.

Both see the data through a differentiator (:mod:`tissuecli.derivatives`).
They work on arrays; reading and writing files is the caller's business.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from emcee.autocorr import integrated_time
from numpy.typing import NDArray
from scipy.signal import welch

from .bayes import ExactPosterior, Posterior, Prior, Stats, run_emcee, stepping_stone
from .derivatives import Differentiator, Gaussian, Kinematics, differentiator
from .errors import FitError
from .models import FORCE_SCALE, PARAMETERS, TissueModel, all_models
from .session import Session

Array = NDArray[np.float64]

MIN_SAMPLES = 200
#: ln Bayes factor beyond which a form is decisively behind (Jeffreys: 100:1)
DECISIVE = float(np.log(100.0))
#: posterior mass beyond the positivity bounds above which the posterior is sampled
CUT_THRESHOLD = 1e-3


def parse_forms(spec: str | Sequence[str] | None) -> list[TissueModel]:
    """``"all"``/None, ``"x,xdot"`` or ``["x,xdot", "x^3,xdot"]`` into models."""
    if spec is None or spec == "all":
        return all_models()
    specs = [spec] if isinstance(spec, str) else list(spec)
    models = []
    for item in specs:
        parts = [p.strip() for p in item.split(",")]
        if len(parts) != 2:
            raise FitError(f"--forms {item!r}: give f0,f1 such as x,xdot or x^3,xdot^2, or all")
        models.append(TissueModel.from_names(*parts))
    return models


def longest_gapless(session: Session) -> tuple[Session, list[str]]:
    """The longest stretch without gaps (lost frames), and a warning if that is not all of it.

    The derivative filters need evenly spaced samples; rather than refuse a
    session with a few lost frames, fit its longest gap-free stretch and say so.
    """
    steps = np.diff(session.time)
    if steps.size == 0:
        return session, []
    dt = float(np.median(steps))
    cuts = np.flatnonzero(np.abs(steps - dt) > 0.25 * dt) + 1
    if cuts.size == 0:
        return session, []
    edges = np.concatenate([[0], cuts, [len(session)]])
    i = int(np.argmax(np.diff(edges)))
    a, b = int(edges[i]), int(edges[i + 1])
    part = Session(
        session.time[a:b],
        session.force[a:b],
        session.position[a:b],
        name=session.name,
        meta=dict(session.meta),
    )
    return part, [
        f"the session has {cuts.size} gap(s) (lost frames); fitted the longest gap-free "
        f"stretch, {session.time[a]:.3f}-{session.time[b - 1]:.3f} s "
        f"({100 * (b - a) / len(session):.0f} % of the samples)"
    ]


def prepare(session: Session, diff: Differentiator) -> tuple[Session, Kinematics, list[str]]:
    """Validate a session, put it on its sample grid, check that it can identify anything,
    and differentiate it without looking through holes.

    Lost frames become holes in the sample grid (filled by interpolation so the
    filters run, but marked), and so do samples at either end of the ADC, when
    the session knows its ADC: a clipped value is not a measurement. Filtered
    samples whose window holds a hole are left out of the fit, so nothing else
    is lost. A grid that cannot be built (repeated or reordered sample times, or
    more lost than kept) falls back to the longest gap-free stretch.

    Returns
    -------
    session : Session
        What is fitted, on a regular grid; holes hold interpolated stand-ins.
    kinematics : Kinematics
    warnings : list of str
        Says what lost frames and clipping cost.
    """
    session.validate()
    n = len(session)
    if n < MIN_SAMPLES:
        raise FitError(f"session has {n} samples; at least {MIN_SAMPLES} are needed to fit")
    grid = on_grid(session)
    warnings: list[str] = []
    if grid is None:
        session, warnings = longest_gapless(session)
        valid = np.ones(len(session), bool)
        lost = 0
    else:
        session, valid = grid
        lost = int(np.count_nonzero(~valid))
    x, f = (
        (session.position, session.force)
        if not lost
        else (u[valid] for u in (session.position, session.force))
    )
    if np.ptp(x) <= 0 or np.std(x) < 1e-9:
        raise FitError(
            "jaw position is constant: nothing to identify; the jaws must move "
            "while the forceps records"
        )
    if np.ptp(f) <= 0:
        raise FitError("force is constant: check the force sensor and its calibration")
    present = valid.copy()
    clipped = adc_ends(session)
    for _, mask in clipped:
        valid &= ~mask
    kin = diff(session.time, session.position, session.force, valid)
    if lost:
        gaps = int(np.count_nonzero(np.diff(present.astype(np.int8)) == 1))
        warnings.append(
            f"the session has {gaps} gap(s) ({lost} lost frame(s)): the fit leaves out the "
            "filtered samples whose window spans one"
        )
    for message, mask in clipped:
        warnings.append(
            f"{message} in {100 * np.mean(mask[present]):.1f} % of samples: clipped values are "
            "not measurements, so the fit leaves out the filtered samples whose window holds "
            "one; grasp more gently or widen the sensor range"
        )
    if lost or clipped:
        full = len(session) - kin.window + 1
        warnings.append(
            f"{100 * (full - kin.time.size) / full:.1f} % of the filtered samples were left "
            "out for lost or clipped samples in their window"
        )
    return session, kin, warnings


def on_grid(session: Session) -> tuple[Session, NDArray[np.bool_]] | None:
    """The session on its regular sample grid, and which grid points were recorded.

    Lost samples get interpolated time, force and position, and ``False``.
    None when the times do not fall on one grid (repeated or reordered), or
    when more samples are missing than present.
    """
    t = session.time
    dt = float(np.median(np.diff(t)))
    k = np.rint((t - t[0]) / dt).astype(np.int64)
    if np.all(np.diff(k) == 1):
        return session, np.ones(len(session), bool)
    if np.any(np.diff(k) < 1) or k[-1] + 1 > 2 * k.size:
        return None
    dt = float((t[-1] - t[0]) / k[-1])  # refined over the whole span
    if np.max(np.abs(t - t[0] - k * dt)) > 0.25 * dt:
        return None
    grid = np.arange(k[-1] + 1)
    valid = np.zeros(grid.size, bool)
    valid[k] = True
    filled = Session(
        *(np.interp(grid, k, u) for u in (t, session.force, session.position)),
        name=session.name,
        meta=dict(session.meta),
    )
    return filled, valid


def adc_ends(session: Session) -> list[tuple[str, NDArray[np.bool_]]]:
    """Samples at either end of the ADC, per channel that has any, when the session
    knows its ADC (as recordings do): ``(description, mask)``."""
    device = session.meta.get("device") or {}
    if not isinstance(device, dict):
        return []
    bits, cal = device.get("adc_bits"), device.get("calibration")
    if not bits or not isinstance(cal, dict):
        return []
    out = []
    for channel, values in (("force", session.force), ("position", session.position)):
        gain, offset = float(cal[channel]["gain"]), float(cal[channel]["offset"])
        ends = offset + gain * np.array([-(2 ** (bits - 1)), 2 ** (bits - 1) - 1])
        mask = (np.abs(values - ends[0]) < abs(gain) / 2) | (
            np.abs(values - ends[1]) < abs(gain) / 2
        )
        if np.any(mask):
            where = f"({ends[0]:.4g} or {ends[1]:.4g})"
            out.append((f"{channel} is at an end of the {bits}-bit ADC {where}", mask))
    return out


def position_noise_sd(x: Array, fs: float) -> float:
    """SD of white noise on position from the flat top of its spectrum (m)."""
    freqs, p = welch(x - x.mean(), fs=fs, nperseg=int(min(x.size, 4096)))
    top = p[freqs > fs / 4]
    return float(np.sqrt(np.median(top) * fs / 2)) if top.size else 0.0


def design(model: TissueModel, kin: Kinematics, x_full: Array, sigma_x: float = 0.0) -> Array:
    """Design matrix (m, 3) consistent with the filtered force.

    The stiffness column filters f0 of the raw position, ``g * f0(x)``, which
    matches ``g * F`` for any f0; damping uses :meth:`Kinematics.damping_input` (exact for
    a linear f1) and inertia the filtered acceleration (exact). ``sigma_x`` (m), the
    position noise, removes the mean that noise adds inside curved forms.
    """
    var = sigma_x**2
    return np.column_stack(
        [
            kin.stiffness_input(model.f0, x_full, var),
            kin.damping_input(model.f1, x_full, var),
            kin.a,
        ]
    )


def eiv_correction(model: TissueModel, kin: Kinematics, x_full: Array, sigma_x: float) -> Array:
    """Expected contribution of position noise to A^T A (errors in variables).

    Column j carries noise ``d_j * (k_j * e)`` to first order, with ``d_j`` the
    form's slope and ``k_j`` its kernel, so ``E[noise_i . noise_j] =
    sigma_x^2 (k_i . k_j) sum_n d_i d_j``. Subtracting it removes the
    attenuation bias that noisy derivatives put on M.
    """
    d = np.column_stack(
        [kin.smooth(model.f0.derivative(x_full)), model.f1.derivative(kin.v), np.ones(kin.v.size)]
    )
    K = np.array([kin.kernels[0], kin.kernels[1], kin.kernels[2]])
    return sigma_x**2 * (K @ K.T) * (d.T @ d)


def residual_tau(r: Array) -> float:
    """Integrated autocorrelation time of residuals (samples), >= 1."""
    return float(max(1.0, integrated_time(r, c=5, tol=0, quiet=True)[0]))


def data_weight(A: Array, r: Array, tau: float) -> float:
    """How much one sample counts, ``n_eff / n``, for honest intervals.

    Starts from ``1 / tau`` (residuals correlated over tau samples) and lowers it
    further if a batch-means estimate of the coefficients' sampling variance
    (robust to any residual correlation and to noise in the regressors) exceeds
    what the tempered Gaussian likelihood implies: the curvature adjustment of
    a misspecified likelihood (Ribatet et al. 2012), kept O(n).
    """
    n = r.size
    block = max(int(np.ceil(5 * tau)), 1)
    if n // block < 30:
        block = max(n // 30, 1)
    nb = n // block
    scores = (A[: nb * block] * r[: nb * block, None]).reshape(nb, block, -1).sum(axis=1)
    G_inv = np.linalg.pinv(A.T @ A)
    v_robust = np.diag(G_inv @ (scores.T @ scores) @ G_inv)
    v_model = (r @ r / n) * np.diag(G_inv)
    ratio = float(np.min(v_model / np.where(v_robust > 0, v_robust, np.inf)))
    return min(1.0 / tau, ratio) if ratio > 0 else 1.0 / tau


@dataclass
class ModelResult:
    """The fit of one model form."""

    model: TissueModel
    ln_evidence: float = float("nan")
    probability: float = float("nan")
    posterior: Posterior | None = None
    ln_evidence_sampler: float | None = None
    status: str = "exact"  # exact | emcee | skipped
    reason: str = ""
    cond: float = float("nan")
    cond_scaled: float = float("nan")
    residual_rms: float = float("nan")
    flags: list[str] = field(default_factory=list)
    gram: Array = field(default_factory=lambda: np.zeros((3, 3)), repr=False)  # A^T A
    correction: Array | None = field(default=None, repr=False)  # errors-in-variables, if applied
    stats: Stats | None = field(default=None, repr=False)
    prior: Prior | None = field(default=None, repr=False)

    @property
    def name(self) -> str:
        return self.model.name


class BayesianFit:
    """Bayesian identification over model forms with model choice.

    Parameters
    ----------
    forms : str or list of str
        ``"all"`` or forms such as ``"x,xdot"``.
    sampler : {"auto", "emcee"}
        ``auto`` samples only where the exact posterior does not apply (the
        positivity bound cuts it); ``emcee`` samples every form not skipped,
        and also estimates its evidence by stepping-stone as a check.
    differentiator : str or Differentiator
    eiv : bool
        Correct the errors-in-variables bias from position noise.
    force_scale : float
        N. Sets the priors: each term of the law is expected to stay within a
        few times this force at jaw-scale closure, speed and acceleration.
    decisive : float
        ln Bayes factor behind the best beyond which a form is not sampled.
    seed : int
    progress : callable, optional
        ``progress(form, steps, tau)`` while sampling.

    Attributes
    ----------
    results_ : list of ModelResult
        One per form, best first.
    best_ : ModelResult
    kinematics_ : Kinematics
    session_ : Session
        What was fitted: the session on its sample grid, lost samples interpolated
        (the kinematics leave out every filtered sample that depends on them).
    tau_ : float
        Integrated autocorrelation time of the best form's residuals (samples).
    n_eff_ : float
        Effective independent samples, n / tau.
    sigma_x_ : float
        Position noise SD estimated from its spectrum (m).
    warnings_ : list of str
    """

    def __init__(
        self,
        forms: str | Sequence[str] = "all",
        *,
        sampler: str = "auto",
        differentiator: str | Differentiator = "gaussian",
        eiv: bool = True,
        decisive: float = DECISIVE,
        force_scale: float = FORCE_SCALE,
        seed: int = 0,
        progress: Callable[[str, int, float], None] | None = None,
    ) -> None:
        self.forms = forms
        self.force_scale = force_scale
        self.sampler = sampler
        self.differentiator = differentiator
        self.eiv = eiv
        self.decisive = decisive
        self.seed = seed
        self.progress = progress

    def _diff(self) -> Differentiator:
        d = self.differentiator
        return differentiator(d) if isinstance(d, str) else (d or Gaussian())

    def fit(self, session: Session) -> BayesianFit:
        if self.sampler not in ("auto", "emcee"):
            raise FitError(f"unknown sampler {self.sampler!r}; choose auto or emcee")
        models = parse_forms(self.forms)
        session, kin, gap_warnings = prepare(session, self._diff())
        self.session_ = session
        x_full = session.position
        fs = 1.0 / float(np.median(np.diff(session.time)))
        self.kinematics_ = kin
        self.sigma_x_ = 0.0
        if self.eiv:
            # quantisation with little dither is not white and hides from the spectrum's
            # flat top, so the ADC step sets a floor: step^2 / 12
            step = float(session.meta.get("position_resolution_m", 0.0) or 0.0)
            self.sigma_x_ = max(position_noise_sd(x_full, fs), step / np.sqrt(12))
        y = kin.force
        rng = np.random.default_rng(self.seed)
        self.warnings_: list[str] = gap_warnings

        # one pass per form keeps only its sufficient statistics, so memory holds one
        # design matrix at a time whatever the number of forms
        firsts = {
            m.name: _first_pass(m, kin, x_full, y, self.sigma_x_ if self.eiv else 0.0)
            for m in models
        }
        # residual correlation from the best-fitting form: smoothing makes neighbouring
        # residuals alike, and treating them as independent would overstate certainty
        best_ls = min(firsts, key=lambda name: firsts[name].rss)
        self._check_prior_conflict(models, firsts[best_ls].beta, best_ls)
        self.tau_ = firsts[best_ls].tau
        A = design(next(m for m in models if m.name == best_ls), kin, x_full, self.sigma_x_)
        weight = data_weight(A, y - A @ firsts[best_ls].beta, self.tau_)
        del A
        self.n_eff_ = y.size * weight

        results = []
        for m in models:
            fp = firsts[m.name]
            corr = fp.correction
            uncorrected = corr is not None and np.any(np.linalg.eigvalsh(fp.gram - corr) <= 0)
            if uncorrected:
                corr = None  # noise dominates a column: the correction would be meaningless
            G = fp.gram - corr if corr is not None else fp.gram
            st = Stats(weight * G, weight * fp.b, weight * fp.yy, weight * y.size)
            prior = Prior(scales=m.prior_scales(self.force_scale))
            post = ExactPosterior(st, prior).summary(rng)
            flags = []
            if uncorrected:
                flags.append(
                    "position noise dominates a column: left uncorrected, so M (and "
                    "perhaps S) are biased towards zero"
                )
            if corr is not None:
                # the correction rests on an estimated noise level: say when it matters
                shift = post.mean - fp.beta
                for j in np.flatnonzero(np.abs(shift) > post.sd):
                    flags.append(
                        f"{PARAMETERS[j]} moved {100 * shift[j] / post.mean[j]:+.1f} % by the "
                        f"position-noise correction (noise {self.sigma_x_ * 1e6:.3g} um); its "
                        "interval does not include that correction's own uncertainty"
                    )
            results.append(
                ModelResult(
                    model=m,
                    ln_evidence=post.ln_evidence,
                    posterior=post,
                    cond=fp.cond,
                    cond_scaled=fp.cond_scaled,
                    residual_rms=float(np.sqrt(fp.rss / y.size)),
                    gram=fp.gram,
                    correction=corr,
                    stats=st,
                    prior=prior,
                    flags=flags,
                )
            )

        top = max(r.ln_evidence for r in results)
        for res in results:
            behind = top - res.ln_evidence
            assert res.posterior is not None
            needs = res.posterior.outside > CUT_THRESHOLD or self.sampler == "emcee"
            if not needs:
                continue
            if behind > self.decisive and len(results) > 1:
                res.status = "skipped"
                res.reason = (
                    f"not sampled: ln Bayes factor {behind:.1f} behind the best "
                    f"(> {self.decisive:.1f}, decisive)"
                )
                continue
            cb = None
            if self.progress is not None:

                def cb(steps: int, tau: float, name: str = res.name) -> None:
                    self.progress(name, steps, tau)  # type: ignore[misc]

            cut = res.posterior.outside
            res.posterior = run_emcee(res.stats, res.prior, rng, progress=cb)
            res.status = "emcee"
            res.reason = (
                f"sampled: the positivity bound cuts {100 * cut:.2g} % of the closed-form posterior"
                if self.sampler == "auto"
                else "sampled on request (--sampler emcee)"
            )
            if self.sampler == "emcee":
                res.ln_evidence_sampler = stepping_stone(res.stats, res.prior, rng)
            post = res.posterior
            if not post.diagnostics.get("converged", True):
                res.flags.append("chain shorter than 50 autocorrelation times")
        for res in results:
            if res.status == "exact" and self.sampler == "auto":
                res.reason = (
                    "exact posterior (closed form); positivity bound cuts "
                    f"{res.posterior.outside:.1e} of it"
                )
        ln_z = np.array([r.ln_evidence for r in results])
        prob = np.exp(ln_z - ln_z.max())
        prob /= prob.sum()
        for r, p in zip(results, prob, strict=True):
            r.probability = float(p)
            r.flags.extend(_identifiability(r))
        results.sort(key=lambda r: -r.ln_evidence)
        self.results_ = results
        self.best_ = results[0]
        self.warnings_.extend(f"{self.best_.name}: {f}" for f in self.best_.flags)
        self.warnings_.extend(self._outlier_warnings())
        return self

    def _outlier_warnings(self, z: float = 8.0) -> list[str]:
        """Raw force samples beyond ``z`` noise SDs of the fit: glitches (ADC spikes, a knock)
        the Gaussian noise model does not explain, and which pull every parameter.

        Raw, not filtered, residuals: filtering smears a spike over the kernel,
        and at high rates with a coarse position ADC the filtered residual carries
        the quantisation of position (plateaus of K q / 2 at every turn of the
        jaw), which is not a glitch but stood at 50 filtered-noise SDs.
        """
        r = self.kinematics_.force_raw - self.fitted_force()
        scale = 1.4826 * float(np.median(np.abs(r - np.median(r))))  # robust SD
        if not scale > 0:
            return []
        bad = np.flatnonzero(np.abs(r) > z * scale)
        if bad.size == 0:
            return []
        t = self.kinematics_.time[bad]
        return [
            f"{bad.size} force sample(s) lie beyond {z:g} noise SDs of the fit, first at "
            f"t = {t[0]:.3f} s: a glitching sensor or a knock; the parameters absorb it, so "
            "inspect the residuals in the report and fit a clean stretch"
        ]

    def _check_prior_conflict(self, models: list[TissueModel], beta: Array, best: str) -> None:
        """Refuse data whose best fit lies far outside the priors: a units mistake, or a
        material the priors were not written for, would otherwise give prior-driven answers."""
        model = next(m for m in models if m.name == best)
        scales = model.prior_scales(self.force_scale)
        ratio = np.abs(beta) / scales
        j = int(np.argmax(ratio))
        if not np.all(np.isfinite(beta)):
            raise FitError(
                "the least-squares fit is not finite; check the session for extreme values"
            )
        if ratio[j] > 10:
            name = PARAMETERS[j]
            raise FitError(
                f"the data put {name} at {beta[j]:.3g} {model.units[name]}, {ratio[j]:.0f} times "
                f"its prior scale ({scales[j]:.3g}) for forces of about {self.force_scale:g} N "
                "at jaw-scale motion; check that position is in m and force in N, or set "
                "--force-scale to the forces this material produces"
            )

    def fitted_force(self, result: ModelResult | None = None) -> Array:
        """Force predicted by a form's posterior mean on the fitted samples (N)."""
        r = result or self.best_
        A = design(r.model, self.kinematics_, self.session_.position, self.sigma_x_)
        return A @ r.posterior.mean  # type: ignore[union-attr]


@dataclass
class _FirstPass:
    """What the fit keeps of one form's design matrix: its sufficient statistics."""

    gram: Array
    b: Array
    yy: float
    beta: Array
    rss: float
    tau: float
    cond: float
    cond_scaled: float
    correction: Array | None


def _first_pass(
    model: TissueModel, kin: Kinematics, x_full: Array, y: Array, sigma_x: float
) -> _FirstPass:
    A = design(model, kin, x_full, sigma_x)
    beta = _lstsq_scaled(A, y)
    r = y - A @ beta
    norms = np.linalg.norm(A, axis=0)
    return _FirstPass(
        gram=A.T @ A,
        b=A.T @ y,
        yy=float(y @ y),
        beta=beta,
        rss=float(r @ r),
        tau=residual_tau(r),
        cond=float(np.linalg.cond(A)),
        cond_scaled=float(np.linalg.cond(A / np.where(norms > 0, norms, 1.0))),
        correction=eiv_correction(model, kin, x_full, sigma_x) if sigma_x > 0 else None,
    )


def _identifiability(r: ModelResult) -> list[str]:
    """Flags for parameters the data do not pin down."""
    flags = []
    post = r.posterior
    assert post is not None
    scales = r.prior.scales if r.prior is not None else r.model.prior_scales()
    for j, name in enumerate(PARAMETERS):
        lo, hi = post.ci95[j]
        if (
            post.sd[j] > 0.3 * scales[j]
            or lo <= 0.02 * max(hi, 1e-300)
            or post.sd[j] > 0.5 * abs(post.mean[j])
        ):
            what = "too little acceleration content" if name == "M" else "too little excitation"
            flags.append(
                f"{name} not identified ({what}): 95 % interval "
                f"[{lo:.3g}, {hi:.3g}] {r.model.units[name]}"
            )
        elif post.sd[j] > 0.25 * abs(post.mean[j]):
            flags.append(
                f"{name} poorly identified: SD is {100 * post.sd[j] / post.mean[j]:.0f} % "
                "of its value"
            )
    return flags


def _lstsq_scaled(A: Array, y: Array) -> Array:
    """Least squares on unit-norm columns (x^3 in SI units is 1e6 smaller than x)."""
    d = np.linalg.norm(A, axis=0)
    d[d == 0] = 1.0
    return np.linalg.lstsq(A / d, y, rcond=None)[0] / d


class WindowedPinv:
    """The paper's identification: pseudoinverse on m windows of n+1 samples.

    Parameters
    ----------
    forms : str
        One form, e.g. ``"x,xdot"``.
    window_s : float
        Window length in s (n+1 = window_s * rate).
    differentiator : str or Differentiator

    Attributes
    ----------
    params_ : ndarray, shape (3,)
        (K, S, M) of the window with the smallest residual, SI.
    windows_ : ndarray, shape (m, 3)
        Parameters of every window.
    residuals_ : ndarray, shape (m,)
        RMS residual of each window (N).
    best_window_ : int
    session_ : Session
        What was fitted (see :class:`BayesianFit`).
    cond_, cond_scaled_ : float
        Condition numbers of the best window's design, raw and column-scaled.
    pooled_ : ndarray, shape (3,)
        All windows in one least-squares problem, for comparison.
    """

    def __init__(
        self,
        forms: str = "x,xdot",
        *,
        window_s: float = 1.0,
        differentiator: str | Differentiator = "gaussian",
    ) -> None:
        self.forms = forms
        self.window_s = window_s
        self.differentiator = differentiator

    def fit(self, session: Session) -> WindowedPinv:
        (model,) = parse_forms(self.forms) if self.forms != "all" else (all_models()[0],)
        d = self.differentiator
        session, kin, self.warnings_ = prepare(
            session, differentiator(d) if isinstance(d, str) else d
        )
        self.session_ = session
        A, y = design(model, kin, session.position), kin.force
        n = max(int(round(self.window_s / np.median(np.diff(kin.time)))), 10)
        m = A.shape[0] // n
        if m < 1:
            raise FitError(
                f"session shorter than one {self.window_s:g} s window; "
                "use a shorter --window or a longer session"
            )
        params, resid = np.empty((m, 3)), np.empty(m)
        for i in range(m):
            Ai, yi = A[i * n : (i + 1) * n], y[i * n : (i + 1) * n]
            params[i] = _lstsq_scaled(Ai, yi)
            resid[i] = np.sqrt(np.mean((yi - Ai @ params[i]) ** 2))
        self.model_ = model
        self.kinematics_ = kin
        self.windows_, self.residuals_ = params, resid
        self.best_window_ = int(np.argmin(resid))
        self.params_ = params[self.best_window_]
        Ab = A[self.best_window_ * n : (self.best_window_ + 1) * n]
        self.cond_ = float(np.linalg.cond(Ab))
        self.cond_scaled_ = float(np.linalg.cond(Ab / np.linalg.norm(Ab, axis=0)))
        self.pooled_ = _lstsq_scaled(A[: m * n], y[: m * n])
        self.window_samples_ = n
        return self

    def summary(self) -> dict[str, Any]:
        return {
            "model": self.model_.name,
            "window_samples": self.window_samples_,
            "windows": int(self.windows_.shape[0]),
            "best_window": self.best_window_,
            "best_residual_rms_N": float(self.residuals_[self.best_window_]),
            "cond": self.cond_,
            "cond_scaled": self.cond_scaled_,
        }
