"""Structure choice and accuracy over families of tissue laws, against the paper's four
forms and a sparse-regression peer (PySINDy), on the same sessions.

Usage::

    pip install -e ".[bench]"        # PySINDy, for the peer column (skipped without it)
    python benchmarks/families.py --seeds 4
    python benchmarks/families.py --seeds 2 --three     # adds three relaxation branches

For each family it simulates ``--seeds`` sessions (10 s at 1 kHz, 12 bits, random
operators), holds out their last 30 %, and fits the rest with the default search
(``forms="all"``) and with the paper's four forms (``forms="paper"``). It prints:

- right: how often the default chose the true structure;
- z RMS: the RMS over coefficients, shape parameters and seeds of (estimate - truth) /
  posterior SD, for the sessions where the structure was right (about 1 if the
  intervals are honest);
- cover: the fraction of 95 % intervals holding the truth, with the range a binomial
  count of that many intervals at 0.95 falls in 95 % of the time;
- held-out RMS over the noise floor for the default, the paper's forms and the peer: the
  RMS error of each fit's prediction of the filtered force after the split, over that
  of the true law (the floor no fit can beat);
- the median fit time of each.

The peer is PySINDy's sparse regression (``ps.STLSQ`` on columns normalised to unit
norm, threshold 0.2 % of the force's norm) on seven candidate terms (x, x^3, xdot,
xdot|xdot|, sign(xdot), xddot, 1), kinematics from ``ps.SmoothedFiniteDifference``
(Savitzky-Golay, 0.1 s window): it has no relaxation or contact terms, so it cannot be
right on those families. Its held-out prediction goes through the default's filter,
like the others'.

Finally, ``--exhaustive`` (on by default) fits every law of a small family (stiffness
x, x^3 or both; damping xdot or xdot|xdot|; with or without an offset; 0, 1 or 2
relaxation branches: 36 laws) on one session of each relaxation family and of the
hardening one, and compares its best law and evidence with the greedy search's.

Timings are wall-clock on whatever machine runs it; compare columns within one run.
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import dataclass, field

import numpy as np

from tissuecli.core.session import Session
from tissuecli.core.terms import Law
from tissuecli.core.tissue import Tissue
from tissuecli.identify import fit_session
from tissuecli.identify.bayes import BayesianFit
from tissuecli.identify.design import design
from tissuecli.sim.families import FAMILIES
from tissuecli.sim.families import THREE_BRANCHES as THREE
from tissuecli.sim.synth import random_session

PEER_TERMS = ("x", "x^3", "xdot", "xdot|xdot|", "sign(xdot)", "xddot", "offset")
HOLD_OUT = 0.3


@dataclass
class Tally:
    right: int = 0
    trials: int = 0
    z: list[float] = field(default_factory=list)
    inside: list[bool] = field(default_factory=list)
    ratio: dict[str, list[float]] = field(default_factory=dict)
    secs: dict[str, list[float]] = field(default_factory=dict)
    peer_right: int = 0

    def add(self, key: str, ratio: float, secs: float) -> None:
        self.ratio.setdefault(key, []).append(ratio)
        self.secs.setdefault(key, []).append(secs)


def _split(s: Session) -> tuple[Session, Session]:
    t = s.time
    i = int(np.searchsorted(t, t[0] + (1.0 - HOLD_OUT) * (t[-1] - t[0])))
    return (
        s.replace(t[:i], s.force[:i], s.position[:i]),
        s.replace(t[i:], s.force[i:], s.position[i:]),
    )


def _held_out_rms(est: BayesianFit, rest: Session, law: Law, coef: np.ndarray) -> float:
    """RMS error of ``law`` with ``coef`` predicting the filtered held-out force."""
    ready = est.prepare(rest)
    kin = ready.kinematics
    pred = design(law, kin, ready.session.position, est.sigma_x_) @ coef
    return float(np.sqrt(np.mean((kin.force - pred) ** 2)))


def _peer(fitted: Session) -> tuple[Law, np.ndarray, float]:
    """PySINDy's sparse regression on the seven candidate terms: law, coefficients, s."""
    import warnings

    import pysindy as ps

    from tissuecli.core.terms import term

    t0 = time.perf_counter()
    dt = float(np.median(np.diff(fitted.time)))
    window = int(round(0.1 / dt)) | 1
    x = fitted.position[:, None]

    def sfd(order: int) -> ps.SmoothedFiniteDifference:
        kws = {"window_length": window, "polyorder": 3}
        return ps.SmoothedFiniteDifference(d=order, smoother_kws=kws)

    velocity = sfd(1)
    v = velocity(x, t=dt)[:, 0]
    a = sfd(2)(x, t=dt)[:, 0]
    xs = np.asarray(velocity.smoothed_x_)[:, 0]
    kin = {"x": xs, "v": v, "a": a, "1": np.ones_like(xs)}
    theta = np.column_stack([term(n)(kin[term(n).variable]) for n in PEER_TERMS])
    h = window // 2
    theta, force = theta[h:-h], fitted.force[h:-h]
    opt = ps.STLSQ(threshold=0.002 * float(np.linalg.norm(force)), normalize_columns=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        opt.fit(theta, force)
    coef = np.asarray(opt.coef_)[0]
    keep = [i for i, c in enumerate(coef) if c != 0] or [0]
    law = Law.of([PEER_TERMS[i] for i in keep])
    order = [PEER_TERMS.index(t.name) for t in law.terms]
    return law, coef[order], time.perf_counter() - t0


def _truth_in(law: Law, tissue: Tissue) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(tissue.coef, dtype=float), np.array(
        [tissue.law.shape[n] for n in law.shape_names]
    )


def _binomial_range(n: int, p: float = 0.95) -> tuple[float, float]:
    from scipy.stats import binom

    return float(binom.ppf(0.025, n, p) / n), float(binom.ppf(0.975, n, p) / n)


def run_family(name: str, tissue: Tissue, seeds: int, peer: bool) -> Tally:
    tally = Tally()
    for seed in range(seeds):
        s, _ = random_session(tissue, rate_hz=1000.0, seed=seed, duration_s=10.0, bits=12)
        fitted, rest = _split(s)
        tally.trials += 1
        outcomes = {}
        for key, forms in (("default", "all"), ("paper", "paper")):
            t0 = time.perf_counter()
            out = fit_session(s, forms=forms, hold_out=HOLD_OUT, seed=seed)
            secs = time.perf_counter() - t0
            outcomes[key] = (out, secs)
        est = outcomes["default"][0].bayes
        floor = _held_out_rms(est, rest, tissue.law, np.asarray(tissue.coef, dtype=float))
        for key, (out, secs) in outcomes.items():
            tally.add(key, out.validation.rms_n / floor, secs)
        best = est.best_
        if best.name == tissue.law.name:
            tally.right += 1
            post = best.posterior
            truth, shapes = _truth_in(best.family or best.model, tissue)
            tally.z += list((post.mean - truth) / post.sd)
            tally.inside += list((post.ci95[:, 0] <= truth) & (truth <= post.ci95[:, 1]))
            for n, v in zip((best.family or best.model).shape_names, shapes, strict=True):
                sp = best.shape_posterior[n]
                tally.z.append((sp["mean"] - v) / sp["sd"])
                tally.inside.append(sp["ci95"][0] <= v <= sp["ci95"][1])
        if peer:
            law, coef, secs = _peer(fitted)
            tally.add("peer", _held_out_rms(est, rest, law, coef) / floor, secs)
            tally.peer_right += law.name == tissue.law.name
    return tally


def exhaustive(tissue: Tissue, seed: int = 0) -> str:
    """The greedy search's choice against the best of 36 laws fitted one by one."""
    laws = []
    for stiffness in (["x"], ["x^3"], ["x", "x^3"]):
        for damping in ("xdot", "xdot|xdot|"):
            for offset in ([], ["offset"]):
                for branches in range(3):
                    laws.append(
                        Law.of([*stiffness, damping, "xddot", *offset, *["maxwell"] * branches])
                    )
    s, _ = random_session(tissue, rate_hz=1000.0, seed=seed, duration_s=10.0, bits=12)
    t0 = time.perf_counter()
    greedy = BayesianFit().fit(s)
    t_greedy = time.perf_counter() - t0
    t0 = time.perf_counter()
    every = BayesianFit(forms=laws).fit(s)
    t_every = time.perf_counter() - t0
    g, e = greedy.best_, every.best_
    same = "same" if g.name == e.name else "DIFFERENT"
    return (
        f"greedy {g.name} ({g.ln_evidence:.1f}, {len(greedy.results_)} laws, {t_greedy:.1f} s) "
        f"vs all 36: {e.name} ({e.ln_evidence:.1f}, {t_every:.1f} s): {same}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--three", action="store_true", help="add the three-branch family")
    ap.add_argument("--no-exhaustive", action="store_true")
    ap.add_argument("--families", default="", help="comma-separated subset of the names")
    args = ap.parse_args()
    try:
        import pysindy  # noqa: F401

        peer = True
    except ImportError:
        peer = False
        print("(PySINDy not installed: no peer column; pip install -e '.[bench]')")
    families = dict(FAMILIES)
    if args.three:
        families["three branches"] = THREE
    if args.families:
        wanted = {f.strip() for f in args.families.split(",")}
        families = {k: v for k, v in families.items() if k in wanted}
    print(
        f"{'family':<18} {'right':>6} {'peer':>5} {'z RMS':>6} {'cover':>6} {'expected':>11} "
        f"{'RMS/floor: default':>18} {'paper':>6} {'peer':>6} {'s: default':>10} "
        f"{'paper':>6} {'peer':>6}"
    )
    for name, tissue in families.items():
        t = run_family(name, tissue, args.seeds, peer)
        z = float(np.sqrt(np.mean(np.square(t.z)))) if t.z else float("nan")
        cover = float(np.mean(t.inside)) if t.inside else float("nan")
        lo, hi = _binomial_range(len(t.inside)) if t.inside else (float("nan"),) * 2

        def med(key: str, what: dict[str, list[float]]) -> str:
            return f"{statistics.median(what[key]):6.3f}" if key in what else f"{'-':>6}"

        print(
            f"{name:<18} {t.right:>3}/{t.trials:<2} {t.peer_right if peer else '-':>5} "
            f"{z:6.2f} {cover:6.2f} [{lo:.2f},{hi:.2f}] {med('default', t.ratio):>18} "
            f"{med('paper', t.ratio)} {med('peer', t.ratio)} {med('default', t.secs):>10} "
            f"{med('paper', t.secs)} {med('peer', t.secs)}",
            flush=True,
        )
    if not args.no_exhaustive:
        print("\ngreedy search against exhaustive enumeration (seed 0):")
        for name in ("hardening x+x^3", "one branch", "two branches"):
            print(f"  {name:<16} {exhaustive(FAMILIES[name])}", flush=True)


if __name__ == "__main__":
    main()
