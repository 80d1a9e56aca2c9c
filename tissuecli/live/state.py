"""What the live view shows: the newest samples in a bounded ring, the recording status
and the running estimate, turned into the JSON of ``/api/state`` on request.

Everything lives in one block of shared memory (an anonymous file mapped by both
processes, :func:`os.memfd_create` where there is one: nothing named to leave
behind) so that the pages are served from another process (``server.py``) and never
take the recorder's interpreter lock. The recorder's acquisition loop is the only writer:
:meth:`LiveState.append` copies a block into the preallocated ring with NumPy and
moves a write index; the status and the estimate are written a few times a second.
It never waits for a reader: there is no lock, only counters that a reader checks
(a sequence number odd while the writer is at a record, as a seqlock, and the
index the writer is about to fill) and reads again where the writer was meanwhile.
This relies on the writer's stores becoming visible to the reader in program order,
as x86-64 guarantees. Everything else (decimation, the current grasp, JSON) runs in
the reader.
"""

from __future__ import annotations

import marshal
import math
import mmap
import os
import tempfile
import threading
import time
import weakref
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
#: room for the estimate (marshalled plain data), bytes
ESTIMATE_BYTES = 1 << 16
#: the status kept, in its slots of the shared block; the last three are counts
STATUS_KEYS = ("elapsed_s", "samples", "rate_hz", "bad_frames", "lost_frames", "file_bytes")
_COUNTS = ("samples", "bad_frames", "lost_frames", "file_bytes")

# The shared block: 16 int64, 16 float64, the three rings, the estimate's bytes.
_I_RESERVED, _I_COUNT, _I_RING_SEQ, _I_STATUS_SEQ, _I_EST_SEQ, _I_EST_LEN, _I_RUNNING = range(7)
_F_NEWEST, _F_OFFSET, _F_START, _F_STATUS = 0, 1, 2, 3  # status: 6 slots from _F_STATUS
_HEADER = 16 * 8 * 2
#: a reader gives up waiting for a writer that stopped within a record after this, s
_READ_TRIES = 10_000


class LiveState:
    """The shared state between the recorder (one writer) and the pages (many readers,
    in this process or another).

    Parameters
    ----------
    session : str
        Session being recorded, shown on the page.
    capacity : int
        Samples kept; the windows shown are at most a third of it.
    fd : int, optional
        Map the shared block of an existing state, open as this file descriptor (the
        server's process does), instead of creating one; ``session`` and ``capacity``
        must be the creator's (:attr:`handle` gives them).
    """

    def __init__(
        self, session: str = "", *, capacity: int = CAPACITY, fd: int | None = None
    ) -> None:
        self.session = session
        self.capacity = int(capacity)
        self.owner = fd is None
        self._m = _Block(self.capacity, fd)
        # the writer's own copies of its counters: it never reads the shared block
        self._count = 0
        self._ring_seq = self._status_seq = self._est_seq = 0
        self._host_offset = math.inf
        self._estimate_source: Any = None
        if self.owner:
            self._m.ints[:] = 0
            self._m.ints[_I_RUNNING] = 1
            self._m.floats[:] = math.nan
            self._m.floats[_F_OFFSET] = math.inf  # monotonic time of the recorder's host_time 0, s
            self._m.floats[_F_START] = time.monotonic()
            self._set_estimate_bytes(marshal.dumps(None))
        # the reader's
        self._estimate: tuple[int, Any] = (-1, None)
        self._cache: tuple[float, bytes] | None = None  # (made at, document)
        self._cache_lock = threading.Lock()
        self._finalizer = weakref.finalize(self, self._m.release)

    @property
    def handle(self) -> tuple[int, str, int]:
        """What another process needs to map the block: ``LiveState(session,
        capacity=..., fd=...)`` with these ``(fd, session, capacity)``, the descriptor
        passed on to it (``subprocess.Popen(pass_fds=...)``)."""
        return self._m.fd, self.session, self.capacity

    def close(self) -> None:
        """Let go of the shared block: it is freed once no process maps it."""
        self._finalizer()

    # -- the recorder's side: quick, no lock, no allocation beyond the block itself -----

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
        m = self._m
        ints, floats = m.ints, m.floats
        # readers of the slots about to be written see them taken before they change
        ints[_I_RESERVED] = self._count + total
        i = (self._count + total - n) % self.capacity  # where the first kept one goes
        first = min(n, self.capacity - i)
        for ring, values in (
            (m.time, block.time),
            (m.position, block.position),
            (m.force, block.force),
        ):
            ring[i : i + first] = values[:first]
            ring[: n - first] = values[first:]
        self._host_offset = min(self._host_offset, now - host_last)
        self._count += total
        self._ring_seq += 1
        ints[_I_RING_SEQ] = self._ring_seq  # odd: the count and times are changing
        ints[_I_COUNT] = self._count
        floats[_F_OFFSET] = self._host_offset
        floats[_F_NEWEST] = self._host_offset + host_last
        self._ring_seq += 1
        ints[_I_RING_SEQ] = self._ring_seq

    def set_status(self, status: Any) -> None:
        """Keep the recorder's latest status (a :class:`~tissuecli.app.record.RecordStatus`
        or anything with its attributes); a number that is not finite is kept as 0."""
        values = [getattr(status, k, math.nan) for k in STATUS_KEYS]
        # NaN marks a quantity not given; one given but not finite is 0
        kept = [
            math.nan if not hasattr(status, k) else (float(v) if math.isfinite(v) else 0.0)
            for k, v in zip(STATUS_KEYS, values, strict=True)
        ]
        self._status_seq += 1
        self._m.ints[_I_STATUS_SEQ] = self._status_seq
        self._m.floats[_F_STATUS : _F_STATUS + len(STATUS_KEYS)] = kept
        self._status_seq += 1
        self._m.ints[_I_STATUS_SEQ] = self._status_seq

    def set_estimate(self, estimate: Any | None) -> None:
        """Keep the latest running estimate (an object with ``as_dict()``, or None);
        the same object again costs nothing."""
        if estimate is self._estimate_source:
            return
        self._estimate_source = estimate
        data = marshal.dumps(None if estimate is None else estimate.as_dict())
        self._set_estimate_bytes(data if len(data) <= ESTIMATE_BYTES else marshal.dumps(None))

    def _set_estimate_bytes(self, data: bytes) -> None:
        self._est_seq += 1
        self._m.ints[_I_EST_SEQ] = self._est_seq
        self._m.blob[: len(data)] = np.frombuffer(data, np.uint8)
        self._m.ints[_I_EST_LEN] = len(data)
        self._est_seq += 1
        self._m.ints[_I_EST_SEQ] = self._est_seq

    def finish(self) -> None:
        """The recording has ended: the page says so and stops asking."""
        self._m.ints[_I_RUNNING] = 0

    # -- the pages' side -------------------------------------------------------------

    def document(self, max_age_s: float = CACHE_S) -> bytes:
        """``/api/state`` as JSON bytes, made at most once per ``max_age_s`` (however
        many samples arrive meanwhile), so that many pages cost little more than one."""
        import json

        with self._cache_lock:
            now = time.monotonic()
            cached = self._cache
            if cached is not None and now - cached[0] < max_age_s:
                return cached[1]
            state = self.snapshot()
            body = json.dumps(state, allow_nan=False, separators=(",", ":")).encode()
            self._cache = (now, body)
            return body

    def snapshot(self) -> dict[str, Any]:
        """The state as a JSON-ready dict (schema in docs/formats.md); SI units."""
        ints, floats = self._m.ints, self._m.floats
        for _ in range(_READ_TRIES):
            count, newest_host, offset = self._consistent(
                _I_RING_SEQ,
                lambda: (int(ints[_I_COUNT]), float(floats[_F_NEWEST]), float(floats[_F_OFFSET])),
            )
            windows = self._windows(count)
            if windows is not None:
                break
        else:  # the writer went round the ring while every attempt read it
            windows = self._windows(0)
            assert windows is not None
        traces, loop = windows
        values = self._consistent(
            _I_STATUS_SEQ, lambda: floats[_F_STATUS : _F_STATUS + len(STATUS_KEYS)].copy()
        )
        status: dict[str, Any] = {
            k: int(v) if k in _COUNTS else float(v)
            for k, v in zip(STATUS_KEYS, values, strict=True)
            if not math.isnan(v)
        }
        running = bool(ints[_I_RUNNING])
        now = time.monotonic()
        elapsed = now - offset if math.isfinite(offset) else now - float(floats[_F_START])
        if running:
            # what the ring knows is newer than the recorder's last status (the
            # same quantities: samples kept, their mean rate since the stream began)
            samples = max(int(status.get("samples", 0)), count)
            rate = samples / elapsed if elapsed > 0 else 0.0
            status.update(samples=samples, elapsed_s=elapsed, rate_hz=rate)
        for key in ("rate_hz", "bad_frames", "lost_frames", "file_bytes"):
            status.setdefault(key, 0)
        return {
            "schema": SCHEMA,
            "session": self.session,
            "running": running,
            "samples_seen": count,
            "server_monotonic_s": now,
            "newest_sample_monotonic_s": _finite(newest_host),
            "sample_age_s": _finite(now - newest_host),
            "status": status,
            "traces": traces,
            "loop": loop,
            "estimate": self._read_estimate(),
        }

    def _consistent(self, seq: int, read: Any) -> Any:
        """``read()`` of a record the writer did not change meanwhile (its sequence
        number even and the same before and after)."""
        ints = self._m.ints
        for _ in range(_READ_TRIES):
            before = int(ints[seq])
            if not before & 1:
                value = read()
                if int(ints[seq]) == before:
                    return value
            time.sleep(0)  # the writer is within the record: let it finish
        return read()  # a writer that died within the record: what is there

    def _read_estimate(self) -> Any:
        """The estimate's plain data, decoded once per new estimate."""
        seq = int(self._m.ints[_I_EST_SEQ])
        if seq != self._estimate[0]:

            def read() -> tuple[int, bytes]:
                n = int(self._m.ints[_I_EST_LEN])
                return int(self._m.ints[_I_EST_SEQ]), self._m.blob[
                    : min(n, ESTIMATE_BYTES)
                ].tobytes()

            seq, data = self._consistent(_I_EST_SEQ, read)
            try:
                self._estimate = (seq, marshal.loads(data))
            except (EOFError, ValueError, TypeError):
                self._estimate = (seq, None)
        return self._estimate[1]

    def _windows(self, count: int) -> tuple[dict[str, Any], dict[str, Any]] | None:
        """The traces of the last TRACE_S and the loop of the current grasp, decimated;
        None if the writer overwrote samples while they were read."""
        empty = {"time_s": [], "position_m": [], "force_n": []}
        if count < 2:
            return {"window_s": TRACE_S, **empty}, {"start_s": None, **empty, "closing": []}
        # the samples of the windows, copied; never more than a third of the ring, so
        # the recorder does not come round to them unless this reader stalls for long
        span = self._span(count, min(count, self.capacity // 3))
        t, x, f = (
            self._read(ring, count, span)
            for ring in (self._m.time, self._m.position, self._m.force)
        )
        if int(self._m.ints[_I_RESERVED]) - self.capacity > count - span:
            return None  # the oldest of them were written over while being copied
        newest = t[-1]
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
        t_new = self._m.time[(count - 1) % self.capacity]
        lo, hi = 1, limit  # binary search on age: ring order is time order
        while lo < hi:
            mid = (lo + hi) // 2
            if t_new - self._m.time[(count - 1 - mid) % self.capacity] >= TRACE_S:
                hi = mid
            else:
                lo = mid + 1
        return lo

    def _read(self, ring: Array, count: int, n: int) -> Array:
        """A copy of the ``n`` newest values of ``ring`` in time order."""
        end = count % self.capacity
        if n <= end:
            return ring[end - n : end].copy()
        return np.concatenate((ring[self.capacity - (n - end) :], ring[:end]))


class _Block:
    """The shared block and the arrays over it, in one place so that they can all be
    dropped before it is unmapped.

    Created (``fd`` None) as an anonymous file for a ring of ``capacity`` samples, or
    mapped from the open descriptor ``fd`` of one.
    """

    def __init__(self, capacity: int, fd: int | None) -> None:
        size = _HEADER + 3 * 8 * capacity + ESTIMATE_BYTES
        self.file: Any = None
        if fd is None:
            if hasattr(os, "memfd_create"):  # Linux: memory, no name
                fd = os.memfd_create("tissuecli-live")
            else:  # elsewhere a temporary file, removed at once
                self.file = tempfile.TemporaryFile()
                fd = self.file.fileno()
            os.ftruncate(fd, size)  # reads as zeros
        self.fd = fd
        self.map = mmap.mmap(fd, size)
        self.ints = np.frombuffer(self.map, np.int64, 16, 0)
        self.floats = np.frombuffer(self.map, np.float64, 16, 16 * 8)
        rings = np.frombuffer(self.map, np.float64, 3 * capacity, _HEADER)
        self.time, self.position, self.force = rings.reshape(3, -1)
        self.blob = np.frombuffer(self.map, np.uint8, ESTIMATE_BYTES, size - ESTIMATE_BYTES)

    def release(self) -> None:
        """Unmap the block and close its descriptor."""
        self.ints = self.floats = self.time = self.position = self.force = self.blob = None  # type: ignore[assignment]
        try:
            self.map.close()
        except BufferError:
            pass  # a reader still holds an array of it: unmapped with the process
        if self.file is not None:
            self.file.close()
        else:
            try:
                os.close(self.fd)
            except OSError:
                pass


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
