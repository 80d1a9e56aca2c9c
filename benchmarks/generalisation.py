"""Generalisation of `fit` to sessions no one has seen: random scenes over a wide space.

Usage::

    python benchmarks/generalisation.py --scenes 24            # a fresh seed, printed
    python benchmarks/generalisation.py --scenes 24 --seed 7   # repeat a run
    python benchmarks/generalisation.py --families paper --contact 20   # the paper's forms,
                                       # and 20 noisy sessions in contact throughout

Each scene comes from :func:`tissuecli.sim.scenes.random_scene` (every family the package
simulates, 250 Hz-10 kHz, 8-16 bits, force noise 0.5-10 % of its range, continuous
contact or grasps with free jaws, 3-60 s, slow squeezes to fast taps). Its last 30 % is
held out; the rest is fitted by

- ``default``: tissuecli's default fit (``BayesianFit()``, ``tissuecli fit FILE``);
- ``paper``: the exact-Bayes fit over the paper's four forms alone
  (``BayesianFit("paper")``, ``--forms paper``), the reference a user could write;
- ``lstsq``: ten lines of NumPy: least squares of the force on ``[x, xdot, 1]``, the
  kinematics from a Savitzky-Golay filter of the closure (20 ms, quadratic).

For each it reports, overall and by family group:

- right: the chosen law has the truth's structure (a term whose force stands below the
  noise in the part fitted, see ``scenes.DETECTABLE`` and ``Scene.judged_on``, may be
  in or out; a relaxation
  branch counts by the part of its force the law's other terms cannot carry,
  ``scenes.branch_detectability``, so a law may leave out a branch no recording of that
  motion can tell from a spring or a damper);
- cover: the fraction of 95 % intervals (coefficients and shape parameters of the
  laws chosen right) that hold the truth, with the range a binomial count of that many
  intervals at 0.95 falls in 95 % of the time;
- |err|: the median relative error of the coefficients of the laws chosen right;
- held-out/floor: the RMS error of each fit's prediction of the held-out force (the
  estimator's ``predict`` on the held-out samples), against the true noise-free force,
  over the noise floor: the RMS error of the best Savitzky-Golay smoother (cubic, the
  window that does best against the truth) of the measured held-out force; median and
  90th percentile;
- the median wall and CPU time of a fit, and the refusals (a fit that raised).

``--families paper`` draws the paper's four forms alone; ``--contact N`` adds N noisy
paper-form sessions in contact throughout (``continuous_contact.noisy_contact_scene``:
an ``x^3`` law, 8-bit ADC, 250-2000 Hz, force noise up to 10 % of the range), grouped
as ``noisy contact``. ``--bits 8-10`` (or ``8,12,16``) draws each scene's ADC depth
among those (from a generator of its own, so the scene's other draws stay as they were).
The scenes where the default's structure is wrong and the reference's right are listed
after the summary.

Every scene prints a line as it goes; the summary follows. Timings are on whatever the
machine gives; compare columns within one run.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from tissuecli.core.errors import TissueError
from tissuecli.core.session import Session
from tissuecli.core.terms import Law
from tissuecli.identify import BayesianFit, whiten
from tissuecli.identify.whiten import LIKELIHOODS
from tissuecli.sim.scenes import FAMILIES, Scene, random_scene

HOLD_OUT = 0.3
FITS = ("default", "paper")


def split(session: Session, hold_out: float = HOLD_OUT) -> tuple[Session, Session, int]:
    """The session's first ``1 - hold_out`` of time, the rest, and the first index of it."""
    t = session.time
    i = int(np.searchsorted(t, t[0] + (1.0 - hold_out) * (t[-1] - t[0])))
    return (
        session.replace(t[:i], session.force[:i], session.position[:i]),
        session.replace(t[i:], session.force[i:], session.position[i:]),
        i,
    )


def prediction(est: BayesianFit, rest: Session) -> tuple[np.ndarray, np.ndarray]:
    """The estimator's prediction of the held-out force and the indices of ``rest`` it is
    at: one value per sample where ``predict`` gives that, else at the samples it fits."""
    pred = np.asarray(est.predict(rest), dtype=float)
    if pred.size == len(rest):
        idx = np.arange(len(rest))
    else:
        times = est.prepare(rest).kinematics.time
        idx = np.clip(np.searchsorted(rest.time, times - 1e-9 * max(1.0, abs(times[-1]))),
                      0, len(rest) - 1)  # fmt: skip
    ok = np.isfinite(pred)
    return pred[ok], idx[ok]


def sg_floor(measured: np.ndarray, truth: np.ndarray, idx: np.ndarray | None = None) -> float:
    """RMS error against ``truth`` at ``idx`` (every sample when None) of the best cubic
    Savitzky-Golay smoother of ``measured`` (windows 5 samples to a third of the series,
    geometrically spaced)."""
    from scipy.signal import savgol_filter

    n = measured.size
    idx = np.arange(n) if idx is None else idx
    top = max(5, n // 3)
    windows = sorted({int(w) | 1 for w in np.geomspace(5, top, 24)})
    best = np.inf
    for w in windows:
        if w > n or w <= 3:
            continue
        smooth = savgol_filter(measured, w, 3, mode="interp")
        best = min(best, float(np.sqrt(np.mean((smooth[idx] - truth[idx]) ** 2))))
    return best


def lstsq_rms(fitted: Session, rest: Session, truth: np.ndarray, idx: np.ndarray) -> float:
    """Least squares of the force on [x, xdot, 1] (Savitzky-Golay kinematics, 20 ms,
    quadratic): its held-out RMS error against ``truth`` at ``idx``."""
    from scipy.signal import savgol_filter

    def columns(s: Session) -> np.ndarray:
        dt = float(np.median(np.diff(s.time)))
        w = max(5, int(round(0.02 / dt)) | 1)
        w = min(w, len(s) if len(s) % 2 else len(s) - 1)
        x = savgol_filter(s.position, w, 2)
        v = savgol_filter(s.position, w, 2, deriv=1, delta=dt)
        return np.column_stack([x, v, np.ones_like(x)])

    coef = np.linalg.lstsq(columns(fitted), fitted.force, rcond=None)[0]
    pred = columns(rest) @ coef
    return float(np.sqrt(np.mean((pred[idx] - truth[idx]) ** 2)))


def chosen_law(est: BayesianFit) -> Law:
    best = est.best_
    return best.family or best.model


def intervals(est: BayesianFit, scene: Scene) -> tuple[list[bool], list[float]]:
    """Whether each 95 % interval of the chosen law holds the truth, and each
    coefficient's relative error: for the terms the chosen law shares with the truth."""
    best = est.best_
    post = best.posterior
    law = chosen_law(est)
    truth = dict(zip(scene.tissue.law.symbols, scene.coefficients, strict=True))
    inside: list[bool] = []
    errors: list[float] = []
    if post is None:
        return inside, errors
    for j, sym in enumerate(best.model.symbols):
        if sym not in truth:
            continue
        lo, hi = post.ci95[j]
        inside.append(bool(lo <= truth[sym] <= hi))
        errors.append(abs(float(post.mean[j]) - truth[sym]) / max(abs(truth[sym]), 1e-300))
    shapes = scene.shapes
    for name in law.shape_names:
        sp = (best.shape_posterior or {}).get(name)
        if sp is None or name not in shapes:
            continue
        inside.append(bool(sp["ci95"][0] <= shapes[name] <= sp["ci95"][1]))
    return inside, errors


def evidence_problems(est: BayesianFit, samples: int, per_sample: float = 20.0) -> list[str]:
    """What is wrong with the evidence of the laws compared: a chosen law whose ln Z is
    not finite, or any ln Z (of a law not set aside with a reason) not finite or beyond
    ``per_sample`` nats per sample in magnitude."""
    out = []
    for r in est.results_:
        z = r.ln_evidence
        set_aside = r.status not in ("exact", "emcee") and bool(r.reason)
        if not np.isfinite(z):
            if r is est.best_ or not set_aside:
                out.append(f"{r.name}: ln Z {z}")
        elif abs(z) > per_sample * samples:
            out.append(f"{r.name}: ln Z {z:.3g} for {samples} samples")
    return out


@dataclass
class Row:
    """One fit of one scene."""

    scene: Scene
    fit: str
    refused: str = ""
    law: str = ""
    probability: float = float("nan")
    right: bool = False
    inside: list[bool] = field(default_factory=list)
    errors: list[float] = field(default_factory=list)
    ratio: float = float("nan")
    wall_s: float = float("nan")
    cpu_s: float = float("nan")
    evidence: list[str] = field(default_factory=list)


def group(scene: Scene) -> str:
    family = scene.family
    if family.startswith("noisy contact"):
        return "noisy contact"
    return "paper" if family.startswith("paper") else family


def run_scene(scene: Scene, fits: Sequence[str] = FITS, seed: int = 0) -> list[Row]:
    """Fit one scene every way, score each against the truth."""
    fitted, rest, i0 = split(scene.session)
    truth = scene.force[i0:]
    judged = scene.judged_on(i0)  # what the fitted head can tell
    rows: list[Row] = []
    floor = idx_default = None
    for key in fits:
        row = Row(scene, key)
        forms = "all" if key == "default" else "paper"
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            est = BayesianFit(forms, seed=seed).fit(fitted)
        except TissueError as e:
            row.refused = str(e)[:160]
            rows.append(row)
            continue
        finally:
            row.wall_s, row.cpu_s = time.perf_counter() - t0, time.process_time() - c0
        law = chosen_law(est)
        row.law, row.probability = law.name, float(est.best_.probability)
        row.right = judged.right(law)
        row.evidence = evidence_problems(est, len(fitted))
        if row.right:
            row.inside, row.errors = intervals(est, scene)
        try:
            pred, idx = prediction(est, rest)
        except TissueError as e:
            row.refused = f"held-out part: {str(e)[:140]}"
            rows.append(row)
            continue
        if idx_default is None:
            idx_default = idx
        floor = sg_floor(rest.force, truth, idx)
        rms = float(np.sqrt(np.mean((pred - truth[idx]) ** 2)))
        row.ratio = rms / max(floor, 1e-300)
        rows.append(row)
    if idx_default is not None:
        row = Row(scene, "lstsq")
        t0, c0 = time.perf_counter(), time.process_time()
        floor = sg_floor(rest.force, truth, idx_default)
        row.ratio = lstsq_rms(fitted, rest, truth, idx_default) / max(floor, 1e-300)
        row.wall_s, row.cpu_s = time.perf_counter() - t0, time.process_time() - c0
        rows.append(row)
    return rows


def binomial_range(n: int, p: float = 0.95) -> tuple[float, float]:
    from scipy.stats import binom

    if n == 0:
        return float("nan"), float("nan")
    return float(binom.ppf(0.025, n, p) / n), float(binom.ppf(0.975, n, p) / n)


def summarise(rows: list[Row], key: str) -> dict[str, Any]:
    mine = [r for r in rows if r.fit == key]
    fitted = [r for r in mine if not r.refused or r.refused.startswith("held-out")]
    inside = [b for r in mine for b in r.inside]
    errors = [e for r in mine for e in r.errors]
    ratios = [r.ratio for r in mine if np.isfinite(r.ratio)]
    lo, hi = binomial_range(len(inside))
    return {
        "n": len(mine),
        "right": sum(r.right for r in fitted),
        "cover": float(np.mean(inside)) if inside else float("nan"),
        "intervals": len(inside),
        "expected": (lo, hi),
        "err": statistics.median(errors) if errors else float("nan"),
        "ratio50": float(np.median(ratios)) if ratios else float("nan"),
        "ratio90": float(np.percentile(ratios, 90)) if ratios else float("nan"),
        "wall": statistics.median([r.wall_s for r in mine]) if mine else float("nan"),
        "cpu": statistics.median([r.cpu_s for r in mine]) if mine else float("nan"),
        "refused": sum(bool(r.refused) for r in mine),
        "evidence": sum(bool(r.evidence) for r in mine),
    }


def table(rows: list[Row], out: Callable[[str], None] = print) -> None:
    groups = ["all", *sorted({group(r.scene) for r in rows})]
    out(
        f"{'group':<16} {'fit':<8} {'scenes':>6} {'right':>6} {'cover':>6} {'expected':>11} "
        f"{'|err|':>7} {'held/floor':>10} {'p90':>6} {'wall s':>7} {'cpu s':>6} "
        f"{'refused':>7} {'bad lnZ':>7}"
    )
    for g in groups:
        part = rows if g == "all" else [r for r in rows if group(r.scene) == g]
        for key in (*FITS, "lstsq"):
            s = summarise(part, key)
            if not s["n"]:
                continue
            lo, hi = s["expected"]
            right = f"{s['right']}/{s['n']}" if key != "lstsq" else "-"
            cover = f"{s['cover']:6.3f}" if key != "lstsq" else f"{'-':>6}"
            exp = f"[{lo:.2f},{hi:.2f}]" if key != "lstsq" else f"{'-':>11}"
            err = f"{s['err']:7.4f}" if key != "lstsq" else f"{'-':>7}"
            out(
                f"{g:<16} {key:<8} {s['n']:>6} {right:>6} {cover} {exp:>11} {err} "
                f"{s['ratio50']:10.2f} {s['ratio90']:6.2f} {s['wall']:7.2f} {s['cpu']:6.2f} "
                f"{s['refused']:>7} {s['evidence']:>7}"
            )


def main(argv: Sequence[str] | None = None) -> list[Row]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=24)
    ap.add_argument("--seed", type=int, default=None, help="repeat a run (default: fresh)")
    ap.add_argument("--max-samples", type=int, default=60_000,
                    help="longest session drawn (samples)")  # fmt: skip
    ap.add_argument(
        "--families",
        default="",
        help="comma-separated names of scenes.FAMILIES ('paper': its four forms)",
    )
    ap.add_argument(
        "--contact",
        type=int,
        default=0,
        help="also this many noisy paper-form sessions in contact throughout",
    )
    ap.add_argument(
        "--bits",
        default="",
        help="draw each scene's ADC bits among these (e.g. 8-10 or 8,12,16); default 8-16",
    )
    ap.add_argument("--quiet", action="store_true", help="the summary alone")
    ap.add_argument("--likelihood", choices=sorted(LIKELIHOODS), help="the fits' likelihood")
    args = ap.parse_args(argv)
    if args.likelihood:
        whiten.DEFAULT_LIKELIHOOD = args.likelihood
    seed = args.seed if args.seed is not None else int.from_bytes(os.urandom(3), "little")
    families = [f.strip() for f in args.families.split(",") if f.strip()] or None
    if families and "paper" in families:
        families.remove("paper")
        families += [f for f in FAMILIES if f.startswith("paper") and f not in families]
    if families:
        unknown = set(families) - set(FAMILIES)
        if unknown:
            ap.error(f"unknown families {sorted(unknown)}; choose among {list(FAMILIES)}")
    bits = _bit_depths(args.bits) if args.bits else None
    if bits is not None and not all(2 <= b <= 24 for b in bits):
        ap.error(f"--bits {args.bits!r}: choose depths between 2 and 24, as 8-10 or 8,12")
    print(f"seed {seed} (repeat with --seed {seed}); load average "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}", flush=True)  # fmt: skip
    rows: list[Row] = []
    draws = [(i, False) for i in range(args.scenes)]
    draws += [(args.scenes + i, True) for i in range(args.contact)]
    total = len(draws)
    for i, contact in draws:
        if contact:
            from continuous_contact import noisy_contact_scene

            scene = noisy_contact_scene(seed + i)
        else:
            fixed = {}
            if bits is not None:  # drawn apart from the scene's own draws, which stay as they were
                fixed["bits"] = int(np.random.default_rng([seed + i, 8]).choice(bits))
            scene = random_scene(seed + i, families=families, max_samples=args.max_samples,
                                 **fixed)  # fmt: skip
        got = run_scene(scene, seed=seed + i)
        rows += got
        if not args.quiet:
            print(f"[{i + 1}/{total}] {scene.describe()} n={len(scene.session)}; "
                  f"truth {scene.tissue.law.name}", flush=True)  # fmt: skip
            for r in got:
                if r.fit == "lstsq":
                    print(f"    lstsq    held/floor {r.ratio:.2f}", flush=True)
                    continue
                what = (f"REFUSED {r.refused}" if r.refused and not r.law else
                        f"{r.law} P={r.probability:.3f} {'right' if r.right else 'WRONG'} "
                        f"held/floor {r.ratio:.2f}")  # fmt: skip
                bad = f" bad lnZ: {'; '.join(r.evidence)[:120]}" if r.evidence else ""
                print(f"    {r.fit:<8} {what} {r.wall_s:.2f} s{bad}", flush=True)
    print(f"\nload average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    table(rows)
    lost = losses(rows)
    if lost:
        print("\ndefault wrong where the paper's forms are right:")
        for scene, default, paper in lost:
            print(f"  seed {scene.settings.get('seed')}: {scene.describe()}; truth "
                  f"{scene.tissue.law.name}; default {default.law or 'REFUSED'} "
                  f"P={default.probability:.3f}; paper {paper.law}")  # fmt: skip
    return rows


def _bit_depths(text: str) -> list[int]:
    """ADC depths from ``8-10`` or ``8,12,16`` (ranges and single depths, commas between)."""
    out: list[int] = []
    for part in text.split(","):
        lo, _, hi = part.strip().partition("-")
        out += list(range(int(lo), int(hi or lo) + 1))
    return out


def losses(rows: list[Row]) -> list[tuple[Scene, Row, Row]]:
    """The scenes where the default's structure is wrong and the paper reference's right:
    each scene with its two rows."""
    out = []
    for r in rows:
        if r.fit != "default" or r.right:
            continue
        paper = next((p for p in rows if p.scene is r.scene and p.fit == "paper"), None)
        if paper is not None and paper.right:
            out.append((r.scene, r, paper))
    return out


if __name__ == "__main__":
    main(sys.argv[1:])
