"""The live view under load: a simulated forceps recorded with ``record --live`` while
several clients poll ``/api/state`` as the page does and one client stalls.

Usage::

    python benchmarks/live_view.py --duration 30 --rates 1000,10000 --clients 4

For each rate, with and without online identification, it records twice from the
same simulator settings, without the live view and with it (N polling clients and one
that asks and never reads), and prints the samples stored, lost and bad, the longest
time the recorder received nothing (``gap``: a stall of the recorder or of the
simulator), the CPU use (fraction of one core, start-up included) of the recorder's
process alone, of the live view's server process and of the simulator, each client's
updates a second, and the sample-to-screen latency: the time a client has the
document less the time the newest sample in it arrived at the recorder, both on the
machine's monotonic clock (the recorder and the clients are processes of one
machine). A page adds its drawing (a frame, at most 17 ms at 60 Hz) to that.

With ``--loop`` it records instead in this process, without the live view, with a
timer round each part of the acquisition loop, and prints the longest times between
two blocks of samples (with how much of each the loop's thread ran: little means it
waited for a core), the garbage collector's longest pause and each part's longest
call::

    python benchmarks/live_view.py --loop --duration 15 --rates 10000
"""

from __future__ import annotations

import argparse
import http.client
import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from tissuecli import formats
from tissuecli.sim.process import SimulatorProcess

#: a page waits this long between the start of one poll and the next, s
POLL_S = 0.05
#: CPU use of the recorder's children and the simulator is sampled this often, s
SAMPLE_CPU_S = 0.2
TICKS = os.sysconf("SC_CLK_TCK")


def cpu_s(pid: int) -> float:
    """User and system CPU time of a running process so far, s (0 once it is gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / TICKS


def children(pid: int) -> list[int]:
    try:
        return [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


def watch_cpu(recorder: int, sim: int, stop: threading.Event, seen: dict[int, float]) -> None:
    """Keep the latest CPU time of the recorder's children (the live view's server)
    and of the simulator, until ``stop``."""
    while not stop.wait(SAMPLE_CPU_S):
        for pid in [*children(recorder), sim]:
            seen[pid] = max(seen.get(pid, 0.0), cpu_s(pid))


def poll(host: str, port: int, stop: threading.Event, out: list[tuple[float, float]]) -> None:
    """Ask for /api/state like the page: one keep-alive connection, at most every 50 ms;
    keep (time received, latency) for each document with a sample."""
    conn = http.client.HTTPConnection(host, port, timeout=10)
    while not stop.is_set():
        sent = time.monotonic()
        try:
            conn.request("GET", "/api/state")
            doc = json.loads(conn.getresponse().read())
        except (OSError, http.client.HTTPException, ValueError):
            break  # the recording ended
        now = time.monotonic()
        if doc["newest_sample_monotonic_s"] is not None:
            out.append((now, now - doc["newest_sample_monotonic_s"]))
        stop.wait(max(0.0, POLL_S - (time.monotonic() - sent)))
    conn.close()


def stall(host: str, port: int) -> socket.socket:
    """A client that asks for the state 500 times and never reads an answer."""
    s = socket.socket()
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1024)
    s.connect((host, port))
    s.setblocking(False)
    try:
        s.send(b"GET /api/state HTTP/1.1\r\nHost: x\r\n\r\n" * 500)
    except BlockingIOError:
        pass
    return s


def run(
    rate: float, duration: float, clients: int, live: bool, root: Path, extra: list[str]
) -> dict[str, float]:
    tag = f"r{int(rate)}{'live' if live else ''}{len(extra)}"
    out = root / f"{tag}.h5"
    args = ["--quiet", "--duration", str(duration), "--session", "bench", "--out", str(out)]
    with SimulatorProcess("forceps", root / f"f{tag}", ["--rate", str(rate)]) as sim:
        assert sim.process is not None
        cmd = [sys.executable, "-m", "tissuecli", "record", "--port", str(sim.link), *args]
        cmd += extra
        t0 = time.monotonic()
        sim_cpu0 = cpu_s(sim.process.pid)
        proc = subprocess.Popen(
            cmd + (["--live"] if live else []),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        samples: list[list[tuple[float, float]]] = [[] for _ in range(clients)]
        stop = threading.Event()
        seen: dict[int, float] = {}
        threads = [threading.Thread(target=watch_cpu, args=(proc.pid, sim.process.pid, stop, seen))]
        threads[0].start()
        stalled = None
        if live:
            line = proc.stdout.readline() if proc.stdout else ""
            host, port = line.split("http://", 1)[1].strip().rstrip("/").rsplit(":", 1)
            stalled = stall(host, int(port))
            for k in range(clients):
                th = threading.Thread(target=poll, args=(host, int(port), stop, samples[k]))
                th.start()
                threads.append(th)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.monotonic() - t0
        stop.set()
        for th in threads:
            th.join()
        sim_cpu = seen.pop(sim.process.pid, 0.0) - sim_cpu0
        if stalled is not None:
            stalled.close()
        err = proc.stderr.read() if proc.stderr else ""
    if status != 0:
        raise RuntimeError(err.strip().splitlines()[-1] if err.strip() else f"exit {status}")
    row = formats.list_sessions(out)[0]
    host_time = formats.read_session(out, "bench", raw=True).meta["raw"]["raw/host_time"]
    view_cpu = sum(seen.values())  # the server's process (its CPU is in the recorder's
    total_cpu = usage.ru_utime + usage.ru_stime  # rusage once waited for)
    result = {
        "rate_hz": rate,
        "live": live,
        "expected": round(rate * duration),
        "stored": row["samples"],
        "lost": row["frames_lost"],
        "bad": row["frames_bad"],
        "gap_ms": float(np.diff(host_time).max()) * 1e3,
        "cpu": (total_cpu - view_cpu) / wall,
        "view_cpu": view_cpu / wall,
        "sim_cpu": sim_cpu / wall,
    }
    if live:
        # the first and last second hold the page's start and the recording's end
        kept = [[(t, lat) for t, lat in c if c[0][0] + 1 < t < c[-1][0] - 1] for c in samples]
        lat = np.array([lat for c in kept for _, lat in c])
        rates = [(len(c) - 1) / (c[-1][0] - c[0][0]) for c in kept if len(c) > 1]
        result.update(
            updates_min=min(rates),
            updates_mean=float(np.mean(rates)),
            lat_median=float(np.median(lat)),
            lat_95=float(np.percentile(lat, 95)),
            lat_max=float(lat.max()),
        )
    return result


def loop_parts(rate: float, duration: float, identify: bool, root: Path) -> None:
    """Record in this process with a timer round each part of the acquisition loop."""
    import collections
    import functools
    import gc

    import tissuecli.app.record as rec
    import tissuecli.formats.writer as wr
    import tissuecli.hw.stream as st

    calls: dict[str, list[tuple[float, float]]] = collections.defaultdict(list)

    def timed(cls: type, name: str, label: str) -> None:
        f = getattr(cls, name)

        @functools.wraps(f)
        def wrapper(*a: object, **k: object) -> object:
            t = time.perf_counter()
            try:
                return f(*a, **k)
            finally:
                calls[label].append((time.monotonic(), time.perf_counter() - t))

        setattr(cls, name, wrapper)

    for cls, name, label in [
        (st.Stream, "poll", "read the port, waits too"),
        (rec._Recording, "_take", "a block, all of it"),
        (wr.SeriesWriter, "append", "writer append"),
        (wr.SeriesWriter, "flush", "writer flush"),
        (rec.Online, "__call__", "identification update"),
        (rec.Online, "estimate", "identification estimate"),
    ]:
        timed(cls, name, label)
    pauses: list[float] = []
    started: list[float] = []
    gc.callbacks.append(
        lambda phase, _: (
            started.append(time.perf_counter())
            if phase == "start"
            else pauses.append(time.perf_counter() - started[-1])
        )
    )
    blocks: list[tuple[float, float]] = []
    tag = f"loop{int(rate)}{identify}"
    with SimulatorProcess("forceps", root / f"f{tag}", ["--rate", str(rate)]) as sim:
        t0 = time.monotonic()
        r = rec.record(
            str(sim.link), root / f"{tag}.h5", "bench", duration_s=duration,
            identify=identify, status_interval_s=0.5, on_status=lambda s: None,
            on_samples=lambda b: blocks.append((time.monotonic(), time.thread_time())),
        )  # fmt: skip
    gc.callbacks.pop()
    print(
        f"{rate:g} Hz, identification {'on' if identify else 'off'}, status every 0.5 s: "
        f"{r.samples} stored, {r.lost_frames} lost, {r.bad_frames} bad"
    )
    at = np.array(blocks)
    wall, ran = np.diff(at[:, 0]), np.diff(at[:, 1])
    for k in np.argsort(wall)[-3:][::-1]:
        print(
            f"  {wall[k] * 1e3:6.0f} ms between blocks at {at[k, 0] - t0:5.2f} s, "
            f"the loop's thread ran {ran[k] * 1e3:4.0f} ms of it"
        )
    print(
        f"  garbage collector: {len(pauses)} passes, longest {max(pauses, default=0) * 1e3:.0f} ms"
    )
    for label, v in calls.items():
        d = np.array([x for _, x in v])
        i = int(np.argmax(d))
        print(
            f"  {label:24s} {len(d):6d} calls, {d.sum() / duration:6.1%} of the time, "
            f"longest {d.max() * 1e3:6.1f} ms at {v[i][0] - t0:5.2f} s"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--duration", type=float, default=30.0)
    parser.add_argument("--rates", default="1000,10000")
    parser.add_argument("--clients", type=int, default=4, help="polling clients (at least 1)")
    parser.add_argument(
        "--identify",
        default="yes,no",
        help="with (yes) and/or without (no) online identification, comma-separated",
    )
    parser.add_argument(
        "--loop", action="store_true", help="time the parts of the acquisition loop instead"
    )
    opts = parser.parse_args()
    if opts.loop:
        with tempfile.TemporaryDirectory() as tmp:
            for rate in (float(r) for r in opts.rates.split(",")):
                for identify in opts.identify.split(","):
                    loop_parts(rate, opts.duration, identify == "yes", Path(tmp))
        return
    print(
        f"{'rate Hz':>7} {'ident':>5} {'live':>4} {'expected':>8} {'stored':>8} {'lost':>5} "
        f"{'bad':>3} {'gap ms':>6} {'CPU rec':>7} {'view':>5} {'sim':>5} "
        f"{'upd/s min':>9} {'mean':>5} {'latency ms: median':>18} {'95%':>5} {'max':>5}"
    )
    with tempfile.TemporaryDirectory() as tmp:
        for rate in (float(r) for r in opts.rates.split(",")):
            for identify in opts.identify.split(","):
                for live in (False, True):
                    extra = [] if identify == "yes" else ["--no-identify"]
                    try:
                        r = run(rate, opts.duration, opts.clients, live, Path(tmp), extra)
                    except RuntimeError as exc:  # a run the machine starved: say so, go on
                        print(
                            f"{rate:7.0f} {identify:>5} {'yes' if live else 'no':>4} failed: {exc}"
                        )
                        continue
                    shown = (
                        f"{r['updates_min']:9.1f} {r['updates_mean']:5.1f} "
                        f"{r['lat_median'] * 1e3:18.1f} {r['lat_95'] * 1e3:5.0f} "
                        f"{r['lat_max'] * 1e3:5.0f}"
                        if live
                        else ""
                    )
                    print(
                        f"{rate:7.0f} {identify:>5} {'yes' if live else 'no':>4} "
                        f"{r['expected']:8d} {r['stored']:8d} {r['lost']:5d} {r['bad']:3d} "
                        f"{r['gap_ms']:6.0f} {r['cpu']:7.1%} {r['view_cpu']:5.1%} "
                        f"{r['sim_cpu']:5.1%} {shown}",
                        flush=True,
                    )


if __name__ == "__main__":
    main()
