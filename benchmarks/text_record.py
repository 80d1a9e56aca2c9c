"""Plain-text loggers: how fast each line dialect is read, and what a recording from the
simulated text logger keeps, the figures behind docs/recording.md.

Usage::

    python benchmarks/text_record.py                          # both parts
    python benchmarks/text_record.py --part parse --lines 100000
    python benchmarks/text_record.py --part record --rates 60,1000 --duration 5

``parse``: lines of each dialect read by :mod:`tissuecli.hw.text`, lines per second of
one core (a 1 kHz logger needs 1000).

``record``: the simulated text logger (its own process, on a real pty, 1 % of lines
broken) recorded by ``record --protocol text`` at each rate: samples kept, malformed
lines counted against the broken lines printed in the same span, lines lost, and the
recorder's CPU time per second of recording.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from tissuecli import formats  # noqa: E402
from tissuecli.app.record import record as record_session  # noqa: E402
from tissuecli.hw.text import MalformedLine, sniff_dialect  # noqa: E402
from tissuecli.sim.process import SimulatorProcess  # noqa: E402
from tissuecli.sim.synth import ForcepsModel  # noqa: E402
from tissuecli.sim.textlogger import TextLogger  # noqa: E402


def parse(n: int) -> None:
    print(f"## lines read per second, one core ({n} lines each)")
    model = ForcepsModel(seed=1)
    for fmt in ("csv", "plotter", "teleplot"):
        logger = TextLogger(model, format=fmt, broken=0.01)
        text = b"".join(logger.lines(0, n // (2 if fmt == "teleplot" else 1)))
        lines = text.decode("utf-8", "replace").splitlines()
        dialect = sniff_dialect(lines[:64])
        dialect.select(dialect.names)
        dialect.reset()
        start = time.perf_counter()
        rows = bad = 0
        for line in lines:
            try:
                rows += bool(dialect.read(line))
            except MalformedLine:
                bad += 1
        took = time.perf_counter() - start
        print(f"{fmt:9s} {len(lines) / took:12,.0f} lines/s  {rows} rows, {bad} malformed")


def record(rates: list[float], duration: float) -> None:
    print(f"## recording {duration:g} s from the simulated text logger, 1 % of lines broken")
    print("rate Hz  samples  malformed  broken printed  lost  CPU s/s")
    for rate in rates:
        with tempfile.TemporaryDirectory() as tmp:
            link = Path(tmp) / "logger"
            args = ["--protocol", "text", "--rate", f"{rate:g}", "--broken", "0.01", "--seed", "2"]
            with SimulatorProcess("forceps", link, args):
                cpu = time.process_time()
                res = record_session(
                    str(link), Path(tmp) / "t.h5", "t", protocol="text", duration_s=duration,
                    identify=False,
                )  # fmt: skip
                cpu = time.process_time() - cpu
            s = formats.read_session(Path(tmp) / "t.h5")
            k0 = int(s.meta["device_stamp_first"] * rate // 1e6)
            k = k0 + np.rint(s.time * rate).astype(int)
            logger = TextLogger(ForcepsModel(seed=2, rate_hz=rate), broken=0.01)
            printed = int(logger.broken_at(np.arange(k0, k[-1] + 1)).sum())
            print(
                f"{rate:7g} {res.samples:8d} {s.meta['lines_malformed']:10d} "
                f"{printed:15d} {res.lost_frames:5d} {cpu / duration:8.3f}"
            )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--part", choices=["parse", "record", "all"], default="all")
    parser.add_argument("--lines", type=int, default=100_000)
    parser.add_argument("--rates", default="60,250,1000")
    parser.add_argument("--duration", type=float, default=5.0)
    a = parser.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    if a.part in ("parse", "all"):
        parse(a.lines)
    if a.part in ("record", "all"):
        record([float(r) for r in a.rates.split(",")], a.duration)


if __name__ == "__main__":
    main()
