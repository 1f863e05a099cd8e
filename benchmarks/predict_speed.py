"""`toolkit static predict` beside the FE it replaces, end to end from the command line.

For each ``--resolutions`` phantom, a 4-plan database and a model of the default network (one
epoch: inference time does not depend on how well the weights are trained) are made once under
``benchmarks/work/predict_speed/``. Each repeat then runs, each as a fresh process of one thread,
in turn so that they share the machine's load of the same minutes:

- ``simulate``: ``toolkit static simulate --resolution R --plan default_plan.toml``;
- ``predict``: ``toolkit static predict --model M --plan default_plan.toml`` (the same plan);
- ``import torch`` and ``import toolkit.static``: what a process pays to import them (a prediction on
  the CPU does not import torch).

Each row is one run: its wall time (``wall_s``, the process from start to exit) and, for the two
commands, the in-process time the summary reports (``in_process_s``: the increments for the FE,
the prediction with its influence matrix for the surrogate).

Writes ``benchmarks/results/predict_speed.csv`` with provenance.

Usage::

    python benchmarks/predict_speed.py                       # coarse and paper, 3 repeats
    python benchmarks/predict_speed.py --resolutions coarse --repeats 1
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
from _provenance import RESULTS, WORK, write_result

#: the code this benchmark measures: a result is stale once any of these changed after its commit
MEASURES = ("toolkit/__init__.py", "toolkit/cli/", "toolkit/static/", "toolkit/common/")

PLAN = Path(__file__).resolve().parent.parent / "toolkit" / "static" / "data" / "default_plan.toml"
ONE_THREAD = {k: "1" for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}


def _toolkit(*args: str) -> list[str]:
    return [sys.executable, "-c", "import sys; from toolkit.cli import main; sys.exit(main(sys.argv[1:]))", *args]


def _run(cmd: list[str], cwd: Path) -> float:
    """Wall seconds of ``cmd`` run to its end in a fresh process of one thread (raises on failure)."""
    t0 = time.perf_counter()
    done = subprocess.run(cmd, cwd=cwd, env={**os.environ, **ONE_THREAD}, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} exited {done.returncode}: {done.stderr[-2000:]}")
    return wall


def prepare(resolution: str, folder: Path) -> Path:
    """The model of ``resolution`` under ``folder`` (made when missing)."""
    model = folder / "model"
    if not (model / "model.pt").exists():
        folder.mkdir(parents=True, exist_ok=True)
        _run(_toolkit("static", "database", "--resolution", resolution, "--plans", "4", "--workers", "0",
                      "--out", "db.h5"), folder)
        _run(_toolkit("static", "train", "--data", "db.h5", "--out", "model", "--epochs", "1"), folder)
    return model


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--resolutions", nargs="+", choices=("coarse", "paper", "fine"), default=["coarse", "paper"])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=RESULTS / "predict_speed.csv")
    args = ap.parse_args(argv)

    work = WORK / "predict_speed"
    rows = []
    for resolution in args.resolutions:
        folder = work / resolution
        model = prepare(resolution, folder)
        for repeat in range(args.repeats):
            for what in ("import torch", "import toolkit.static", "simulate", "predict"):
                out = folder / f"out-{what.replace(' ', '_')}"
                shutil.rmtree(out, ignore_errors=True)
                if what.startswith("import"):
                    cmd = [sys.executable, "-c", what]
                elif what == "simulate":
                    cmd = _toolkit("static", "simulate", "--resolution", resolution, "--plan", str(PLAN),
                                   "--out", str(out), "--no-preview")
                else:
                    cmd = _toolkit("static", "predict", "--model", str(model), "--plan", str(PLAN),
                                   "--out", str(out), "--no-preview")
                wall = _run(cmd, folder)
                summary = json.loads((out / "summary.json").read_text()) if out.exists() else {}
                rows.append({"resolution": resolution, "nodes": summary.get("nodes"), "run": what,
                             "repeat": repeat, "wall_s": wall, "in_process_s": summary.get("wall_time_s")})
                print(rows[-1], flush=True)
    table = pd.DataFrame(rows)
    write_result(args.out, table, argv=argv)
    print(table.groupby(["resolution", "run"], sort=False)[["wall_s", "in_process_s"]].median())
    return table


if __name__ == "__main__":
    main()
