"""Where the default fit's 95 % intervals stand: z-scores of the truth and the data weight.

Usage::

    python benchmarks/interval_z.py --scenes 40 --seed 9127701 --families paper
    python benchmarks/interval_z.py --scenes 40 --seed 6601203 \\
        --families "hardening,friction,offset,friction+offset,Hunt-Crossley,one branch,two branches"

Each scene is :func:`tissuecli.sim.scenes.random_scene` (as ``generalisation.py`` draws
it, the first 70 % fitted by the default ``BayesianFit()``). For the laws chosen right it
prints, by family and parameter, the coverage of the 95 % intervals, the RMS and mean of
``z = (mean - truth) / sd`` (RMS 1 and mean 0 for calibrated, unbiased intervals), and
for every scene the data weight the fit used and the weight the sensor noise alone
gives the chosen law's columns, both over the smoothing filter's ``1 / tau_g``: white
force noise through the filter, each kept row's window on the raw grid (the grasps'
edges included), matched to the tempered likelihood's covariance in geometric mean
over the coefficients. The coverage that weight would give (every interval rescaled
by the square root of the ratio) is printed beside the fit's.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections import defaultdict
from collections.abc import Sequence

import generalisation as gen
import numpy as np

from tissuecli.core.errors import TissueError
from tissuecli.identify import BayesianFit
from tissuecli.identify.derivatives import Kinematics
from tissuecli.identify.design import design
from tissuecli.identify.noise import filter_tau
from tissuecli.sim.scenes import FAMILIES, random_scene


def noise_weight(A: np.ndarray, kin: Kinematics, n_raw: int) -> float:
    """The data weight white force noise through the smoothing filter gives columns ``A``
    (shape (m, p), at the kept rows of ``kin``) over a raw grid of ``n_raw`` samples: the
    geometric mean of the generalised eigenvalues of ``A^T A`` against ``A^T S A``, ``S``
    the filtered noise's correlation over the rows (per unit of its variance)."""
    g = kin.kernels[0]
    m = g.size
    keep = np.arange(n_raw)[kin.keep] if isinstance(kin.keep, slice) else np.asarray(kin.keep)
    U = np.zeros((n_raw, A.shape[1]))
    for j in range(A.shape[1]):
        s = np.zeros(n_raw - m + 1)
        s[keep - m // 2] = A[:, j]
        U[:, j] = np.convolve(s, g)  # the filter's adjoint: each row's window on the raw grid
    G, S = A.T @ A, U.T @ U / float(g @ g)
    d = np.sqrt(np.diag(G))
    ev = np.linalg.eigvals(np.linalg.solve(S / np.outer(d, d), G / np.outer(d, d))).real
    return float(np.exp(np.mean(np.log(ev))))


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=40)
    ap.add_argument("--seed", type=int, default=None, help="repeat a run (default: fresh)")
    ap.add_argument("--max-samples", type=int, default=10_000)
    ap.add_argument("--families", default="", help="as generalisation.py ('paper': its forms)")
    args = ap.parse_args(argv)
    seed = args.seed if args.seed is not None else int.from_bytes(os.urandom(3), "little")
    families = [f.strip() for f in args.families.split(",") if f.strip()] or None
    if families and "paper" in families:
        families.remove("paper")
        families += [f for f in FAMILIES if f.startswith("paper") and f not in families]
    print(f"seed {seed} (repeat with --seed {seed}); load average "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}", flush=True)  # fmt: skip
    zs: dict[tuple[str, str], list[tuple[float, float]]] = defaultdict(list)
    ratios = []
    for k in range(args.scenes):
        scene = random_scene(seed + k, families=families, max_samples=args.max_samples)
        fitted, _, i0 = gen.split(scene.session)
        try:
            est = BayesianFit(seed=seed + k).fit(fitted)
        except TissueError:
            continue
        law, best, kin = gen.chosen_law(est), est.best_, est.kinematics_
        post = best.posterior
        if post is None:
            continue
        w_f = 1.0 / filter_tau(kin.kernels[0])
        w_used = est.n_eff_ / kin.time.size
        A = design(best.model, kin, est.session_.position, est.sigma_x_)
        w_noise = noise_weight(A, kin, len(est.session_))
        ratios.append((w_used / w_f, w_noise / w_f))
        right = scene.judged_on(i0).right(law)
        print(f"[{k + 1}/{args.scenes}] {scene.family}: {law.name} "
              f"{'right' if right else 'WRONG'}; weight used {w_used / w_f:.2f}, "
              f"noise {w_noise / w_f:.2f} of the filter's", flush=True)  # fmt: skip
        if not right:
            continue
        family = "paper" if scene.family.startswith("paper") else scene.family
        truth = dict(zip(scene.tissue.law.symbols, scene.coefficients, strict=True))
        rescale = float(np.sqrt(w_noise / w_used))
        for j, sym in enumerate(best.model.symbols):
            if sym in truth and post.sd[j] > 0:
                zs[(family, sym)].append(((post.mean[j] - truth[sym]) / post.sd[j], rescale))
        for name, sp in (best.shape_posterior or {}).items():
            if name in scene.shapes and sp["sd"] > 0:
                zs[(family, name)].append(((sp["mean"] - scene.shapes[name]) / sp["sd"], rescale))
    print(f"\nload average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    if ratios:
        r = np.array(ratios)
        print(f"weight over the filter's: used {np.min(r[:, 0]):.2f}-{np.max(r[:, 0]):.2f} "
              f"(median {np.median(r[:, 0]):.2f}); sensor noise {np.min(r[:, 1]):.2f}-"
              f"{np.max(r[:, 1]):.2f} (median {np.median(r[:, 1]):.2f})")  # fmt: skip
    print(f"{'family':<16} {'param':<6} {'n':>4} {'cover':>6} {'RMS z':>6} {'mean z':>7} "
          f"{'cover at noise weight':>22}")  # fmt: skip
    pooled: dict[str, list[tuple[float, float]]] = defaultdict(list)
    for (family, _), v in sorted(zs.items()):
        pooled[family] += v
    rows = [((f, s), v) for (f, s), v in sorted(zs.items())]
    rows += [((f, "all"), v) for f, v in sorted(pooled.items())]
    for (family, sym), v in rows:
        z = np.array([a for a, _ in v])
        zn = np.array([a * b for a, b in v])
        capped = np.clip(z, -10, 10)
        print(f"{family:<16} {sym:<6} {z.size:>4} {np.mean(np.abs(z) < 1.96):6.3f} "
              f"{np.sqrt(np.mean(capped**2)):6.2f} {np.mean(capped):+7.2f} "
              f"{np.mean(np.abs(zn) < 1.96):22.3f}")  # fmt: skip


if __name__ == "__main__":
    main(sys.argv[1:])
