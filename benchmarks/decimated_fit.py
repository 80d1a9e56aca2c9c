"""The default fit of long sessions scored on every stride-th filtered sample
(:mod:`tissuecli.identify.decimate`) against the same fit scored on every sample: CPU
seconds of each, the stride, the chosen laws, the largest difference of a coefficient's
posterior mean in posterior SDs, the SDs' ratio and the effective samples.

Usage::

    python benchmarks/decimated_fit.py [--scene SCENE] [SECONDS ...]
    python benchmarks/decimated_fit.py --against CHECKOUT [--repeats R] [--scene SCENE]
        [SECONDS ...]

The simulated forceps at 10 kHz (default 20, 60 and 100 s: 200,000, 600,000 and
1,000,000 samples), each fitted once each way in this process (``time.process_time``);
the load average is printed before each session. ``--scene hunt-crossley-12bit``
fits instead a random operator's noisy 12-bit Hunt-Crossley session at 10 kHz in
continuous contact (``random_session(FAMILIES["Hunt-Crossley"], rate_hz=10000.0,
seed=300, duration_s=SECONDS, bits=12)``), whose closure flickers over about a dozen
of its 1,800 ADC levels in every stride of the coarse grid.

``--against CHECKOUT`` times the default fit alone (decimated, as ``tissuecli fit``
runs it) of this checkout and of another, side by side: two worker processes, each
with its checkout first on ``PYTHONPATH``, fit the same sessions (each built by its
own code) R times (default 3) by turns, who goes first alternating, so that both see
the same load (this file's worker, the checkout's code). Each prints the CPU seconds
of its fits (median and range), its chosen law and that law's ln evidence.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from tissuecli.identify import BayesianFit, decimate
from tissuecli.identify.decimate import fit_stride
from tissuecli.sim.families import FAMILIES
from tissuecli.sim.synth import ForcepsModel, random_session, synthesize

#: the sessions ``--scene`` names: SECONDS in, the session out
SCENES = {
    "forceps": lambda s: synthesize(ForcepsModel(seed=1, rate_hz=10000.0), s)[0],
    "hunt-crossley-12bit": lambda s: random_session(
        FAMILIES["Hunt-Crossley"], rate_hz=10000.0, seed=300, duration_s=s, bits=12
    )[0],
}


def fit(session: object, above: int) -> tuple[BayesianFit, float]:
    """The default fit with sessions above ``above`` filtered samples decimated, and its
    CPU seconds."""
    decimate.DECIMATE_ABOVE = above
    c0 = time.process_time()
    out = BayesianFit().fit(session)  # type: ignore[arg-type]
    return out, time.process_time() - c0


def load() -> str:
    return ", ".join(f"{v:.1f}" for v in os.getloadavg())


def worker(scene: str) -> None:
    """Fit the ``scene``'s session of each length (s) read from stdin by default; print
    the CPU seconds, the chosen law and its ln evidence."""
    BayesianFit().fit(synthesize(ForcepsModel(seed=1), 2.0)[0])  # loads SciPy
    made: dict[float, object] = {}
    import tissuecli

    print(Path(tissuecli.__file__).parents[1], flush=True)
    for line in sys.stdin:
        s = float(line)
        if s not in made:
            made[s] = SCENES[scene](s)
        c0 = time.process_time()
        est = BayesianFit().fit(made[s])  # type: ignore[arg-type]
        cpu = time.process_time() - c0
        print(f"{cpu!r}\t{est.best_.name}\t{est.best_.ln_evidence:.6f}", flush=True)


def against(checkout: str, repeats: int, seconds: list[float], scene: str) -> None:
    """This checkout and ``checkout`` by turns (see the module's docstring)."""
    here = str(Path(__file__).resolve().parents[1])
    workers = {}
    for name, root in (("this checkout", here), (checkout, checkout)):
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([root, os.environ.get("PYTHONPATH", "")]))
        workers[name] = subprocess.Popen(
            [sys.executable, __file__, "--worker", scene],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env,
        )  # fmt: skip
    for name, p in workers.items():
        assert p.stdout is not None
        print(f"{name}: the code of {p.stdout.readline().strip()}", flush=True)
    print(f"load average {load()}", flush=True)
    for s in seconds:
        cpu: dict[str, list[float]] = {name: [] for name in workers}
        chosen: dict[str, str] = {}
        for k in range(repeats):
            order = list(workers) if k % 2 == 0 else list(workers)[::-1]
            for name in order:
                p = workers[name]
                assert p.stdin is not None and p.stdout is not None
                p.stdin.write(f"{s}\n")
                p.stdin.flush()
                c, law, ln_z = p.stdout.readline().rstrip("\n").split("\t")
                cpu[name].append(float(c))
                chosen[name] = f"{law}, ln Z {float(ln_z):.3f}"
        n = int(round(s * 10000.0))
        for name in workers:
            t = cpu[name]
            print(f"{n} samples, {name}: CPU median {np.median(t):.2f} s (min {min(t):.2f}, max "
                  f"{max(t):.2f} of {repeats}); {chosen[name]}", flush=True)  # fmt: skip
        print(f"load average {load()}", flush=True)
    for p in workers.values():
        assert p.stdin is not None
        p.stdin.close()
        p.wait()


def take_scene(args: list[str]) -> str:
    """The ``--scene NAME`` option's name, taken out of ``args`` (default ``forceps``);
    exits with the names to choose from if it is not one of :data:`SCENES`."""
    scene = "forceps"
    if "--scene" in args:
        i = args.index("--scene")
        scene = args[i + 1]
        del args[i : i + 2]
    if scene not in SCENES:
        sys.exit(f"unknown scene {scene!r}; choose {', '.join(SCENES)}")
    return scene


def main() -> None:
    if "--worker" in sys.argv:
        worker(sys.argv[sys.argv.index("--worker") + 1])
        return
    args = sys.argv[1:]
    if "-h" in args or "--help" in args:
        print(__doc__)
        return
    checkout, repeats, scene = None, 3, take_scene(args)
    if "--against" in args:
        i = args.index("--against")
        checkout = args[i + 1]
        del args[i : i + 2]
    if "--repeats" in args:
        i = args.index("--repeats")
        repeats = int(args[i + 1])
        del args[i : i + 2]
    seconds = [float(a) for a in args] or [20.0, 60.0, 100.0]
    if checkout is not None:
        against(checkout, repeats, seconds, scene)
        return
    default = decimate.DECIMATE_ABOVE
    BayesianFit().fit(synthesize(ForcepsModel(seed=1), 2.0)[0])  # loads SciPy
    for s in seconds:
        session = SCENES[scene](s)
        print(f"load average {load()}", flush=True)
        full, t_full = fit(session, 10**15)
        coarse, t_coarse = fit(session, default)
        stride = fit_stride(coarse.kinematics_)
        pf, pc = full.best_.posterior, coarse.best_.posterior
        same = full.best_.name == coarse.best_.name
        shift = float(np.max(np.abs(pc.mean - pf.mean) / pf.sd)) if same else float("nan")
        ratio = pc.sd / pf.sd if same else np.array([np.nan])
        print(
            f"{len(session)} samples: every sample CPU {t_full:.2f} s ({full.best_.name}, "
            f"{full.n_eff_:.0f} effective); stride {stride} CPU {t_coarse:.2f} s "
            f"({coarse.best_.name}, {coarse.n_eff_:.0f} effective); "
            f"{t_full / t_coarse:.1f}x; largest shift {shift:.4f} SD, SDs x{ratio.min():.3f}-"
            f"{ratio.max():.3f}",
            flush=True,
        )
    decimate.DECIMATE_ABOVE = default


if __name__ == "__main__":
    main()
