"""Sessions in HDF5 files: ``/sessions/<name>`` groups of time, force and position (SI)
and, for recordings, the raw frames; written whole or streamed, read, listed."""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import h5py
import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..core.calibration import Adc, calibration_from_dict
from ..core.errors import InputError, SessionExists, StorageError
from ..core.session import QUANTITIES, Session, check_name
from .hdf5 import (
    CHUNK_ROWS,
    H5_ERRORS,
    INTEGERS,
    NUMBERS,
    Column,
    StrPath,
    check_schema,
    check_size,
    clip,
    count_value,
    damaged,
    dataset_problem,
    decode_attrs,
    exists_message,
    file_size,
    first_line,
    flag_value,
    foreign_message,
    group_names,
    has_group,
    is_own_file,
    number_value,
    opened,
    start_key,
    unreadable,
    usable_rows,
)
from .space import HEADROOM_BYTES, check_free_space, preflight_bytes
from .writer import SeriesWriter, row_bytes

#: parent group of every recorded or imported session
SESSIONS = "sessions"
#: keys of ``Session.meta`` that exist only in memory and are never stored as attributes
READ_ONLY_META = ("file", "raw", "calibration", "warnings")
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


#: the device's clock faults a recording counts (docs/protocol.md), listed when non-zero
CLOCK_FAULTS = ("clock_jumps", "clock_steps", "sequence_restarts", "frames_rejected")

#: what each dataset of a session must hold: dtype kinds and the shape of one row
SESSION_SCHEMA: dict[str, tuple[str, tuple[int, ...]]] = {
    col.name: (INTEGERS if np.dtype(col.dtype).kind in "iu" else NUMBERS, col.shape)
    for col in SESSION_COLUMNS
}
#: datasets every session has; the raw ones exist only for recordings
REQUIRED = tuple(q.name for q in QUANTITIES)
#: session attributes read as something other than free text, and what they must be;
#: a value of another type is treated as missing and named in ``warnings``
ATTR_KINDS = {
    "schema_version": "count",
    "rows_committed": "count",
    "frames_good": "count",
    "frames_lost": "count",
    "frames_bad": "count",
    "frames_rejected": "count",
    "clock_jumps": "count",
    "clock_steps": "count",
    "sequence_restarts": "count",
    "complete": "flag",
    "rate_hz": "number",
    "clock_hz": "number",
    "tissue": "text",
    "specimen": "text",
    "operator": "text",
    "note": "text",
    "source": "text",
    "start_utc": "text",
    "created_utc": "text",
    "software_version": "text",
    "stop_reason": "text",
    "import_samples_lost": "count",
    "import_lines_skipped": "count",
    "clock_map": "mapping",
    "device": "mapping",
}
_KIND_WORDS = {
    "count": "a whole number >= 0",
    "flag": "true or false",
    "number": "a number",
    "text": "text",
    "mapping": "a JSON object",
}


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
        If the file exists but is not a readable HDF5 file or was not written by
        tissuecli, its directory is missing, or its drive has less than
        :data:`~.space.HEADROOM_BYTES` free.
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
    else:
        with opened(file, "r") as f:
            try:
                own = is_own_file(f)
                taken = own and group in f
            except H5_ERRORS as exc:
                raise damaged(file, "the root group", exc) from None
            if not own:
                raise StorageError(foreign_message(file, "--out"))
            if taken:
                raise SessionExists(exists_message("session", name, file))
    check_free_space(file, HEADROOM_BYTES, what="a new session")


def session_writer(
    path: StrPath,
    name: str,
    *,
    meta: Mapping[str, Any],
    calibration: Mapping[str, Mapping[str, float]] | None,
    raw: bool = True,
    flush_interval_s: float = 0.25,
    fsync: bool = True,
    min_free_bytes: int | None = None,
    chunk_rows: int = CHUNK_ROWS,
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
    flush_interval_s, fsync, chunk_rows
        See :class:`SeriesWriter`.
    min_free_bytes : int, optional
        Free space needed before the file is touched, bytes; by default 10 s of data
        at ``meta['rate_hz']`` (if given) plus 1 MiB (:func:`~.space.preflight_bytes`).

    Returns
    -------
    SeriesWriter
        Takes blocks with keys ``time``, ``force``, ``position`` (+ ``raw/*``).

    Raises
    ------
    SessionExists
        If the file already holds a session of that name.
    StorageError
        If the drive lacks `min_free_bytes`, or the file cannot be written.
    """
    group = session_group(name)
    attrs = {k: v for k, v in meta.items() if k not in READ_ONLY_META}
    attrs.setdefault("source", "device" if raw else "import")
    columns = session_columns(raw=raw, calibration=calibration)
    if min_free_bytes is None:
        rate = number_value(meta.get("rate_hz"))
        min_free_bytes = preflight_bytes((rate or 0.0) * row_bytes(columns))
    return SeriesWriter(
        path,
        group,
        columns,
        attrs,
        flush_interval_s=flush_interval_s,
        fsync=fsync,
        kind="session",
        min_free_bytes=min_free_bytes,
        chunk_rows=chunk_rows,
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
    StorageError
        If the drive cannot hold the session plus 1 MiB, or writing fails.
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
    # the whole session is known: room for every chunk of it plus the headroom
    chunks = -(-n // CHUNK_ROWS) * CHUNK_ROWS
    need = chunks * row_bytes(session_columns(raw=raw is not None)) + HEADROOM_BYTES
    with session_writer(
        path,
        session.name,
        meta=session.meta,
        calibration=calibration,
        raw=raw is not None,
        flush_interval_s=float("inf"),
        min_free_bytes=need,
    ) as writer:
        writer.append(block)


def session_names(path: StrPath) -> list[str]:
    """Names of the sessions in `path`, oldest first."""
    return group_names(path, SESSIONS)


def _pick_session(path: str, name: str | None) -> str:
    # a named session is one lookup: listing a file of many sessions for each of them
    # read them in quadratic time (400 sessions of one file took 37 s to read)
    if name is not None and "/" not in name and has_group(path, SESSIONS, name):
        return name
    names = session_names(path)
    if name is None:
        if len(names) == 1:
            return names[0]
        if not names:
            raise StorageError(f"{path} holds no sessions; record or import one first")
        raise StorageError(
            f"{path} holds {len(names)} sessions ({clip(', '.join(names), 200)}); "
            "pass --session NAME"
        )
    if name not in names:
        available = clip(", ".join(names), 200) if names else "none"
        raise StorageError(
            f'no session "{clip(name)}" in {path}; available: {available}; pass one with --session'
        )
    return name


class _Damage(StorageError):
    """A session group that does not follow the documented layout."""

    def __init__(self, where: str, reason: str) -> None:
        super().__init__(f"{where} is damaged: {reason}")
        self.reason = reason


@dataclass
class _Checked:
    """A session group checked against the layout (see :func:`_check_session`)."""

    datasets: dict[str, h5py.Dataset]
    attrs: dict[str, Any]
    rows: int
    complete: bool
    warnings: list[str] = field(default_factory=list)


def _check_session(f: h5py.File, g: h5py.Group, where: str) -> _Checked:
    """Check a session group against docs/formats.md.

    Datasets ``time``, ``force``, ``position`` must exist; they and any ``raw/*``
    dataset must be numeric (integers for ``raw/counts``, ``raw/sequence``,
    ``raw/device_clock``) with one row per sample. Attributes of :data:`ATTR_KINDS`
    of another type are dropped and named in ``warnings``.

    Raises
    ------
    StorageError
        ``_Damage`` naming the dataset that breaks the layout, or a newer schema.
    """
    warnings: list[str] = []
    try:
        attrs = _checked_attrs(decode_attrs(g.attrs, warnings), warnings)
    except H5_ERRORS as exc:
        raise _Damage(where, f"its attributes cannot be read ({first_line(exc)})") from None
    check_schema(attrs.get("schema_version"), where)
    datasets: dict[str, h5py.Dataset] = {}
    for key, (kinds, trailing) in SESSION_SCHEMA.items():
        try:
            link = g.get(key, getlink=True)
            obj = None if link is None or isinstance(link, h5py.ExternalLink) else g.get(key)
        except H5_ERRORS as exc:
            raise _Damage(where, f"dataset {key} cannot be read ({first_line(exc)})") from None
        if isinstance(link, h5py.ExternalLink):
            raise _Damage(where, f"dataset {key} is a link to another file")
        if obj is None and key not in REQUIRED:
            continue
        problem = dataset_problem(obj, kinds, trailing)
        if problem:
            raise _Damage(where, f"dataset {key} {problem}")
        datasets[key] = obj
    complete = attrs.get("complete")
    n = usable_rows(
        [ds.shape[0] for ds in datasets.values()], complete, attrs.get("rows_committed")
    )
    size = file_size(f)
    for key, ds in datasets.items():
        problem = check_size(ds, n, size)
        if problem:
            raise _Damage(where, f"dataset {key} {problem}")
    return _Checked(datasets, attrs, n, complete is True, warnings)


_CHECKS = {"count": count_value, "flag": flag_value, "number": number_value}


def _checked_attrs(attrs: dict[str, Any], warnings: list[str]) -> dict[str, Any]:
    """`attrs` with the values of :data:`ATTR_KINDS` checked; wrong ones dropped and named."""
    out = dict(attrs)
    for key, kind in ATTR_KINDS.items():
        if key not in out:
            continue
        value = out.pop(key)
        if value is None:  # an empty attribute: stored as missing
            continue
        if kind == "text":
            checked = value if isinstance(value, str) else None
        elif kind == "mapping":
            checked = value if isinstance(value, dict) else None
        else:
            checked = _CHECKS[kind](value)
        if checked is None:
            warnings.append(
                f"attribute {key} is {_describe_value(value)}, not {_KIND_WORDS[kind]}; ignored"
            )
        else:
            out[key] = checked
    return out


def _describe_value(value: Any) -> str:
    if isinstance(value, str):
        return "text"
    if isinstance(value, (bool, np.bool_)):
        return "a boolean"
    if isinstance(value, (int, float, np.integer, np.floating)):
        return "a number out of range"
    if isinstance(value, dict):
        return "a JSON object"
    if isinstance(value, list):
        return "a list"
    if isinstance(value, np.ndarray):
        return f"an array of shape {value.shape}"
    return f"a {type(value).__name__}"


def _open_session(f: h5py.File, file: str, name: str) -> h5py.Group:
    try:
        g = f.get(session_group(name))
    except H5_ERRORS as exc:
        where = f'session "{clip(name)}" in {file}'
        raise _Damage(where, f"cannot be opened ({first_line(exc)})") from None
    if not isinstance(g, h5py.Group):
        raise StorageError(
            f'no session "{clip(name)}" in {file}; list them with tissuecli sessions'
        )
    return g


HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


def is_session_file(path: StrPath) -> bool:
    """Whether ``path`` is an HDF5 file of tissuecli's (its signature at the start and
    tissuecli's root attributes, or empty), rather than a recording of another logger
    (text, .npz, a MATLAB v7.3 file, whose HDF5 signature follows a 512-byte header,
    or other HDF5 data). A file that cannot be read counts as one by its suffix, so
    that reading it gives the session reader's message."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(len(HDF5_SIGNATURE))
    except OSError:
        return os.fspath(path).lower().endswith((".h5", ".hdf5"))
    if head != HDF5_SIGNATURE:
        return False
    try:
        with h5py.File(path, "r") as f:
            return is_own_file(f)
    except (OSError, RuntimeError, KeyError, ValueError):
        return True  # damaged: the session reader says how


def session_rows(path: StrPath, name: str | None = None) -> int:
    """How many usable rows a session holds, from its datasets' shapes and attributes
    (nothing is read but the layout)."""
    file = os.fspath(path)
    name = _pick_session(file, name)
    with opened(file, "r") as f:
        return _check_session(
            f, _open_session(f, file, name), f'session "{clip(name)}" in {file}'
        ).rows


def read_session(
    path: StrPath,
    name: str | None = None,
    *,
    raw: bool = False,
    rows: tuple[int, int] | None = None,
) -> Session:
    """Read one session, checked against the documented layout.

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
    rows : (int, int), optional
        Read only rows [start, stop) (clipped to the usable rows), so that a session
        longer than memory can be read block by block.

    Returns
    -------
    Session
        time in s, force in N, position in m; ``meta`` holds the group attributes
        plus ``'file'``, and ``'warnings'`` if attributes of the wrong type were
        ignored. A session cut short by a crash (``meta['complete']`` False) holds
        the rows committed before the crash.

    Raises
    ------
    StorageError
        Missing, non-HDF5 or damaged file; no or several sessions without a name;
        unknown name; a session whose datasets are not numeric with one row per sample
        (the message names the file, the session and the dataset).
    """
    file = os.fspath(path)
    name = _pick_session(file, name)
    where = f'session "{clip(name)}" in {file}'
    with opened(file, "r") as f:
        checked = _check_session(f, _open_session(f, file, name), where)
        keys = [k for k in checked.datasets if raw or not k.startswith("raw/")]
        try:
            a, b = (0, checked.rows) if rows is None else rows
            a, b = max(0, a), min(b, checked.rows)
            columns = {key: checked.datasets[key][a:b] for key in keys}
            counts = checked.datasets.get("raw/counts")
            calibration = _read_calibration(counts, checked.warnings) if counts else {}
        except H5_ERRORS as exc:
            raise StorageError(unreadable(where, exc)) from None
    meta = checked.attrs
    meta["file"] = file
    if checked.warnings:
        meta["warnings"] = checked.warnings
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


def _read_calibration(ds: h5py.Dataset, warnings: list[str]) -> dict[str, dict[str, float]]:
    """Counts-to-SI calibration from the NWB attributes of ``raw/counts`` ({} if none)."""
    attrs = decode_attrs(ds.attrs, warnings)
    if attrs.get("conversion") is None:
        return {}
    gains = _numbers(attrs["conversion"])
    offsets = _numbers(attrs.get("offset", 0.0))
    channels = attrs.get("channels", list(CHANNELS))
    if gains is None or offsets is None or not all(isinstance(c, str) for c in channels):
        warnings.append("the calibration attributes of raw/counts are not numbers; ignored")
        return {}
    if offsets.size < gains.size:
        offsets = np.resize(offsets, gains.shape)
    return {
        str(c): {"gain": float(gains[i]), "offset": float(offsets[i])}
        for i, c in enumerate(channels)
        if i < gains.size
    }


def _numbers(value: Any) -> NDArray[np.float64] | None:
    """A numeric attribute as a 1-D float array (None if it is not numeric)."""
    arr = np.atleast_1d(np.asarray(value, dtype=object if isinstance(value, list) else None))
    if arr.dtype == object:
        if not all(number_value(v) is not None for v in arr.ravel()):
            return None
        arr = arr.astype(float)
    if arr.dtype.kind not in NUMBERS or arr.size == 0:
        return None
    return arr.ravel().astype(np.float64)


def list_sessions(path: StrPath) -> list[dict[str, Any]]:
    """Summaries of every session in `path`, oldest first; damaged ones included.

    Returns
    -------
    list of dict
        Keys ``name``; ``status``: ``'complete'``, ``'incomplete'`` (still being
        recorded, or cut short by a crash or a fault) or ``'damaged: <reason>'``;
        ``tissue``, ``samples``, ``duration_s`` (s), ``rate_hz`` (Hz, from the median
        sample interval), ``frames_lost``, ``frames_bad``, ``complete``, ``start_utc``
        (ISO 8601), ``source``, ``clock_faults`` (the non-zero counts of
        :data:`CLOCK_FAULTS`: clock jumps and steps, sequence restarts, frames rejected),
        ``warnings`` (attributes of the wrong type that were ignored), ``stop_reason``,
        ``ended`` (why it ended in a word or two, see :func:`ended`), and for an imported
        session ``import_samples_lost`` and ``import_lines_skipped`` (what the import
        counted; None otherwise). Numbers a
        damaged session cannot give are None.

    Raises
    ------
    StorageError
        If the file is missing, not HDF5, or its list of sessions cannot be read.
    """
    file = os.fspath(path)
    out: list[dict[str, Any]] = []
    with opened(file, "r") as f:
        try:
            root = f.get(SESSIONS)
            keys = list(root.keys()) if isinstance(root, h5py.Group) else []
        except H5_ERRORS as exc:
            raise damaged(file, f"/{SESSIONS}", exc) from None
        for key in keys:
            try:
                g = root.get(key)
            except H5_ERRORS as exc:
                out.append(_damaged_row(key, "", f"cannot be opened ({first_line(exc)})"))
                continue
            if isinstance(g, h5py.Group):
                out.append(_summary(f, g, file, key))
    out.sort(key=lambda s: (str(s["start_utc"]), s["name"]))
    return out


def _summary(f: h5py.File, g: h5py.Group, file: str, key: str) -> dict[str, Any]:
    """One row of :func:`list_sessions`."""
    try:
        checked = _check_session(f, g, f'session "{clip(key)}" in {file}')
        duration, step = _time_span(checked.datasets["time"], checked.rows)
    except _Damage as exc:
        return _damaged_row(key, start_key(g), exc.reason)
    except StorageError as exc:  # a newer schema
        return _damaged_row(key, start_key(g), str(exc), status="unreadable")
    except H5_ERRORS as exc:
        return _damaged_row(key, start_key(g), f"cannot be read ({first_line(exc)})")
    attrs, n = checked.attrs, checked.rows
    return {
        "name": key,
        "status": "complete" if checked.complete else "incomplete",
        "tissue": attrs.get("tissue", ""),
        "samples": int(n),
        "duration_s": duration if math.isfinite(duration) else None,
        "rate_hz": 1.0 / step if math.isfinite(step) and step > 0 else 0.0,
        "frames_lost": attrs.get("frames_lost", 0),
        "frames_bad": attrs.get("frames_bad", 0),
        "complete": checked.complete,
        "start_utc": attrs.get("start_utc") or attrs.get("created_utc", ""),
        "source": attrs.get("source", ""),
        "clock_faults": {k: attrs[k] for k in CLOCK_FAULTS if attrs.get(k)},
        "warnings": checked.warnings,
        "stop_reason": attrs.get("stop_reason", ""),
        "ended": ended(attrs, checked.complete),
        "import_samples_lost": attrs.get("import_samples_lost"),
        "import_lines_skipped": attrs.get("import_lines_skipped"),
    }


#: how a stop reason begins -> why the session ended, in a word or two
ENDINGS = (
    ("duration reached", "duration"),
    ("interrupted by signal", "signal"),
    ("interrupted", "signal"),
    ("device lost", "device lost"),
    ("storage fault: disk full", "disk full"),
    ("storage fault: disk quota", "disk quota"),
    ("storage fault: file size limit", "file size limit"),
    ("storage fault", "storage fault"),
    ("error", "error"),
)


def ended(attrs: Mapping[str, Any], complete: bool) -> str:
    """Why a session ended, in a word or two: ``duration``, ``signal``, ``device lost``,
    ``disk full`` (and other storage faults), ``error``, ``imported`` (read from another
    logger's file), ``crashed`` (never closed, no reason: the recorder was killed or
    is still running), or the stop reason itself when it is none of these."""
    reason = str(attrs.get("stop_reason") or "")
    for start, word in ENDINGS:
        if reason.startswith(start):
            return word
    if reason:
        return reason[:40]
    if "import_samples_lost" in attrs or "import_units" in attrs:
        return "imported"
    return "" if complete else "crashed"


#: rows of the time column a summary reads: blocks spread over the session
SUMMARY_BLOCKS, SUMMARY_ROWS = 16, 1 << 15


def _time_span(ds: h5py.Dataset, n: int) -> tuple[float, float]:
    """Duration (s) and median sample interval (s) of a session's first `n` times, read
    in at most :data:`SUMMARY_BLOCKS` blocks of :data:`SUMMARY_ROWS` rows spread over the
    session, so that listing any file takes a few megabytes whatever its length."""
    if n < 2:
        return 0.0, float("nan")
    starts = np.unique(np.linspace(0, max(0, n - SUMMARY_ROWS), SUMMARY_BLOCKS).astype(np.int64))
    steps = [np.diff(np.asarray(ds[i : min(n, i + SUMMARY_ROWS)], np.float64)) for i in starts]
    return float(ds[n - 1]) - float(ds[0]), float(np.median(np.concatenate(steps)))


def _damaged_row(key: str, start: str, reason: str, status: str = "damaged") -> dict[str, Any]:
    return {
        "stop_reason": "",
        "ended": "",
        "import_samples_lost": None,
        "import_lines_skipped": None,
        "name": key,
        "status": f"{status}: {reason}",
        "tissue": "",
        "samples": None,
        "duration_s": None,
        "rate_hz": None,
        "frames_lost": None,
        "frames_bad": None,
        "complete": False,
        "start_utc": start,
        "source": "",
        "clock_faults": {},
        "warnings": [],
    }


def discard_session(path: StrPath, name: str, created: bool) -> None:
    """Remove session `name` that an import left unfinished (its source turned out bad
    part way): the file too if the import created it, else only the group."""
    file = os.fspath(path)
    if not os.path.exists(file):
        return
    if created:
        try:
            os.remove(file)
        except OSError:
            pass
        return
    try:
        with h5py.File(file, "a") as f:
            group = session_group(name)
            if group in f:
                del f[group]
    except H5_ERRORS:
        pass  # left marked incomplete, as any interrupted write
