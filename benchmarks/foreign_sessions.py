"""Accuracy on sessions as other loggers record them, against the same sessions clean.

For each seed, one simulated session (the default tissue, 20 s at 333 Hz) is fitted
clean and after each damage of :mod:`tissuecli.sim.loggers`; the table gives, per
coefficient, the RMS relative error over the seeds of each version, the ratio to
the clean one (the acceptance bound is 1.5), and the RMS z-score (error over
posterior SD: 1 for calibrated intervals). Three more rows compare grasps between
free motion on a 0.3 N offset sensor with the same squeezes in one long contact
(with the free jaws inside the closure sensor's range, and opening beyond its end),
and a 100 kg / 200 N stage fitted with no options.

Usage::

    python benchmarks/foreign_sessions.py [--seeds 40]
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable

import numpy as np

from tissuecli.core.session import Session
from tissuecli.core.terms import Law
from tissuecli.core.tissue import DEFAULT_TISSUE, Tissue
from tissuecli.identify import BayesianFit
from tissuecli.sim import loggers
from tissuecli.sim.synth import (
    ForcepsModel,
    GraspingOperator,
    Operator,
    Sensors,
    random_session,
    synthesize,
)

RATE = 1000 / 3.003
DAMAGE: dict[str, Callable[[Session, np.random.Generator], Session]] = {
    "millisecond stamps": lambda s, r: loggers.host_stamps(s, r, quantum_s=1e-3),
    "+-0.3 ms jitter": lambda s, r: loggers.host_stamps(s, r, quantum_s=0.0, jitter_s=3e-4),
    "one 0.5 s pause": lambda s, r: loggers.pause(s, 7.3, 0.5),
    "5 % lost at random": lambda s, r: loggers.lose_at_random(s, 0.05, r),
}


def _errors(est: BayesianFit, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    post = est.best_.posterior
    k = truth.size
    return (post.mean[:k] - truth) / truth, (post.mean[:k] - truth) / post.sd[:k]


def _grasping(seed: int) -> tuple[Session, Session, Session]:
    """Grasps with the free jaws (2 mm open) inside the closure range, the same grasps
    with the default range (-0.5 mm: the free jaws clip), and the squeezes in contact."""
    op = Operator.random(np.random.default_rng(seed))
    sensors = Sensors(position_range_m=(-3e-3, 15e-3), force_offset_n=0.3)
    grasping = GraspingOperator(squeeze=op, grasp_s=3.0, free_s=1.0, ramp_s=0.3)
    s, _ = synthesize(ForcepsModel(sensors=sensors, seed=seed, operator=grasping), 20.0)
    clip = Sensors(force_offset_n=0.3)
    k, _ = synthesize(ForcepsModel(sensors=clip, seed=seed, operator=grasping), 20.0)
    c, _ = synthesize(ForcepsModel(sensors=sensors, seed=seed, operator=op), 15.0)
    return s, k, c


def _stage(seed: int) -> Session:
    stage = Tissue(Law.paper("x", "xdot"), 20000.0, 1000.0, 100.0)
    sensors = Sensors(
        bits=16, force_noise_n=0.05, force_range_n=(-250.0, 250.0), position_range_m=(-1e-3, 2e-2)
    )
    op = Operator.random(np.random.default_rng(seed))
    return synthesize(ForcepsModel(tissue=stage, sensors=sensors, seed=seed, operator=op), 10.0)[0]


def main(argv: list[str] | None = None) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=40)
    args = parser.parse_args(argv)
    truth = np.array(DEFAULT_TISSUE.coef)
    rows: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {"clean": []}
    for name in DAMAGE:
        rows[name] = []
    for name in ("one long contact + offset", "grasps + offset", "grasps, jaws clipped between"):
        rows[name] = []
    rows["100 kg stage"] = []
    # each row is compared with the clean session, grasps with the same squeezes in contact
    reference = {
        **dict.fromkeys(DAMAGE, "clean"),
        **dict.fromkeys(
            ("grasps + offset", "grasps, jaws clipped between"), "one long contact + offset"
        ),
    }
    law = "x+xdot+xddot"
    for seed in range(args.seeds):
        clean = random_session(DEFAULT_TISSUE, rate_hz=RATE, seed=seed, duration_s=20.0)[0]
        rows["clean"].append(_errors(BayesianFit(law).fit(clean), truth))
        rng = np.random.default_rng(1000 + seed)
        for name, damage in DAMAGE.items():
            rows[name].append(_errors(BayesianFit(law).fit(damage(clean, rng)), truth))
        grasps, clipped, contact = _grasping(seed)
        both = np.array([*truth, 0.3])
        rows["grasps + offset"].append(_errors(BayesianFit().fit(grasps), both))
        rows["grasps, jaws clipped between"].append(_errors(BayesianFit().fit(clipped), both))
        rows["one long contact + offset"].append(_errors(BayesianFit().fit(contact), both))
        stage_truth = np.array([20000.0, 1000.0, 100.0])
        rows["100 kg stage"].append(_errors(BayesianFit().fit(_stage(seed)), stage_truth))
        print(f"\rseed {seed + 1}/{args.seeds}", end="", file=sys.stderr, flush=True)
    print(file=sys.stderr)
    out: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    print(f"{args.seeds} seeds; RMS relative error of K, S, M (ratio to the reference); RMS z")
    print("| session | K | S | M | RMS z (K, S, M) |")
    print("| --- | --- | --- | --- | --- |")
    for name, values in rows.items():
        rel = np.sqrt(np.mean([v[0][:3] ** 2 for v in values], axis=0))
        z = np.sqrt(np.mean([v[1][:3] ** 2 for v in values], axis=0))
        ref = out[reference[name]][0] if name in reference else None
        cells = [
            f"{100 * e:.3g} %" + (f" ({e / ref[j]:.2f}x)" if ref is not None else "")
            for j, e in enumerate(rel)
        ]
        print(f"| {name} | {' | '.join(cells)} | {', '.join(f'{v:.2f}' for v in z)} |")
        out[name] = (rel, z)
    return out


if __name__ == "__main__":
    main(sys.argv[1:])
