"""What the default fit reports on fixed-seed sessions of every family, written as JSON,
and the comparison of two such files: to check that a change meant only to make the fit
faster leaves every result as it was.

Usage::

    python benchmarks/fit_fingerprint.py write OUT.json      # fit the sessions
    python benchmarks/fit_fingerprint.py compare A.json B.json

``write`` fits twelve sessions (the paper form of ``search_timing.py`` with grasp
detection at 16 and at 8 bits, each family of :mod:`tissuecli.sim.families` as recorded by a random
operator, a constant-speed pull and a ramp-and-hold test) and keeps of each the chosen
law, the warnings, and per law its status, probability, ln evidence, reason, flags,
posterior means, SDs and 95 % intervals (coefficients, noise and shape). ``compare``
prints, per session, the largest difference of each kind: text must match exactly,
ln evidence to 1e-6 nats, every other figure to a relative 1e-9. Exit status 1 if any
differs.
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "identify"))

from lab_protocols import constant_speed, relaxation  # noqa: E402

from tissuecli.core.session import Session  # noqa: E402
from tissuecli.identify import BayesianFit  # noqa: E402
from tissuecli.sim.families import FAMILIES  # noqa: E402
from tissuecli.sim.synth import ForcepsModel, Sensors, random_session, synthesize  # noqa: E402

LN_Z_NATS = 1e-6
RELATIVE = 1e-9


def sessions() -> dict[str, tuple[Session, str]]:
    """The sessions fitted, by label: the session and its ``grasps`` option."""
    out = {
        "paper form (search_timing)": (
            synthesize(ForcepsModel(seed=1, sensors=Sensors(bits=16)), 10.0)[0],
            "all",
        ),
        "paper form at 8 bits (search_timing)": (
            synthesize(ForcepsModel(seed=1, sensors=Sensors(bits=8)), 10.0)[0],
            "all",
        ),
    }
    for label, tissue in FAMILIES.items():
        s = random_session(tissue, rate_hz=1000.0, seed=300, duration_s=10.0, bits=12)[0]
        out[label] = (s, "all")
    out["constant-speed pull"] = (constant_speed(0)[0], "none")
    out["ramp and hold"] = (relaxation(0)[0], "none")
    return out


def _floats(v: Any) -> list[float]:
    return [float(x) for x in np.ravel(np.asarray(v, dtype=float))]


def fingerprint(est: BayesianFit) -> dict[str, Any]:
    """What one fit reports."""
    laws = []
    for r in est.results_:
        post = r.posterior
        law: dict[str, Any] = {
            "name": r.name,
            "status": r.status,
            "reason": r.reason,
            "flags": list(r.flags),
            "probability": float(r.probability),
            "ln_evidence": float(r.ln_evidence),
        }
        if post is not None:
            law["figures"] = {
                "mean": _floats(post.mean),
                "sd": _floats(post.sd),
                "ci95": _floats(post.ci95),
                "sigma": [post.sigma_mean, *post.sigma_ci95],
            }
        if r.shape_posterior:
            law["figures"]["shape"] = [
                float(x)
                for name in sorted(r.shape_posterior)
                for x in (r.shape_posterior[name]["mean"], r.shape_posterior[name]["sd"],
                          *r.shape_posterior[name]["ci95"])
            ]  # fmt: skip
        laws.append(law)
    return {"best": est.best_.name, "warnings": list(est.warnings_), "laws": laws}


def write(path: str) -> None:
    out = {}
    for label, (s, grasps) in sessions().items():
        c0 = time.process_time()
        est = BayesianFit(grasps=grasps).fit(s)
        out[label] = fingerprint(est)
        print(f"{label}: {est.best_.name}, CPU {time.process_time() - c0:.2f} s", flush=True)
    Path(path).write_text(json.dumps(out, indent=1))


def _rel(a: list[float], b: list[float]) -> float:
    if len(a) != len(b):
        return math.inf
    worst = 0.0
    for x, y in zip(a, b, strict=True):
        if x == y or (math.isnan(x) and math.isnan(y)):
            continue
        worst = max(worst, abs(x - y) / max(abs(x), abs(y), 1e-300))
    return worst


def compare(path_a: str, path_b: str) -> bool:
    a, b = json.loads(Path(path_a).read_text()), json.loads(Path(path_b).read_text())
    same = True
    for label in a:
        fa, fb = a[label], b.get(label)
        problems = []
        if fb is None:
            print(f"{label}: missing")
            same = False
            continue
        if fa["best"] != fb["best"]:
            problems.append(f"best {fa['best']} vs {fb['best']}")
        if fa["warnings"] != fb["warnings"]:
            problems.append(f"warnings {fa['warnings']} vs {fb['warnings']}")
        la = {r["name"]: r for r in fa["laws"]}
        lb = {r["name"]: r for r in fb["laws"]}
        if list(la) != list(lb):
            problems.append(f"laws {list(la)} vs {list(lb)}")
        dz, dp, df = 0.0, 0.0, 0.0
        for name in set(la) & set(lb):
            ra, rb = la[name], lb[name]
            for key in ("status", "reason", "flags"):
                if ra[key] != rb[key]:
                    problems.append(f"{name} {key}: {ra[key]!r} vs {rb[key]!r}")
            za, zb = ra["ln_evidence"], rb["ln_evidence"]
            if za != zb:
                dz = max(dz, abs(za - zb) if math.isfinite(za - zb) else math.inf)
            dp = max(dp, _rel([ra["probability"]], [rb["probability"]]))
            fa_, fb_ = ra.get("figures", {}), rb.get("figures", {})
            for key in set(fa_) | set(fb_):
                df = max(df, _rel(fa_.get(key, []), fb_.get(key, [])))
        if dz > LN_Z_NATS or dp > RELATIVE or df > RELATIVE:
            problems.append(f"figures differ: ln Z {dz:.2g} nats, P {dp:.2g}, others {df:.2g}")
        same &= not problems
        status = "; ".join(problems) if problems else "same"
        print(f"{label}: {status} (ln Z {dz:.2g} nats, P {dp:.2g}, intervals {df:.2g})")
    return same


def main() -> None:
    if len(sys.argv) == 3 and sys.argv[1] == "write":
        write(sys.argv[2])
    elif len(sys.argv) == 4 and sys.argv[1] == "compare":
        sys.exit(0 if compare(sys.argv[2], sys.argv[3]) else 1)
    else:
        sys.exit(__doc__)


if __name__ == "__main__":
    main()
