"""Kernels the toolkit leans on, at one and at two threads: why every command runs on one.

Each thread count runs in a fresh interpreter whose BLAS/OpenMP pools and torch are limited with
:func:`toolkit.set_threads`: the 2-norm of a 10,000-vector (numpy/BLAS), an AMG-preconditioned
solve of a 2D Poisson problem of 90,000 unknowns (pyamg, the static solver's preconditioner) and
a scatter-add of 400,000 rows of 3 into 100,000 (torch ``index_add_``, PointNet++'s grouping
and the impact LSTM's batches). Each kernel's median over repeats, s. Writes
``benchmarks/results/threads.csv``.

Usage::

    python benchmarks/threads.py                   # threads 1 and 2, about a minute
    python benchmarks/threads.py --threads 1 2 4
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import pandas as pd
from _provenance import RESULTS, write_result

#: the code this benchmark measures: a result is stale once any of these changed after its commit
MEASURES = ("toolkit/common/runtime.py",)

KERNELS = """
import json, statistics, sys, time
import numpy as np
from toolkit import set_threads

set_threads(int(sys.argv[1]))


def median(f, repeats):
    f()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        f()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


out = {}
x = np.random.default_rng(0).standard_normal(10_000)
out["numpy norm, 10k"] = median(lambda: np.linalg.norm(x), 2000)
import pyamg

A = pyamg.gallery.poisson((300, 300), format="csr")
b = np.ones(A.shape[0])
ml = pyamg.smoothed_aggregation_solver(A)
out["pyamg solve, 90k"] = median(lambda: ml.solve(b, tol=1e-8, accel="cg"), 5)
import torch

index = torch.randint(0, 100_000, (400_000,), generator=torch.Generator().manual_seed(0))
rows = torch.randn(400_000, 3)
target = torch.zeros(100_000, 3)
out["torch index_add_, 400k x 3"] = median(lambda: target.index_add_(0, index, rows), 50)
print(json.dumps(out))
"""


def main(argv=None) -> pd.DataFrame:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--out", type=Path, default=RESULTS / "threads.csv")
    args = ap.parse_args(argv)
    rows = []
    for n in args.threads:
        done = subprocess.run([sys.executable, "-c", KERNELS, str(n)], capture_output=True, text=True, check=True)
        for kernel, seconds in json.loads(done.stdout).items():
            rows.append({"kernel": kernel, "threads": n, "seconds": seconds})
    df = pd.DataFrame(rows)
    write_result(args.out, df)
    print(df.pivot(index="kernel", columns="threads", values="seconds").to_string())
    return df


if __name__ == "__main__":
    main()
