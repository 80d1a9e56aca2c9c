"""Sessions in HDF5 files: ``/sessions/<name>`` groups of time, force and position (SI)
and, for recordings, the raw frames; written whole or streamed, read, listed."""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any

import h5py
import numpy as np
from numpy.typing import ArrayLike

from ..core.calibration import Adc, calibration_from_dict
from ..core.errors import InputError, SessionExists, StorageError
from ..core.session import QUANTITIES, Session, check_name
from .hdf5 import (
    Column,
    StrPath,
    columns_of,
    decode_attrs,
    exists_message,
    from_attr,
    group_names,
    opened,
    read_group,
    unreadable,
    usable_rows,
)
from .writer import SeriesWriter

#: parent group of every recorded or imported session
SESSIONS = "sessions"
#: keys of ``Session.meta`` that exist only in memory and are never stored as attributes
READ_ONLY_META = ("file", "raw", "calibration")
CHANNELS = ("force", "position")


#: the datasets of a session group: the samples in SI, then the raw frames of a recording
SESSION_COLUMNS: list[Column] = [
    *(
        Column(q.name, "float64", (), {"unit": q.unit, "description": q.description})
        for q in QUANTITIES
    ),
    Column(
        "raw/counts",
        "int16",
        (2,),
        {
            "unit": "count",
            "channels": list(CHANNELS),
            "description": "raw ADC counts as sent by the device, one column per channel",
        },
    ),
    Column(
        "raw/sequence",
        "uint32",
        (),
        {"unit": "1", "description": "frame sequence number as sent by the device"},
    ),
    Column(
        "raw/device_clock",
        "int64",
        (),
        {"unit": "tick", "description": "device clock, unwrapped to 64 bits"},
    ),
    Column(
        "raw/host_time",
        "float64",
        (),
        {"unit": "s", "description": "host monotonic clock, s since the session started"},
    ),
]


def session_group(name: str) -> str:
    """HDF5 group path of session `name`, e.g. ``'sessions/liver-1'``."""
    check_name(name, "session")
    return f"{SESSIONS}/{name}"


def session_columns(
    *, raw: bool = True, calibration: Mapping[str, Mapping[str, float]] | None = None
) -> list[Column]:
    """Columns of a session group, with calibration attributes filled in.

    Parameters
    ----------
    raw : bool, optional
        Include the ``raw/*`` columns (sessions recorded from a device).
    calibration : mapping, optional
        ``{'force': {'gain': N/count, 'offset': N}, 'position': {'gain': m/count,
        'offset': m}}``; SI value = count * gain + offset.

    Returns
    -------
    list of Column
    """
    gains: dict[str, float] = {}
    offsets: dict[str, float] = {}
    for channel in CHANNELS:
        cal = (calibration or {}).get(channel)
        if calibration is not None and (cal is None or "gain" not in cal):
            raise ValueError(f"calibration lacks {channel!r} gain: {calibration}")
        gains[channel] = float(cal["gain"]) if cal else float("nan")
        offsets[channel] = float(cal.get("offset", 0.0)) if cal else float("nan")
    out: list[Column] = []
    for col in SESSION_COLUMNS:
        if col.name.startswith("raw/") and not raw:
            continue
        attrs = dict(col.attrs)
        if col.name in CHANNELS:
            # NWB meaning: the stored values are SI already; resolution is one count
            attrs.update(conversion=1.0, offset=0.0, resolution=gains[col.name])
        elif col.name == "raw/counts":
            # NWB meaning per channel: SI = counts * conversion + offset
            attrs.update(
                conversion=np.array([gains[c] for c in CHANNELS]),
                offset=np.array([offsets[c] for c in CHANNELS]),
            )
        out.append(Column(col.name, col.dtype, col.shape, attrs))
    return out


def check_new_session(path: StrPath, name: str) -> None:
    """Check, before any work, that session `name` can be created in `path`.

    Raises
    ------
    InputError
        If the name is empty or contains '/'.
    SessionExists
        If the file already holds a session of that name.
    StorageError
        If the file exists but is not a readable HDF5 file, or its directory is missing.
    """
    group = session_group(name)
    file = os.fspath(path)
    if not os.path.exists(file):
        parent = os.path.dirname(os.path.abspath(file))
        if not os.path.isdir(parent):
            raise StorageError(
                f"cannot create {file}: its directory does not exist; create it or choose "
                "another path"
            )
        return
    with opened(file, "r") as f:
        if group in f:
            raise SessionExists(exists_message("session", name, file))


def session_writer(
    path: StrPath,
    name: str,
    *,
    meta: Mapping[str, Any],
    calibration: Mapping[str, Mapping[str, float]] | None,
    raw: bool = True,
    flush_interval_s: float = 0.25,
    fsync: bool = True,
) -> SeriesWriter:
    """Start writing session `name` into `path` (see :class:`SeriesWriter`).

    Parameters
    ----------
    path : str or os.PathLike
        HDF5 file (created if missing).
    name : str
        Session name; the group is ``/sessions/<name>``.
    meta : mapping
        Session attributes (tissue, note, source, start_utc, counters, ...).
    calibration : mapping or None
        Device calibration, see :func:`session_columns`.
    raw : bool, optional
        Include the ``raw/*`` columns; blocks must then carry them too.
    flush_interval_s, fsync
        See :class:`SeriesWriter`.

    Returns
    -------
    SeriesWriter
        Takes blocks with keys ``time``, ``force``, ``position`` (+ ``raw/*``).

    Raises
    ------
    SessionExists
        If the file already holds a session of that name.
    """
    group = session_group(name)
    attrs = {k: v for k, v in meta.items() if k not in READ_ONLY_META}
    attrs.setdefault("source", "device" if raw else "import")
    return SeriesWriter(
        path,
        group,
        session_columns(raw=raw, calibration=calibration),
        attrs,
        flush_interval_s=flush_interval_s,
        fsync=fsync,
        kind="session",
    )


RAW_KEYS = ("counts", "sequence", "device_clock", "host_time")


def write_session(
    path: StrPath, session: Session, *, raw: Mapping[str, ArrayLike] | None = None
) -> None:
    """Write a whole session at once (import, demo); never overwrites.

    Parameters
    ----------
    path : str or os.PathLike
        HDF5 file (created if missing).
    session : Session
        Session to store under ``/sessions/<session.name>``; ``session.meta`` becomes
        the group attributes (``meta['calibration']``, if any, goes to ``raw/counts``).
    raw : mapping, optional
        Raw arrays ``counts`` (n, 2) int16, ``sequence`` (n,), ``device_clock`` (n,)
        in ticks, ``host_time`` (n,) in s; keys may also carry the ``raw/`` prefix.

    Raises
    ------
    SessionExists
        If the name is taken.
    InputError
        If the session has no name or its arrays differ in length.
    """
    check_name(session.name, "session")
    n = len(session)
    for label in ("force", "position"):
        if getattr(session, label).shape != (n,):
            raise InputError(
                f"{label} has shape {getattr(session, label).shape}; expected ({n},) like time"
            )
    block: dict[str, ArrayLike] = {
        "time": session.time,
        "force": session.force,
        "position": session.position,
    }
    if raw is not None:
        for key, value in raw.items():
            short = key.removeprefix("raw/")
            if short not in RAW_KEYS:
                raise ValueError(f"unknown raw array {key!r}; expected {RAW_KEYS}")
            block[f"raw/{short}"] = value
        lengths = {k: np.shape(v)[0] if np.ndim(v) else 0 for k, v in block.items()}
        if len(set(lengths.values())) != 1:
            raise InputError(f"raw arrays and samples differ in length: {lengths}")
    calibration = session.meta.get("calibration")
    with session_writer(
        path,
        session.name,
        meta=session.meta,
        calibration=calibration,
        raw=raw is not None,
        flush_interval_s=float("inf"),
    ) as writer:
        writer.append(block)


def _sessions_root(f: h5py.File) -> h5py.Group | None:
    root = f.get(SESSIONS)
    return root if isinstance(root, h5py.Group) else None


def session_names(path: StrPath) -> list[str]:
    """Names of the sessions in `path`, oldest first."""
    return group_names(path, SESSIONS)


def _pick_session(path: str, name: str | None) -> str:
    names = session_names(path)
    if name is None:
        if len(names) == 1:
            return names[0]
        if not names:
            raise StorageError(f"{path} holds no sessions; record or import one first")
        raise StorageError(
            f"{path} holds {len(names)} sessions ({', '.join(names)}); pass --session NAME"
        )
    if name not in names:
        available = ", ".join(names) if names else "none"
        raise StorageError(
            f'no session "{name}" in {path}; available: {available}; pass one with --session'
        )
    return name


def read_session(path: StrPath, name: str | None = None, *, raw: bool = False) -> Session:
    """Read one session.

    Parameters
    ----------
    path : str or os.PathLike
        HDF5 file.
    name : str, optional
        Session name; may be omitted when the file holds exactly one session.
    raw : bool, optional
        Also return the raw arrays in ``meta['raw']``, keyed by dataset name as in
        :data:`SESSION_COLUMNS` (``'raw/counts'`` (n, 2), ``'raw/sequence'``,
        ``'raw/device_clock'``, ``'raw/host_time'``), and the calibration in
        ``meta['calibration']``; empty dicts if the session has no raw data.

    Returns
    -------
    Session
        time in s, force in N, position in m; ``meta`` holds the group attributes
        plus ``'file'``. A session cut short by a crash (``meta['complete']`` False)
        holds the rows committed before the crash.

    Raises
    ------
    StorageError
        Missing or non-HDF5 file, no or several sessions without a name, unknown name.
    """
    file = os.fspath(path)
    name = _pick_session(file, name)
    columns, meta = read_group(file, session_group(name))
    missing = [c for c in ("time", *CHANNELS) if c not in columns]
    if missing:
        raise StorageError(
            f'session "{name}" in {file} lacks dataset(s) {", ".join(missing)}; it was not '
            "written by tissuecli"
        )
    meta["file"] = file
    calibration = _read_calibration(file, session_group(name))
    if raw:
        meta["raw"] = {key: value for key, value in columns.items() if key.startswith("raw/")}
        meta["calibration"] = calibration
    return Session(
        time=columns["time"],
        force=columns["force"],
        position=columns["position"],
        name=name,
        meta=meta,
        adc=_adc(meta, calibration),
    )


def _adc(meta: Mapping[str, Any], calibration: Mapping[str, Any]) -> Adc | None:
    """The ADC a recording came through: bits from the device's IDENTIFY reply, counts to
    SI from the calibration the recorder applied (else the device's own); None if unknown."""
    device = meta.get("device")
    if not isinstance(device, Mapping):
        return None
    bits = device.get("adc_bits")
    if not isinstance(bits, int) or isinstance(bits, bool) or not 2 <= bits <= 32:
        return None
    try:
        return Adc(bits, calibration_from_dict(calibration or device.get("calibration") or {}))
    except InputError:
        return None


def _read_calibration(path: str, group: str) -> dict[str, dict[str, float]]:
    with opened(path, "r") as f:
        ds = f.get(f"{group}/raw/counts")
        if not isinstance(ds, h5py.Dataset) or "conversion" not in ds.attrs:
            return {}
        gains = np.atleast_1d(ds.attrs["conversion"])
        offsets = np.atleast_1d(ds.attrs.get("offset", np.zeros_like(gains)))
        channels = from_attr(ds.attrs.get("channels", np.array(CHANNELS, dtype=object)))
    return {
        str(c): {"gain": float(gains[i]), "offset": float(offsets[i])}
        for i, c in enumerate(channels)
        if i < gains.size
    }


def list_sessions(path: StrPath) -> list[dict[str, Any]]:
    """Summaries of every session in `path`, oldest first.

    Returns
    -------
    list of dict
        Keys ``name``, ``tissue``, ``samples``, ``duration_s`` (s), ``rate_hz`` (Hz,
        from the median sample interval), ``frames_lost``, ``frames_bad``,
        ``complete``, ``start_utc`` (ISO 8601), ``source``.
    """
    file = os.fspath(path)
    out: list[dict[str, Any]] = []
    with opened(file, "r") as f:
        root = _sessions_root(f)
        if root is None:
            return []
        for key, g in root.items():
            if not isinstance(g, h5py.Group) or not isinstance(g.get("time"), h5py.Dataset):
                continue
            try:
                attrs = decode_attrs(g.attrs)
                n = usable_rows(g, columns_of(g))
                t = g["time"][:n]
            except (OSError, RuntimeError, KeyError) as exc:
                raise StorageError(unreadable(f'session "{key}" in {file}', exc)) from None
            steps = np.diff(t)
            out.append(
                {
                    "name": key,
                    "tissue": attrs.get("tissue", ""),
                    "samples": int(n),
                    "duration_s": float(t[-1] - t[0]) if n > 1 else 0.0,
                    "rate_hz": float(1.0 / np.median(steps))
                    if n > 1 and np.median(steps) > 0
                    else 0.0,
                    "frames_lost": int(attrs.get("frames_lost", 0) or 0),
                    "frames_bad": int(attrs.get("frames_bad", 0) or 0),
                    "complete": bool(attrs.get("complete", False)),
                    "start_utc": attrs.get("start_utc") or attrs.get("created_utc", ""),
                    "source": attrs.get("source", ""),
                }
            )
    out.sort(key=lambda s: (str(s["start_utc"]), s["name"]))
    return out
