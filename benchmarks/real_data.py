"""Import and fit every recording of data/ with the commands of data/recordings.json, and
print what each fit explains: the law chosen, its coefficients, and the prediction error
on the held-out end of the recording (the table of docs/real-data.md).

Usage::

    python benchmarks/real_data.py [--only NAME]

Each recording is imported into a fresh HDF5 file and fitted as a user would, through
the command line (in process); the figures come from the parameter file it writes.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from click.testing import CliRunner

from tissuecli.cli import cli
from tissuecli.identify import whiten
from tissuecli.identify.whiten import LIKELIHOODS

DATA = Path(__file__).resolve().parents[1] / "data"


def manifest() -> list[dict[str, Any]]:
    """The recordings and their commands (data/recordings.json)."""
    return json.loads((DATA / "recordings.json").read_text())["recordings"]


def run(entry: dict[str, Any], workdir: Path) -> dict[str, Any]:
    """Import and fit one recording; returns the parameter file, with the run's output
    (``"output"``) and wall time (``"seconds"``) added.

    Raises
    ------
    RuntimeError
        If either command fails, with its output.
    """
    h5, params = workdir / f"{Path(entry['file']).stem}.h5", workdir / "params.json"
    params.unlink(missing_ok=True)
    runner = CliRunner()
    start = time.perf_counter()
    outputs = []
    for args in (
        ["import", str(DATA / entry["file"]), "--out", str(h5), *entry["import"]],
        ["fit", str(h5), "--out", str(params), *entry["fit"]],
    ):
        result = runner.invoke(cli, args)
        outputs.append(result.output)
        if result.exit_code != 0:
            raise RuntimeError(f"tissuecli {' '.join(args)}:\n{result.output}")
    doc = json.loads(params.read_text())
    doc["output"] = "\n".join(outputs)
    doc["seconds"] = time.perf_counter() - start
    return doc


def row(entry: dict[str, Any], doc: dict[str, Any]) -> str:
    """One line of the table: recording, law, coefficients, fitted and held-out R^2, error."""
    law = doc["law"]
    terms = ", ".join(
        f"{t['symbol']} = {t['mean']:.4g} ± {t['sd']:.2g} {t['unit']}" for t in law["terms"]
    )
    v = doc["validation"]
    kind = "measured" if entry["measured"] else "simulated"
    return (
        f"| `{entry['file']}` ({kind}) | {law['name']} | {terms} | {v['r2_fitted']:.3f} | "
        f"{v['r2_held_out']:.3f} | {v['rms_N']:.3g} N of {v['force_sd_N']:.3g} N | "
        f"{doc['seconds']:.1f} s |"
    )


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", default=None, help="Run the recordings whose file name has this.")
    parser.add_argument("--likelihood", choices=sorted(LIKELIHOODS), help="the fits' likelihood")
    args = parser.parse_args(argv)
    if args.likelihood:
        whiten.DEFAULT_LIKELIHOOD = args.likelihood
    print(
        "| recording | law | coefficients (posterior mean ± SD) | R² fitted | R² held out | "
        "held-out RMS error of force SD | import + fit |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- |")
    docs = []
    with tempfile.TemporaryDirectory() as tmp:
        for entry in manifest():
            if args.only and args.only not in entry["file"]:
                continue
            doc = run(entry, Path(tmp))
            print(row(entry, doc), flush=True)
            print(f"{entry['file']}: {doc['data']['effective_samples']:.0f} effective samples of "
                  f"{doc['data']['samples_used']}",
                  file=sys.stderr, flush=True)  # fmt: skip
            docs.append(doc)
    return docs


if __name__ == "__main__":
    main(sys.argv[1:])
