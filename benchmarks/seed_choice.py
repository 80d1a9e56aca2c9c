"""The law a plain ``tissuecli fit`` chooses for a recording of data/, seed by seed.

A fit's random numbers (the shape chain, the exact draws) should move intervals by their
Monte Carlo error, never the chosen law. This imports one recording of
``data/recordings.json`` and fits it with no options but ``--seed``, for each seed,
printing the chosen law, its probability, the CPU time and, where the shape of a law
was sampled, the chain's length::

    python benchmarks/seed_choice.py phantom 0 1 2 3
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import real_data  # noqa: E402


def main() -> None:
    if len(sys.argv) < 3:
        sys.exit("usage: python benchmarks/seed_choice.py RECORDING SEED [SEED ...]")
    name, seeds = sys.argv[1], [int(s) for s in sys.argv[2:]]
    entry = next(e for e in real_data.manifest() if e["file"].startswith(name))
    for seed in seeds:
        with tempfile.TemporaryDirectory() as tmp:
            start = time.process_time()
            doc = real_data.run({**entry, "fit": ["--seed", str(seed)]}, Path(tmp))
            cpu = time.process_time() - start
        law = doc["law"]["name"]
        chains = [
            f"{k}: {v['sampler']['shape_emcee']['steps']} steps"
            for k, v in doc["laws"].items()
            if "shape_emcee" in v.get("sampler", {})
        ]
        print(f"{entry['file']} seed {seed}: {law} (P {doc['law']['probability']:.3f}), "
              f"import and fit CPU {cpu:.2f} s; shape chains: {', '.join(chains) or 'none'}",
              flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
