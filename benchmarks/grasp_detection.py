"""How the grasp detector reads randomised paper-form sessions, from a fresh seed.

Grasp scenes (free jaws resting open between grasps) of the paper's four forms from
:func:`tissuecli.sim.scenes.random_scene` (250 Hz-10 kHz, 8-16 bits, force noise
0.5-10 % of its range, cut at 20,000 samples): how many are read as one contact, and
the least share of free-jaw samples read free where grasps are found. Then as many
scenes in contact throughout: how many are cut into grasps, and the least share of
samples kept in contact where they are.

Usage::

    python benchmarks/grasp_detection.py [--scenes 500] [--seed N]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from tissuecli.identify.contact import find_contact
from tissuecli.sim.scenes import FAMILIES, random_scene

PAPER_FAMILIES = [name for name in FAMILIES if name.startswith("paper")]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=500)
    ap.add_argument("--seed", type=int, help="first seed (fresh if unset)")
    args = ap.parse_args()
    seed = args.seed if args.seed is not None else int(np.random.SeedSequence().entropy % 2**31)
    print(f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}; "
          f"seeds {seed}-{seed + args.scenes - 1} (--seed {seed} repeats them)")  # fmt: skip
    c0, whole, free_read_free = time.process_time(), [], []
    for s in range(seed, seed + args.scenes):
        scene = random_scene(s, families=PAPER_FAMILIES, max_samples=20_000, contact="grasps")
        found = find_contact(scene.session)
        if found.all_contact:
            whole.append(s)
        else:
            free_read_free.append(float(np.mean(~found.mask[scene.x <= 0])))
    print(f"grasp scenes read as one contact   {len(whole)} of {args.scenes}; free jaws read "
          f"free where grasps are found: least {min(free_read_free, default=float('nan')):.3f}"
          f"  cpu {time.process_time() - c0:.1f} s")  # fmt: skip
    c0, kept = time.process_time(), []
    for s in range(seed, seed + args.scenes):
        scene = random_scene(s, families=PAPER_FAMILIES, max_samples=20_000,
                             contact="continuous")  # fmt: skip
        found = find_contact(scene.session)
        if not found.all_contact:
            kept.append(float(np.mean(found.mask)))
    print(f"continuous scenes cut into grasps  {len(kept)} of {args.scenes}; least share kept "
          f"{min(kept, default=1.0):.2f}  cpu {time.process_time() - c0:.1f} s")  # fmt: skip
    print(f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
