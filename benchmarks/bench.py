"""Run time against error for every identification configuration, with peers.

Usage::

    python benchmarks/bench.py                      # the full run (about 10 min here)
    python benchmarks/bench.py --quick              # a smoke run (seconds)
    python benchmarks/bench.py --out docs/img       # where the plots go
    python benchmarks/bench.py --durations 1,60 --noise 4 --rates 1000   # other scenes

It draws synthetic sessions with known truth (every form; 250 Hz to 10 kHz;
8- to 16-bit ADCs; random operators; fixed seeds), runs each configuration:

- ``pinv``: the paper's windowed pseudoinverse, the form with the smallest
  best-window residual;
- ``bayes``: the default fit (exact posteriors), once per differentiator;
- ``bayes+emcee N``: the default fit, then emcee on the chosen form for N steps;
- peers when installed (``pip install '.[bench]'``): PySINDy and lmfit+emcee;

and prints, per configuration, the median run time, the median |error| of K,
S and M and how often the true form was chosen, marks the Pareto front (no
other configuration both faster and more accurate), compares every scene
family with the peers and the Cramer-Rao bound (with a paired test of the
default against each peer: RMS error in units of each session's bound, and a
bootstrap interval on the ratio), and measures how run time grows with
session length. Plots are written to ``--out``. Every scene stays inside the
sensor ranges (:func:`tissuecli.sim.synth.random_session`): a clipped session has no
truth to score against.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from tissuecli.core.session import Session  # noqa: E402
from tissuecli.core.terms import Law, paper_laws  # noqa: E402
from tissuecli.core.tissue import Tissue  # noqa: E402
from tissuecli.identify import BayesianFit, WindowedPinv  # noqa: E402
from tissuecli.identify.sampling import run_emcee  # noqa: E402
from tissuecli.sim.synth import ForcepsModel, Sensors, random_session, synthesize  # noqa: E402

TISSUES = [
    Tissue(Law.paper("x", "xdot"), 350.0, 3.0, 0.05),
    Tissue(Law.paper("x^3", "xdot"), 8e6, 3.0, 0.05),
    Tissue(Law.paper("x", "xdot^2"), 350.0, 60.0, 0.05),
    Tissue(Law.paper("x^3", "xdot^2"), 8e6, 60.0, 0.05),
]


#: peers too slow to run on every scene (lmfit's emcee evaluates the model per walker)
SLOW_PEERS = {"lmfit+emcee"}


@dataclass
class Scene:
    tissue: Tissue
    rate_hz: float
    bits: int
    seed: int
    duration_s: float
    noise: float = 1.0  # times the default analogue noise of both sensors
    label_duration: bool = False  # name the duration in the family (a study over durations)

    @property
    def family(self) -> str:
        noise = f" noise x{self.noise:g}" if self.noise != 1.0 else ""
        length = f" {self.duration_s:g} s" if self.label_duration else ""
        return f"{self.tissue.law.name} {self.rate_hz:g} Hz {self.bits}-bit{noise}{length}"

    def draw(self) -> tuple[Session, ForcepsModel]:
        return random_session(
            self.tissue,
            rate_hz=self.rate_hz,
            seed=self.seed,
            duration_s=self.duration_s,
            bits=self.bits,
            force_noise_n=self.noise * Sensors.force_noise_n,
            position_noise_m=self.noise * Sensors.position_noise_m,
        )


@dataclass
class Outcome:
    form: str
    params: np.ndarray
    seconds: float


@dataclass
class Tally:
    times: list[float] = field(default_factory=list)
    errors: list[np.ndarray] = field(default_factory=list)  # |rel error| of K, S, M when right
    right: list[bool] = field(default_factory=list)
    families: dict[str, list[np.ndarray]] = field(default_factory=dict)
    #: signed relative error of (K, S, M) per scene index, when the form was right
    signed: dict[int, np.ndarray] = field(default_factory=dict)


def _timed(fn: Callable[[], tuple[str, np.ndarray]]) -> Outcome:
    t0 = time.perf_counter()
    form, params = fn()
    return Outcome(form, np.asarray(params, float), time.perf_counter() - t0)


def pinv_config(s: Session) -> tuple[str, np.ndarray]:
    fits = [WindowedPinv(m.name).fit(s) for m in paper_laws()]
    best = min(fits, key=lambda p: p.residuals_[p.best_window_])
    return best.model_.name, best.params_


def bayes_config(differentiator: str) -> Callable[[Session], tuple[str, np.ndarray]]:
    def run(s: Session) -> tuple[str, np.ndarray]:
        est = BayesianFit("paper", differentiator=differentiator).fit(s)
        return est.best_.name, est.best_.posterior.mean  # type: ignore[union-attr]

    return run


def emcee_config(steps: int) -> Callable[[Session], tuple[str, np.ndarray]]:
    def run(s: Session) -> tuple[str, np.ndarray]:
        est = BayesianFit("paper").fit(s)
        best = est.best_
        post = run_emcee(
            best.stats,
            best.prior,
            np.random.default_rng(0),
            chunk=steps,  # type: ignore[arg-type]
            min_steps=steps,
            max_steps=steps,
        )
        return best.name, post.mean

    return run


def configurations(quick: bool) -> dict[str, Callable[[Session], tuple[str, np.ndarray]]]:
    configs: dict[str, Callable[[Session], tuple[str, np.ndarray]]] = {
        "pinv (paper)": pinv_config,
        "bayes gaussian (default)": bayes_config("gaussian"),
        "bayes savgol": bayes_config("savgol"),
        "bayes gradient": bayes_config("gradient"),
    }
    for steps in (300,) if quick else (500, 2000, 8000):
        configs[f"bayes + emcee {steps}"] = emcee_config(steps)
    try:
        import peers
    except ImportError:
        return configs
    for name, fn in (
        ("pysindy", getattr(peers, "pysindy_fit", None)),
        ("lmfit+emcee", getattr(peers, "lmfit_emcee_fit", None)),
    ):
        if fn is None:
            continue
        try:
            __import__("pysindy" if name == "pysindy" else "lmfit")
        except ImportError:
            continue

        def run(s: Session, fn: Callable = fn) -> tuple[str, np.ndarray]:
            r = fn(s)
            return r.model, r.params

        configs[name] = run
    return configs


def scenes(
    quick: bool,
    seeds: int,
    rates: tuple[float, ...] | None = None,
    durations: tuple[float, ...] = (10.0,),
    forms: list[str] | None = None,
    noise: float = 1.0,
) -> list[Scene]:
    rates = rates or ((1000.0,) if quick else (250.0, 1000.0, 10000.0))
    bits = (8,) if quick else (8, 16)
    tissues = TISSUES[:2] if quick else TISSUES
    if forms:
        tissues = [t for t in tissues if t.law.name in forms]
    return [
        Scene(t, r, b, seed, 2.0 if quick else d, noise, len(durations) > 1)
        for d in durations
        for t in tissues
        for r in rates
        for b in bits
        for seed in range(seeds)
    ]


def pareto(rows: list[tuple[str, float, float]]) -> set[str]:
    """Names not dominated: no other row both faster and at least as accurate (lower error)."""
    front = set()
    for name, t, e in rows:
        if not any(
            (t2 <= t and e2 <= e) and (t2 < t or e2 < e) for n2, t2, e2 in rows if n2 != name
        ):
            front.add(name)
    return front


def cramer_rao_rel(scene: Scene, model: ForcepsModel) -> np.ndarray:
    try:
        import peers
    except ImportError:
        return np.full(3, np.nan)
    crb = peers.cramer_rao(scene.tissue, model, scene.duration_s)
    return crb / scene.tissue.coef


def rms(a: np.ndarray, axis: int | None = None) -> np.ndarray:
    """Root mean square along ``axis`` (all of ``a`` by default)."""
    return np.sqrt(np.mean(np.square(a), axis=axis))


def paired_ratio(
    ours: np.ndarray, peer: np.ndarray, rng: np.random.Generator, draws: int = 2000
) -> tuple[float, float, float]:
    """RMS error of ours over the peer's on the same sessions, with a 95 % bootstrap interval.

    ``ours`` and ``peer`` are (n,) errors in units of each session's Cramer-Rao
    bound, so sessions of different difficulty weigh alike. Sessions are
    resampled in pairs, which keeps the correlation the shared noise puts
    between the two estimators.
    """
    ratio = float(rms(ours) / rms(peer))
    idx = rng.integers(0, ours.size, (draws, ours.size))
    boot = rms(ours[idx], axis=1) / rms(peer[idx], axis=1)
    lo, hi = np.quantile(boot, [0.025, 0.975])
    return ratio, float(lo), float(hi)


def peer_table(
    tallies: dict[str, Tally],
    bounds: dict[int, np.ndarray],
    families: dict[int, str],
    reference: str,
    peer: str,
) -> list[str]:
    """Per family and parameter (K, S): paired RMS(error / CRB) of reference and peer."""
    rng = np.random.default_rng(0)
    lines = [
        f"{reference} against {peer}: RMS of error / Cramer-Rao bound on the sessions both "
        "got right,\nand the ratio reference / peer with its 95 % paired bootstrap interval "
        "(< 1: reference better)",
        f"{'family':<36} {'n':>3}  {'K ref':>6} {'K peer':>6} {'ratio [95 % CI]':>22}  "
        f"{'S ref':>6} {'S peer':>6} {'ratio [95 % CI]':>22}",
    ]
    verdicts = {"better": 0, "level": 0, "worse": 0}
    for family in dict.fromkeys(families.values()):
        both = [
            i
            for i, f in families.items()
            if f == family and i in tallies[reference].signed and i in tallies[peer].signed
        ]
        if len(both) < 3:
            continue
        crb = np.array([bounds[i] for i in both])
        ours = np.array([tallies[reference].signed[i] for i in both]) / crb
        theirs = np.array([tallies[peer].signed[i] for i in both]) / crb
        cells = []
        for j in (0, 1):
            r, lo, hi = paired_ratio(ours[:, j], theirs[:, j], rng)
            verdicts["better" if hi < 1 else "worse" if lo > 1 else "level"] += 1
            rms_ours, rms_peer = float(rms(ours[:, j])), float(rms(theirs[:, j]))
            mark = "*" if lo > 1 else " "
            cells.append(f"{rms_ours:6.2f} {rms_peer:6.2f} {r:6.2f} [{lo:5.2f}, {hi:5.2f}]{mark}")
        lines.append(f"{family:<36} {len(both):>3}  " + "  ".join(cells))
    if len(lines) == 2:
        return [f"{reference} against {peer}: fewer than 3 sessions per family; use --seeds 3+"]
    lines.append(
        f"(K and S over all families: reference better in {verdicts['better']}, level in "
        f"{verdicts['level']}, worse in {verdicts['worse']} (marked *))"
    )
    return lines


def length_scaling(quick: bool) -> list[tuple[int, float]]:
    """Default fit time against session length at 1 kHz (one x,xdot session each)."""
    out = []
    for duration in (1.0, 4.0) if quick else (1.0, 10.0, 60.0, 600.0):
        s, _ = synthesize(ForcepsModel(seed=1), duration)
        BayesianFit("paper").fit(s)  # warm caches (FFT plans) once
        t0 = time.perf_counter()
        BayesianFit("paper").fit(s)
        out.append((len(s), time.perf_counter() - t0))
    return out


def plots(
    out: Path,
    summary: dict[str, tuple[float, float, float]],
    front: set[str],
    lengths: list[tuple[int, float]],
) -> list[Path]:
    from matplotlib.figure import Figure

    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for key, label, fname in (
        (1, "median |error| of K and S (%)", "bench_time_error.png"),
        (2, "form chosen wrongly (%)", "bench_time_choice.png"),
    ):
        fig = Figure(figsize=(7, 4.5))
        ax = fig.subplots()
        for name, vals in summary.items():
            y = vals[key] if key == 1 else 100 * (1 - vals[2])
            ax.scatter(vals[0], max(y, 1e-3), color="C3" if name in front else "C0")
            ax.annotate(
                name, (vals[0], max(y, 1e-3)), fontsize=7, xytext=(4, 2), textcoords="offset points"
            )
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("median run time per session (s)")
        ax.set_ylabel(label)
        ax.set_title("red: Pareto front (nothing both faster and more accurate)", fontsize=9)
        ax.grid(alpha=0.3)
        fig.tight_layout()
        fig.savefig(out / fname, dpi=110)
        paths.append(out / fname)
    fig = Figure(figsize=(6, 4))
    ax = fig.subplots()
    n, t = np.array(lengths, float).T
    ax.loglog(n, t, "o-")
    ax.set_xlabel("samples")
    ax.set_ylabel("default fit time (s)")
    ax.grid(alpha=0.3, which="both")
    fig.tight_layout()
    fig.savefig(out / "bench_length.png", dpi=110)
    paths.append(out / "bench_length.png")
    return paths


def floats(text: str) -> tuple[float, ...]:
    """``"250,1000"`` -> ``(250.0, 1000.0)``; argparse reports a ValueError as a usage error."""
    return tuple(float(v) for v in text.split(","))


def main(argv: list[str] | None = None) -> dict[str, object]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="a smoke run in seconds")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--out", type=Path, default=Path("docs/img"))
    ap.add_argument("--rates", type=floats, default=None, help="comma-separated rates in Hz")
    ap.add_argument(
        "--configs", default=None, help="comma-separated configuration names to run (default: all)"
    )
    ap.add_argument("--forms", default=None, help="semicolon-separated true forms, e.g. 'x,xdot'")
    ap.add_argument(
        "--durations",
        type=floats,
        default=(10.0,),
        help="comma-separated session lengths in s (default 10)",
    )
    ap.add_argument(
        "--noise", type=float, default=1.0, help="analogue noise of both sensors, times the default"
    )
    ap.add_argument("--no-scaling", action="store_true", help="skip the session-length study")
    args = ap.parse_args(argv)
    configs = configurations(args.quick)
    if args.configs:
        wanted = {c.strip() for c in args.configs.split(",")}
        configs = {k: v for k, v in configs.items() if k in wanted}
    tallies = {name: Tally() for name in configs}
    crb: dict[str, list[np.ndarray]] = {}
    scene_crb: dict[int, np.ndarray] = {}
    families: dict[int, str] = {}
    rates = args.rates
    forms = args.forms.split(";") if args.forms else None
    all_scenes = scenes(
        args.quick,
        1 if args.quick else args.seeds,
        rates,
        args.durations,
        forms,
        args.noise,
    )
    for i, scene in enumerate(all_scenes, 1):
        s, model = scene.draw()
        scene_crb[i] = cramer_rao_rel(scene, model)
        families[i] = scene.family
        crb.setdefault(scene.family, []).append(scene_crb[i])
        for name, fn in configs.items():
            if name in SLOW_PEERS and scene.rate_hz > 1000 and not args.configs:
                continue  # ~1 min per session at 10 kHz: only when asked for by --configs
            try:
                o = _timed(lambda fn=fn, s=s: fn(s))
            except Exception as exc:  # a refusal counts as a miss, with its time unknown
                print(f"  {name} on {scene.family}: {type(exc).__name__}: {exc}", file=sys.stderr)
                tallies[name].right.append(False)
                continue
            tally = tallies[name]
            tally.times.append(o.seconds)
            ok = o.form == scene.tissue.law.name
            tally.right.append(ok)
            if ok:
                tally.signed[i] = o.params / scene.tissue.coef - 1
                err = np.abs(tally.signed[i])
                tally.errors.append(err)
                tally.families.setdefault(scene.family, []).append(err)
        print(f"\r{i}/{len(all_scenes)} sessions", end="", file=sys.stderr, flush=True)
    print(file=sys.stderr)

    summary: dict[str, tuple[float, float, float]] = {}
    print(
        f"{'configuration':<26} {'time s':>8} {'|dK| %':>8} {'|dS| %':>8} {'|dM| %':>8} "
        f"{'right':>7}  front"
    )
    rows = []
    for name, t in tallies.items():
        if not t.times:
            continue
        med = np.median(t.errors, axis=0) * 100 if t.errors else np.full(3, np.nan)
        acc = float(np.mean(t.right))
        summary[name] = (float(np.median(t.times)), float(np.mean(med[:2])), acc)
        # one accuracy figure: K and S error plus the share of wrong forms, in %;
        # a configuration that never got the form right has no error to show: infinite
        err = summary[name][1] if np.isfinite(summary[name][1]) else np.inf
        rows.append((name, summary[name][0], err + 100 * (1 - acc)))
    front = pareto(rows)
    for name, t in tallies.items():
        if name not in summary:
            continue
        med = np.median(t.errors, axis=0) * 100 if t.errors else np.full(3, np.nan)
        print(
            f"{name:<26} {summary[name][0]:8.3f} {med[0]:8.4f} {med[1]:8.3f} {med[2]:8.2f} "
            f"{100 * summary[name][2]:6.1f}%  {'*' if name in front else ''}"
        )

    print("\nper scene family: median |error| of K / S (%), and the Cramer-Rao floor")
    names = list(summary)
    print(f"{'family':<36} " + " ".join(f"{n[:16]:>17}" for n in names) + f" {'CRB':>17}")
    for family, bounds in crb.items():
        cells = []
        for n in names:
            errs = tallies[n].families.get(family)
            cells.append(
                f"{np.median(errs, axis=0)[0] * 100:7.4f}/{np.median(errs, axis=0)[1] * 100:<9.3f}"
                if errs
                else f"{'-':>17}"
            )
        b = np.nanmedian(bounds, axis=0) * 100 if np.isfinite(bounds).any() else np.full(3, np.nan)
        print(f"{family:<36} " + " ".join(cells) + f" {b[0]:7.4f}/{b[1]:<9.3f}")

    if np.isfinite(list(scene_crb.values())).all():
        print("\nper scene family: RMS of error / Cramer-Rao bound, K / S (1 = efficient)")
        print(f"{'family':<36} " + " ".join(f"{n[:16]:>17}" for n in names))
        for family in crb:
            cells = []
            for n in names:
                z = [
                    tallies[n].signed[i] / scene_crb[i]
                    for i in tallies[n].signed
                    if families[i] == family
                ]
                r = rms(np.array(z), axis=0) if z else None
                cells.append(f"{r[0]:7.2f}/{r[1]:<9.2f}" if r is not None else f"{'-':>17}")
            print(f"{family:<36} " + " ".join(cells))

    reference = "bayes gaussian (default)"
    for peer in ("lmfit+emcee", "pysindy"):
        if reference in summary and peer in summary and np.isfinite(list(scene_crb.values())).all():
            print()
            print("\n".join(peer_table(tallies, scene_crb, families, reference, peer)))

    if args.no_scaling:
        return {"summary": summary, "front": front}
    lengths = length_scaling(args.quick)
    per_sample = [t / n for n, t in lengths]
    print("\ndefault fit time against session length (1 kHz):")
    for n, t in lengths:
        print(f"  {n:>9} samples: {t:7.3f} s ({1e6 * t / n:.2f} us per sample)")
    n_arr, t_arr = np.array(lengths, float).T
    slope, intercept = np.polyfit(n_arr, t_arr, 1)
    print(f"  linear fit: {intercept * 1e3:.1f} ms + {slope * 1e6:.2f} us per sample")
    paths = plots(args.out, summary, front, lengths)
    print("\nplots: " + ", ".join(str(p) for p in paths))
    return {"summary": summary, "front": front, "lengths": lengths, "per_sample": per_sample}


if __name__ == "__main__":
    main()
