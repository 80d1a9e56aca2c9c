"""Where each term's force lies in a grasp session, and what the fit keeps of it.

Usage::

    python benchmarks/grasp_edges.py 4455139:paper 4455138:paper 4455140 4455138

Each argument is a scene seed of :func:`tissuecli.sim.scenes.random_scene` (10,000
samples at most), with ``:paper`` to draw from the paper's four forms (otherwise from
the other families, as ``generalisation.py`` and its ``scene_one`` reruns do). The first
70 % is fitted by the default fit. Printed per scene: the filter's taps, the samples in
contact and those fitted (a filtered sample is fitted where its window touches a grasp,
the tissue's columns gated by the contact flags on the raw grid; before, only where its
whole window lay inside one), the chosen law and the truth's law with their ln
evidence, and for each term of the truth its force RMS over the samples in contact and
over the fitted ones, and ``snr2``: the fitted rows' term force over the filtered
noise, squared, times the effective samples (about twice the nats it can earn). Last,
the RMS error of the filtered velocity against the same filter applied to the true
closure, beside what the errors-in-variables correction assumes (position noise SD
times the filter's velocity gain): a ratio well above 1 says the ADC's staircase is not
white noise to the filter.

Then, for a truth without memory terms, what a design gated by the grasps would recover
from the same samples: every filtered sample whose window touches a grasp, the force
filtered by the half kernel ``g_h`` and each column ``g_h * (grasped * f(g_h x))``
(the kinematics from the half kernels, as nonlinear damping's columns are made, an
offset column beside them), least squares of the truth's law and of it without each
term: its coefficients against the truth's, and the nats each term buys (the rise in the
residual sum of squares over twice the filtered noise variance times the filter's
correlation time).
"""

from __future__ import annotations

import argparse

import numpy as np
from generalisation import split

from tissuecli.core.session import Session
from tissuecli.identify import BayesianFit
from tissuecli.identify.derivatives.gaussian import Gaussian
from tissuecli.sim.scenes import FAMILIES, Scene, random_scene

OTHERS = [f for f in FAMILIES if not f.startswith("paper")]
PAPER = [f for f in FAMILIES if f.startswith("paper")]


def one(arg: str) -> None:
    seed_s, _, which = arg.partition(":")
    seed = int(seed_s)
    scene = random_scene(seed, families=PAPER if which == "paper" else OTHERS,
                         max_samples=10000)  # fmt: skip
    fitted, _, i0 = split(scene.session)
    est = BayesianFit("all", seed=seed).fit(fitted)
    kin = est.kinematics_
    t = np.asarray(scene.session.time)
    rows = np.searchsorted(t, kin.time)  # the fitted rows on the scene's grid
    dt = float(t[1] - t[0])
    touching = np.flatnonzero(scene.x[:i0] > 0)
    truth = scene.tissue.law.name
    ln_z = {r.name: r.ln_evidence for r in est.results_}
    print(f"\n{seed}: {scene.describe()}")
    print(f"  taps {kin.kernels[0].size}, in contact {touching.size}, fitted {rows.size}, "
          f"n_eff {est.n_eff_:.1f}")  # fmt: skip
    z_truth = f"{ln_z[truth]:.1f}" if truth in ln_z else "not scored"
    print(f"  chosen {est.best_.name} P={est.best_.probability:.3f} ln Z "
          f"{est.best_.ln_evidence:.1f}; truth {truth} ln Z {z_truth}")  # fmt: skip
    sd = scene.noise_n * kin.noise_gain[0]  # force noise after the smoothing filter
    xs = np.maximum(scene.x, 0.0)
    for term, c in zip(scene.tissue.law.terms, scene.tissue.coef, strict=True):
        col = (term.series(dt, xs, scene.v, scene.a) if term.memory
               else term.regressor(scene.x, scene.v, scene.a))  # fmt: skip
        inside = abs(c) * float(np.sqrt(np.mean(col[touching] ** 2)))
        kept = abs(c) * float(np.sqrt(np.mean(col[rows] ** 2)))
        print(f"  {term.name:12s} force RMS in contact {inside:9.3g} N, fitted rows "
              f"{kept:9.3g} N, snr2 {(kept / sd) ** 2 * est.n_eff_:9.3g}")  # fmt: skip
    v_true = np.convolve(scene.x, kin.kernels[1], mode="same")[rows]
    err = float(np.sqrt(np.mean((kin.v - v_true) ** 2)))
    model = est.sigma_x_ * kin.noise_gain[1]
    print(f"  velocity error {err:.3g} m/s, errors-in-variables model {model:.3g} m/s "
          f"(x{err / max(model, 1e-300):.2f})")  # fmt: skip
    if not any(term.memory for term in scene.tissue.law.terms):
        gated(scene, fitted, est)


def gated(scene: Scene, fitted: Session, est: BayesianFit) -> None:
    """The truth's law fitted on a design gated by the grasps (module docstring)."""
    x, force = np.asarray(fitted.position, float), np.asarray(fitted.force, float)
    dt = float(fitted.time[1] - fitted.time[0])
    gh, gh1, gh2, _ = Gaussian().half_kernels(x, dt)

    def smooth(k: np.ndarray, y: np.ndarray) -> np.ndarray:
        return np.convolve(y, k, mode="same")

    xs, vs, acc = smooth(gh, x), smooth(gh1, x), smooth(gh2, x)
    grasped = est.contact_.mask.astype(float)
    h = gh.size // 2
    rows = np.zeros(x.size, bool)
    rows[2 * h : -2 * h] = True  # both passes inside the record
    rows &= smooth(gh, grasped) > 1e-3
    g = np.convolve(gh, gh)  # the two passes: the full filter
    tau = float(g.sum() ** 2 / np.sum(g**2))
    var = scene.noise_n**2 * float(np.sum(g**2))
    terms = scene.tissue.law.terms
    cols = [smooth(gh, grasped * t.regressor(xs, vs, acc)) for t in terms]
    y = smooth(gh, force)[rows]

    def rss(keep: list[int]) -> tuple[np.ndarray, float]:
        A = np.column_stack([cols[j] for j in keep] + [smooth(gh, np.ones_like(x))])[rows]
        b = np.linalg.lstsq(A, y, rcond=None)[0]
        return b, float(np.sum((y - A @ b) ** 2))

    b, full = rss(list(range(len(terms))))
    pairs = zip(terms, b[: len(terms)], scene.tissue.coef, strict=True)
    print(f"  gated design: {np.count_nonzero(rows)} rows; coefficients "
          + ", ".join(f"{t.name} {c:.4g} (truth {c0:.4g})" for t, c, c0 in pairs))  # fmt: skip
    for j, t in enumerate(terms):
        _, without = rss([k for k in range(len(terms)) if k != j])
        print(f"    {t.name:12s} buys {(without - full) / (2 * var * tau):9.3g} nats")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scenes", nargs="+", help="SEED or SEED:paper")
    for arg in p.parse_args().scenes:
        one(arg)


if __name__ == "__main__":
    main()
