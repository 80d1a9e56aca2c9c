"""The stress suite of lab protocols: what testing machines run, at every scale.

Usage::

    python benchmarks/protocols.py --repeats 2              # a fresh seed, printed
    python benchmarks/protocols.py --repeats 2 --seed 7     # repeat a run
    python benchmarks/protocols.py --protocols "ramp linear,ramp-hold SLS"

Each protocol of :data:`tissuecli.sim.protocols.PROTOCOLS` (constant-speed ramps:
linear, with a load-cell offset, damped, stiffening; loading-unloading triangle cycles;
ramp-and-hold of a standard linear solid and of two branches; a staircase; creep under
constant force; a sine sweep) is drawn ``--repeats`` times over the stress space
(closure amplitude 1 um-10 mm, 20 Hz-20 kHz, force and length units scaled by
1e-6..1e6, float32 exports or 16-bit quantisation, force noise 0.1-10 % of its range)
and fitted whole by the default fit with every sample (``BayesianFit(grasps="none")``,
``tissuecli fit FILE --grasps none``). For each fit it prints the chosen law and its
probability, whether it uses only terms the truth is written with (columns the design
cannot tell apart count as one: on a constant speed xdot, xdot|xdot|, sign(xdot) and the
offset; xddot where nothing accelerates is free), K against the truth, the other
coefficients' relative errors, the largest |ln Z| per sample over every law compared,
and the wall and CPU time.

The summary gives, by protocol, how many fits held each bound the fit must hold on
constant-speed ramps, triangle cycles and ramp-and-hold of a standard linear solid
(marked *): every ln Z finite and within 20 nats per sample, only the truth's terms,
K within 2 % (10 % on the stiffening ramp), at most 10 s.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from generalisation import chosen_law, evidence_problems  # noqa: E402

from tissuecli.core.errors import TissueError  # noqa: E402
from tissuecli.identify import BayesianFit  # noqa: E402
from tissuecli.sim.protocols import MUST_HOLD, PROTOCOLS, random_protocol  # noqa: E402
from tissuecli.sim.scenes import Scene  # noqa: E402

#: the bounds: nats per sample, K's relative error (stiffening ramp apart), seconds
LN_Z_PER_SAMPLE = 20.0
K_TOLERANCE = {"ramp stiffening": 0.10}
K_DEFAULT = 0.02
TIME_LIMIT_S = 10.0


@dataclass
class Outcome:
    """One protocol's fit, scored against its truth."""

    scene: Scene
    refused: str = ""
    law: str = ""
    probability: float = float("nan")
    within: bool = False
    right: bool = False
    k_error: float = float("nan")
    errors: dict[str, float] = field(default_factory=dict)
    worst_per_sample: float = float("nan")
    evidence: list[str] = field(default_factory=list)
    wall_s: float = float("nan")
    cpu_s: float = float("nan")

    @property
    def k_ok(self) -> bool:
        tol = K_TOLERANCE.get(self.scene.family, K_DEFAULT)
        return bool(np.isfinite(self.k_error) and self.k_error <= tol)

    @property
    def holds(self) -> bool:
        """Every bound: evidence, terms, K, time."""
        return (not self.refused and not self.evidence and self.within and self.k_ok
                and self.wall_s <= TIME_LIMIT_S)  # fmt: skip


def fit_protocol(scene: Scene, grasps: str = "none", seed: int = 0) -> Outcome:
    """Fit ``scene`` whole with the default fit; score it."""
    out = Outcome(scene)
    s = scene.session
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        est = BayesianFit(grasps=grasps, seed=seed).fit(s)
    except TissueError as e:
        out.refused = str(e)[:160]
        return out
    finally:
        out.wall_s, out.cpu_s = time.perf_counter() - t0, time.process_time() - c0
    law = chosen_law(est)
    out.law, out.probability = law.name, float(est.best_.probability)
    out.within, out.right = scene.within_truth(law), scene.right(law)
    n = len(s)
    out.evidence = evidence_problems(est, n, LN_Z_PER_SAMPLE)
    finite = [abs(r.ln_evidence) for r in est.results_ if np.isfinite(r.ln_evidence)]
    out.worst_per_sample = max(finite) / n if finite else float("nan")
    post = est.best_.posterior
    truth = dict(zip(scene.tissue.law.symbols, scene.coefficients, strict=True))
    if post is not None:
        for j, sym in enumerate(est.best_.model.symbols):
            if sym in truth:
                out.errors[sym] = abs(float(post.mean[j]) / truth[sym] - 1.0)
    out.k_error = out.errors.get("K", float("nan"))
    return out


def describe(o: Outcome) -> str:
    s = o.scene.settings
    head = (f"{o.scene.family:<22} {s['rate_hz']:8.1f} Hz amp {s['amplitude_m']:.2g} m "
            f"units {o.scene.units[0]:.0e}/{o.scene.units[1]:.0e} {str(s['quantisation']):<7} "
            f"noise {100 * s['noise_frac']:.2g} % n={len(o.scene.session)}")  # fmt: skip
    if o.refused:
        return f"{head}\n    REFUSED {o.refused}"
    errs = " ".join(f"{k} {100 * v:.2g}%" for k, v in o.errors.items())
    mark = "ok" if o.within else "EXTRA TERMS"
    bad = f" BAD lnZ: {'; '.join(o.evidence)[:160]}" if o.evidence else ""
    return (
        f"{head}\n    truth {o.scene.tissue.law.name}; chose {o.law} P={o.probability:.3f} "
        f"({mark}); errors {errs}; max|lnZ|/n {o.worst_per_sample:.3g}; "
        f"{o.wall_s:.2f} s wall {o.cpu_s:.2f} s cpu{bad}"
    )


def table(outcomes: list[Outcome], out: Callable[[str], None] = print) -> None:
    out(
        f"{'protocol':<24} {'fits':>4} {'refused':>7} {'lnZ ok':>6} {'terms ok':>8} "
        f"{'right':>5} {'K ok':>5} {'K err med':>9} {'<=10 s':>6} {'all':>4} "
        f"{'wall s med':>10} {'max':>6} {'cpu s med':>9}"
    )
    for name in PROTOCOLS:
        mine = [o for o in outcomes if o.scene.family == name]
        if not mine:
            continue
        fitted = [o for o in mine if not o.refused]
        kerr = [o.k_error for o in fitted if np.isfinite(o.k_error)]
        mark = "*" if name in MUST_HOLD else " "
        out(
            f"{name + mark:<24} {len(mine):>4} {len(mine) - len(fitted):>7} "
            f"{sum(not o.evidence for o in fitted):>6} {sum(o.within for o in fitted):>8} "
            f"{sum(o.right for o in fitted):>5} {sum(o.k_ok for o in fitted):>5} "
            f"{(100 * statistics.median(kerr)) if kerr else float('nan'):8.2f}% "
            f"{sum(o.wall_s <= TIME_LIMIT_S for o in mine):>6} {sum(o.holds for o in mine):>4} "
            f"{statistics.median(o.wall_s for o in mine):10.2f} "
            f"{max(o.wall_s for o in mine):6.1f} {statistics.median(o.cpu_s for o in mine):9.2f}"
        )


def main(argv: Sequence[str] | None = None) -> list[Outcome]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=2, help="draws of each protocol")
    ap.add_argument("--seed", type=int, default=None, help="repeat a run (default: fresh)")
    ap.add_argument("--protocols", default="", help="comma-separated names (default: all)")
    ap.add_argument("--max-samples", type=int, default=60_000)
    ap.add_argument("--grasps", default="none", help="the fit's --grasps (default none)")
    args = ap.parse_args(argv)
    seed = args.seed if args.seed is not None else int.from_bytes(os.urandom(3), "little")
    names = [p.strip() for p in args.protocols.split(",") if p.strip()] or list(PROTOCOLS)
    unknown = set(names) - set(PROTOCOLS)
    if unknown:
        ap.error(f"unknown protocols {sorted(unknown)}; choose among {list(PROTOCOLS)}")
    print(f"seed {seed} (repeat with --seed {seed}); load average "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}", flush=True)  # fmt: skip
    outcomes = []
    k = 0
    for _ in range(args.repeats):
        for name in names:
            scene = random_protocol(seed + k, name, max_samples=args.max_samples)
            k += 1
            o = fit_protocol(scene, args.grasps, seed=seed)
            outcomes.append(o)
            print(describe(o), flush=True)
    print(f"\nload average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    table(outcomes)
    return outcomes


if __name__ == "__main__":
    main(sys.argv[1:])
