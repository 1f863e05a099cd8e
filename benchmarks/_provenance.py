"""Provenance of benchmark results, and the one writer every benchmark uses.

A result is a pair of files in ``benchmarks/results/``:

- ``NAME.csv``: the table (one row per run or per case), read by ``benchmarks/report.py``;
- ``NAME.json``: its sidecar, ``{"name", "provenance", "runs", "extra"}``, where ``provenance``
  is :func:`provenance` (machine, library versions, git commit, command, date) of the last
  write, ``runs`` lists every command whose rows the table holds (a resumable benchmark adds
  rows command after command: each entry has its command, date and commit), and ``extra``
  holds small facts that are not rows (a test's p-value, the size a surrogate was trained at).

Both files are written atomically (a temporary name in the same folder, then a rename), so an
interrupted benchmark never leaves a half-written table. Large outputs (HDF5 databases,
trained models, per-run ``.npz`` fields) go to :data:`WORK` (``benchmarks/work/``, not
tracked), never to :data:`RESULTS`.

    from _provenance import RESULTS, write_result
    write_result(RESULTS / "phantoms.csv", df)              # df: a pandas DataFrame
"""

from __future__ import annotations

import datetime
import importlib.metadata
import json
import os
import platform
import shlex
import subprocess
import sys
import time
from pathlib import Path

__all__ = ["RESULTS", "WORK", "ROOT", "provenance", "write_result", "write_json", "read_sidecar", "work_folder"]

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
WORK = ROOT / "benchmarks" / "work"
#: distributions whose versions a result records (absent ones are left out)
PACKAGES = ("numpy", "scipy", "torch", "scikit-fem", "meshio", "pandas", "mkl", "pypardiso", "scikit-sparse",
            "pyamg", "facial-biomech-toolkit")
#: paths whose uncommitted changes make a result's commit "dirty" (the code that produced it)
CODE_PATHS = ("toolkit", "benchmarks/*.py", "pyproject.toml")
_START = time.perf_counter()  # the benchmark imports this module first: its elapsed time starts here


def _cpu() -> dict:
    """CPU model name, family and model numbers from ``/proc/cpuinfo`` (first processor)."""
    info = {}
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            key = key.strip()
            if key in ("model name", "cpu family", "model") and key not in info:
                info[key] = value.strip()
            if not line.strip() and info:
                break
    except OSError:
        pass
    return {"cpu": info.get("model name") or platform.processor() or platform.machine(),
            "cpu_family": info.get("cpu family", ""), "cpu_model": info.get("model", "")}


def _threads() -> dict:
    """Thread counts in force: the BLAS/OpenMP pools (threadpoolctl) and torch if imported."""
    out = {"env": {k: os.environ[k] for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                                               "TOOLKIT_NUM_THREADS") if k in os.environ}}
    try:
        from threadpoolctl import threadpool_info

        out["pools"] = sorted({f"{p['internal_api']}={p['num_threads']}" for p in threadpool_info()})
    except ImportError:
        pass
    torch = sys.modules.get("torch")
    if torch is not None:
        out["torch"] = torch.get_num_threads()
    return out


def _git() -> dict:
    def run(*cmd):
        return subprocess.run(["git", *cmd], cwd=ROOT, capture_output=True, text=True, check=False).stdout.rstrip()

    commit = run("rev-parse", "HEAD")
    dirty = run("status", "--porcelain", "--untracked-files=no", "--", *CODE_PATHS)
    return {"commit": commit or "unknown", "dirty": bool(dirty),
            "dirty_files": [line[3:] for line in dirty.splitlines()][:20]}


#: the code the benchmark runs is the code at its start: a commit made while it runs is not it
_GIT_AT_START = _git()


def provenance(argv: list[str] | None = None) -> dict:
    """Machine, versions, git commit, command and date of the running benchmark.

    Parameters
    ----------
    argv : list of str, optional
        The command's arguments (default ``sys.argv``); recorded as
        ``python <script relative to the repository> <args>``.

    Returns
    -------
    dict
        ``machine`` (CPU model name, family and model from ``/proc/cpuinfo``, logical cores,
        threads in force),
        ``versions`` (python and :data:`PACKAGES` that are installed), ``git`` (``commit``,
        ``dirty``: whether :data:`CODE_PATHS` have uncommitted changes, both read when the
        benchmark imported this module, i.e. of the code it runs), ``command``, ``date``
        (UTC, ISO 8601), ``elapsed_s`` (wall time of the command so far, s).
    """
    argv = list(sys.argv if argv is None else argv)
    script = Path(argv[0]).resolve() if argv else None
    if script is not None and script.is_file():
        try:
            argv[0] = str(script.relative_to(ROOT))
        except ValueError:
            pass
    versions = {"python": platform.python_version()}
    for name in PACKAGES:
        try:
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            pass
    return {
        "machine": {**_cpu(), "cores": os.cpu_count(), "threads": _threads(), "system": platform.system()},
        "versions": versions,
        "git": _GIT_AT_START,
        "command": "python " + shlex.join(argv),
        "date": datetime.datetime.now(datetime.UTC).replace(microsecond=0).isoformat(),
        "elapsed_s": round(time.perf_counter() - _START, 1),
    }


def work_folder(out: Path) -> Path:
    """Folder for the large outputs behind the result ``out``: ``benchmarks/work/<stem>`` for a
    result in :data:`RESULTS`, ``<folder of out>/work/<stem>`` for one written elsewhere (a trial)."""
    out = Path(out).resolve()
    return (WORK if out.parent == RESULTS else out.parent / "work") / out.stem


def _atomic_write(path: Path, write) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def write_json(path: Path, data: dict) -> None:
    """Write ``data`` as indented JSON to ``path`` atomically."""
    _atomic_write(Path(path), lambda tmp: tmp.write_text(json.dumps(data, indent=2, default=_plain) + "\n"))


def _plain(value):
    """JSON form of numpy scalars and paths."""
    if hasattr(value, "item"):
        return value.item()
    return str(value)


def write_result(path: Path, table, argv: list[str] | None = None, extra: dict | None = None,
                 sidecar: bool = True, resumed: bool = False) -> Path:
    """Write ``table`` to ``path`` (CSV) and its provenance to ``path.with_suffix('.json')``.

    Parameters
    ----------
    path : Path
        ``benchmarks/results/NAME.csv`` (or another folder, for a trial run).
    table : pandas.DataFrame
        The rows.
    argv : list of str, optional
        The command (default ``sys.argv``).
    extra : dict, optional
        Small facts stored beside the provenance in the sidecar.
    sidecar : bool
        False while a resumable benchmark writes its rows after each run; the final write
        passes True.
    resumed : bool
        True when ``table`` keeps rows of an earlier command (a resumed benchmark): the
        sidecar's ``runs`` keeps that command's entry beside this one.

    Returns
    -------
    Path
        ``path``.
    """
    path = Path(path)
    _atomic_write(path, lambda tmp: table.to_csv(tmp, index=False))
    if sidecar:
        prov = provenance(argv)
        run = {"command": prov["command"], "date": prov["date"], "elapsed_s": prov["elapsed_s"],
               "commit": prov["git"]["commit"], "dirty": prov["git"]["dirty"]}
        runs = [r for r in read_sidecar(path).get("runs", []) if r["command"] != run["command"]] if resumed else []
        write_json(path.with_suffix(".json"), {"name": path.stem, "provenance": prov, "runs": [*runs, run],
                                               "extra": extra or {}})
    return path


def read_sidecar(path: Path) -> dict:
    """The sidecar of ``NAME.csv`` (``{}`` when there is none)."""
    side = Path(path).with_suffix(".json")
    return json.loads(side.read_text()) if side.exists() else {}
