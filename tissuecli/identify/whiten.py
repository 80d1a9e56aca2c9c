"""How the evidence counts correlated residuals: the likelihood strategies.

The force a fit sees is smoothed, and a law that does not follow every feature of
the tissue leaves residuals correlated over many samples; a Gaussian likelihood that
took them as independent would be sure of everything. Two ways to count them:

- :class:`Tempered` (the default): the likelihood is raised to a power, the data
  weight ``n_eff / n`` (:func:`~tissuecli.identify.noise.data_weight`): one over the
  residuals' integrated autocorrelation time, lowered further by a batch-means check.
  That weight is what the residuals say about a constant: about a law's coefficients
  it can be far too low, since the data weight of a misfitting law on a long session
  is its slowest misfit's.
- :class:`Prewhitened`: the residuals are modelled as an autoregressive process of
  order ``q`` (chosen by BIC over Levinson-Durbin fits to the residuals of the law
  that explains the data best), and force and design matrix pass alike through its
  whitening filter ``e_t = r_t - sum_k a_k r_{t-k}``. The exact evidence of the
  filtered problem is the (conditional) Gaussian likelihood of AR(q) noise: each
  frequency counts by its signal-to-residual ratio, not all by the lowest's. Every
  law compared passes through the one filter, so their evidences stay comparable.

The tempered strategy reports ``n w`` as its effective samples. The prewhitened one
reports the evidence's own count: the sample count at which a white-noise likelihood
would give the chosen law's coefficients the precision this one does (the geometric
mean of the precisions' ratios); for AR(1) noise of coefficient ``phi`` and a
constant, ``n (1 - phi) / (1 + phi)``. It is not the default: on a recording no law
follows its generalised least-squares coefficients fit the force's changes rather
than its level, and predicted held-out data worse (docs/benchmarks.md, "The
prewhitened likelihood, measured").
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

#: highest autoregressive order tried (rows of the fitted grid)
MAX_ORDER = 40

#: rows per autoregressive coefficient, at least (a short session tries fewer orders)
ROWS_PER_ORDER = 20


class ARFilter:
    """An autoregressive model of residuals and its whitening filter.

    Parameters
    ----------
    max_order : int
        Highest order tried; the order is chosen by BIC among ``0..max_order``.
    step : int
        Rows between the model's lags: ``r_t = sum_k a_k r_{t - k step} + e_t``. The
        fit's force is smoothed, so its sensor noise is correlated over the smoothing
        filter's ``tau_g`` rows whatever the law; at lags of ``tau_g`` the model sees
        only what correlates residuals beyond that (a law's misfit, coloured noise),
        and the filter never undoes the smoothing (which would hand the regression the
        position noise the smoothing took out of the derivatives).

    Attributes
    ----------
    order_ : int
        ``q``, the chosen order.
    coef_ : ndarray, shape (q,)
        ``a_1..a_q`` of ``r_t = sum_k a_k r_{t-k} + e_t``.
    innovation_var_ : float
        Variance of ``e_t`` (units of the residual squared).
    variance_ : float
        Variance of the residuals themselves.
    """

    def __init__(self, max_order: int = MAX_ORDER, step: int = 1) -> None:
        self.max_order = max_order
        self.step = step

    def fit(self, r: Array) -> ARFilter:
        """Fit the order and coefficients to residuals ``r``, shape (n,); returns self.

        Levinson-Durbin on the biased autocovariance (a stable filter by
        construction), the order minimising ``n ln s_q^2 + q ln n``.
        """
        r = np.asarray(r, dtype=float)
        step = max(int(self.step), 1)
        n_all = r.size
        n = n_all // step  # independent rows, as BIC counts them
        top = int(max(0, min(self.max_order, n // ROWS_PER_ORDER)))
        x = r - r.mean() if n_all else r
        size = 2 << int(np.ceil(np.log2(max(n_all, 1))))
        f = np.fft.rfft(x, size)
        acov = np.fft.irfft(f.real**2 + f.imag**2, size)[: top * step + 1 : step] / max(n_all, 1)
        self.variance_ = float(acov[0])
        best_bic, best = n * math.log(max(acov[0], 1e-300)), np.zeros(0)
        best_var = float(acov[0])
        if acov[0] > 0:
            a = np.zeros(0)
            err = float(acov[0])
            for q in range(1, top + 1):
                k = (acov[q] - a @ acov[q - 1 : 0 : -1]) / err if q > 1 else acov[1] / err
                a = np.concatenate([a - k * a[::-1], [k]])
                err *= 1.0 - k * k
                if err <= 0:
                    break
                bic = n * math.log(err) + q * math.log(n)
                if bic < best_bic:
                    best_bic, best, best_var = bic, a.copy(), err
        self.coef_ = best
        self.order_ = int(best.size)
        self.innovation_var_ = float(best_var)
        return self

    @property
    def phi(self) -> Array:
        """The whitening filter's taps ``(1, -a_1, ..., -a_q)``, shape (q + 1,)."""
        return np.concatenate([[1.0], -self.coef_])

    def transform(self, X: Array) -> Array:
        """``X`` through the whitening filter along its first axis, the first ``q step``
        rows (which have no full history) left out: shape (n - q step, ...)."""
        X = np.asarray(X, dtype=float)
        q = self.order_ * max(int(self.step), 1)
        out = X[q:].copy()
        for k, a in enumerate(self.coef_, start=1):
            lag = k * max(int(self.step), 1)
            out -= a * X[q - lag : X.shape[0] - lag]
        return out

    @property
    def span(self) -> int:
        """Rows the filter leaves out at the start: ``q step``."""
        return self.order_ * max(int(self.step), 1)

    def kernels(self, K: Array, stride: int = 1) -> Array:
        """Noise kernels (one a row, on the raw grid) as the filtered columns see them:
        each convolved with the filter's taps ``step stride`` raw samples apart (the
        filter runs on every ``stride``-th sample), shape (p, w + q step stride)."""
        K = np.atleast_2d(np.asarray(K, dtype=float))
        spacing = max(int(self.step), 1) * stride
        taps = np.zeros(self.order_ * spacing + 1)
        taps[::spacing] = self.phi
        out = np.zeros((K.shape[0], K.shape[1] + taps.size - 1))
        for i, k in enumerate(K):
            out[i] = np.convolve(k, taps)
        return out

    @property
    def tau(self) -> float:
        """Integrated autocorrelation time of the fitted process (rows):
        ``s_e^2 / (s_r^2 (1 - sum a_k)^2)``, its spectrum at zero over its variance."""
        if self.variance_ <= 0:
            return 1.0
        gain = (1.0 - float(self.coef_.sum())) ** 2
        return max(self.innovation_var_ / (self.variance_ * gain), 1e-12) if gain > 0 else math.inf


def precision_ratio(gram_white: Array, var_white: float, gram: Array, var: float) -> float:
    """Geometric mean over a law's coefficients of how much the prewhitened likelihood's
    precision ``A_w^T A_w / s_e^2`` holds against a white one's ``A^T A / s_r^2`` (the
    generalised eigenvalues' geometric mean): the effective samples per sample."""
    p = gram.shape[0]
    if p == 0 or var_white <= 0 or var <= 0:
        return 1.0
    d = np.sqrt(np.clip(np.diag(gram), 1e-300, None))
    s1 = np.linalg.slogdet(gram_white / np.outer(d, d))
    s0 = np.linalg.slogdet(gram / np.outer(d, d))
    if s1[0] <= 0 or s0[0] <= 0:
        return 1.0
    return float(np.exp((s1[1] - s0[1]) / p) * var / var_white)


class Likelihood:
    """How the evidence counts correlated residuals (the base of the strategies)."""

    name = ""

    def get_params(self) -> dict[str, object]:
        return {}

    def __repr__(self) -> str:
        params = ", ".join(f"{k}={v!r}" for k, v in self.get_params().items())
        return f"{type(self).__name__}({params})"


class Tempered(Likelihood):
    """The likelihood raised to the data weight (batch means and autocorrelation time)."""

    name = "tempered"


class Prewhitened(Likelihood):
    """The exact likelihood of AR(q) residuals: force and design pass through the
    whitening filter of :class:`ARFilter` fitted to the best law's residuals.

    Parameters
    ----------
    max_order : int
        Highest autoregressive order tried.
    """

    name = "prewhitened"

    def __init__(self, max_order: int = MAX_ORDER) -> None:
        self.max_order = max_order

    def get_params(self) -> dict[str, object]:
        return {"max_order": self.max_order}

    def filter_for(self, r: Array, step: int = 1) -> ARFilter:
        """The whitening filter fitted to residuals ``r``, lags ``step`` rows apart."""
        return ARFilter(self.max_order, step).fit(r)


#: the likelihood strategies by name
LIKELIHOODS: dict[str, type[Likelihood]] = {"tempered": Tempered, "prewhitened": Prewhitened}


#: the strategy of a fit that names none (a name or an instance)
DEFAULT_LIKELIHOOD: str | Likelihood = "tempered"


def likelihood_strategy(spec: str | Likelihood | None) -> Likelihood:
    """A likelihood strategy by name or as given (None: :data:`DEFAULT_LIKELIHOOD`).

    Raises
    ------
    FitError
        For an unknown name.
    """
    if spec is None:
        spec = DEFAULT_LIKELIHOOD
    if isinstance(spec, Likelihood):
        return spec
    if spec not in LIKELIHOODS:
        from ..core.errors import FitError

        raise FitError(f"unknown likelihood {spec!r}; choose {' or '.join(LIKELIHOODS)}")
    return LIKELIHOODS[spec]()
