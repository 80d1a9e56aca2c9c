"""CPU of the phantom's plain fit and of its shape chain, for two source trees taking
turns (a commit before a change and after it, checked out side by side), seed by seed,
with the load average: a speed change measured under one load. Each tree's figures
come from a child process importing ``tissuecli`` from that tree; the chosen law's
figures are compared between the trees (``same`` when every figure is equal)::

    git worktree add /tmp/before COMMIT
    python benchmarks/shape_chain_cpu.py /tmp/before . 0 1 2 3
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve()


def child(root: Path, seed: str) -> None:
    """Fit the phantom at ``seed`` with the tissuecli of ``root``; print one JSON line."""
    sys.path[:0] = [str(root), str(root / "benchmarks")]
    import tissuecli.identify.sampling as sampling

    assert str(root) in sampling.__file__, sampling.__file__
    spent: list[tuple[float, int]] = []
    original = sampling.sample_shapes

    def timed(*args, **kwargs):  # type: ignore[no-untyped-def]
        start = time.process_time()
        out = original(*args, **kwargs)
        spent.append((time.process_time() - start, out[1]["steps"]))
        return out

    sampling.sample_shapes = timed
    import real_data

    entry = next(e for e in real_data.manifest() if e["file"].startswith("phantom"))
    with tempfile.TemporaryDirectory() as tmp:
        start = time.process_time()
        doc = real_data.run({**entry, "fit": ["--seed", seed]}, Path(tmp))
        cpu = time.process_time() - start
    name = doc["law"]["name"]
    print(json.dumps({"law": name, "p": doc["law"]["probability"], "cpu": cpu,
                      "chain": spent[0][0] if spent else 0.0,
                      "steps": spent[0][1] if spent else 0,
                      "figures": doc["laws"][name]}, default=str, sort_keys=True))  # fmt: skip


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        child(Path(sys.argv[2]).resolve(), sys.argv[3])
        return
    if len(sys.argv) < 4:
        sys.exit("usage: python benchmarks/shape_chain_cpu.py BEFORE_TREE AFTER_TREE SEED ...")
    trees = [Path(a).resolve() for a in sys.argv[1:3]]
    print(f"load average {', '.join(f'{v:.1f}' for v in os.getloadavg())}", flush=True)
    for seed in sys.argv[3:]:
        docs = []
        for label, root in zip(("before", "after"), trees, strict=True):
            env = {**os.environ, "PYTHONPATH": str(root)}
            out = subprocess.run([sys.executable, str(HERE), "--child", str(root), seed],
                                 env=env, capture_output=True, text=True, check=True)  # fmt: skip
            doc = json.loads(out.stdout.strip().splitlines()[-1])
            docs.append(doc)
            print(f"{label} seed {seed}: {doc['law']} (P {doc['p']:.3f}), import and fit CPU "
                  f"{doc['cpu']:.2f} s, shape chain {doc['chain']:.2f} s over {doc['steps']} "
                  "steps", flush=True)  # fmt: skip
        same = docs[0]["figures"] == docs[1]["figures"]
        print(f"seed {seed}: the chosen law's figures {'same' if same else 'differ'}", flush=True)
    print(f"load average {', '.join(f'{v:.1f}' for v in os.getloadavg())}", flush=True)


if __name__ == "__main__":
    main()
