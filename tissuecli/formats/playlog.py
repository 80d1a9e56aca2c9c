"""Play logs: every frame of a play, as group ``plays/<name>`` of an HDF5 file, written by
a thread of its own so the control loop never waits for the disk."""

from __future__ import annotations

import os
import queue
import threading
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ..core.errors import StorageError
from ..core.session import check_name
from .hdf5 import (
    H5_ERRORS,
    Column,
    StrPath,
    damaged,
    foreign_message,
    group_names,
    is_own_file,
    number_value,
    opened,
)
from .space import check_free_space, preflight_bytes
from .writer import SeriesWriter, row_bytes

#: parent group of every play log
PLAYS = "plays"
#: Rows handed to the writer thread at a time.
LOG_BLOCK = 100
#: Longest a logged row stays in memory, s: each flush fsyncs, which cost the display
#: process deadlines on a 2-core machine at 0.25 s; a crash loses at most this much log.
LOG_FLUSH_S = 1.0

LOG_COLUMNS = [
    Column(
        "time", "float64", attrs={"unit": "s", "description": "display clock since the first frame"}
    ),
    Column(
        "xp",
        "float64",
        attrs={"unit": "m", "description": "piston position, filtered estimate, positive down"},
    ),
    Column(
        "xm",
        "float64",
        attrs={"unit": "m", "description": "tissue model position under the observed force"},
    ),
    Column("e", "float64", attrs={"unit": "m", "description": "xp - xm"}),
    Column(
        "V", "float64", attrs={"unit": "V", "description": "voltage sent in answer to this frame"}
    ),
    Column(
        "V_applied",
        "float64",
        attrs={"unit": "V", "description": "voltage the display reported applying"},
    ),
    Column(
        "force_observed",
        "float64",
        attrs={
            "unit": "N",
            "description": "Mp xp'' + b xp' + Kp xp + alpha V^2 over the last period",
        },
    ),
    Column(
        "flags",
        "uint8",
        attrs={
            "unit": "1",
            "description": "0x01 watchdog, 0x02 end stop (display); 0x10 saturated, 0x20 "
            "unrenderable, 0x40 non-finite (controller)",
        },
    ),
    Column("counts", "int32", attrs={"unit": "count", "description": "raw encoder reading"}),
]


#: bytes one logged control period takes on disk
LOG_ROW_BYTES = row_bytes(LOG_COLUMNS)


def check_log(path: StrPath, rate_hz: float) -> None:
    """Check, before the display is touched, that a play log can be written to `path`.

    Parameters
    ----------
    path : path
        The log file (it may not exist yet).
    rate_hz : float
        Control-loop rate, Hz: the drive must hold 10 s of log at this rate plus 1 MiB.

    Raises
    ------
    StorageError
        If the file is not an HDF5 file written by tissuecli (an empty one is fine), is
        damaged, its directory is missing, or its drive lacks the room.
    """
    file = os.fspath(path)
    if os.path.exists(file):
        with opened(file, "r") as f:
            try:
                own = is_own_file(f)
            except H5_ERRORS as exc:
                raise damaged(file, "the root group", exc) from None
        if not own:
            raise StorageError(foreign_message(file, "--log"))
    elif not os.path.isdir(os.path.dirname(os.path.abspath(file))):
        raise StorageError(
            f"cannot create {file}: its directory does not exist; create it or choose another path"
        )
    check_free_space(file, preflight_bytes(rate_hz * LOG_ROW_BYTES), what="the play log")


class PlayLog:
    """The log of one play: rows buffered by the loop, written by a thread of its own.

    A flush (fsync included) took up to 8.5 ms here; in the control loop that would
    starve the display's 5 ms watchdog. The thread spends its wait in fsync, which
    releases the GIL.

    Parameters
    ----------
    path : path
        HDF5 file (created if missing; other groups are never touched).
    name : str
        Group name under ``plays/``; a suffix ``-2``, ``-3``, ... is added if taken.
    meta : mapping
        Group attributes (tissue, profile, gains, ...); ``rate_hz`` sets the free space
        needed to start (10 s of log plus 1 MiB, see :func:`check_log`).

    Attributes
    ----------
    group : str
        The group written, ``plays/<name>``.
    """

    def __init__(self, path: StrPath, name: str, meta: Mapping[str, Any]) -> None:
        name = _unique_name(Path(path), check_name(name, "play"))
        self.path = str(path)
        self.group = f"{PLAYS}/{name}"
        rate = number_value(meta.get("rate_hz")) or 0.0
        self.writer = SeriesWriter(
            path,
            self.group,
            LOG_COLUMNS,
            meta,
            kind="play",
            option="--log",
            flush_interval_s=LOG_FLUSH_S,
            min_free_bytes=preflight_bytes(rate * LOG_ROW_BYTES),
        )
        self.error: BaseException | None = None
        self._rows: dict[str, list[float]] = {c.name: [] for c in LOG_COLUMNS}
        self._queue: queue.Queue[dict[str, np.ndarray] | None] = queue.Queue()
        self._thread = threading.Thread(target=self._run, name="play-log", daemon=True)
        self._thread.start()

    def add(
        self,
        t: float,
        xp: float,
        xm: float,
        volts: float,
        volts_applied: float,
        force: float,
        flags: int,
        counts: int,
    ) -> None:
        """Buffer one frame's row; hand a block to the writer every :data:`LOG_BLOCK` rows."""
        rows = self._rows
        rows["time"].append(t)
        rows["xp"].append(xp)
        rows["xm"].append(xm)
        rows["e"].append(xp - xm)
        rows["V"].append(volts)
        rows["V_applied"].append(volts_applied)
        rows["force_observed"].append(force)
        rows["flags"].append(flags)
        rows["counts"].append(counts)
        if len(rows["time"]) >= LOG_BLOCK:
            self.flush()

    def flush(self) -> None:
        """Hand the buffered rows to the writer thread (re-raising its error, if any)."""
        if self.error is not None:
            raise self.error
        if self._rows["time"]:
            block = {c.name: np.asarray(self._rows[c.name], dtype=c.dtype) for c in LOG_COLUMNS}
            for c in LOG_COLUMNS:
                self._rows[c.name].clear()
            self._queue.put(block)

    def _run(self) -> None:
        while True:
            block = self._queue.get()
            if block is None:
                return
            if self.error is not None:
                continue
            try:
                self.writer.append(block)
            except BaseException as exc:  # re-raised in the control loop by flush()
                self.error = exc

    def close(self, complete: bool, **attrs: Any) -> None:
        """Write what is buffered, store ``attrs`` and ``complete``, and close the file."""
        try:
            self.flush()
        except Exception:  # reported below
            pass
        self._queue.put(None)
        self._thread.join()
        self.writer.close(complete=complete and self.error is None, **attrs)
        if self.error is not None:
            raise self.error


def _unique_name(log: Path, name: str) -> str:
    """``name``, or ``name-2``, ``name-3`` ... if the log already holds it (never overwrite)."""
    if not log.exists():
        return name
    taken = set(group_names(log, PLAYS))
    candidate, i = name, 1
    while candidate in taken:
        i += 1
        candidate = f"{name}-{i}"
    return candidate
