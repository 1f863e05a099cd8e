"""Linear solvers for the static face system: time and peak memory per solve.

Assembles the constrained system of the first increment (default plan, mucosa sliding
normal constraints, fixed and moving nodes) on each resolution and solves it with every
available method, each in a fresh process (peak resident memory is per process). CHOLMOD
needs ``scikit-sparse`` and the system SuiteSparse and is skipped when missing;
SuperLU is skipped above ``--superlu-max-dofs`` (SPEC: > 3 min and > 5 GB at 150k dofs).

Writes ``benchmarks/results/static_solvers.csv`` and prints a table.

    python benchmarks/static_solvers.py [--resolutions paper fine]
"""

from __future__ import annotations

import argparse
import resource
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pandas as pd

RESULTS = Path(__file__).parent / "results"


def _system(resolution: str):
    from toolkit.common import face_hex
    from toolkit.static import Constraints, StaticProblem, default_plan, material_assignment
    from toolkit.static.boundary import BoundaryConditions, NodeType

    ph = face_hex(resolution)
    plan = default_plan(ph).increments(3)[0]
    bc = BoundaryConditions.from_mesh(ph.mesh, ph.segments)
    X = ph.mesh.points
    fixed, moving = bc.nodes(NodeType.FIXED), bc.nodes(NodeType.MOVING)
    target = X.copy()
    for s, name in enumerate(bc.segment_names):
        ids = moving[bc.segment[moving] == s]
        target[ids] = plan.motions[name].apply(X[ids])
    nodes = np.concatenate([fixed, moving])
    mucosa = bc.nodes(NodeType.MUCOSA_SLIDING)
    normals = np.tile([0.0, 1.0, 0.0], (mucosa.size, 1))  # any valid sliding rows: the solver sees their shape
    c = Constraints(ph.mesh.n_points, nodes, target[nodes] - X[nodes], mucosa, normals, np.zeros(mucosa.size))
    problem = StaticProblem(ph.mesh, material_assignment("linear", ph.mesh))
    T, u0 = c.reduction()
    K = problem.stiffness
    A = (T.T @ K @ T).tocsr()
    b = -(T.T @ (K @ u0))
    return problem, T, A, b


def run_one(resolution: str, method: str) -> dict:
    from toolkit.static.solvers import SolverError, solve

    t0 = time.perf_counter()
    problem, T, A, b = _system(resolution)
    t_build = time.perf_counter() - t0
    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    row = {"resolution": resolution, "method": method, "dofs": A.shape[0], "nnz": A.nnz, "build_s": t_build}
    try:
        modes = T.T @ problem._modes if method == "amg" else None
        x, info = solve(A, b, method=method, near_nullspace=modes)
        row.update(status="ok", solve_s=info.seconds, iterations=info.iterations, residual=info.residual)
    except SolverError as exc:
        row.update(status=f"unavailable: {str(exc)[:80]}")
    row["peak_rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    row["rss_before_solve_mib"] = rss_before
    return row


def main(argv=None) -> pd.DataFrame:
    parser = argparse.ArgumentParser(description="static linear solver comparison")
    parser.add_argument("--resolutions", nargs="+", default=["coarse", "paper", "fine"])
    parser.add_argument("--methods", nargs="+", default=["superlu", "amg", "cholmod"])
    parser.add_argument("--superlu-max-dofs", type=int, default=60_000)
    parser.add_argument("--out", type=Path, default=RESULTS / "static_solvers.csv")
    args = parser.parse_args(argv)
    from toolkit.common.io import atomic_path
    from toolkit.common.phantom import face_hex

    rows = []
    with ProcessPoolExecutor(max_workers=1, max_tasks_per_child=1) as pool:
        for res in args.resolutions:
            n_dofs = 3 * face_hex(res).mesh.n_points
            for method in args.methods:
                if method == "superlu" and n_dofs > args.superlu_max_dofs:
                    rows.append({"resolution": res, "method": method, "dofs": n_dofs,
                                 "status": f"skipped (> {args.superlu_max_dofs} dofs)"})
                    continue
                rows.append(pool.submit(run_one, res, method).result())
                with atomic_path(args.out) as tmp:
                    pd.DataFrame(rows).to_csv(tmp, index=False)
    df = pd.DataFrame(rows)
    with pd.option_context("display.width", 200, "display.float_format", "{:.3g}".format):
        print(df.to_string(index=False))
    print(f"wrote {args.out}")
    return df


if __name__ == "__main__":
    main()
