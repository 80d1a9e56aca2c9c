"""What the live view shows: the newest samples in a bounded ring, the recording status
and the running estimate, turned into the JSON of ``/api/state`` on request.

The recorder's acquisition loop only calls :meth:`LiveState.append` (a copy into a
preallocated ring under a lock held for microseconds); everything else (decimation,
the current grasp, JSON) runs in the server's threads, reading the ring outside the
lock: samples older than the newest count are never written again until the ring has
gone round, and it holds many times the longest window shown.
"""

from __future__ import annotations

import math
import threading
import time
from typing import Any

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

#: version of the ``/api/state`` document (docs/formats.md)
SCHEMA = 1
#: seconds of force and closure traces shown
TRACE_S = 10.0
#: longest force-closure loop shown, s; a grasp younger than MIN_LOOP_S shows the one before too
LOOP_S = 5.0
MIN_LOOP_S = 1.0
#: most points per trace and per loop sent to a page (bucket means)
TRACE_POINTS = 1500
LOOP_POINTS = 1000
#: a grasp begins where the force rises through this fraction of its range over the
#: traces' window above the lowest force (the free jaw); it ends below LEAVE_FRACTION
ENTER_FRACTION, LEAVE_FRACTION = 0.10, 0.05
#: one document serves every page that asks within this time, s: the pages' number
#: does not change the work (at most 20 documents a second)
CACHE_S = 0.05
#: decimals sent of time (s: 1 us), closure (m: 1 nm) and force (N: 1 uN)
DECIMALS = (6, 9, 6)
#: ring capacity, samples: 10 s at 20 kHz (the simulator's highest rate) fits 2.6 times
CAPACITY = 1 << 19


class LiveState:
    """The shared state between the recorder (one writer) and the pages (many readers).

    Parameters
    ----------
    session : str
        Session being recorded, shown on the page.
    capacity : int
        Samples kept; the windows shown are at most a third of it.
    """

    def __init__(self, session: str = "", *, capacity: int = CAPACITY) -> None:
        self.session = session
        self.capacity = int(capacity)
        self._time = np.zeros(self.capacity)
        self._position = np.zeros(self.capacity)
        self._force = np.zeros(self.capacity)
        self._lock = threading.Lock()
        self._count = 0  # samples appended so far; sample i sits at i % capacity
        self._newest_host = math.nan  # CLOCK_MONOTONIC when the newest sample arrived, s
        self._host_offset = math.inf  # monotonic time of the recorder's host_time 0, s
        self._t_start = time.monotonic()
        self._status: dict[str, Any] = {}
        self._estimate: dict[str, Any] | None = None
        self._running = True
        self._cache: tuple[int, float, bytes] | None = None  # (count, made at, document)
        self._cache_lock = threading.Lock()

    # -- the recorder's side: quick, no allocation beyond the block itself ------------

    def append(self, block: Any) -> None:
        """Add a block of samples (``time``, ``position``, ``force``, ``host_time``, SI).

        ``host_time`` counts from the start of the recorder's stream; the monotonic time
        of that start is bounded by ``now - host_time[-1]`` at every block, and the
        tightest bound is kept, so that the newest sample's arrival is known on the
        machine's monotonic clock (for the sample-to-screen latency).
        """
        n = total = len(block.time)
        if n == 0:
            return
        now = time.monotonic()
        host_last = float(block.host_time[-1])
        if n > self.capacity:  # only the newest fit
            block = _tail(block, self.capacity)
            n = self.capacity
        with self._lock:
            i = (self._count + total - n) % self.capacity  # where the first kept one goes
            first = min(n, self.capacity - i)
            for ring, values in (
                (self._time, block.time),
                (self._position, block.position),
                (self._force, block.force),
            ):
                ring[i : i + first] = values[:first]
                ring[: n - first] = values[first:]
            self._host_offset = min(self._host_offset, now - host_last)
            self._newest_host = self._host_offset + host_last
            self._count += total

    def set_status(self, status: Any) -> None:
        """Keep the recorder's latest status (a :class:`~tissuecli.app.record.RecordStatus`
        or anything with its attributes); a number that is not finite is kept as 0."""
        keep = ("elapsed_s", "samples", "rate_hz", "bad_frames", "lost_frames", "file_bytes")
        values = {k: getattr(status, k) for k in keep if hasattr(status, k)}
        self._status = {k: v if math.isfinite(v) else 0 for k, v in values.items()}

    def set_estimate(self, estimate: Any | None) -> None:
        """Keep the latest running estimate (an object with ``as_dict()``, or None)."""
        self._estimate = None if estimate is None else estimate.as_dict()

    def finish(self) -> None:
        """The recording has ended: the page says so and stops asking."""
        self._running = False

    # -- the pages' side -------------------------------------------------------------

    def document(self, max_age_s: float = CACHE_S) -> bytes:
        """``/api/state`` as JSON bytes, made at most once per ``max_age_s`` while no new
        sample arrives, so that many pages cost little more than one."""
        import json

        with self._cache_lock:
            now = time.monotonic()
            cached = self._cache
            if cached is not None and cached[0] == self._count and now - cached[1] < max_age_s:
                return cached[2]
            state = self.snapshot()
            body = json.dumps(state, allow_nan=False, separators=(",", ":")).encode()
            self._cache = (state["samples_seen"], now, body)
            return body

    def snapshot(self) -> dict[str, Any]:
        """The state as a JSON-ready dict (schema in docs/formats.md); SI units."""
        with self._lock:
            count, newest_host, offset = self._count, self._newest_host, self._host_offset
        now = time.monotonic()
        status = dict(self._status)
        elapsed = now - offset if math.isfinite(offset) else now - self._t_start
        if self._running:
            # what the ring knows is newer than the recorder's last status (the
            # same quantities: samples kept, their mean rate since the stream began)
            samples = max(int(status.get("samples", 0)), count)
            rate = samples / elapsed if elapsed > 0 else 0.0
            status.update(samples=samples, elapsed_s=elapsed, rate_hz=rate)
        for key in ("rate_hz", "bad_frames", "lost_frames", "file_bytes"):
            status.setdefault(key, 0)
        traces, loop = self._windows(count)
        return {
            "schema": SCHEMA,
            "session": self.session,
            "running": self._running,
            "samples_seen": count,
            "server_monotonic_s": now,
            "newest_sample_monotonic_s": _finite(newest_host),
            "sample_age_s": _finite(now - newest_host),
            "status": status,
            "traces": traces,
            "loop": loop,
            "estimate": self._estimate,
        }

    def _windows(self, count: int) -> tuple[dict[str, Any], dict[str, Any]]:
        """The traces of the last TRACE_S and the loop of the current grasp, decimated."""
        empty = {"time_s": [], "position_m": [], "force_n": []}
        if count < 2:
            return {"window_s": TRACE_S, **empty}, {"start_s": None, **empty, "closing": []}
        # the samples of the windows; never more than a third of the ring, so the
        # recorder cannot overwrite them while they are read
        newest = self._time[(count - 1) % self.capacity]
        span = self._span(count, min(count, self.capacity // 3))
        t, x, f = (
            self._read(ring, count, span) for ring in (self._time, self._position, self._force)
        )
        start_index = count - span  # global index of t[0]
        series = zip((t, x, f), DECIMALS, strict=True)
        tt, xt, ft = (_means(a, start_index, TRACE_POINTS, d) for a, d in series)
        traces = {"window_s": TRACE_S, "time_s": tt, "position_m": xt, "force_n": ft}
        # the loop: from the start of the current grasp (found on the traces' means),
        # within LOOP_S
        t_mean = np.asarray(tt)
        start = t_mean[_grasp_start(t_mean, np.asarray(ft), newest)]
        half = (t_mean[-1] - t_mean[0]) / (2 * (t_mean.size - 1)) if t_mean.size > 1 else 0.0
        g = int(np.searchsorted(t, start - half, side="left"))  # the bucket's first sample
        series = zip((t, x, f), DECIMALS, strict=True)
        tl, xl, fl = (_means(a[g:], start_index + g, LOOP_POINTS, d) for a, d in series)
        loop = {
            "start_s": float(t[g]),
            "time_s": tl,
            "position_m": xl,
            "force_n": fl,
            "closing": _closing(np.asarray(xl)),
        }
        return traces, loop

    def _span(self, count: int, limit: int) -> int:
        """How many of the newest samples lie within TRACE_S (at most ``limit``)."""
        t_new = self._time[(count - 1) % self.capacity]
        lo, hi = 1, limit  # binary search on age: ring order is time order
        while lo < hi:
            mid = (lo + hi) // 2
            if t_new - self._time[(count - 1 - mid) % self.capacity] >= TRACE_S:
                hi = mid
            else:
                lo = mid + 1
        return lo

    def _read(self, ring: Array, count: int, n: int) -> Array:
        """The ``n`` newest values of ``ring`` in time order: a view, or a copy where
        they wrap round the ring's end."""
        end = count % self.capacity
        if n <= end:
            return ring[end - n : end]
        return np.concatenate((ring[self.capacity - (n - end) :], ring[:end]))


def _tail(block: Any, n: int) -> Any:
    from types import SimpleNamespace

    return SimpleNamespace(
        time=block.time[-n:],
        position=block.position[-n:],
        force=block.force[-n:],
        host_time=block.host_time[-n:],
    )


def _finite(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def _means(values: Array, first_index: int, points: int, decimals: int) -> list[float]:
    """Means of buckets of ``k`` samples aligned on global sample indices (so that the
    points do not shimmer from one update to the next), ``k`` such that at most
    ``points`` remain; the last, partial bucket included. Rounded to ``decimals``
    (far below what a screen shows) so that the JSON stays short."""
    n = values.size
    if n == 0:
        return []
    k = max(1, math.ceil(n / points))
    if k == 1:
        return np.round(values, decimals).tolist()
    head = (-first_index) % k  # samples before the first aligned bucket
    edges = np.arange(head, n, k)
    if head:
        edges = np.concatenate(([0], edges))
    sums = np.add.reduceat(values, edges)
    sizes = np.diff(np.append(edges, n))
    return np.round(sums / sizes, decimals).tolist()


def _grasp_start(t: Array, f: Array, newest: float) -> int:
    """Index in ``t`` where the loop of the current grasp begins.

    The free jaw is the lowest force of the window; a grasp begins where the force rises
    through ENTER_FRACTION of the window's range above it after falling below
    LEAVE_FRACTION. The loop starts at the latest such entry at least MIN_LOOP_S old
    (a grasp just begun shows the one before as well), never more than LOOP_S ago.
    """
    first = int(np.searchsorted(t, newest - LOOP_S, side="left"))
    lo, hi = float(f.min()), float(f.max())
    if not hi > lo:
        return first
    enter, leave = lo + ENTER_FRACTION * (hi - lo), lo + LEAVE_FRACTION * (hi - lo)
    seg = f[first:]
    # hysteresis: the state changes only when the force crosses the far threshold
    above = np.where(seg > enter, 1, np.where(seg < leave, 0, -1))
    known = np.flatnonzero(above >= 0)
    if known.size == 0:
        return first
    state = above[known]
    rises = known[1:][(state[1:] == 1) & (state[:-1] == 0)]
    old_enough = rises[t[first + rises] <= newest - MIN_LOOP_S]
    return first + int(old_enough[-1]) if old_enough.size else first


def _closing(x: Array) -> list[bool]:
    """Loading (the jaws closing, x rising) or unloading, per loop point; the slope is
    taken over a few points either side so that noise does not flicker the colour."""
    if x.size < 2:
        return [True] * int(x.size)
    h = max(1, x.size // 100)
    padded = np.concatenate((np.full(h, x[0]), x, np.full(h, x[-1])))
    slope = padded[2 * h :] - padded[: -2 * h]
    return (slope >= 0).tolist()
