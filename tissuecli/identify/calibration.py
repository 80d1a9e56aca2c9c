"""Calibration fits, numerics only: a sensor channel against known references, the
display's static voltage sweep and its free ring-down.

- :class:`ChannelFit`: raw readings against reference values, ``raw = a + b ref``
  (plus a tested quadratic term), inverted to the ``value = gain * raw + offset``
  that calibration files store, with intervals;
- :func:`fit_ringdown`: a damped oscillation about an equilibrium, the equilibrium,
  decay rate and frequency with their covariance;
- :func:`fit_display`: the display's spring, solenoid, moving mass and damping from
  every frame of a voltage sweep and its ring-downs under a known weight;
- :func:`slow_force_warning`, :func:`held_rate`: a load cell read too slowly to see the
  mass term, and how often a reading repeated on a faster line really changes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..core.errors import InputError
from .noise import data_weight, integrated_time

Array = NDArray[np.float64]

#: Standard gravity, m/s^2 (a reference mass's weight is m g).
G = 9.80665
#: Two-sided level of every interval here.
LEVEL = 0.95
#: A quadratic term whose F-test p-value is below this is reported as nonlinearity.
QUADRATIC_P = 0.05

#: Largest reference (N or m) and raw reading a calibration accepts: beyond any sensor.
MAX_REFERENCE = 1e6
MAX_RAW = 1e12

#: Slowest force reading that still resolves the mass term M at grasp speeds, Hz. Grasps
#: carry motion up to about 20 Hz (a jaw-scale stiffness of 100-1350 N/m on a 0.05 kg
#: jaw has its natural frequency at 7-26 Hz), and an acceleration is seen only with
#: about ten samples a period of the fastest motion: 10 x 20 Hz.
MIN_FORCE_RATE_HZ = 200.0


def _t(dof: int, level: float = LEVEL) -> float:
    """Two-sided Student t quantile for ``dof`` degrees of freedom."""
    from scipy.stats import t  # loaded when a calibration is fitted

    return float(t.ppf(0.5 + level / 2, dof))


@dataclass
class ChannelFit:
    """One sensor channel calibrated against known references.

    The raw reading carries the noise and the reference is known (a weight, a gauge
    block), so the regression is ``raw = a + b ref`` (ordinary least squares), inverted
    to ``value = gain * raw + offset`` with ``gain = 1 / b`` and ``offset = -a / b``;
    intervals by the delta method with Student t quantiles. A quadratic term
    ``+ q ref^2`` is tested by the extra-sum-of-squares F-test; its largest departure
    from the straight line over the references is the nonlinearity.

    Parameters
    ----------
    level : float
        Two-sided level of the intervals.
    p_quadratic : float
        A quadratic term with an F-test p-value below this is significant.

    Attributes
    ----------
    gain_, offset_ : float
        SI per raw unit, SI.
    gain_ci_, offset_ci_ : tuple of float
        Their intervals at ``level``.
    residual_sd_ : float
        SD of the straight line's residuals, in SI (raw residuals times ``|gain|``).
    n_ : int
        Points fitted.
    quadratic_p_ : float or None
        F-test p-value of the quadratic term (None with fewer than 4 distinct references).
    nonlinearity_ : float
        Largest departure of the quadratic fit from the straight line over the
        references, SI (0 without a quadratic test).
    span_ : float
        Range of the references, SI.
    """

    level: float = LEVEL
    p_quadratic: float = QUADRATIC_P
    gain_: float = field(init=False, default=math.nan)
    offset_: float = field(init=False, default=math.nan)
    gain_ci_: tuple[float, float] = field(init=False, default=(math.nan, math.nan))
    offset_ci_: tuple[float, float] = field(init=False, default=(math.nan, math.nan))
    residual_sd_: float = field(init=False, default=math.nan)
    n_: int = field(init=False, default=0)
    quadratic_p_: float | None = field(init=False, default=None)
    nonlinearity_: float = field(init=False, default=0.0)
    span_: float = field(init=False, default=0.0)

    def fit(self, reference: ArrayLike, raw: ArrayLike, what: str = "channel") -> ChannelFit:
        """Fit raw readings (shape (n,), any unit) against references (shape (n,), SI).

        Raises
        ------
        InputError
            Fewer than 3 points, fewer than 2 distinct references, non-finite values,
            or raw readings that do not change with the reference.
        """
        ref = np.asarray(reference, dtype=float).ravel()
        y = np.asarray(raw, dtype=float).ravel()
        if ref.shape != y.shape:
            raise InputError(f"{what}: {ref.size} references but {y.size} readings")
        if not (np.all(np.isfinite(ref)) and np.all(np.isfinite(y))):
            raise InputError(f"{what}: every reference and reading must be a finite number")
        distinct = np.unique(ref).size
        if ref.size < 3 or distinct < 2:
            raise InputError(
                f"{what}: {ref.size} point(s) at {distinct} reference value(s); give at "
                "least 3 points at 2 or more reference values (5 or more to test linearity)"
            )
        if np.max(np.abs(ref)) > MAX_REFERENCE or np.max(np.abs(y)) > MAX_RAW:
            raise InputError(
                f"{what}: a reference beyond {MAX_REFERENCE:g} (SI) or a reading beyond "
                f"{MAX_RAW:g}: beyond any sensor; check the columns and units"
            )
        try:
            return self._fit(ref, y, distinct, what)
        except (np.linalg.LinAlgError, FloatingPointError, ZeroDivisionError):
            raise InputError(
                f"{what}: the references are too close together for their readings to "
                "give a line; spread them over the range you record"
            ) from None

    def _fit(self, ref: Array, y: Array, distinct: int, what: str) -> ChannelFit:
        n = ref.size
        # centred and scaled so the normal equations are well conditioned in any unit
        mu, scale = float(ref.mean()), float(np.ptp(ref))
        u = (ref - mu) / scale
        X = np.column_stack([np.ones(n), u])
        coef, rss1 = _lstsq(X, y)
        dof = n - 2
        s2 = rss1 / dof if dof > 0 else 0.0
        cov_u = s2 * np.linalg.inv(X.T @ X)
        t = _t(dof, self.level)
        floor = max(t * math.sqrt(cov_u[1, 1]), 1e-9 * float(np.max(np.abs(y))))
        if not (np.isfinite(coef[1]) and abs(coef[1]) > floor):
            raise InputError(
                f"{what}: the readings do not change with the reference (more than their "
                "scatter): is the right channel connected?"
            )
        # back to raw = a + b ref
        b = coef[1] / scale
        a = coef[0] - b * mu
        J = np.array([[1.0, -mu / scale], [0.0, 1.0 / scale]])  # (a, b) from (c0, c1)
        cov = J @ cov_u @ J.T
        gain, offset = float(1.0 / b), float(-a / b)
        # delta method: d(gain)/d(a, b) = (0, -1/b^2); d(offset)/d(a, b) = (-1/b, a/b^2)
        g_grad = np.array([0.0, -1.0 / b**2])
        o_grad = np.array([-1.0 / b, a / b**2])
        g_sd = math.sqrt(max(float(g_grad @ cov @ g_grad), 0.0))
        o_sd = math.sqrt(max(float(o_grad @ cov @ o_grad), 0.0))
        self.gain_, self.offset_ = gain, offset
        self.gain_ci_ = (float(gain - t * g_sd), float(gain + t * g_sd))
        self.offset_ci_ = (float(offset - t * o_sd), float(offset + t * o_sd))
        self.residual_sd_ = math.sqrt(s2) * abs(gain)
        self.n_, self.span_ = n, scale
        self.quadratic_p_, self.nonlinearity_ = None, 0.0
        if distinct >= 3 and n >= 4:
            X2 = np.column_stack([X, u**2])
            coef2, rss2 = _lstsq(X2, y)
            dof2 = n - 3
            if rss2 <= 0.0:
                p = 0.0 if rss1 > 1e-12 * float(np.sum((y - y.mean()) ** 2)) else 1.0
            else:
                from scipy.stats import f as f_dist

                F = (rss1 - rss2) / (rss2 / dof2)
                p = float(f_dist.sf(max(F, 0.0), 1, dof2))
            grid = np.linspace(float(u.min()), float(u.max()), 101)
            line = coef[0] + coef[1] * grid
            curve = coef2[0] + coef2[1] * grid + coef2[2] * grid**2
            self.quadratic_p_ = p
            self.nonlinearity_ = float(np.max(np.abs(curve - line))) * abs(gain)
        return self

    @property
    def nonlinear(self) -> bool:
        """True when the quadratic term is significant at ``p_quadratic``."""
        return self.quadratic_p_ is not None and self.quadratic_p_ < self.p_quadratic


def _lstsq(X: Array, y: Array) -> tuple[Array, float]:
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    r = y - X @ coef
    return coef, float(r @ r)


@dataclass(frozen=True)
class RingDown:
    """A damped oscillation ``x(t) = c + exp(-sigma t) (A cos(w t) + B sin(w t))``.

    Attributes
    ----------
    c : float
        Equilibrium, m.
    sigma : float
        Decay rate, 1/s.
    omega : float
        Damped angular frequency, rad/s.
    cov : ndarray, shape (3, 3)
        Covariance of (c, sigma, omega).
    amplitude : float
        ``hypot(A, B)`` at the first sample, m.
    residual_sd : float
        SD of the residuals, m.
    n : int
        Samples fitted.
    """

    c: float
    sigma: float
    omega: float
    cov: Array
    amplitude: float
    residual_sd: float
    n: int

    @property
    def omega_n(self) -> float:
        """Natural (undamped) angular frequency ``sqrt(w^2 + sigma^2)``, rad/s."""
        return math.hypot(self.omega, self.sigma)

    @property
    def zeta(self) -> float:
        """Damping ratio ``sigma / omega_n``."""
        return self.sigma / self.omega_n


def _ringdown_columns(t: Array, sigma: float, omega: float) -> Array:
    e = np.exp(-sigma * t)
    return np.column_stack([np.ones_like(t), e * np.cos(omega * t), e * np.sin(omega * t)])


def fit_ringdown(t: ArrayLike, x: ArrayLike) -> RingDown:
    """Fit a damped oscillation about an equilibrium to samples ``x`` (m) at ``t`` (s).

    Started by linear prediction (Prony: ``x[k+1] = a1 x[k] + a2 x[k-1] + d`` on a
    uniform grid gives ``exp(-sigma dt)`` and ``omega dt``), then refined by
    Levenberg-Marquardt over all five parameters; the covariance is the residual
    variance times the inverse Gauss-Newton matrix.

    Parameters
    ----------
    t, x : array_like, shape (n,)
        Times (s, increasing, nearly uniform) and positions (m).

    Raises
    ------
    InputError
        Too few samples, or no oscillation in them (overdamped or still).
    """
    t = np.asarray(t, dtype=float).ravel()
    x = np.asarray(x, dtype=float).ravel()
    if t.size < 20:
        raise InputError(f"a ring-down needs at least 20 samples, not {t.size}")
    t = t - t[0]
    dt = float(np.median(np.diff(t)))
    # Prony on the (nearly) uniform grid
    P = np.column_stack([x[1:-1], x[:-2], np.ones(x.size - 2)])
    (a1, a2, _), *_ = np.linalg.lstsq(P, x[2:], rcond=None)
    r2 = -a2
    if not (0 < r2 < 1) or abs(a1) >= 2 * math.sqrt(r2):
        raise InputError(
            "no damped oscillation in the ring-down (the piston did not swing freely: "
            "is it at an end stop, or held?)"
        )
    r = math.sqrt(r2)
    sigma, omega = -math.log(r) / dt, math.acos(a1 / (2 * r)) / dt
    theta = np.array([0.0, 0.0, 0.0, sigma, omega])
    lin, *_ = np.linalg.lstsq(_ringdown_columns(t, sigma, omega), x, rcond=None)
    theta[:3] = lin

    def residual(th: Array) -> Array:
        return x - _ringdown_columns(t, th[3], th[4]) @ th[:3]

    def jacobian(th: Array) -> Array:
        c, A, B, s, w = th
        e = np.exp(-s * t)
        cos, sin = np.cos(w * t), np.sin(w * t)
        osc = e * (A * cos + B * sin)
        return np.column_stack(
            [np.ones_like(t), e * cos, e * sin, -t * osc, t * e * (-A * sin + B * cos)]
        )

    lam = 1e-3
    res = residual(theta)
    cost = float(res @ res)
    for _ in range(100):
        J = jacobian(theta)
        JtJ, g = J.T @ J, J.T @ res
        step = np.linalg.solve(JtJ + lam * np.diag(np.diag(JtJ)), g)
        trial = theta + step
        tres = residual(trial)
        tcost = float(tres @ tres)
        if tcost < cost:
            done = cost - tcost <= 1e-12 * cost
            theta, res, cost, lam = trial, tres, tcost, lam / 3
            if done:
                break
        else:
            lam *= 5
            if lam > 1e8:
                break
    J = jacobian(theta)
    dof = max(x.size - 5, 1)
    s2 = cost / dof
    cov5 = s2 * np.linalg.pinv(J.T @ J)
    keep = [0, 3, 4]
    return RingDown(
        c=float(theta[0]),
        sigma=float(theta[3]),
        omega=abs(float(theta[4])),
        cov=cov5[np.ix_(keep, keep)],
        amplitude=float(math.hypot(theta[1], theta[2])),
        residual_sd=math.sqrt(s2),
        n=int(x.size),
    )


@dataclass(frozen=True)
class Estimate:
    """A value with its standard deviation and interval at :data:`LEVEL`."""

    value: float
    sd: float
    lo: float
    hi: float

    @classmethod
    def normal(cls, value: float, sd: float, t: float | None = None) -> Estimate:
        z = 1.959963984540054 if t is None else t
        return cls(value, sd, value - z * sd, value + z * sd)

    def as_dict(self) -> dict[str, float]:
        return {"value": self.value, "sd": self.sd, "ci95": [self.lo, self.hi]}


@dataclass(frozen=True)
class DisplayFit:
    """The display's constants from every frame of a calibration, off the end stops.

    With a reference mass ``m`` on the piston and the solenoid at ``V(t)`` (each
    frame says what it applied, held over the period that follows), the piston obeys

        x'' + 2 sigma x' + omega^2 x = omega^2 (x0 - kappa V^2),
        x0 = m g / Kp,  kappa = alpha / Kp,  omega^2 = Kp / (Mp + m),  2 sigma = b / (Mp + m).

    The held voltages of the sweep set the equilibria (``x0`` and ``kappa``, so
    ``Kp`` and ``alpha``), the steps between them and the releases ring down
    (``omega`` and ``sigma``, so ``Mp`` and ``b``). The law is discretised exactly for
    a voltage held over each period, and fitted as an output error (the predicted
    trajectory against the encoder), so the encoder's step biases nothing; a frame
    where the solenoid was cut (the watchdog) is simply a known input. Each stretch
    of frames off the end stops has its own initial state.

    Attributes
    ----------
    Kp, alpha, Mp, b : Estimate
        N/m, N/V^2, kg, N s/m.
    frequency_hz, zeta : Estimate
        Natural frequency (Hz) and damping ratio with the mass on.
    x0 : float
        Rest position under the mass at 0 V, m below the top stop.
    frames, segments : int
        Frames fitted and stretches they form.
    residual_sd : float
        SD of the encoder about the fitted trajectory, m.
    """

    Kp: Estimate
    alpha: Estimate
    Mp: Estimate
    b: Estimate
    frequency_hz: Estimate
    zeta: Estimate
    x0: float
    frames: int
    segments: int
    residual_sd: float


def _zoh(omega: float, sigma: float, dt: float) -> tuple[float, float, float, float]:
    """``x[k+1] = a1 x[k] + a2 x[k-1] + c1 w[k] + c2 w[k-1]``: the exact discretisation of
    ``x'' + 2 sigma x' + omega^2 x = omega^2 w`` with ``w`` held over each period ``dt``."""
    wd = np.sqrt(complex(omega * omega - sigma * sigma))

    def step(t: float) -> float:  # unit step response (complex wd covers overdamping)
        if abs(wd) < 1e-12:
            return float(1 - math.exp(-sigma * t) * (1 + sigma * t))
        return float(
            np.real(1 - np.exp(-sigma * t) * (np.cos(wd * t) + sigma / wd * np.sin(wd * t)))
        )

    r = math.exp(-sigma * dt)
    a1 = float(np.real(2 * r * np.cos(wd * dt)))
    a2 = -r * r
    s1, s2 = step(dt), step(2 * dt)
    c1 = s1
    c2 = s2 - a1 * s1 - c1
    return a1, a2, c1, c2


def _display_columns(
    omega: float, sigma: float, u: Array, bounds: list[tuple[int, int]], dt: float
) -> Array:
    """Design columns at (omega, sigma): the response to ``w = 1`` (for ``x0``), to
    ``w = -V^2`` (for ``kappa``), and two free responses per stretch."""
    from scipy.signal import lfilter

    a1, a2, c1, c2 = _zoh(omega, sigma, dt)
    b, a = [0.0, c1, c2], [1.0, -a1, -a2]
    n = u.size
    X = np.zeros((n, 2 + 2 * len(bounds)))
    for j, (lo, hi) in enumerate(bounds):
        m = hi - lo
        X[lo:hi, 0] = lfilter(b, a, np.ones(m))
        X[lo:hi, 1] = lfilter(b, a, -u[lo:hi])
        imp = np.zeros(m)
        imp[0] = 1.0
        X[lo:hi, 2 + 2 * j] = lfilter([1.0], a, imp)
        if m > 1:
            imp = np.zeros(m)
            imp[1] = 1.0
            X[lo:hi, 3 + 2 * j] = lfilter([1.0], a, imp)
    return X


def off_stops(x: ArrayLike, lo: float, hi: float, margin: float) -> NDArray[np.bool_]:
    """Frames (shape (n,)) whose piston cannot have touched an end stop from the frame
    before to the frame after: a touch stops it dead, which the linear law does not
    follow. The reach between frames is the largest step on either side."""
    x = np.asarray(x, dtype=float).ravel()
    step = np.abs(np.diff(x))
    reach = np.zeros_like(x)
    if x.size > 1:
        reach[:-1] = step
        reach[1:] = np.maximum(reach[1:], step)
    return (x - reach > lo + margin) & (x + reach < hi - margin)


def fit_display(
    x: ArrayLike,
    volts: ArrayLike,
    segment: ArrayLike,
    dt: float,
    mass_kg: float,
    start: tuple[float, float] | None = None,
) -> DisplayFit:
    """Fit the display's constants to a calibration's frames (see :class:`DisplayFit`).

    Parameters
    ----------
    x : array_like, shape (n,)
        Piston position, m below the top stop, one per frame.
    volts : array_like, shape (n,)
        Voltage the display applied over the period after each frame, V.
    segment : array_like of int, shape (n,)
        Stretch of consecutive frames off the end stops each frame belongs to; a new
        stretch starts wherever the label changes.
    dt : float
        Frame period, s.
    mass_kg : float
        Reference mass on the piston, kg.
    start : (omega, sigma), optional
        Starting natural frequency (rad/s) and decay rate (1/s); by default from
        linear prediction on the longest stretch at one voltage.

    Raises
    ------
    InputError
        Too few frames, no voltage change to separate ``x0`` from ``kappa``, or a fit
        that gives a non-physical display.
    """
    from scipy.optimize import least_squares

    x = np.asarray(x, dtype=float).ravel()
    u = np.asarray(volts, dtype=float).ravel() ** 2
    seg = np.asarray(segment).ravel()
    cuts = np.flatnonzero(np.diff(seg) != 0) + 1
    edges = [0, *cuts.tolist(), x.size]
    bounds = [(lo, hi) for lo, hi in zip(edges[:-1], edges[1:], strict=True) if hi - lo >= 20]
    keep = np.concatenate([np.arange(lo, hi) for lo, hi in bounds]) if bounds else np.array([])
    if keep.size < 200:
        raise InputError(
            f"only {keep.size} frames off the end stops: use a mass that holds the piston "
            "near mid-stroke at 0 V"
        )
    x, u = x[keep], u[keep]
    offs = np.cumsum([0] + [hi - lo for lo, hi in bounds])
    bounds = [(int(offs[i]), int(offs[i + 1])) for i in range(len(bounds))]
    if np.ptp(u) <= 0:
        raise InputError(
            "the voltage never changed off the end stops: nothing separates Kp from alpha"
        )
    if start is None:
        start = _start(x, u, bounds, dt)

    def residual(theta: Array) -> Array:
        X = _display_columns(theta[0], theta[1], u, bounds, dt)
        beta, *_ = np.linalg.lstsq(X, x, rcond=None)
        return x - X @ beta

    scale = np.array([start[0], max(start[1], 0.05 * start[0])])
    sol = least_squares(residual, np.asarray(start), x_scale=scale, method="lm", xtol=1e-12)
    omega, sigma = float(sol.x[0]), float(sol.x[1])
    X = _display_columns(omega, sigma, u, bounds, dt)
    beta, *_ = np.linalg.lstsq(X, x, rcond=None)
    r = x - X @ beta
    # full Jacobian: the two nonlinear parameters by central differences, the rest exact
    cols = []
    for i, h in ((0, 1e-6 * omega), (1, 1e-6 * max(abs(sigma), 1e-3 * omega))):
        th_p, th_m = np.array([omega, sigma]), np.array([omega, sigma])
        th_p[i] += h
        th_m[i] -= h
        fp = _display_columns(*th_p, u, bounds, dt) @ beta
        fm = _display_columns(*th_m, u, bounds, dt) @ beta
        cols.append((fp - fm) / (2 * h))
    J = np.column_stack([*cols, X])
    dof = max(x.size - J.shape[1], 1)
    s2 = float(r @ r) / dof
    # residuals that are not white (the encoder's step, and any misfit of the law)
    # count for fewer samples: intervals widened by the data weight
    weight = data_weight(J, r, integrated_time(r))
    cov = s2 * np.linalg.pinv(J.T @ J)[:4, :4] / weight  # (omega, sigma, x0, kappa)
    x0, kappa = float(beta[0]), float(beta[1])
    if not (x0 > 0 and kappa > 0 and omega > 0):
        raise InputError(
            "the calibration's frames do not fit a spring-and-solenoid piston under the "
            "weight (rest position or pull not positive): is the mass on the piston?"
        )
    mg = mass_kg * G
    kp = mg / x0
    alpha = kappa * kp
    total = kp / omega**2
    mp = total - mass_kg
    if not mp > 0:
        raise InputError(
            f"the ring-downs give a moving mass of {total:.4g} kg, not above the "
            f"{mass_kg:g} kg reference mass: is the mass given right?"
        )
    b = 2 * sigma * total
    d_total = np.array([-2 * kp / omega**3, 0.0, -mg / (x0**2 * omega**2), 0.0])
    grads = {
        "Kp": np.array([0.0, 0.0, -mg / x0**2, 0.0]),
        "alpha": np.array([0.0, 0.0, -kappa * mg / x0**2, mg / x0]),
        "Mp": d_total,
        "b": 2 * sigma * d_total + np.array([0.0, 2 * total, 0.0, 0.0]),
        "f": np.array([1 / (2 * math.pi), 0.0, 0.0, 0.0]),
        "zeta": np.array([-sigma / omega**2, 1 / omega, 0.0, 0.0]),
    }

    def est(value: float, key: str) -> Estimate:
        g = grads[key]
        return Estimate.normal(value, math.sqrt(max(float(g @ cov @ g), 0.0)))

    return DisplayFit(
        Kp=est(kp, "Kp"),
        alpha=est(alpha, "alpha"),
        Mp=est(mp, "Mp"),
        b=est(b, "b"),
        frequency_hz=est(omega / (2 * math.pi), "f"),
        zeta=est(sigma / omega, "zeta"),
        x0=x0,
        frames=int(x.size),
        segments=len(bounds),
        residual_sd=math.sqrt(s2),
    )


def _start(x: Array, u: Array, bounds: list[tuple[int, int]], dt: float) -> tuple[float, float]:
    """(omega, sigma) from linear prediction on the longest stretch at one voltage where
    the piston swings (a stretch at rest has nothing to predict)."""
    runs: list[tuple[int, int]] = []
    for lo, hi in bounds:
        changes = np.flatnonzero(np.diff(u[lo:hi]) != 0) + lo + 1
        edges = [lo, *changes.tolist(), hi]
        runs.extend((a, b) for a, b in zip(edges[:-1], edges[1:], strict=True) if b - a >= 20)
    for lo, hi in sorted(runs, key=lambda r: r[0] - r[1])[:8]:
        try:
            ring = fit_ringdown(np.arange(hi - lo) * dt, x[lo:hi])
        except InputError:
            continue
        return ring.omega_n, ring.sigma
    raise InputError(
        "the piston never swung freely at a held voltage: is it free to move, with the "
        "mass resting on it?"
    )


def held_rate(values: ArrayLike, rate_hz: float) -> float | None:
    """The rate at which a reading really changes, Hz, when a faster line repeats it:
    ``values`` (shape (n,)) that change every ``k >= 2`` samples, regularly (four
    runs in five a multiple of the commonest run, as a load cell board read more slowly
    than the line that carries it), give ``rate_hz / k``; None otherwise (noise at
    rest changes at random, not every ``k`` samples)."""
    v = np.asarray(values, dtype=float).ravel()
    changes = np.flatnonzero(np.diff(v) != 0)
    if changes.size < 10:
        return None
    runs = np.diff(changes)
    k = int(np.argmax(np.bincount(runs)))
    if k < 2 or np.mean(runs % k == 0) < 0.8:
        return None
    return rate_hz / k


def slow_force_warning(force_rate_hz: float) -> str | None:
    """One line when the force is read more slowly than :data:`MIN_FORCE_RATE_HZ`,
    naming the rate; None otherwise."""
    if not force_rate_hz < MIN_FORCE_RATE_HZ:
        return None
    return (
        f"the force is read at {force_rate_hz:.4g} Hz, below the {MIN_FORCE_RATE_HZ:g} Hz "
        "that resolves the mass term M at grasp speeds (motion up to about 20 Hz, ten "
        "samples a period): an HX711-type load cell board (10-80 Hz) sees stiffness and "
        "damping only; read the force faster, or fit without xddot (--forms x+xdot)"
    )
