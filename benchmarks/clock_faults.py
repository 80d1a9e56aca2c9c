"""Clock drift and clock faults: the figures behind docs/recording.md.

Usage::

    python benchmarks/clock_faults.py                      # everything
    python benchmarks/clock_faults.py --part drift --repeats 3 --durations 5,30
    python benchmarks/clock_faults.py --part synthetic --seeds 200
    python benchmarks/clock_faults.py --part faults

``drift``: a simulated forceps (its own process, on a real pty) at 0 and 200 ppm is
recorded for each duration; the drift is fitted from the stored arrival times by the
old least-squares fit and by the lower-envelope fit that replaced it, which also says
whether time was rescaled.

``synthetic``: sessions of known drift with one-sided random latency (exponential,
quantised to 1 ms USB frames) and bursts (a stall of 50-300 ms, then the backlog
at once), fitted by both methods: error quantiles, and how often the drift counted
as resolved.

``faults``: a scripted forceps on a pty sends valid-CRC frames with absurd content
(clock jumps and steps, backwards clocks, sequence restarts, absurd sequence numbers,
garbage, losses); each trial prints what was injected and what the recorder counted.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from tests.app.fakedevice import TICKS, FakeForceps, good_info, sample_frames  # noqa: E402
from tissuecli import formats  # noqa: E402
from tissuecli.app.record import record  # noqa: E402
from tissuecli.core.clock import fit_clock_map, fit_clock_map_lsq  # noqa: E402
from tissuecli.core.errors import TissueError  # noqa: E402
from tissuecli.sim.process import SimulatorProcess  # noqa: E402


def _device_and_host(path: Path, session: str) -> tuple[np.ndarray, np.ndarray]:
    s = formats.read_session(path, session, raw=True)
    cmap = s.meta.get("clock_map") or {}
    device = s.time / cmap["slope"] if cmap.get("time_rescaled") else s.time
    return device, s.meta["raw"]["raw/host_time"]


def part_drift(durations: list[float], drifts: list[float], repeats: int) -> None:
    print("simulated forceps over a pty, recorded in this process")
    print(
        f"{'drift':>6} {'dur s':>6} {'run':>4} {'old LSQ ppm':>12} "
        f"{'new ppm':>9} {'+-':>6} {'rescaled':>9}"
    )
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        for drift in drifts:
            for duration in durations:
                for run in range(repeats):
                    link = root / f"f{drift}-{duration}-{run}"
                    args = ["--drift-ppm", str(drift), "--seed", str(run)]
                    with SimulatorProcess("forceps", link, args) as sim:
                        out = root / f"{drift}-{duration}-{run}.h5"
                        res = record(str(sim.link), out, "s", duration_s=duration)
                    device, host = _device_and_host(out, "s")
                    old = fit_clock_map_lsq(device, host)
                    new = fit_clock_map(device, host)
                    assert old is not None and new is not None
                    print(
                        f"{drift:6g} {duration:6g} {run:4d} {old.drift_ppm:12.1f} "
                        f"{new.drift_ppm:9.1f} {new.drift_uncertainty_ppm:6.1f} "
                        f"{str(res.time_rescaled):>9}"
                    )


def _synthetic(
    drift_ppm: float, duration_s: float, rng: np.random.Generator, bursts: int
) -> tuple[np.ndarray, np.ndarray]:
    """Device time of 1 kHz samples and their host arrival: latency one-sided, in 1 ms
    USB frames, a host wake-up delay, plus ``bursts`` stalls after which the backlog
    arrives at once."""
    n = int(duration_s * 1000)
    device = np.arange(n) * 1e-3
    true = device / (1.0 + drift_ppm * 1e-6)  # host time at which each sample is taken
    latency = 0.2e-3 + rng.exponential(0.4e-3, n)
    phase = rng.uniform(0, 1e-3)  # of the USB frames relative to the samples
    # delivered in 1 ms USB frames, then read by a host that wakes up a little late
    arrival = np.ceil((true + latency - phase) / 1e-3) * 1e-3 + phase
    arrival += rng.exponential(30e-6, n)
    for _ in range(bursts):
        start = rng.uniform(0, true[-1])
        stall = rng.uniform(0.05, 0.3)
        hit = (arrival > start) & (arrival < start + stall)
        arrival[hit] = start + stall
    arrival = np.maximum.accumulate(arrival)  # a serial line delivers in order
    return device, arrival


def part_synthetic(seeds: int) -> None:
    print(f"synthetic sessions, {seeds} seeds each: |error| quantiles in ppm, share resolved")
    print(
        f"{'drift':>6} {'dur s':>6} {'bursts':>6} | {'old median':>10} {'old 95%':>8} | "
        f"{'new median':>10} {'new 95%':>8} {'|err|<2u':>8} {'resolved':>8}"
    )
    for drift, duration, bursts in [
        (0, 5, 0),
        (0, 5, 2),
        (0, 30, 0),
        (0, 30, 3),
        (200, 5, 0),
        (200, 20, 2),
        (200, 30, 0),
        (200, 30, 3),
    ]:
        old, new, covered, resolved = [], [], 0, 0
        for seed in range(seeds):
            rng = np.random.default_rng(seed)
            d, h = _synthetic(drift, duration, rng, bursts)
            o, m = fit_clock_map_lsq(d, h), fit_clock_map(d, h)
            assert o is not None and m is not None
            old.append(abs(o.drift_ppm - drift))
            new.append(abs(m.drift_ppm - drift))
            covered += abs(m.drift_ppm - drift) <= 2 * m.drift_uncertainty_ppm
            resolved += m.resolved
        print(
            f"{drift:6g} {duration:6g} {bursts:6d} | {np.median(old):10.1f} "
            f"{np.quantile(old, 0.95):8.1f} | {np.median(new):10.1f} "
            f"{np.quantile(new, 0.95):8.1f} {covered / seeds:8.2f} {resolved / seeds:8.2f}"
        )


def _trial(name: str, injected: str, stream: list[bytes], duration: float | None) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "g.h5"
        with FakeForceps(good_info(), stream) as dev:
            try:
                res = record(dev.path, out, "s", duration_s=duration, idle_timeout_s=0.3)
                reason = res.stop_reason
            except TissueError as exc:
                reason = str(exc).split(";")[0].split(":")[0]
        try:
            s = formats.read_session(out, "s")
        except TissueError:
            print(f"{name:<28} {injected:<28} no session: {reason}")
            return
        m = s.meta
        increasing = bool(np.all(np.diff(s.time) > 0))
        print(
            f"{name:<28} {injected:<28} {len(s):6d} {s.time[-1]:7.3f} {str(increasing):>5} "
            f"{m['clock_jumps']:5d} {m['clock_steps']:5d} {m['sequence_restarts']:5d} "
            f"{m['frames_rejected']:5d} {m['frames_lost']:5d} {m['clock_wraps']:5d} "
            f"{m['frames_bad']:5d}  {reason}"
        )


def part_faults() -> None:
    rng = np.random.default_rng(7)
    n = 1500
    seq = np.arange(n) + 1000
    clk = np.arange(n) * TICKS + 123_456
    print("scripted forceps over a pty, 1 kHz, 1500 frames unless said otherwise")
    print(
        f"{'trial':<28} {'injected':<28} {'kept':>6} {'last s':>7} {'incr':>5} "
        f"{'jump':>5} {'step':>5} {'rest':>5} {'rej':>5} {'lost':>5} {'wrap':>5} {'bad':>5}  "
        "stop"
    )
    trials: list[tuple[str, str, list[bytes], float | None]] = []
    c = clk.copy()
    c[700] += 1 << 31
    trials.append(("clock +2^31 once", "1 jump", sample_frames(seq, c), None))
    c = clk.copy()
    c[[300, 600, 900, 1200]] = rng.integers(0, 1 << 32, 4)
    trials.append(("4 random stamps", "4 jumps", sample_frames(seq, c), None))
    c = clk.copy()
    c[500:] += 4_000_000
    trials.append(("clock +4 s lasting", "1 step; --duration 1.2", sample_frames(seq, c), 1.2))
    c = clk.copy()
    c[500:] -= 300_000
    trials.append(("clock -0.3 s lasting", "1 step", sample_frames(seq, c), None))
    s2, c = seq.copy(), clk.copy()
    s2[800:] = np.arange(n - 800) + 7
    c[800:] = np.arange(n - 800) * TICKS + 55
    trials.append(("device reset", "1 restart", sample_frames(s2, c), None))
    s2 = seq.copy()
    s2[[200, 400]] = rng.integers(0, 1 << 32, 2)
    trials.append(("2 absurd sequence numbers", "2 rejected, 2 lost", sample_frames(s2, clk), None))
    frames = sample_frames(seq, clk)
    frames = frames[:600] + [frames[599]] * 3 + frames[600:]
    trials.append(("a frame repeated 3 times", "3 rejected", frames, None))
    c = (clk + (1 << 32) - 700 * TICKS - 123_456) & 0xFFFFFFFF
    trials.append(("genuine 32-bit wrap", "1 wrap", sample_frames(seq, c), None))
    keep = rng.random(n) > 0.3
    first = int(np.argmax(keep))  # time 0 is the first frame received
    kept = np.flatnonzero(keep)
    kept = kept[kept < first + 1000]  # the frames of the first second
    trials.append(
        (
            "30 % loss, --duration 1",
            f"{kept[-1] - first + 1 - kept.size} lost among the kept",
            # an empty item keeps the pace: the device sampled, the line lost it
            [f if k else b"" for f, k in zip(sample_frames(seq, clk), keep, strict=True)],
            1.0,
        )
    )
    frames = sample_frames(seq, clk)
    garbage = [rng.integers(1, 256, 40, dtype=np.uint8).tobytes() + b"\0" for _ in range(50)]
    mixed: list[bytes] = []
    for i, f in enumerate(frames):
        mixed.append(f)
        if i % 30 == 0 and i // 30 < len(garbage):
            mixed.append(garbage[i // 30])
    trials.append(("garbage between frames", "50 bad frames", mixed, None))
    junk = sample_frames(rng.integers(0, 1 << 32, 40), rng.integers(0, 1 << 32, 40))
    frames = sample_frames(seq, clk)
    trials.append(
        (
            "40 random frames mid-stream",
            "40 rejected or jumps",
            frames[:700] + junk + frames[700:],
            None,
        )
    )
    junk = sample_frames(rng.integers(0, 1 << 32, 800), rng.integers(0, 1 << 32, 800))
    trials.append(("only random frames", "refused: nothing usable", junk, None))
    for name, injected, stream, duration in trials:
        _trial(name, injected, stream, duration)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--part", choices=["drift", "synthetic", "faults", "all"], default="all")
    ap.add_argument("--durations", default="5,30")
    ap.add_argument("--drifts", default="0,200")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seeds", type=int, default=200)
    args = ap.parse_args()
    if args.part in ("faults", "all"):
        part_faults()
        print()
    if args.part in ("synthetic", "all"):
        part_synthetic(args.seeds)
        print()
    if args.part in ("drift", "all"):
        part_drift(
            [float(x) for x in args.durations.split(",")],
            [float(x) for x in args.drifts.split(",")],
            args.repeats,
        )


if __name__ == "__main__":
    main()
