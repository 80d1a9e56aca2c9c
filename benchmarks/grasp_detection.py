"""How the grasp detector reads randomised sessions, from a fresh seed.

Grasp scenes (free jaws resting open between grasps) from
:func:`tissuecli.sim.scenes.random_scene` (250 Hz-10 kHz, 8-16 bits, force noise
0.5-10 % of its range, cut at 20,000 samples), of the paper's four forms
(``--families paper``, the default) or of every family (``--families all``), scored
sample by sample against the true contact (closure above 0):

- how many are read as one contact, and the least share of free-jaw samples read free
  where grasps are found;
- per-sample errors: the share of free-jaw samples read in contact and of contact
  samples read free (median and worst over the scenes whose grasps are found);
- grasps merged (one found grasp over two true ones or more), missed (no found grasp
  over a true one), split (a true grasp cut in two or more), spurious (a found grasp
  over no true one);
- the true force read free: the RMS over the session of the noise-free force on contact
  samples read free, in noise SDs (what a prediction that sets the tissue's force to
  zero on free jaws loses; a soft law's contact at near zero force costs nothing);
- edge offsets of the grasps matched one to one, in samples and in smoothing widths
  (found minus true, start and stop);
- each scene read wrong is classed as ``one contact``, ``merged``, ``missed``,
  ``split``, ``spurious``, ``edges`` (a matched edge more than 3 smoothing widths off)
  or ``ok``, with its rate, free stretch and excitation for the worst cases.

Then as many scenes in contact throughout: how many are cut into grasps, and the least
share of samples kept in contact where they are.

Usage::

    python benchmarks/grasp_detection.py [--scenes 500] [--seed N] [--families all]
"""

from __future__ import annotations

import argparse
import os
import time
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from tissuecli.identify.contact import SMOOTH_S, find_contact
from tissuecli.sim.scenes import FAMILIES, random_scene

PAPER_FAMILIES = [name for name in FAMILIES if name.startswith("paper")]
#: a matched grasp edge further off than this many smoothing widths is an edge error
EDGE_WIDTHS = 3.0


@dataclass
class Reading:
    """One grasp scene's detection scored against its true contact."""

    seed: int
    one_contact: bool
    free_as_contact: float  # share of free-jaw samples read in contact
    contact_as_free: float  # share of contact samples read free
    merged: int = 0
    missed: int = 0
    split: int = 0
    spurious: int = 0
    edges: list[tuple[int, int]] = field(default_factory=list)  # (start, stop) offsets
    width: int = 1  # smoothing width, samples
    missed_force: float = 0.0  # RMS of the true force on contact read free, noise SDs
    settings: dict = field(default_factory=dict)

    def worst_edge(self) -> int:
        return max((max(abs(a), abs(b)) for a, b in self.edges), default=0)

    def verdict(self) -> str:
        if self.one_contact:
            return "one contact"
        for name in ("merged", "missed", "split", "spurious"):
            if getattr(self, name):
                return name
        if self.worst_edge() > EDGE_WIDTHS * self.width:
            return "edges"
        return "ok"


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(np.int8), [0]])))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist(), strict=True))


def score(seed: int, true: np.ndarray, found_mask: np.ndarray, one_contact: bool,
          width: int, settings: dict) -> Reading:  # fmt: skip
    """Score a detected contact mask against the true one."""
    free = ~true
    r = Reading(
        seed,
        one_contact,
        float(np.mean(found_mask[free])) if free.any() else 0.0,
        float(np.mean(~found_mask[true])) if true.any() else 0.0,
        width=width,
        settings=settings,
    )
    if one_contact:
        return r
    t_runs, f_runs = _runs(true), _runs(found_mask)

    def overlaps(a: tuple[int, int], runs: list[tuple[int, int]]) -> list[int]:
        return [k for k, b in enumerate(runs) if a[0] < b[1] and b[0] < a[1]]

    t_hits = [overlaps(g, f_runs) for g in t_runs]
    f_hits = [overlaps(g, t_runs) for g in f_runs]
    r.missed = sum(not h for h in t_hits)
    r.split = sum(len(h) > 1 for h in t_hits)
    r.merged = sum(len(h) > 1 for h in f_hits)
    r.spurious = sum(not h for h in f_hits)
    for k, h in enumerate(t_hits):
        if len(h) == 1 and len(f_hits[h[0]]) == 1:
            (s0, e0), (s1, e1) = t_runs[k], f_runs[h[0]]
            # a true grasp cut by the session's ends has no edge there
            r.edges.append((s1 - s0 if s0 > 0 else 0, e1 - e0 if e0 < true.size else 0))
    return r


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=500)
    ap.add_argument("--seed", type=int, help="first seed (fresh if unset)")
    ap.add_argument("--families", default="paper", choices=("paper", "all"))
    ap.add_argument("--max-samples", type=int, default=20_000)
    ap.add_argument("--list", type=int, default=12, help="worst scenes listed")
    args = ap.parse_args()
    families = PAPER_FAMILIES if args.families == "paper" else list(FAMILIES)
    seed = args.seed if args.seed is not None else int(np.random.SeedSequence().entropy % 2**31)
    print(f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}; "
          f"seeds {seed}-{seed + args.scenes - 1} (--seed {seed} repeats them); "
          f"families {args.families}")  # fmt: skip
    c0, readings = time.process_time(), []
    for s in range(seed, seed + args.scenes):
        scene = random_scene(s, families=families, max_samples=args.max_samples,
                             contact="grasps")  # fmt: skip
        found = find_contact(scene.session)
        dt = 1.0 / float(scene.settings["rate_hz"])
        width = max(1, int(round(SMOOTH_S / dt)))
        settings = {k: scene.settings[k] for k in ("family", "rate_hz", "bits", "noise_frac",
                                                    "excitation", "duration_s")}  # fmt: skip
        true = scene.x > 0
        runs = _runs(~true)
        inner = [b - a for a, b in runs if a > 0 and b < true.size]
        settings["free_s"] = (min(inner) if inner else 0) * dt
        r = score(s, true, found.mask, found.all_contact, width, settings)
        missed = np.where(true & ~found.mask, scene.force, 0.0)
        r.missed_force = float(np.sqrt(np.mean(missed**2))) / scene.noise_n
        readings.append(r)
    cpu = time.process_time() - c0
    n = len(readings)
    found_rs = [r for r in readings if not r.one_contact]
    whole = n - len(found_rs)
    fc = np.array([r.free_as_contact for r in found_rs]) if found_rs else np.zeros(1)
    cf = np.array([r.contact_as_free for r in found_rs]) if found_rs else np.zeros(1)
    print(f"grasp scenes read as one contact   {whole} of {n}; free jaws read "
          f"free where grasps are found: least {1 - fc.max():.3f}  cpu {cpu:.1f} s")  # fmt: skip
    print(f"free samples read in contact       median {np.median(fc):.4f}  90th "
          f"{np.percentile(fc, 90):.4f}  worst {fc.max():.4f}")  # fmt: skip
    print(f"contact samples read free          median {np.median(cf):.4f}  90th "
          f"{np.percentile(cf, 90):.4f}  worst {cf.max():.4f}")  # fmt: skip
    mf = np.array([r.missed_force for r in readings])
    print(f"true force read free, noise SDs    median {np.median(mf):.3f}  90th "
          f"{np.percentile(mf, 90):.3f}  worst {mf.max():.3f}; scenes over 0.5: "
          f"{int(np.sum(mf > 0.5))}")  # fmt: skip
    print(f"scenes with grasps merged {sum(r.merged > 0 for r in found_rs)}, missed "
          f"{sum(r.missed > 0 for r in found_rs)}, split {sum(r.split > 0 for r in found_rs)}, "
          f"spurious {sum(r.spurious > 0 for r in found_rs)}")  # fmt: skip
    starts = np.array([a for r in found_rs for a, _ in r.edges] or [0])
    stops = np.array([b for r in found_rs for _, b in r.edges] or [0])
    w_starts = np.array([a / r.width for r in found_rs for a, _ in r.edges] or [0.0])
    w_stops = np.array([b / r.width for r in found_rs for _, b in r.edges] or [0.0])
    print(f"edge offsets, samples (found - true): start median {np.median(starts):+.0f} "
          f"[5 %, 95 %] [{np.percentile(starts, 5):+.0f}, {np.percentile(starts, 95):+.0f}];"
          f" stop median {np.median(stops):+.0f} [{np.percentile(stops, 5):+.0f}, "
          f"{np.percentile(stops, 95):+.0f}]")  # fmt: skip
    print(f"edge offsets, smoothing widths:    start median {np.median(w_starts):+.2f} "
          f"[{np.percentile(w_starts, 5):+.2f}, {np.percentile(w_starts, 95):+.2f}];"
          f" stop median {np.median(w_stops):+.2f} [{np.percentile(w_stops, 5):+.2f}, "
          f"{np.percentile(w_stops, 95):+.2f}]")  # fmt: skip
    verdicts = Counter(r.verdict() for r in readings)
    print("verdicts  " + ", ".join(f"{k} {v}" for k, v in verdicts.most_common()))
    bad = sorted((r for r in readings if r.verdict() != "ok"),
                 key=lambda r: -(r.free_as_contact + r.contact_as_free))  # fmt: skip
    for r in bad[: args.list]:
        st = r.settings
        print(f"  seed {r.seed:<11d} {r.verdict():<11s} free->contact {r.free_as_contact:.2f}"
              f" contact->free {r.contact_as_free:.2f}  {st['family']}, "
              f"{st['rate_hz']:.0f} Hz, {st['bits']} bits, noise {st['noise_frac']:.3f}, "
              f"{st['excitation']}, {st['duration_s']:.1f} s, "
              f"free {st['free_s']:.2f} s")  # fmt: skip
    c0, kept = time.process_time(), []
    for s in range(seed, seed + args.scenes):
        scene = random_scene(s, families=families, max_samples=args.max_samples,
                             contact="continuous")  # fmt: skip
        found = find_contact(scene.session)
        if not found.all_contact:
            kept.append(float(np.mean(found.mask)))
    print(f"continuous scenes cut into grasps  {len(kept)} of {args.scenes}; least share kept "
          f"{min(kept, default=1.0):.2f}  cpu {time.process_time() - c0:.1f} s")  # fmt: skip
    print(f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
