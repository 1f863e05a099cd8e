"""Benchmark: time and memory to build each phantom at each resolution.

Writes ``benchmarks/results/phantoms.csv`` (or ``--out``) with its provenance sidecar and prints a table:
node and element counts, minimum and 1st-percentile scaled Jacobian, build time
(median of ``--repeat`` runs, s) and peak traced memory (MiB, tracemalloc).

    python benchmarks/phantoms.py [--repeat 3] [--out benchmarks/results/phantoms.csv]
"""

from __future__ import annotations

import argparse
import statistics
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pandas as pd
from _provenance import RESULTS, write_result

from toolkit.common.phantoms.phantom import ball, face_hex, face_tet

#: the code this benchmark measures: a result is stale once any of these changed after its commit
MEASURES = ("toolkit/common/phantoms/", "toolkit/common/meshes/", "toolkit/common/fem/reference.py",
            "toolkit/common/papers.py")

CASES = [
    *[("face_hex", r, lambda r=r: face_hex(r).mesh) for r in ("coarse", "paper", "fine")],
    *[(f"face_tet{4 if o == 1 else 10}", r, lambda r=r, o=o: face_tet(r, o))
      for r in ("coarse", "paper", "fine") for o in (1, 2)],
    *[(f"ball_tet{4 if o == 1 else 10}", r, lambda r=r, o=o: ball(resolution=r, order=o))
      for r in ("coarse", "paper", "fine") for o in (1, 2)],
]


def measure(build, repeat: int) -> dict:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        mesh = build()
        times.append(time.perf_counter() - t0)
    tracemalloc.start()
    mesh = build()
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    t0 = time.perf_counter()
    sj = mesh.scaled_jacobian()
    t_sj = time.perf_counter() - t0
    return {
        "nodes": mesh.n_points,
        "elements": mesh.n_cells,
        "cell_type": mesh.volume_type,
        "min_scaled_jacobian": float(sj.min()),
        "p01_scaled_jacobian": float(np.percentile(sj, 1)),
        "build_s": statistics.median(times),
        "quality_s": t_sj,
        "peak_mib": peak / 2**20,
    }


def main(argv=None) -> pd.DataFrame:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--out", type=Path, default=RESULTS / "phantoms.csv")
    args = parser.parse_args(argv)
    from toolkit.common.runtime import set_threads

    set_threads(1)  # one thread is fastest on the 2-core AMD EPYC; worker processes inherit it
    rows = [{"phantom": name, "resolution": res, **measure(build, args.repeat)} for name, res, build in CASES]
    df = pd.DataFrame(rows)
    write_result(args.out, df)
    with pd.option_context("display.width", 160, "display.float_format", "{:.3f}".format):
        print(df.to_string(index=False))
    print(f"wrote {args.out}")
    return df


if __name__ == "__main__":
    main()
