"""A resumable, crash-safe HDF5 learning database filled by jobs on any executor.

A database is one HDF5 file built from *jobs* (one simulation each, with a stable
``key`` and JSON ``params``) run by a picklable ``worker(params) -> Record`` on any
``concurrent.futures``-style executor: local processes by default
(``ProcessPoolExecutor``), in-process with ``workers=0``, or a Dask cluster (pass a
``dask.distributed.Client``; its ``get_executor()`` is used).

Safety:

- only the main process writes; each finished job is first written as its own small
  *shard* file (``<db>.shards/<key>.h5``, atomically renamed into place), so a crash or
  Ctrl-C loses at most the jobs still running;
- shards are merged into the main file copy-on-write (a copy is extended and renamed
  over the original), every ``merge_every`` seconds, at the end, on Ctrl-C, SIGTERM or
  SIGHUP (a cluster's time limit, a closed terminal) or a failure (a second Ctrl-C waits
  for that merge) and at the next start: the main file is always a
  consistent database, and after an interrupt it alone holds every finished job;
- the keys of the last run's jobs are stored (root attribute ``planned``), so a reader
  tells a finished database from an interrupted one (:func:`database_status`: "N of M
  done; rerun the same command to finish it");
- one run at a time: a run holds ``<db>.lock`` (``flock``), and a second command on the
  same file is refused ("being filled by another process") instead of racing its merges;
- a job that raised is recorded with its reason and traceback under ``/failures`` and
  skipped on the next run unless ``retry_failed``.

Layout: root attributes ``format`` (a tag naming the kind of database), ``format_version``,
``config`` (JSON: what generated it; a rerun with another configuration is refused,
naming the differences, except for the keys the database ``grows`` along) and ``planned``
(JSON list of the last run's job keys); ``/shared/...`` arrays common to every record (a mesh);
``/records/<key>/`` each record's arrays with ``params`` (JSON) and its scalar ``attrs``;
``/failures/<key>`` (``reason``, ``traceback``, ``params``); ``/index``, a table with one
row per record (key, params, scalar attributes). :func:`read_index` reads it (or another table
of the file, such as a static database's ``/samples``) as a DataFrame with ``str`` strings::

    from toolkit.common.training.database import read_index
    index = read_index("db.h5")

HDF5 has no text type that h5py returns as ``str`` inside a table (its variable-length strings
come back as ``bytes``), so a reader with h5py and pandas alone decodes them::

    with h5py.File("db.h5") as f:
        index = pd.DataFrame(f["index"][()])
    index = index.apply(lambda c: c.str.decode("utf-8") if c.dtype == object else c)
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import signal
import threading
import time
import traceback
import warnings
from collections.abc import Callable, Iterable, Mapping
from concurrent.futures import FIRST_COMPLETED, Executor, Future, ProcessPoolExecutor, wait
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from toolkit.common.config_diff import jsonable, require_same
from toolkit.common.errors import ToolkitError
from toolkit.common.meshes.io import atomic_path, ensure_room
from toolkit.common.runtime import count_finished, default_threads, deferred_interrupt, set_threads

__all__ = ["Job", "Record", "RunReport", "DatabaseError", "Database", "run_jobs", "read_index", "read_failures",
           "InProcessExecutor", "DatabaseStatus", "database_status", "IncompleteDatabaseWarning",
           "check_complete", "deferred_interrupt"]

log = logging.getLogger(__name__)


class DatabaseError(ToolkitError, ValueError):
    """A file is not a database of the expected kind, version or configuration, or is unreadable."""


class IncompleteDatabaseWarning(UserWarning):
    """A database is used while some jobs of its last run are not finished (it was interrupted)."""


@dataclass(frozen=True)
class DatabaseStatus:
    """How far the last run of a database got: ``done`` records and ``failed`` jobs among the
    ``planned`` ones (``planned`` is None for a file that does not record it), ``records`` held in
    all, ``pending`` finished jobs still in ``<db>.shards/`` (merged by the next run), and whether
    a run is filling it now (``running``: another process holds its lock)."""

    path: Path
    done: int
    failed: int
    planned: int | None
    records: int
    pending: int
    running: bool = False

    @property
    def complete(self) -> bool:
        """Every planned job finished (done or failed) and merged."""
        return self.pending == 0 and (self.planned is None or self.done + self.failed >= self.planned)

    def message(self, command: str = "the same command") -> str:
        """``interrupted database FILE: N of M simulations done; rerun ... to finish it`` (or, while
        a run fills it, ``database FILE is being filled by another process: N of M ...``)."""
        total = self.records if self.planned is None else self.planned
        finished = self.records if self.planned is None else self.done
        if self.running:
            return (f"database {self.path} is being filled by another process: {finished} of {total} simulations "
                    f"done so far; wait for it to finish")
        text = f"interrupted database {self.path}: {finished} of {total} simulations done"
        if self.failed:
            text += f", {self.failed} failed"
        if self.pending:
            text += f", {self.pending} more finished in {self.path.name}.shards/ (not yet merged)"
        return text + f"; rerun {command} to finish it"


@dataclass(frozen=True)
class Job:
    """One unit of work: ``key`` (unique, stable across runs, no ``/``) and JSON ``params``."""

    key: str
    params: Mapping = field(default_factory=dict)

    def __post_init__(self):
        if not isinstance(self.key, str) or not self.key or "/" in self.key or self.key.startswith("."):
            raise ValueError(f"job key {self.key!r} must be a non-empty string without '/' or a leading '.'")
        object.__setattr__(self, "params", jsonable(dict(self.params)))


@dataclass(frozen=True, eq=False)
class Record:
    """What a worker returns: named ``arrays`` (any shapes) and scalar ``attrs`` (numbers, strings,
    booleans; they also go into the index table)."""

    arrays: Mapping[str, np.ndarray]
    attrs: Mapping[str, object] = field(default_factory=dict)


@dataclass(frozen=True)
class RunReport:
    """Outcome of :func:`run_jobs`: keys ``done`` now, ``failed`` now (key -> reason), ``skipped``
    (already in the database or failed before), and the wall time ``seconds``."""

    done: list
    failed: dict
    skipped: list
    seconds: float


class InProcessExecutor(Executor):
    """Runs each submitted call at once in this process (``workers=0``: debugging, notebooks)."""

    def submit(self, fn, /, *args, **kwargs):
        fut = Future()
        try:
            fut.set_result(fn(*args, **kwargs))
        except BaseException as exc:  # noqa: BLE001 - handed to the future like a pool would
            if isinstance(exc, KeyboardInterrupt):
                raise
            fut.set_exception(exc)
        return fut


def _call(worker: Callable, params: dict):
    """Run in the worker: ``("done", Record, warnings)`` or ``("failed", reason, traceback)``."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            record = worker(params)
        except Exception as exc:  # noqa: BLE001 - every failure is recorded, not raised
            return "failed", f"{type(exc).__name__}: {exc}", traceback.format_exc()
    if not isinstance(record, Record):
        return "failed", f"worker returned {type(record).__name__}, expected a Record", ""
    seen = list(dict.fromkeys(f"{w.category.__name__}: {w.message}" for w in caught))
    return "done", record, seen


class Database:
    """The HDF5 file at ``path`` holding records made by a given ``config``.

    Parameters
    ----------
    path : the ``.h5`` file
    kind : format tag (e.g. ``"toolkit.impact.database"``); a file with another tag is refused
    version : format version the caller reads and writes
    config : JSON-able description of what generates the records; must match an existing file's
    grows : dotted keys of ``config`` that may differ from the stored ones (the database grows
        along them, e.g. the number of plans); each run stores its own values
    """

    def __init__(self, path: str | os.PathLike, kind: str, version: int, config: Mapping, grows: tuple = ()):
        self.path = Path(path)
        self.kind, self.version, self.config = kind, int(version), jsonable(dict(config))
        self.grows = tuple(grows)
        self.shards = self.path.with_name(self.path.name + ".shards")

    # ------------------------------------------------------------------ opening / checking
    @staticmethod
    def open_attrs(path: Path) -> dict:
        """Root attributes of an existing database file, or :class:`DatabaseError` if unreadable."""
        import h5py

        try:
            with h5py.File(path, "r") as f:
                return {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
        except OSError as exc:
            raise DatabaseError(f"cannot read {path} as HDF5 (corrupt, truncated or not HDF5): {exc}") from exc

    @classmethod
    def verified_attrs(cls, path: str | os.PathLike, kind: str, version: int, remedy: str) -> dict:
        """Root attributes of the database at ``path``, refusing another format tag (``remedy``
        says what to do instead) or version with a :class:`DatabaseError`."""
        attrs = cls.open_attrs(Path(path))
        if attrs.get("format") != kind:
            raise DatabaseError(f"{path} is not a {kind!r} database (its format tag is {attrs.get('format')!r}); "
                                f"{remedy}")
        if int(attrs.get("format_version", -1)) != version:
            raise DatabaseError(f"{path} has format version {attrs.get('format_version')}, this toolkit reads "
                                f"version {version}; regenerate it")
        return attrs

    def check(self) -> None:
        """Refuse an existing file of another kind, version or configuration."""
        attrs = self.verified_attrs(self.path, self.kind, self.version, "choose another output file")
        stored = json.loads(attrs.get("config", "{}"))
        require_same(stored, self.config, f"database {self.path}", ignore=self.grows,
                     hint="use the options it was made with, or another output file")

    def create(self, shared: Mapping[str, np.ndarray] | None = None, shared_attrs: Mapping | None = None) -> None:
        """Create the file (atomically) if absent, with ``/shared`` arrays; else :meth:`check` it."""
        import h5py


        if self.path.exists():
            self.check()
            return
        ensure_room(self.path, sum(np.asarray(a).nbytes for a in (shared or {}).values()))
        with atomic_path(self.path) as tmp:
            with h5py.File(tmp, "w") as f:
                f.attrs["format"] = self.kind
                f.attrs["format_version"] = self.version
                f.attrs["config"] = json.dumps(self.config)
                g = f.create_group("shared")
                for name, arr in (shared or {}).items():
                    g.create_dataset(name, data=np.asarray(arr))
                for k, v in (shared_attrs or {}).items():
                    g.attrs[k] = v
                f.create_group("records")
                f.create_group("failures")
                _write_index(f)

    def begin(self, keys: Iterable[str]) -> None:
        """Record the keys of the run about to start (``planned``) and this run's ``config``
        (copy-on-write; nothing is written when both are already stored)."""
        import h5py


        planned, config = json.dumps(list(keys)), json.dumps(self.config)
        attrs = self.open_attrs(self.path)
        if attrs.get("planned") == planned and attrs.get("config") == config:
            return
        ensure_room(self.path, self.path.stat().st_size, anew=True)
        with atomic_path(self.path) as tmp:
            shutil.copyfile(self.path, tmp)
            with h5py.File(tmp, "a") as f:
                f.attrs["planned"] = planned
                f.attrs["config"] = config

    @contextmanager
    def locked(self):
        """Hold the run lock ``<db>.lock`` inside the block: another process's run (or a second
        command on the same file) is refused with a :class:`DatabaseError` instead of racing this
        one's merges; :func:`run_jobs` takes it, and a caller may take it around more writes."""
        release = _acquire_lock(self)
        try:
            yield self
        finally:
            release()

    # ------------------------------------------------------------------ contents
    def keys(self) -> list[str]:
        """Keys of finished records (merged and pending shards)."""
        import h5py

        with h5py.File(self.path, "r") as f:
            done = set(f["records"].keys())
        return sorted(done | {k for k, status in self._shard_status().items() if status == "done"})

    def failures(self) -> dict[str, str]:
        """Failed keys -> reason (merged and pending)."""
        import h5py

        with h5py.File(self.path, "r") as f:
            out = {k: _str(g.attrs["reason"]) for k, g in f["failures"].items()}
        for k, status in self._shard_status().items():
            if status == "failed":
                with h5py.File(self.shards / f"{k}.h5", "r") as s:
                    out[k] = _str(s.attrs["reason"])
            else:
                out.pop(k, None)
        return out

    def _shard_status(self) -> dict[str, str]:
        import h5py

        out = {}
        if self.shards.is_dir():
            for p in sorted(self.shards.glob("*.h5")):
                if p.name.startswith("."):
                    continue  # a temporary file of an interrupted atomic write
                with h5py.File(p, "r") as s:
                    out[_str(s.attrs["key"])] = _str(s.attrs["status"])
        return out

    # ------------------------------------------------------------------ writing
    def write_shard(self, job: Job, status: str, payload, extra) -> None:
        """Write one finished job as ``<db>.shards/<key>.h5`` (atomically)."""
        import h5py


        self.shards.mkdir(exist_ok=True)
        if status == "done":
            ensure_room(self.shards / f"{job.key}.h5", sum(np.asarray(a).nbytes for a in payload.arrays.values()))
        with atomic_path(self.shards / f"{job.key}.h5") as tmp:
            with h5py.File(tmp, "w") as s:
                s.attrs["key"] = job.key
                s.attrs["status"] = status
                s.attrs["params"] = json.dumps(job.params)
                if status == "done":
                    for name, arr in payload.arrays.items():
                        s.create_dataset(name, data=np.asarray(arr))
                    attrs = dict(payload.attrs)
                    if extra:
                        attrs["warnings"] = "; ".join(extra)
                    s.attrs["record_attrs"] = json.dumps(jsonable(attrs))
                else:
                    s.attrs["reason"] = payload
                    s.attrs["traceback"] = extra or ""

    def merge(self) -> int:
        """Fold pending shards into the main file copy-on-write; returns how many were merged."""
        import h5py


        shards = [p for p in sorted(self.shards.glob("*.h5")) if not p.name.startswith(".")] \
            if self.shards.is_dir() else []
        if not shards:
            return 0
        # the copy and every shard, checked first: HDF5 reports a full disk late, or crashes on it
        ensure_room(self.path, self.path.stat().st_size + sum(p.stat().st_size for p in shards), anew=True)
        with atomic_path(self.path) as tmp:
            shutil.copyfile(self.path, tmp)
            with h5py.File(tmp, "a") as f:
                for p in shards:
                    with h5py.File(p, "r") as s:
                        key, status = _str(s.attrs["key"]), _str(s.attrs["status"])
                        for group in ("records", "failures"):
                            if key in f[group]:
                                del f[group][key]
                        if status == "done":
                            g = f["records"].create_group(key)
                            for name in s:
                                s.copy(s[name], g, name=name)
                            g.attrs["params"] = s.attrs["params"]
                            g.attrs["attrs"] = s.attrs["record_attrs"]
                        else:
                            g = f["failures"].create_group(key)
                            for a in ("params", "reason", "traceback"):
                                g.attrs[a] = s.attrs[a]
                _write_index(f)
        for p in shards:
            p.unlink()
        try:
            self.shards.rmdir()
        except OSError:
            pass
        return len(shards)


def _str(v) -> str:
    return v.decode() if isinstance(v, bytes) else str(v)


def _write_index(f) -> None:
    """(Re)write ``/index``: one row per record with its key, params and scalar attributes."""
    import h5py

    rows = []
    for key, g in f["records"].items():
        row = {"key": key}
        row.update(_flat(json.loads(_str(g.attrs["params"]))))
        row.update(_flat(json.loads(_str(g.attrs["attrs"]))))
        rows.append(row)
    columns = list(dict.fromkeys(c for r in rows for c in r))
    if "index" in f:
        del f["index"]
    if not rows:
        f.create_dataset("index", shape=(0,), dtype=np.dtype([("key", h5py.string_dtype())]))
        return
    dtypes = []
    for c in columns:
        values = [r.get(c) for r in rows]
        if all(isinstance(v, bool) for v in values):
            dt = np.dtype(np.bool_)
        elif all(isinstance(v, int) and not isinstance(v, bool) for v in values):
            dt = np.dtype(np.int64)
        elif all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
            dt = np.dtype(np.float64)
        else:
            dt = h5py.string_dtype()
        dtypes.append((c, dt))
    table = np.zeros(len(rows), dtype=np.dtype(dtypes))
    for c, dt in dtypes:
        if dt.kind == "O":
            table[c] = ["" if r.get(c) is None else str(r.get(c)) for r in rows]
        else:
            table[c] = [r.get(c) for r in rows]
    f.create_dataset("index", data=table)


def _flat(d: Mapping, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, Mapping):
            out.update(_flat(v, f"{prefix}{k}."))
        elif isinstance(v, (list, tuple)):
            out[f"{prefix}{k}"] = json.dumps(v)
        else:
            out[f"{prefix}{k}"] = v
    return out


def read_index(path: str | os.PathLike, table: str = "index"):
    """A table of the database at ``path`` as a DataFrame with its strings as ``str`` (h5py alone
    gives ``bytes``): ``/index`` by default (one row per finished record), or another table
    (``"samples"``: a static database's one row per increment)."""
    import h5py
    import pandas as pd

    Database.open_attrs(Path(path))
    with h5py.File(path, "r") as f:
        if table not in f or not isinstance(f[table], h5py.Dataset) or f[table].dtype.names is None:
            tables = sorted(k for k, v in f.items() if isinstance(v, h5py.Dataset) and v.dtype.names)
            raise DatabaseError(f"{path} has no table {table!r}; its tables: {tables}")
        frame = pd.DataFrame(f[table][()])
    for c in frame.columns:
        if frame[c].dtype == object:
            frame[c] = frame[c].map(_str)
    return frame


def read_failures(path: str | os.PathLike):
    """Failed jobs of the database: DataFrame with ``key``, ``reason``, ``params`` (JSON)."""
    import h5py
    import pandas as pd

    Database.open_attrs(Path(path))
    with h5py.File(path, "r") as f:
        rows = [{"key": k, "reason": _str(g.attrs["reason"]), "params": _str(g.attrs["params"])}
                for k, g in f["failures"].items()]
    return pd.DataFrame(rows, columns=["key", "reason", "params"])


def _terminate_as_interrupt() -> Callable[[], None]:
    """From now on a SIGTERM or SIGHUP (a cluster's time limit, a closed terminal) stops the run
    like a Ctrl-C (KeyboardInterrupt), so finished jobs are merged; returns the function that
    restores the previous handlers. Only in the main thread (elsewhere nothing changes)."""
    if threading.current_thread() is not threading.main_thread():
        return lambda: None

    def interrupt(signum, frame):
        raise KeyboardInterrupt(f"signal {signal.Signals(signum).name}")

    names = [n for n in ("SIGTERM", "SIGHUP") if hasattr(signal, n)]
    previous = {n: signal.signal(getattr(signal, n), interrupt) for n in names}

    def restore():
        for n, handler in previous.items():
            signal.signal(getattr(signal, n), handler)
    return restore


def database_status(path: str | os.PathLike) -> DatabaseStatus:
    """How complete the database at ``path`` is (:class:`DatabaseStatus`)."""
    import h5py

    path = Path(path)
    attrs = Database.open_attrs(path)
    planned = json.loads(attrs["planned"]) if "planned" in attrs else None
    with h5py.File(path, "r") as f:
        records = set(f["records"].keys()) if "records" in f else set()
        failures = set(f["failures"].keys()) if "failures" in f else set()
    shards = path.with_name(path.name + ".shards")
    pending = len([p for p in shards.glob("*.h5") if not p.name.startswith(".")]) if shards.is_dir() else 0
    running = _locked_elsewhere(path)
    if planned is None:
        return DatabaseStatus(path, len(records), len(failures), None, len(records), pending, running)
    planned = set(planned)
    return DatabaseStatus(path, len(planned & records), len(planned & failures - records), len(planned),
                          len(records), pending, running)


def _lock_path(path: Path) -> Path:
    return path.with_name(path.name + ".lock")


def _locked_elsewhere(path: Path) -> bool:
    """Whether another process holds the run lock of the database at ``path``."""
    try:
        import fcntl
    except ImportError:  # not POSIX: no lock
        return False
    try:
        fd = os.open(_lock_path(path), os.O_RDONLY)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        return False
    except OSError:
        return True
    finally:
        os.close(fd)


#: run locks this process holds: database path -> nesting depth
_HELD: dict[Path, int] = {}


def _acquire_lock(db: Database):
    """Take the run lock ``<db>.lock`` (one run per database at a time; this process may take it
    again), or refuse with a :class:`DatabaseError`; returns the function that releases it (and
    removes the file)."""
    try:
        import fcntl
    except ImportError:  # not POSIX: no lock
        return lambda: None
    key = db.path.resolve()
    if key in _HELD:
        _HELD[key] += 1

        def release_nested():
            _HELD[key] -= 1
        return release_nested
    lock = _lock_path(db.path)
    try:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as exc:
        raise DatabaseError(f"cannot write next to the database {db.path} ({exc.strerror}: {lock}); choose an "
                            f"output file in an existing, writable folder") from exc
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        raise DatabaseError(f"database {db.path} is being filled by another process (it holds {lock}); wait for "
                            f"it to finish, or write to another output file") from None

    _HELD[key] = 1

    def release():
        _HELD[key] -= 1
        if _HELD[key] == 0:
            del _HELD[key]
            try:
                lock.unlink()
            except OSError:
                pass
            os.close(fd)
    return release


def check_complete(path: str | os.PathLike, command: str) -> DatabaseStatus:
    """Refuse a database holding no record (:class:`DatabaseError`), warn
    (:class:`IncompleteDatabaseWarning`) on an interrupted one; ``command`` is the remedy's
    command (e.g. ``"`toolkit static database` with the same options"``)."""
    status = database_status(path)
    if status.records == 0:
        if not status.complete:
            raise DatabaseError(status.message(command))
    elif not status.complete:
        warnings.warn(status.message(command), IncompleteDatabaseWarning, stacklevel=3)
    return status


def _resolve_executor(executor, workers: int):
    if executor is not None:
        if hasattr(executor, "get_executor"):  # a dask.distributed Client
            return executor.get_executor(pure=False), False
        return executor, False
    if workers == 0:
        return InProcessExecutor(), True
    import multiprocessing


    # spawn: the parent may hold threads (tqdm, BLAS, torch) that fork would copy mid-state; each
    # worker runs on TOOLKIT_NUM_THREADS threads (1 unless set_threads said otherwise), so W
    # workers do not each start a pool per core
    return ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                               initializer=_init_worker, initargs=(default_threads(),)), True


def _init_worker(threads: int) -> None:
    """A local worker process: ``threads`` BLAS/torch threads, and deaf to Ctrl-C. A Ctrl-C in a
    terminal reaches every process of the command; the main process alone answers it (it keeps
    the finished jobs and stops the workers), so a worker prints no traceback of its own. tqdm
    takes a thread lock here instead of its default process-shared one: a worker stopped by the
    main process then leaves no semaphore behind ("leaked semaphore" at exit)."""
    from tqdm.auto import tqdm


    signal.signal(signal.SIGINT, signal.SIG_IGN)
    tqdm.set_lock(threading.RLock())
    set_threads(threads)


def check_workers(workers: int) -> None:
    """Refuse a negative number of worker processes (0 runs the jobs in this process); the
    database commands call it before they create their file."""
    if int(workers) < 0:
        raise ValueError(f"workers must be >= 0 (0: in this process), got {workers}")


def run_jobs(db: Database, jobs: Iterable[Job], worker: Callable, *, executor=None, workers: int = 1,
             retry_failed: bool = False, progress: bool = True, merge_every: float = 60.0) -> RunReport:
    """Run the jobs of ``jobs`` not yet in ``db`` and store their records.

    Parameters
    ----------
    db : Database (created with :meth:`Database.create` beforehand)
    jobs : Job objects with distinct keys
    worker : picklable ``worker(params) -> Record`` (a module-level function or an instance of a
        module-level class); exceptions it raises become recorded failures
    executor : any object with ``submit(fn, *args) -> Future`` (``concurrent.futures``), or a
        ``dask.distributed.Client``; default: a process pool of ``workers`` processes
        (``workers=0``: run in this process)
    retry_failed : rerun jobs recorded as failed
    progress : tqdm bar over jobs
    merge_every : seconds between merges of finished shards into the main file

    Returns
    -------
    RunReport

    Raises
    ------
    DatabaseError : another process is running jobs on the same database
    """
    t0 = time.perf_counter()
    jobs = list(jobs)
    keys = [j.key for j in jobs]
    if len(set(keys)) != len(keys):
        dup = sorted({k for k in keys if keys.count(k) > 1})
        raise ValueError(f"job keys must be unique; repeated: {dup}")
    check_workers(workers)
    with db.locked():
        return _run_locked(db, jobs, keys, worker, executor, workers, retry_failed, progress, merge_every, t0)


def _stop_pool(pool) -> None:
    """Terminate a local pool's worker processes and wait for them, so that the pool's queues
    and locks are released (no "leaked semaphore" warning at exit)."""
    processes = list((getattr(pool, "_processes", None) or {}).values())
    for proc in processes:
        proc.terminate()
    for proc in processes:
        proc.join(timeout=10)


def _run_locked(db, jobs, keys, worker, executor, workers, retry_failed, progress, merge_every, t0) -> RunReport:
    from tqdm.auto import tqdm

    db.merge()  # shards left by a crashed run
    db.begin(keys)
    done_before, failed_before = set(db.keys()), db.failures()
    skip = done_before | (set() if retry_failed else set(failed_before))
    todo = [j for j in jobs if j.key not in skip]
    skipped = [j.key for j in jobs if j.key in skip]
    report = RunReport([], {}, skipped, 0.0)
    if not todo:
        return RunReport([], {}, skipped, time.perf_counter() - t0)
    pool, owned = _resolve_executor(executor, int(workers))
    # a sliding window of submitted jobs: results are stored as they come (an in-process
    # executor runs one at a time), and a Ctrl-C leaves few jobs queued
    window = 1 if isinstance(pool, InProcessExecutor) else (2 * int(workers) if owned else len(todo))
    pending, futures = list(reversed(todo)), {}
    bar = tqdm(total=len(todo), desc="simulations", disable=not progress)
    last_merge = time.perf_counter()
    restore_signals = _terminate_as_interrupt()
    try:
        while pending or futures:
            while pending and len(futures) < window:
                job = pending.pop()
                futures[pool.submit(_call, worker, dict(job.params))] = job
            finished, _ = wait(futures, return_when=FIRST_COMPLETED)
            for fut in finished:
                job = futures.pop(fut)
                try:
                    status, payload, extra = fut.result()
                except Exception as exc:  # noqa: BLE001 - the worker process itself died
                    status, payload, extra = "failed", f"{type(exc).__name__}: {exc}", traceback.format_exc()
                db.write_shard(job, status, payload, extra)
                if status == "done":
                    report.done.append(job.key)
                else:
                    report.failed[job.key] = payload
                    log.warning("job %s failed: %s", job.key, payload)
                bar.update(1)
                bar.set_postfix(failed=len(report.failed))
                count_finished("job")
            if time.perf_counter() - last_merge > merge_every:
                db.merge()
                last_merge = time.perf_counter()
    except KeyboardInterrupt:
        for fut, job in futures.items():
            if fut.done() and not fut.cancelled():  # finished before the interrupt: keep it
                try:
                    status, payload, extra = fut.result()
                except BaseException:  # noqa: BLE001 - the worker died or was interrupted; it reruns next time
                    continue
                db.write_shard(job, status, payload, extra)
            else:
                fut.cancel()
        if owned:  # do not wait for running simulations: stop the workers, then close the pool
            _stop_pool(pool)
        raise
    finally:
        restore_signals()
        bar.close()
        if owned:  # the workers have exited when the run returns (none is left to a later Ctrl-C)
            with deferred_interrupt():
                pool.shutdown(wait=True, cancel_futures=True)
        with deferred_interrupt():  # the .h5 alone holds every finished job, even after a second Ctrl-C
            db.merge()
    return RunReport(report.done, report.failed, skipped, time.perf_counter() - t0)
