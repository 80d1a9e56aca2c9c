"""Three diagnostics of one random scene's fit, as docs/benchmarks.md quotes them.

Usage::

    python benchmarks/fit_diagnostics.py offset SEED [DRAWS]
    python benchmarks/fit_diagnostics.py ridge SEED
    python benchmarks/fit_diagnostics.py lattice [SEED ...]

- ``offset``: a paper-form scene (``random_scene(SEED, families=paper forms,
  max_samples=10000)``, its first 70 % fitted) under DRAWS realisations of its noise
  (default 12; the first the scene's own): the default fit's chosen law and
  probability, and the posterior z of the offset of the true law with an offset added.
- ``ridge``: a scene of the other families, fitted with its true law: the ln evidence
  over the shape along the Laplace peak's principal axes, at -4 to +4 of their SDs
  (a Gaussian falls 8, 4.5, 1.5 and 0.5 at 4, 3, sqrt 3 and 1), and where the truth lies
  in them.
- ``lattice``: 3000-sample scenes of one relaxation branch and of Hunt-Crossley contact
  (default seeds 100-111), each fitted with the shape grid's orthant masses as the fit
  takes them and with every node at the full target (``shaped.TIGHT_SHARE = -1``): the
  largest difference of any law's ln Z, whether the choice is the same, and CPU of each.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from generalisation import split  # noqa: E402

from tissuecli.identify import BayesianFit, shaped, shapes  # noqa: E402
from tissuecli.sim.scenes import FAMILIES, random_scene  # noqa: E402

PAPER = [f for f in FAMILIES if f.startswith("paper")]
OTHERS = ["hardening", "friction", "offset", "friction+offset", "Hunt-Crossley",
          "one branch", "two branches"]  # fmt: skip


def offset(seed: int, draws: int) -> None:
    zs = []
    for k in range(draws):
        scene = random_scene(seed, families=PAPER, max_samples=10_000,
                             noise_seed=None if k == 0 else 1000 + k)  # fmt: skip
        fitted = split(scene.session)[0]
        est = BayesianFit().fit(fitted)
        name = scene.tissue.law.name + "+offset"
        with_offset = next((r for r in est.results_ if r.name == name), None)
        z = float("nan")
        if with_offset is not None and with_offset.posterior is not None:
            i = list(with_offset.model.symbols).index("F0")
            z = with_offset.posterior.mean[i] / with_offset.posterior.sd[i]
            zs.append(z)
        print(f"draw {k}: {est.best_.name} P {est.best_.probability:.3f}; offset z {z:+.2f}",
              flush=True)  # fmt: skip
    if zs:
        sd = np.std(zs, ddof=1) if len(zs) > 1 else float("nan")
        print(f"offset z over {len(zs)} draws: mean {np.mean(zs):+.2f}, SD {sd:.2f}")


def ridge(seed: int) -> None:
    scene = random_scene(seed, families=OTHERS, max_samples=10_000)
    fitted = split(scene.session)[0]
    seen: dict[str, object] = {}
    laplace = shaped.laplace

    def keep(log_z, grid, starts, hint=None):  # type: ignore[no-untyped-def]
        peak = laplace(log_z, grid, starts, hint)
        seen.update(f=log_z, grid=grid, peak=peak)
        return peak

    shaped.laplace = keep
    try:
        BayesianFit(scene.tissue.law).fit(fitted)
    finally:
        shaped.laplace = laplace
    peak, f, grid = seen.get("peak"), seen.get("f"), seen.get("grid")
    if peak is None:
        print(f"{scene.tissue.law.name}: no Laplace peak (the grid integrates the shape)")
        return
    axes = shapes.principal_axes(peak.cov)  # type: ignore[attr-defined]
    truth = grid.to_u(scene.shapes)  # type: ignore[attr-defined]
    where = np.linalg.solve(axes, truth - peak.u)  # type: ignore[attr-defined]
    print(f"{scene.tissue.law.name}: SDs {np.round(peak.sd, 8)}; truth at "  # type: ignore[attr-defined]
          f"{np.round(where, 2)} of the axes' SDs")
    zs = (-4.0, -3.0, -np.sqrt(3.0), -1.0, 1.0, np.sqrt(3.0), 3.0, 4.0)
    for k in range(axes.shape[1]):
        drops = []
        for z in zs:
            u = peak.u + z * axes[:, k]  # type: ignore[attr-defined]
            inside = grid.inside(u)  # type: ignore[attr-defined]
            drops.append(f(u) - peak.log_z if inside else float("nan"))  # type: ignore[operator, attr-defined]
        print(f"axis {k}: " + " ".join(f"{d:+6.2f}" for d in drops))


def lattice(seeds: list[int]) -> None:
    for seed in seeds:
        for family in ("one branch", "Hunt-Crossley"):
            session = random_scene(seed, families=[family], max_samples=3000).session
            fits, cpu = [], []
            for share in (shaped.TIGHT_SHARE, -1.0):
                saved, shaped.TIGHT_SHARE = shaped.TIGHT_SHARE, share
                try:
                    c0 = time.process_time()
                    fits.append(BayesianFit(seed=0).fit(session))
                    cpu.append(time.process_time() - c0)
                finally:
                    shaped.TIGHT_SHARE = saved
            z = [{r.name: r.ln_evidence for r in e.results_} for e in fits]
            worst = max(abs(z[0][k] - z[1][k]) for k in z[1] if k in z[0] and np.isfinite(z[1][k]))
            same = fits[0].best_.name == fits[1].best_.name
            print(f"{seed} {family}: largest ln Z difference {worst:.1e}, same choice {same}, "
                  f"CPU {cpu[0]:.2f} s against {cpu[1]:.2f} s", flush=True)  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=["offset", "ridge", "lattice"])
    ap.add_argument("numbers", type=int, nargs="*")
    args = ap.parse_args()
    if args.what == "offset":
        offset(args.numbers[0] if args.numbers else 9260004,
               args.numbers[1] if len(args.numbers) > 1 else 12)  # fmt: skip
    elif args.what == "ridge":
        ridge(args.numbers[0] if args.numbers else 6630441)
    else:
        lattice(args.numbers or list(range(100, 112)))


if __name__ == "__main__":
    main()
