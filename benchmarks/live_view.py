"""The live view under load: a simulated forceps recorded with ``record --live`` while
several clients poll ``/api/state`` as the page does and one client stalls.

Usage::

    python benchmarks/live_view.py --duration 30 --rates 1000,10000 --clients 4

For each rate it records twice from the same simulator settings, with the live view
(N polling clients and one that asks and never reads) and without it, and prints the
samples stored and lost, the recorder's CPU use (fraction of one core, start-up
included), each client's updates a second, and the sample-to-screen latency: the time a
client has the document less the time the newest sample in it arrived at the recorder,
both on the machine's monotonic clock (the recorder and the clients are processes of
one machine). A page adds its drawing (a frame, at most 17 ms at 60 Hz) to that.
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
    tag = f"r{int(rate)}{'live' if live else ''}"
    out = root / f"{tag}.h5"
    args = ["--quiet", "--duration", str(duration), "--session", "bench", "--out", str(out)]
    with SimulatorProcess("forceps", root / f"f{tag}", ["--rate", str(rate)]) as sim:
        cmd = [sys.executable, "-m", "tissuecli", "record", "--port", str(sim.link), *args]
        cmd += extra
        t0 = time.monotonic()
        proc = subprocess.Popen(
            cmd + (["--live"] if live else []),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        samples: list[list[tuple[float, float]]] = [[] for _ in range(clients)]
        stop = threading.Event()
        threads: list[threading.Thread] = []
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
        if stalled is not None:
            stalled.close()
        err = proc.stderr.read() if proc.stderr else ""
    if status != 0:
        raise SystemExit(f"record failed at {rate} Hz: {err}")
    row = formats.list_sessions(out)[0]
    result = {
        "rate_hz": rate,
        "live": live,
        "expected": round(rate * duration),
        "stored": row["samples"],
        "lost": row["frames_lost"],
        "cpu": (usage.ru_utime + usage.ru_stime) / wall,
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--duration", type=float, default=30.0)
    parser.add_argument("--rates", default="1000,10000")
    parser.add_argument("--clients", type=int, default=4, help="polling clients (at least 1)")
    parser.add_argument(
        "--no-identify", action="store_true", help="record without online identification"
    )
    opts = parser.parse_args()
    print(
        f"{'rate Hz':>8} {'live':>5} {'expected':>9} {'stored':>9} {'lost':>5} {'CPU':>6} "
        f"{'upd/s min':>9} {'mean':>6} {'latency ms: median':>19} {'95%':>6} {'max':>6}"
    )
    with tempfile.TemporaryDirectory() as tmp:
        for rate in (float(r) for r in opts.rates.split(",")):
            for live in (False, True):
                extra = ["--no-identify"] if opts.no_identify else []
                r = run(rate, opts.duration, opts.clients, live, Path(tmp), extra)
                shown = (
                    f"{r['updates_min']:9.1f} {r['updates_mean']:6.1f} "
                    f"{r['lat_median'] * 1e3:19.1f} {r['lat_95'] * 1e3:6.1f} "
                    f"{r['lat_max'] * 1e3:6.1f}"
                    if live
                    else ""
                )
                print(
                    f"{rate:8.0f} {'yes' if live else 'no':>5} {r['expected']:9d} "
                    f"{r['stored']:9d} {r['lost']:5d} {r['cpu']:6.1%} {shown}",
                    flush=True,
                )


if __name__ == "__main__":
    main()
