"""Many sessions: batch fitting speed-up, compare's calibration, classify's accuracy.

Usage::

    python benchmarks/batch.py speed        # 4 tissues x 10 specimens x 10 sessions
    python benchmarks/batch.py calibration  # compare, on studies drawn from its model
    python benchmarks/batch.py classify --catalogue DIR/two.db   # after speed
    python benchmarks/batch.py cpu          # CPU time of the parent and of the workers

``speed`` simulates the study with ``tissuecli simulate study``, fits it with
``tissuecli fit --jobs 1`` and ``--jobs 2`` into two catalogues, side by side, then
repeats the second command (which must fit nothing), and prints wall times, the
speed-up and the load average. ``calibration`` draws whole studies' session posteriors
from the hierarchical model (no fitting) and bins P(A > B) against what happened, and
counts how often two groups with one mean are judged the same. ``classify`` runs
leave-one-specimen-out classification on the fitted catalogue against the truth's own
classifier (the design's group values and spreads). ``cpu`` fits the study in a child
process with ``--jobs 1`` and ``--jobs 2`` and reports the CPU time each process used per
session fitted: the parent's (its start and imports, reading, hashing, storing,
dispatching) and the workers' (theirs too).
CPU time depends far less on the machine's load than wall time does, so these figures say
on a busy machine where a batch's work is.
"""

from __future__ import annotations

import argparse
import math
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from tissuecli.identify.hierarchy import Estimates, Hierarchy, classify_probabilities


def load() -> str:
    return "load average " + ", ".join(f"{v:.2f}" for v in os.getloadavg())


def run(*args: str) -> tuple[float, str]:
    t0 = time.perf_counter()
    r = subprocess.run(
        [sys.executable, "-m", "tissuecli", *args], capture_output=True, text=True, check=False
    )
    seconds = time.perf_counter() - t0
    if r.returncode != 0:
        raise SystemExit(
            f"tissuecli {' '.join(args)} failed:\n{r.stdout[-2000:]}{r.stderr[-2000:]}"
        )
    return seconds, r.stdout


def speed(a: argparse.Namespace) -> None:
    where = Path(a.dir or tempfile.mkdtemp(prefix="batch-bench-"))
    where.mkdir(parents=True, exist_ok=True)
    study = where / "study.h5"
    if not study.exists():
        size = ["--groups", str(a.groups), "--specimens", str(a.specimens)]
        run("simulate", "study", "--out", str(study), *size, "--sessions", str(a.sessions))
    n = a.groups * a.specimens * a.sessions
    extra = ["--forms", a.forms] if a.forms else []
    print(
        f"study: {a.groups} tissues x {a.specimens} specimens x {a.sessions} sessions = {n} "
        f"sessions of 4 s at 1 kHz, in {where}; fit settings: {extra or 'default'}"
    )
    print(f"before: {load()}; {os.cpu_count()} cores")
    times = {}
    for jobs in (1, 2):
        db = where / f"jobs{jobs}.db"
        if db.exists():
            db.unlink()
        t, out = run("fit", str(study), "--catalogue", str(db), "--jobs", str(jobs), *extra)
        times[jobs] = t
        print(f"--jobs {jobs}: {t:7.1f} s  ({t / n * 1e3:.0f} ms a session); {load()}")
        print("    " + out.strip().splitlines()[-1])
    print(f"speed-up --jobs 2 over --jobs 1: {times[1] / times[2]:.2f}x")
    t, out = run("fit", str(study), "--catalogue", str(where / "jobs2.db"), "--jobs", "2", *extra)
    fitted = re.search(r"(\d+) of (\d+) session\(s\) fitted", out)
    print(f"repeated --jobs 2: {t:.1f} s, {fitted.group(0) if fitted else out.strip()}; {load()}")


CHILD = """
import json, os, sys, time
t0 = time.perf_counter()
import psutil
from tissuecli.app.batch import fit_batch
db, study, jobs, forms = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4] or None
extra = {"forms": forms} if forms else {}
r = fit_batch([study], catalogue=db, jobs=jobs, **extra)
parent = time.process_time()  # the whole process, its start and imports too
kids = sum(sum(p.cpu_times()[:2]) for p in psutil.Process().children(recursive=True))
print(json.dumps({"parent": parent, "workers": kids, "wall": time.perf_counter() - t0,
                  "fitted": len(r.fitted), "fit": sum(f.seconds for f in r.fitted)}))
"""


def cpu(a: argparse.Namespace) -> None:
    import json

    where = Path(a.dir or tempfile.mkdtemp(prefix="batch-cpu-"))
    where.mkdir(parents=True, exist_ok=True)
    study = where / "study.h5"
    if not study.exists():
        size = ["--groups", str(a.groups), "--specimens", str(a.specimens)]
        run("simulate", "study", "--out", str(study), *size, "--sessions", str(a.sessions))
    print(f"study {study}: {a.groups} x {a.specimens} x {a.sessions} sessions; fit settings: "
          f"{['--forms', a.forms] if a.forms else 'default'}; {load()}")  # fmt: skip
    print("jobs   wall s   parent ms/fit   workers ms/fit   fit ms/fit   all CPU s")
    total = {}
    for jobs in (1, 2):
        db = where / f"cpu{jobs}.db"
        if db.exists():
            db.unlink()
        r = subprocess.run(
            [sys.executable, "-c", CHILD, str(db), str(study), str(jobs), a.forms or ""],
            capture_output=True, text=True, check=True,
        )  # fmt: skip
        f = json.loads(r.stdout.strip().splitlines()[-1])
        n = max(f["fitted"], 1)
        total[jobs] = f["parent"] + f["workers"]
        print(f"{jobs:4d} {f['wall']:8.1f} {1e3 * f['parent'] / n:15.1f} "
              f"{1e3 * f['workers'] / n:16.1f} {1e3 * f['fit'] / n:12.1f} "
              f"{total[jobs]:11.1f}")  # fmt: skip
    # on 2 idle cores --jobs 1 takes its CPU time, --jobs 2 at best half of its own
    print(
        f"speed-up --jobs 2 over --jobs 1 that the CPU times allow on 2 idle cores: "
        f"{total[1] / (total[2] / 2):.2f}x; {load()}"
    )


def draw(rng: np.random.Generator, mu: np.ndarray, omega: float, tau: float,
         specimens: int, sessions: int) -> Estimates:  # fmt: skip
    """Session posteriors of one study from the model: each session's posterior SD
    between 0.2 % and 2 % (the fitted sessions' range on the log scale)."""
    vals, var, gs, ss = [], [], [], []
    for g, m in enumerate(mu):
        for k in range(specimens):
            eta = rng.normal(m, tau)
            for _ in range(sessions):
                v = rng.uniform(0.002, 0.02) ** 2
                vals.append(rng.normal(rng.normal(eta, omega), math.sqrt(v)))
                var.append(v)
                gs.append(f"g{g}")
                ss.append(f"s{k}")
    return Estimates.of(vals, var, gs, ss)


def calibration(a: argparse.Namespace) -> None:
    rng = np.random.default_rng(a.seed)
    upper = 0.3
    print(f"{a.studies} studies of 4 groups x {a.specimens} specimens x {a.sessions} sessions "
          f"drawn from the model; omega, tau ~ U(0, {upper}); seed {a.seed}")  # fmt: skip
    for truth_sd, model_sd in ((0.1, 0.1), (1.0, 1.0), (0.1, 1.0)):
        t0 = time.perf_counter()
        ps, hits, same = [], [], 0
        for i in range(a.studies):
            omega, tau = rng.uniform(0, upper, 2)
            mu = rng.normal(0.0, truth_sd, 4)
            model = Hierarchy(prior_mean=0.0, prior_sd=model_sd, upper=upper, grid=48)
            h = model.fit(draw(rng, mu, omega, tau, a.specimens, a.sessions))
            for x in range(4):
                for y in range(x + 1, 4):
                    ps.append(h.prob_greater(x, y))
                    hits.append(mu[x] > mu[y])
            # one tissue twice: groups 0 and 1 share a mean
            mu[1] = mu[0]
            h = Hierarchy(prior_mean=0.0, prior_sd=model_sd, upper=upper, grid=48).fit(
                draw(rng, mu, omega, tau, a.specimens, a.sessions)
            )
            same += h.ln_bayes_same(0, 1) > 0
            del i
        p, hit = np.array(ps), np.array(hits)
        print(f"\ngroup means ~ N(0, {truth_sd}^2), model prior SD {model_sd}: "
              f"{p.size} pairs, {time.perf_counter() - t0:.1f} s")  # fmt: skip
        print("   predicted P   pairs   mean P   observed   binomial SE   z")
        edges = np.array([0, 0.05, 0.2, 0.4, 0.6, 0.8, 0.95, 1.0])
        worst = 0.0
        for lo, hi in zip(edges[:-1], edges[1:], strict=True):
            m = (p >= lo) & ((p < hi) | (hi == 1.0))
            if not m.any():
                continue
            pred, seen = p[m].mean(), hit[m].mean()
            se = math.sqrt(max(np.mean(p[m] * (1 - p[m])), 1e-6) / m.sum())
            z = (seen - pred) / se
            worst = max(worst, abs(z))
            row = f"{m.sum():7d}  {pred:7.3f}  {seen:9.3f}  {se:12.3f}  {z:5.1f}"
            print(f"   {lo:4.2f}-{hi:4.2f}  {row}")
        print(f"   largest |z| {worst:.1f}; same tissue judged same (ln BF > 0) in "
              f"{same}/{a.studies} = {100 * same / a.studies:.1f} % of studies")  # fmt: skip


def classify(a: argparse.Namespace) -> None:
    from tissuecli.app.compare import estimates, parse_quantity_spec
    from tissuecli.formats.catalogue import Catalogue
    from tissuecli.sim.study import GROUPS, StudyDesign

    design = StudyDesign()
    with Catalogue(a.catalogue, create=False) as cat:
        entries = cat.entries()
    quantities = ("K", "S")
    ests = []
    for q in quantities:
        e, _, _ = estimates(entries, "tissue", parse_quantity_spec(q), "log")
        ests.append(e)
    e0 = ests[0]
    if any(e.value.size != e0.value.size for e in ests):
        raise SystemExit("every fit must have K and S: fit with a law that has both")
    groups = list(e0.groups)
    truth = np.array([[math.log(getattr(GROUPS[g], q)) for g in groups] for q in quantities])
    spread = design.specimen_sd**2 + design.session_sd**2
    right = best = 0
    n = e0.value.size
    for k in range(len(e0.specimens)):
        out = e0.specimen == k
        lps, lps_truth = [], []
        for qi, e in enumerate(ests):
            keep = ~out
            sub = Estimates.of(
                e.value[keep], e.var[keep], [e.groups[g] for g in e.group[keep]],
                [e.specimens[s] for s in e.specimen[keep]],
            )  # fmt: skip
            h = Hierarchy(prior_sd=1.0).fit(sub)
            order = [sub.groups.index(g) for g in groups]
            lps.append(h.ln_predictive(e.value[out], e.var[out])[:, order])
            s2 = spread + e.var[out][:, None]
            lps_truth.append(-0.5 * ((e.value[out][:, None] - truth[qi]) ** 2 / s2 + np.log(s2)))
        want = e0.group[out]
        right += int(np.sum(np.argmax(classify_probabilities(lps), axis=1) == want))
        best += int(np.sum(np.argmax(classify_probabilities(lps_truth), axis=1) == want))
    print(f"leave-one-specimen-out over {len(e0.specimens)} specimens, {n} sessions, "
          f"by {' and '.join(quantities)} on the log scale")  # fmt: skip
    print(f"classify: {right}/{n} = {100 * right / n:.1f} % right; the truth's own classifier "
          f"(design values and spreads): {best}/{n} = {100 * best / n:.1f} %")  # fmt: skip


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="part", required=True)
    s = sub.add_parser("speed")
    s.add_argument("--groups", type=int, default=4)
    s.add_argument("--specimens", type=int, default=10)
    s.add_argument("--sessions", type=int, default=10)
    s.add_argument("--forms", default=None, help="fit --forms [default: the fit's default]")
    s.add_argument("--dir", default=None, help="work folder (kept) [default: a new temporary one]")
    c = sub.add_parser("calibration")
    c.add_argument("--studies", type=int, default=400)
    c.add_argument("--specimens", type=int, default=10)
    c.add_argument("--sessions", type=int, default=10)
    c.add_argument("--seed", type=int, default=20261125)
    u = sub.add_parser("cpu")
    u.add_argument("--groups", type=int, default=4)
    u.add_argument("--specimens", type=int, default=10)
    u.add_argument("--sessions", type=int, default=10)
    u.add_argument("--forms", default="paper", help="fit --forms [default: paper]")
    u.add_argument("--dir", default=None, help="work folder (kept) [default: a new temporary one]")
    k = sub.add_parser("classify")
    k.add_argument("--catalogue", required=True)
    a = ap.parse_args(argv)
    parts = {"speed": speed, "calibration": calibration, "classify": classify, "cpu": cpu}
    parts[a.part](a)


if __name__ == "__main__":
    main()
