"""The batch ``fit`` service: many inputs (files, folders, globs, every session of an HDF5
file) fitted on all cores (joblib/loky) or on a Dask cluster, each worker's BLAS pinned
to one thread; results go to the catalogue, written by this (the parent) process only.

A fit's key is the SHA-256 of the session's samples (SI, as read) and of the fit
settings: a key already in the catalogue is not fitted again (``refit`` forces it), so a
repeated command refits nothing and an interrupted one resumes.
"""

from __future__ import annotations

import csv
import glob
import hashlib
import json
import os
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import nullcontext
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from ..core import errors
from ..core.errors import InputError, TissueError
from ..core.session import Session
from ..formats.catalogue import LABELS, Catalogue, Fit, FitRows, fit_rows
from ..formats.params import _finite as finite_tree
from ..formats.params import document
from ..formats.sessions import is_session_file, session_names
from .transfer import load_session

#: file suffixes a folder is searched for (sessions and every recording ``import`` reads)
SUFFIXES = (".h5", ".hdf5", ".csv", ".tsv", ".txt", ".dat", ".mat", ".npz")
#: the fit settings a key is made of (keywords of :func:`fit_session`)
SETTINGS = (
    "method", "forms", "sampler", "differentiator", "window_s", "force_scale", "seed",
    "grasps", "start_s", "end_s", "hold_out",
)  # fmt: skip

#: environment variables that set the threads of BLAS and OpenMP in a worker
BLAS_VARS = (
    "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS", "NUMBA_NUM_THREADS", "NUMEXPR_NUM_THREADS",
)  # fmt: skip


@dataclass(frozen=True)
class Input:
    """One session to fit: a file, and the session's name in it (None: the file's only
    session, or a recording read on the fly)."""

    file: str
    session: str | None = None

    def __str__(self) -> str:
        return self.file if self.session is None else f"{self.file}:{self.session}"


def expand_inputs(paths: Sequence[str | Input], session: str | None = None) -> list[Input]:
    """Every session the arguments name: a file (each session of a tissuecli HDF5 file,
    or ``session`` alone), a folder (its files with a suffix in :data:`SUFFIXES`, at any
    depth) or a glob pattern (``'data/**/*.h5'``); in order, without repeats.

    Raises
    ------
    InputError
        A path that does not exist, a pattern or folder that matches nothing.
    """
    if all(isinstance(p, Input) for p in paths):
        return list(dict.fromkeys(paths))  # type: ignore[arg-type]
    files: list[str] = []
    for p in map(str, paths):
        if os.path.isdir(p):
            found = sorted(
                str(f) for f in Path(p).rglob("*") if f.is_file() and f.suffix.lower() in SUFFIXES
            )
            if not found:
                raise InputError(
                    f"folder {p} holds no sessions or recordings ({', '.join(SUFFIXES)})"
                )
            files += found
        elif os.path.exists(p):
            files.append(p)
        elif glob.has_magic(p):
            found = sorted(f for f in glob.glob(p, recursive=True) if os.path.isfile(f))
            if not found:
                raise InputError(f"no file matches {p}")
            files += found
        else:
            raise InputError(f"no file {p}; give files, folders or patterns such as 'data/*.h5'")
    out: list[Input] = []
    for f in dict.fromkeys(files):
        if is_session_file(f):
            names = session_names(f) if session is None else [session]
            out += [Input(f, n) for n in names]
        else:
            out.append(Input(f, session))
    return list(dict.fromkeys(out))


def read_manifest(path: str | os.PathLike[str]) -> dict[tuple[str, str | None], dict[str, str]]:
    """Labels from a manifest CSV: columns ``file`` (relative to the manifest's folder,
    or absolute), optionally ``session`` (empty: every session of the file), then
    ``tissue``, ``specimen``, ``operator``, ``note`` and any other label.

    Returns
    -------
    dict
        ``(absolute file, session or None)`` to the row's labels.
    """
    base = Path(path).resolve().parent
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:
            rows = list(csv.DictReader(fh))
            header = rows[0].keys() if rows else []
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"cannot read the manifest {path}: {exc}") from None
    if "file" not in header:
        raise InputError(
            f"manifest {path} has no 'file' column; give columns file[,session],tissue,specimen,..."
        )
    out = {}
    for i, row in enumerate(rows, 2):
        name = (row.pop("file") or "").strip()
        if not name:
            raise InputError(f"manifest {path} line {i}: the file is empty")
        sess = (row.pop("session", None) or "").strip() or None
        labels = {k.strip(): (v or "").strip() for k, v in row.items() if k}
        out[(str((base / name).resolve()), sess)] = labels
    return out


def labels_of(
    item: Input,
    name: str,
    own: Mapping[str, str],
    manifest: Mapping[tuple[str, str | None], dict[str, str]],
    where: str | None = None,
) -> dict[str, str]:
    """The session's labels: its own attributes (``own``: tissue, specimen, operator,
    note), then the manifest's row for its file, then the row for the session itself
    (named ``name``); ``where`` is the file's absolute path, if known."""
    out = {k: str(own.get(k) or "") for k in LABELS}
    where = where or str(Path(item.file).resolve())
    for key in ((where, None), (where, name)):
        out.update({k: v for k, v in manifest.get(key, {}).items() if v != ""})
    return out


def content_sha256(session: Session) -> str:
    """SHA-256 of a session's samples (time, force, position as float64, SI)."""
    h = hashlib.sha256()
    for a in (session.time, session.force, session.position):
        h.update(np.ascontiguousarray(a, dtype="<f8").tobytes())
    return h.hexdigest()


def settings_json(settings: Mapping[str, Any]) -> str:
    return json.dumps({k: settings.get(k) for k in SETTINGS}, sort_keys=True)


def settings_id(settings: Mapping[str, Any]) -> str:
    """A short name for a set of fit settings (12 hex digits of their SHA-256)."""
    return hashlib.sha256(settings_json(settings).encode()).hexdigest()[:12]


def fit_key(content: str, settings: Mapping[str, Any]) -> str:
    """The catalogue key of a session's fit with ``settings``."""
    return hashlib.sha256(f"{content}\n{settings_json(settings)}".encode()).hexdigest()


# -- executors ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Task:
    """What a worker needs: where the session is (a worker on this machine reads it
    itself, so that the parent's time goes to storing results alone), or the session
    itself (``data``, for a cluster's workers, which may not see the file).

    Attributes
    ----------
    index : int
        The input's place in the batch.
    file, session
        Where to read the session (:func:`~.transfer.load_session`).
    settings : dict
        Keywords of :func:`fit_session`.
    reading : dict, optional
        How to read another logger's recording.
    expected : frozenset of str
        Keys the catalogue holds for this file and session with these settings: a
        session that hashes to one of them is not fitted again.
    data : Session, optional
        The session, read by the parent.
    """

    index: int
    file: str
    session: str | None
    settings: dict[str, Any]
    reading: dict[str, Any] | None = None
    expected: frozenset[str] = frozenset()
    data: Session | None = None


@dataclass(frozen=True)
class Done:
    """A worker's answer, compact: the session's name, hash and own labels, and the
    catalogue's rows of its fit (built by the worker), or the failure's one line.

    Attributes
    ----------
    stage : str
        Where a failure happened: "read" or "fit".
    error_class : str
        The failure's exception class (in :mod:`tissuecli.core.errors`).
    skipped : bool
        The session hashed to a key the task expected: not fitted.
    seconds : float
        Time the fit took (s); 0 when not fitted.
    """

    index: int
    name: str | None = None
    content: str | None = None
    key: str | None = None
    labels: dict[str, str] = field(default_factory=dict)
    rows: FitRows | None = None
    law: str | None = None
    probability: float | None = None
    error: str | None = None
    error_class: str = "InputError"
    stage: str = "fit"
    skipped: bool = False
    seconds: float = 0.0


#: whether this process's BLAS is pinned to one thread for good (a loky worker's is)
_pinned = False


def _pin_blas() -> None:
    """A loky worker's start: BLAS pinned to one thread once, not at every fit."""
    global _pinned
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1)
    _pinned = True


def _internal(exc: Exception) -> str:
    return f"internal error: {type(exc).__name__}: {exc}"


def run_task(task: Task) -> Done:
    """Read (unless given), hash and fit one session in a worker, its BLAS pinned to one
    thread; a failure is returned, not raised, so the batch goes on."""
    from threadpoolctl import threadpool_limits

    # loaded here, not with this module: a parent that only dispatches never needs it
    from ..identify.outcome import fit_session

    try:
        data = task.data
        if data is None:
            data, _ = load_session(task.file, task.session, **(task.reading or {}))
        content = content_sha256(data)
    except TissueError as exc:
        return Done(task.index, error=str(exc), error_class=type(exc).__name__, stage="read")
    except Exception as exc:  # a bug: one input's, kept from stopping the others
        return Done(task.index, error=_internal(exc), stage="read")
    key = fit_key(content, task.settings)
    own = {k: str(data.meta.get(k) or "") for k in LABELS}
    if key in task.expected:
        return Done(task.index, data.name, content, key, own, skipped=True)
    t0 = time.perf_counter()
    try:
        with threadpool_limits(limits=1) if not _pinned else nullcontext():
            outcome = fit_session(data, **task.settings)
        doc = finite_tree(document(outcome))
        law = doc.get("law") or {}
        return Done(
            task.index, data.name, content, key, own, fit_rows(doc), law.get("name"),
            law.get("probability"), seconds=time.perf_counter() - t0,
        )  # fmt: skip
    except TissueError as exc:
        error, cls = str(exc), type(exc).__name__
    except Exception as exc:  # a bug: one input's, kept from stopping the others
        error, cls = _internal(exc), "InputError"
    return Done(task.index, data.name, content, key, own, error=error, error_class=cls,
                seconds=time.perf_counter() - t0)  # fmt: skip


class Executor(ABC):
    """Runs tasks somewhere and yields their results as they finish, in any order."""

    #: shown in the summary
    name: str = ""
    #: whether the workers see this machine's files (then they read the sessions)
    reads_files: bool = True

    @abstractmethod
    def map(self, fn: Callable[[Task], Done], tasks: Iterable[Task]) -> Iterator[Done]: ...

    @property
    def workers(self) -> int:
        return 1


class SerialExecutor(Executor):
    """In this process, one task after another."""

    name = "this process"

    def map(self, fn: Callable[[Task], Done], tasks: Iterable[Task]) -> Iterator[Done]:
        for t in tasks:
            yield fn(t)


class LokyExecutor(Executor):
    """``jobs`` worker processes on this machine (joblib's loky backend)."""

    def __init__(self, jobs: int) -> None:
        self.jobs = jobs
        self.name = f"{jobs} worker processes"

    @property
    def workers(self) -> int:
        return self.jobs

    def map(self, fn: Callable[[Task], Done], tasks: Iterable[Task]) -> Iterator[Done]:
        from concurrent.futures import FIRST_COMPLETED, Future, wait

        from joblib.externals.loky import get_reusable_executor

        # BLAS pinned to 1 thread in each worker before it starts (as joblib's
        # inner_max_num_threads); futures waited on, not polled, so that the parent
        # sleeps while the workers fit
        pool = get_reusable_executor(
            max_workers=self.jobs, env=dict.fromkeys(BLAS_VARS, "1"), initializer=_pin_blas
        )
        # enough fits queued that no worker waits for the parent between two short fits
        # (with 2 per worker, 40 ms fits on 2 cores ran 1.5x faster than on one, not 1.9x)
        window = 8 * self.jobs
        running: set[Future[Done]] = set()
        todo = iter(tasks)
        try:
            while True:
                for t in todo:
                    running.add(pool.submit(fn, t))
                    if len(running) >= window:
                        break
                if not running:
                    return
                finished, running = wait(running, return_when=FIRST_COMPLETED)
                for f in finished:
                    yield f.result()
        except BaseException:
            # stopped (Ctrl-C, a signal, --on-error stop): no fit is left running
            for f in running:
                f.cancel()
            pool.shutdown(wait=False, kill_workers=True)
            raise


class DaskExecutor(Executor):
    """The workers of a running Dask distributed cluster (``tcp://HOST:PORT``), through
    joblib's dask backend. Its workers may not see this machine's files: the parent
    reads each session and sends it."""

    reads_files = False

    def __init__(self, address: str, *, timeout_s: float = 20.0) -> None:
        try:
            from distributed import Client
        except ImportError:
            raise InputError("--scheduler needs Dask: pip install 'tissuecli[dask]'") from None
        try:
            self.client = Client(address, timeout=f"{timeout_s}s", set_as_default=False)
        except (OSError, TimeoutError, ValueError) as exc:
            raise InputError(f"cannot reach the Dask scheduler at {address}: {exc}") from None
        self.address = address
        n = sum(w.get("nthreads", 1) for w in self.client.scheduler_info()["workers"].values())
        self._workers = max(n, 1)
        self.name = f"Dask cluster {address} ({self._workers} worker threads)"

    @property
    def workers(self) -> int:
        return self._workers

    def map(self, fn: Callable[[Task], Done], tasks: Iterable[Task]) -> Iterator[Done]:
        from joblib import Parallel, delayed, parallel_config

        try:
            with self.client.as_current(), parallel_config(backend="dask"):
                par = Parallel(n_jobs=-1, return_as="generator_unordered")
                yield from par(delayed(fn)(t) for t in tasks)
        finally:
            self.client.close()


def make_executor(jobs: int | None, scheduler: str | None, inputs: int) -> Executor:
    """The executor for ``--jobs`` / ``--scheduler``: a Dask cluster if a scheduler is
    given; else ``jobs`` processes (default: every core for several inputs, this
    process for one)."""
    if scheduler:
        if jobs is not None:
            raise InputError("give --jobs or --scheduler, not both (the cluster sets its workers)")
        return DaskExecutor(scheduler)
    if jobs is None:
        jobs = (
            len(os.sched_getaffinity(0))
            if hasattr(os, "sched_getaffinity")
            else os.cpu_count() or 1
        )
        jobs = min(jobs, max(inputs, 1))
    if jobs < 1:
        raise InputError(f"--jobs {jobs}: give 1 or more")
    return SerialExecutor() if jobs == 1 else LokyExecutor(jobs)


# -- the batch -----------------------------------------------------------------------------


@dataclass
class Fitted:
    """One input's result in the batch's report."""

    input: Input
    session: str
    law: str | None
    probability: float | None
    labels: dict[str, str]
    seconds: float


@dataclass
class BatchResult:
    """What a batch did.

    Attributes
    ----------
    inputs : int
        Sessions named.
    fitted : list of Fitted
        Fitted now.
    skipped : list of Input
        Already in the catalogue with the same settings (not fitted again).
    failed : list of (Input, str)
        Inputs that could not be read or fitted, with why.
    seconds : float
        Wall time.
    executor : str
        Where the fits ran.
    catalogue_fits : int or None
        Fits the catalogue holds afterwards.
    """

    inputs: int
    fitted: list[Fitted] = field(default_factory=list)
    skipped: list[Input] = field(default_factory=list)
    relabelled: int = 0
    failed: list[tuple[Input, str]] = field(default_factory=list)
    seconds: float = 0.0
    executor: str = ""
    catalogue_fits: int | None = None


Progress = Callable[[int, int, float | None], None]
#: the catalogue is written at most this often (s): the fits that arrived meanwhile in
#: one transaction
COMMIT_S = 0.5


def fit_batch(
    paths: Sequence[str | Input],
    *,
    session: str | None = None,
    catalogue: str | os.PathLike[str] | None = None,
    manifest: str | os.PathLike[str] | None = None,
    jobs: int | None = None,
    scheduler: str | None = None,
    on_error: str = "continue",
    refit: bool = False,
    reading: dict[str, Any] | None = None,
    progress: Progress | None = None,
    **settings: Any,
) -> BatchResult:
    """Fit every session ``paths`` name, in parallel, into the catalogue.

    Parameters
    ----------
    paths : sequence of str or Input
        Files, folders or glob patterns (:func:`expand_inputs`), or the inputs it made.
    session : str, optional
        Fit only this session of each HDF5 file.
    catalogue : path, optional
        SQLite catalogue to add the fits to (created if missing); without one nothing
        is stored and nothing skipped.
    manifest : path, optional
        Labels by file and session (:func:`read_manifest`).
    jobs, scheduler
        See :func:`make_executor`.
    on_error : {"continue", "stop"}
        Go on after a failed input and list the failures at the end, or stop at the
        first (raising its error).
    refit : bool
        Fit inputs already in the catalogue again.
    reading : dict, optional
        How to read recordings of other loggers (see :func:`~.transfer.load_session`).
    progress : callable, optional
        ``progress(done, total, seconds_left or None)`` as inputs finish.
    **settings
        Keywords of :func:`~tissuecli.identify.fit_session` (method, forms, ...).
    """
    if on_error not in ("continue", "stop"):
        raise InputError(f"--on-error {on_error}: choose continue or stop")
    t0 = time.perf_counter()
    items = expand_inputs(paths, session)
    labels_by = read_manifest(manifest) if manifest else {}
    settings = {k: v for k, v in settings.items() if k in SETTINGS}
    settings["grasps"] = settings.get("grasps", "all")
    sid = settings_id(settings)
    store = Catalogue(catalogue) if catalogue is not None else None
    result = BatchResult(inputs=len(items))
    unsaved: list[Fit] = []
    last_save = time.perf_counter()

    def save() -> None:
        # one transaction for the fits of the last COMMIT_S: one write to the disk
        nonlocal last_save
        if store is not None and unsaved:
            fits = list(unsaved)
            unsaved.clear()
            store.add_many(fits)
        last_save = time.perf_counter()

    try:
        catalogued = store.keys() if store is not None and not refit else set()
        by_place = store.keys_by_place(sid) if store is not None and not refit else {}
        executor = make_executor(jobs, scheduler, len(items))
        result.executor = executor.name
        resolved = {f: str(Path(f).resolve()) for f in dict.fromkeys(i.file for i in items)}
        stored: set[str] = set()  # keys fitted in this batch
        total = len(items)
        finished = 0
        fit_times: list[float] = []

        def tick() -> None:
            if progress is None:
                return
            left = total - finished
            eta = None
            if fit_times:
                per = (time.perf_counter() - t_fit) / len(fit_times)
                eta = per * left
            progress(finished, total, eta)

        def fail(item: Input, done: Done) -> None:
            error = done.error or "no result"
            if on_error == "stop":
                if done.stage == "read":
                    cls = getattr(errors, done.error_class, InputError)
                    raise (cls if issubclass(cls, TissueError) else InputError)(error)
                raise InputError(f"{item}: {error}")
            result.failed.append((item, error))

        def tasks() -> Iterator[Task]:
            nonlocal finished
            sent: set[str] = set()
            for i, item in enumerate(items):
                if executor.reads_files:
                    name = item.session or (reading or {}).get("sheet") or Path(item.file).stem
                    expected = frozenset(by_place.get((resolved[item.file], name), ()))
                    yield Task(i, item.file, item.session, settings, reading, expected)
                    continue
                try:
                    data, _ = load_session(item.file, item.session, **(reading or {}))
                except TissueError as exc:
                    fail(item, Done(i, error=str(exc), error_class=type(exc).__name__,
                                    stage="read"))  # fmt: skip
                    finished += 1
                    tick()
                    continue
                key = fit_key(content_sha256(data), settings)
                if key in catalogued or key in sent:
                    own = {k: str(data.meta.get(k) or "") for k in LABELS}
                    skip(item, key, labels_of(item, data.name, own, labels_by, resolved[item.file]))
                    finished += 1
                    tick()
                    continue
                sent.add(key)  # the same samples twice in one batch: fitted once
                yield Task(i, item.file, item.session, settings, data=data)

        def skip(item: Input, key: str, labels: dict[str, str]) -> None:
            result.skipped.append(item)
            if store is not None and key in catalogued:
                result.relabelled += store.relabel(key, labels)

        t_fit = time.perf_counter()
        tick()
        for done in executor.map(run_task, tasks()):
            item = items[done.index]
            finished += 1
            if done.error is not None:
                fail(item, done)
            elif done.key is not None and done.name is not None and done.content is not None:
                labels = labels_of(item, done.name, done.labels, labels_by, resolved[item.file])
                if done.skipped or done.key in catalogued or done.key in stored:
                    skip(item, done.key, labels)
                elif done.rows is not None:
                    stored.add(done.key)
                    unsaved.append(
                        Fit(
                            done.key, resolved[item.file], done.name, done.content, settings,
                            sid, labels, done.rows,
                            datetime.now(timezone.utc).isoformat(timespec="seconds"),
                            done.seconds,
                        )
                    )  # fmt: skip
                    result.fitted.append(
                        Fitted(item, done.name, done.law, done.probability, labels,
                               done.seconds)
                    )  # fmt: skip
                    fit_times.append(done.seconds)
            if time.perf_counter() - last_save >= COMMIT_S:
                save()
            tick()
        save()
        order = {item: i for i, item in enumerate(items)}
        result.fitted.sort(key=lambda f: order[f.input])
        result.skipped.sort(key=lambda f: order[f])
        result.failed.sort(key=lambda f: order[f[0]])
        if store is not None:
            result.catalogue_fits = len(store.keys())
    finally:
        if store is not None:
            try:
                save()  # what finished before a failure or an interruption is kept
            finally:
                store.close()
    result.seconds = time.perf_counter() - t0
    return result
