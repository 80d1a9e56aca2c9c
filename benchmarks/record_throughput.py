"""Recording throughput: a simulated forceps at several rates, recorded over a real pty.

Usage::

    python benchmarks/record_throughput.py --duration 60 --rates 1000,10000,20000

Prints, per rate, the samples expected and stored, lost and bad frames, and the
recorder's CPU use (fraction of one core).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from tissuecli import formats
from tissuecli.sim.process import SimulatorProcess


def run(rate: float, duration: float, root: Path) -> dict[str, float]:
    out = root / f"r{int(rate)}.h5"
    with SimulatorProcess("forceps", root / f"forceps{int(rate)}", ["--rate", str(rate)]) as sim:
        t0 = time.monotonic()
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "tissuecli",
                "record",
                "--quiet",
                "--port",
                str(sim.link),
                "--out",
                str(out),
                "--session",
                "bench",
                "--duration",
                str(duration),
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.monotonic() - t0
        err = proc.stderr.read() if proc.stderr else ""
    if status != 0:
        raise SystemExit(f"record failed at {rate} Hz: {err}")
    row = formats.list_sessions(out)[0]
    return {
        "rate_hz": rate,
        "expected": round(rate * duration),
        "stored": row["samples"],
        "lost": row["frames_lost"],
        "bad": row["frames_bad"],
        "cpu_fraction": (usage.ru_utime + usage.ru_stime) / wall,
        "file_mb": out.stat().st_size / 1e6,
    }


def decode_rate(frames: int = 100_000) -> float:
    """Frames per second the host's decoder handles, on one core."""
    from tissuecli.hw.protocol import FrameDecoder, Sample, encode

    stream = b"".join(encode(Sample(k, k * 1000, -3, 120)) for k in range(frames))
    t0 = time.perf_counter()
    got = FrameDecoder().feed(stream)
    assert len(got) == frames
    return frames / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--rates", default="1000,10000,20000")
    args = ap.parse_args()
    print(
        f"{'rate Hz':>8} {'expected':>9} {'stored':>9} {'lost':>5} {'bad':>5} {'CPU':>6} {'MB':>7}"
    )
    print(f"decoder alone: {decode_rate():,.0f} frames/s on one core")
    with tempfile.TemporaryDirectory() as tmp:
        for rate in (float(r) for r in args.rates.split(",")):
            r = run(rate, args.duration, Path(tmp))
            print(
                f"{r['rate_hz']:8.0f} {r['expected']:9d} {r['stored']:9d} {r['lost']:5d} "
                f"{r['bad']:5d} {100 * r['cpu_fraction']:5.1f}% {r['file_mb']:7.2f}"
            )


if __name__ == "__main__":
    main()
