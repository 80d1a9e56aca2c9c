"""Noisy sessions in contact throughout: how many the grasp detector cuts into grasps,
how much of each it fits, and how many the fit refuses.

Each seed draws a paper-form ``x^3`` session (``x^3`` with ``xdot`` or ``xdot|xdot|``,
and ``xddot``) that never leaves the tissue: 8-bit ADC, 250-2000 Hz, 4-20 s, force
noise up to 10 % of the force's range (70 % of seeds uniform in 0-10 %, the rest
log-uniform in 0.1-10 %), the force sensor's range a little wider than the force.
The soft law rests near zero force at the smallest closures, where it looks like
free jaws.

Usage::

    python benchmarks/continuous_contact.py [--seeds 300] [--fit]

``--fit`` also runs the fit over the paper's four forms on every session and counts
refusals (slower).
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from tissuecli.core.errors import FitError
from tissuecli.core.session import Session
from tissuecli.core.terms import Law
from tissuecli.core.tissue import Tissue
from tissuecli.identify import BayesianFit
from tissuecli.identify.derivatives import Gaussian
from tissuecli.identify.prepare import prepare
from tissuecli.sim.scenes import DETECTABLE, Scene, detectability
from tissuecli.sim.synth import ForcepsModel, Operator, Sensors, synthesize


def noisy_contact(
    seed: int,
    *,
    rate_hz: float | None = None,
    noise_fraction: float | None = None,
    duration_s: float | None = None,
) -> Session:
    """A paper-form ``x^3`` session in contact throughout (the closure never reaches 0);
    arguments left unset are drawn from ``seed``."""
    return noisy_contact_truth(
        seed, rate_hz=rate_hz, noise_fraction=noise_fraction, duration_s=duration_s
    )[0]


def noisy_contact_truth(
    seed: int,
    *,
    rate_hz: float | None = None,
    noise_fraction: float | None = None,
    duration_s: float | None = None,
) -> tuple[Session, Tissue]:
    """:func:`noisy_contact`'s session and the tissue it was drawn with (its law and
    coefficients in SI units)."""
    session, _, tissue, _ = _draw(
        seed, rate_hz=rate_hz, noise_fraction=noise_fraction, duration_s=duration_s
    )
    return session, tissue


def noisy_contact_scene(seed: int) -> Scene:
    """:func:`noisy_contact`'s session as a :class:`~tissuecli.sim.scenes.Scene`: its
    truth (true force, kinematics, noise SD) and the terms whose force stands below the
    noise (:func:`~tissuecli.sim.scenes.detectability`), for the generalisation
    benchmark's scoring."""
    session, truth, tissue, noise = _draw(seed)
    rate = float(session.meta["rate_hz"])
    snr = detectability(tissue, truth["x"], truth["v"], truth["a"], rate, noise)
    weak = frozenset(k for k, v in snr.items() if v < DETECTABLE)
    settings = {"family": f"noisy contact {tissue.law.name}", "rate_hz": rate, "bits": 8,
                "noise_frac": noise / max(float(np.ptp(truth["F"])), 1e-300),
                "contact": "continuous", "duration_s": len(session) / rate,
                "seed": seed, "detectability": snr}  # fmt: skip
    return Scene(session, tissue, truth["F"], truth["x"], truth["v"], truth["a"], noise,
                 settings, unexcited=weak)  # fmt: skip


def _draw(
    seed: int,
    *,
    rate_hz: float | None = None,
    noise_fraction: float | None = None,
    duration_s: float | None = None,
) -> tuple[Session, dict[str, np.ndarray], Tissue, float]:
    """The session, its truth (:func:`~tissuecli.sim.synth.synthesize`), the tissue and
    the force noise's SD (N) of :func:`noisy_contact_truth`."""
    rng = np.random.default_rng(seed)
    rate = float(rng.uniform(250, 2000)) if rate_hz is None else rate_hz
    speed = str(rng.choice(["xdot", "xdot|xdot|"]))
    law = Law.of(["x^3", speed, "xddot"])
    damping = 10 ** rng.uniform(-0.5, 1) if speed == "xdot" else 10 ** rng.uniform(0.5, 2)
    tissue = Tissue(law, 10 ** rng.uniform(6, 7.5), damping, 10 ** rng.uniform(-2.5, -1))
    base = Operator.random(rng)
    operator = Operator(
        mean_m=sum(base.amplitudes_m) * rng.uniform(1.0, 1.3),  # the jaws never open
        amplitudes_m=base.amplitudes_m,
        frequencies_hz=base.frequencies_hz,
        phases_rad=base.phases_rad,
    )
    duration = float(rng.uniform(4, 20)) if duration_s is None else duration_s
    clean = ForcepsModel(tissue=tissue, rate_hz=rate, operator=operator, seed=seed)
    f = clean.truth(np.arange(int(duration * rate)))[3]
    if noise_fraction is None:
        uniform = rng.uniform() < 0.7
        frac = float(rng.uniform(0.0, 0.1) if uniform else 10 ** rng.uniform(-3, -1))
    else:
        frac = noise_fraction
    sd = frac * float(np.ptp(f))
    pad = rng.uniform(0.02, 0.5) * np.ptp(f) + 4 * sd
    sensors = Sensors(
        bits=8,
        force_noise_n=sd,
        force_range_n=(float(f.min() - pad), float(f.max() + pad)),
        position_noise_m=10 ** rng.uniform(-6.5, -5),
    )
    model = ForcepsModel(tissue=tissue, rate_hz=rate, operator=operator, sensors=sensors, seed=seed)
    session, truth = synthesize(model, duration)
    return session, truth, tissue, sd


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=300)
    ap.add_argument("--fit", action="store_true", help="fit every session and count refusals")
    args = ap.parse_args()
    start = time.perf_counter()
    cut, kept, refused = 0, [], 0
    for seed in range(args.seeds):
        session = noisy_contact(seed)
        try:
            ready = prepare(session, Gaussian())
            cut += not ready.contact.all_contact
            kept.append(ready.kinematics.time.size / len(session))
        except FitError:
            refused += 1
            kept.append(0.0)
        if args.fit:
            try:
                BayesianFit("paper").fit(session)
            except FitError:
                refused += 1
    k = np.array(kept)
    print(
        f"{args.seeds} sessions in contact throughout ({time.perf_counter() - start:.0f} s, "
        f"load average {os.getloadavg()[0]:.1f})"
    )
    print(f"  cut into grasps:           {cut}")
    print(
        f"  fitted samples (fraction): min {k.min():.3f}, 5th percentile "
        f"{np.percentile(k, 5):.3f}, median {np.median(k):.3f}"
    )
    print(
        f"  refused:                   {refused}{' (fit over the paper forms)' if args.fit else ''}"
    )


if __name__ == "__main__":
    main()
