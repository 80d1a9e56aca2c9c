"""How a coarse ADC's staircase, rebuilt through its level crossings, reads the closure's
turns, and what that does to the inertia M.

Usage::

    python benchmarks/staircase_turns.py [--sessions N]

The simulated forceps with an 8-bit ADC (``ForcepsModel(rate_hz, seed,
Sensors(bits=8))``, 20 s), seeds 0 to N-1 (default 3 for the turns, 6 for M):

- **turns**: at 1 kHz, each turn's apex as the rebuilt closure puts it
  (``staircase._crossings``) against the true closure's extreme between the crossings
  either side, in steps past the threshold crossed twice: the mean error over all
  turns, and by the true apex's height; with the sensors' own position noise and with
  none (``position_noise_m=1e-9``);
- **M**: the mean and RMS z of M (``BayesianFit("x+xdot+xddot")``, ``+offset`` with the
  grasping operator) over N sessions, continuous and grasping, at 1 and 10 kHz; the
  truth is the forceps' default tissue.
"""

from __future__ import annotations

import argparse
import os

import numpy as np

from tissuecli.core.tissue import DEFAULT_TISSUE
from tissuecli.identify import BayesianFit
from tissuecli.identify.derivatives import staircase as stair
from tissuecli.sim.synth import ForcepsModel, GraspingOperator, Sensors, synthesize

#: true apex heights (steps past the threshold) the turns are grouped by
BANDS = ((-1.0, 0.0), (0.0, 0.25), (0.25, 0.5), (0.5, 0.75), (0.75, 1.01))


def turns(sessions: int, position_noise_m: float | None) -> np.ndarray:
    """(estimated, true) apex of every turn, steps past the threshold, shape (k, 2)."""
    rows = []
    for seed in range(sessions):
        sensors = Sensors(bits=8) if position_noise_m is None else Sensors(
            bits=8, position_noise_m=position_noise_m
        )
        session, truth = synthesize(ForcepsModel(rate_hz=1000.0, seed=seed, sensors=sensors), 20.0)
        x, dt = session.position, 1e-3
        step = stair.adc_step(x)
        assert step is not None
        base = float(np.min(x))
        codes = np.round((x - base) / step)
        t, v = stair._crossings(codes, codes[1:] != codes[:-1], dt)
        true = (np.asarray(truth["x"], float) - base) / step
        # an apex is a point off the half-integer thresholds
        for k in np.flatnonzero(np.abs(v - np.floor(v) - 0.5) > 1e-9):
            if k == 0 or k == t.size - 1:
                continue
            seg = true[int(t[k - 1] / dt) : int(t[k + 1] / dt) + 1]
            side = np.sign(v[k] - v[k - 1])
            top = seg.max() if side > 0 else seg.min()
            rows.append((side * (v[k] - v[k - 1]), side * (top - v[k - 1])))
    return np.array(rows)


def m_z(sessions: int) -> None:
    """M's mean and RMS z over ``sessions`` sessions of each operator and rate."""
    for grasping in (False, True):
        for rate in (1000.0, 10000.0):
            zs = []
            for seed in range(sessions):
                kw = {"operator": GraspingOperator()} if grasping else {}
                model = ForcepsModel(rate_hz=rate, seed=seed, sensors=Sensors(bits=8), **kw)
                est = BayesianFit("x+xdot+xddot" + ("+offset" if grasping else "")).fit(
                    synthesize(model, 20.0)[0]
                )
                zs.append((est.coef_[2] - DEFAULT_TISSUE.coef[2]) / est.coef_sd_[2])
            z = np.array(zs)
            print(f"M, {'grasping' if grasping else 'continuous'} at {rate / 1000:g} kHz: "
                  f"mean z {z.mean():+.2f}, RMS {np.sqrt(np.mean(z**2)):.2f} "
                  f"({sessions} sessions)", flush=True)  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", type=int, default=None)
    args = ap.parse_args()
    print(f"load average {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    for label, noise in (("sensors' position noise", None), ("no position noise", 1e-9)):
        r = turns(args.sessions or 3, noise)
        err = r[:, 0] - r[:, 1]
        print(f"turns, {label}: {len(r)}, apex error mean {err.mean():+.3f} steps")
        for lo, hi in BANDS:
            m = (r[:, 1] >= lo) & (r[:, 1] < hi)
            if m.any():
                print(f"   true apex {lo:g} to {hi:g}: {m.sum()} turns, error mean "
                      f"{err[m].mean():+.3f}, SD {err[m].std():.3f}")  # fmt: skip
    m_z(args.sessions or 6)


if __name__ == "__main__":
    main()
