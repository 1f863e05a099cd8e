"""Linear solvers for the static face system: time and peak memory per solve, the
fill-aware automatic choice, and the reuse of a factorization.

Assembles the constrained system of the first increment (default plan, mucosa sliding
normal constraints, fixed and moving nodes) on each phantom resolution, on the paper face
split into tetrahedra (``paper-tet4``), and on a bulky tetrahedral block of ~8,800 nodes
(``bulk-tet4``: 26k dofs like a real volumetric tet mesh, bottom fixed, top pushed), and on the
paper phantom's surfaces meshed by ``toolkit mesh`` in quadratic tetrahedra (``meshed-5mm``,
``meshed-3mm``: 24k and 94k nodes; the mesh is kept in ``benchmarks/work/static_solvers/``), and
solves it with every available method (``amg``: with a quadratic mesh's corner-node coarse space
first, as the toolkit solves; ``amg-sa``: smoothed aggregation alone), each in a fresh process (peak resident memory is
per process). Each row also gives the factor size ``auto`` expects
(:func:`~toolkit.common.fem.solvers.estimate_factor_entries`) and its choice, and the time of
a second solve after tying 5 more pairs (the next lip-contact iteration) by CG preconditioned
with the first factorization (``reuse_s``, ``reuse_iterations``). CHOLMOD needs
``scikit-sparse`` and the system SuiteSparse and is skipped when missing; SuperLU is
skipped above ``--superlu-max-dofs`` (more than 3 min and 5 GB at 150k dofs on a 2-core AMD EPYC).

Writes ``benchmarks/results/static_solvers.csv`` with its provenance sidecar and prints a table.

    python benchmarks/static_solvers.py [--meshes paper fine bulk-tet4]
"""

from __future__ import annotations

import argparse
import resource
import time
from concurrent.futures import ProcessPoolExecutor
from functools import partial
from pathlib import Path

import numpy as np
import pandas as pd
import scipy.sparse as sp
from _provenance import RESULTS, write_result

#: the code this benchmark measures: a result is stale once any of these changed after its commit
MEASURES = ("toolkit/mesh/", "toolkit/static/", "toolkit/common/fem/", "toolkit/common/meshes/",
            "toolkit/common/phantoms/", "toolkit/common/analysis/surface_distance.py", "toolkit/common/papers.py")

MESHES = ("coarse", "paper", "fine", "paper-tet4", "bulk-tet4", "meshed-5mm", "meshed-3mm")
METHODS = ("superlu", "pardiso", "amg", "amg-sa", "cholmod", "auto")


def _meshed_face(name: str):
    """The paper phantom's surfaces meshed by ``toolkit mesh`` at the size in ``name``
    (``meshed-5mm``), tet10, and its bony segments; cached in the work folder."""
    import pickle

    from _provenance import WORK

    from toolkit.static import load_case

    path = WORK / "static_solvers" / f"{name}.pkl"
    if path.exists():
        mesh, bones = pickle.loads(path.read_bytes())
    else:
        from toolkit.common.phantoms.phantom import face_hex
        from toolkit.mesh import mesh_face
        from toolkit.mesh.phantom import phantom_surfaces

        surfaces = phantom_surfaces(face_hex("paper"))
        face = mesh_face(surfaces.tissue, surfaces.bones, surfaces.commissures,
                         size_mm=float(name.split("-")[1].removesuffix("mm")), order=2)
        mesh, bones = face.mesh, {k: v for k, v in face.bones.items() if k != "skull"}
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        tmp.write_bytes(pickle.dumps((mesh, bones)))
        tmp.replace(path)
    case = load_case(mesh, plan=load_case(resolution="paper").plan, bones=bones)
    return mesh, case.segments, case.plan


def dirichlet(mesh, bc, plan) -> tuple[np.ndarray, np.ndarray]:
    """The prescribed nodes of ``mesh`` under boundary conditions ``bc`` (FIXED, then MOVING) and
    their displacements ``(p, 3)`` mm: zero, and each moving node carried by its segment's motion
    in ``plan``."""
    from toolkit.static.boundary import NodeType

    X = mesh.points
    fixed, moving = bc.nodes(NodeType.FIXED), bc.nodes(NodeType.MOVING)
    target = X.copy()
    for s, seg in enumerate(bc.segment_names):
        ids = moving[bc.segment[moving] == s]
        target[ids] = plan.motion(seg).apply(X[ids])
    nodes = np.concatenate([fixed, moving])
    return nodes, target[nodes] - X[nodes]


def _system(name: str):
    """Problem, reduction, reduced matrix and right-hand side, and 20 tie pairs for ``name``."""
    from toolkit.common import face_hex
    from toolkit.common.phantoms.face_variants import remeshed
    from toolkit.common.phantoms.phantom import block
    from toolkit.static import Constraints, StaticProblem, default_plan, material_assignment
    from toolkit.static.boundary import BoundaryConditions, NodeType

    if name == "bulk-tet4":
        mesh = block([np.linspace(0, 60, 21), np.linspace(0, 60, 21), np.linspace(0, 57, 20)], "tet4")
        x = mesh.points
        bottom, top = np.flatnonzero(x[:, 2] == 0), np.flatnonzero(x[:, 2] == x[:, 2].max())
        c = Constraints(mesh.n_points, np.concatenate([bottom, top]),
                        np.vstack([np.zeros((bottom.size, 3)), np.tile([1.0, 0.0, -2.0], (top.size, 1))]))
        free = np.setdiff1d(np.arange(mesh.n_points), np.concatenate([bottom, top]))
    else:
        if name.startswith("meshed-"):
            mesh, segments, full_plan = _meshed_face(name)
            plan = full_plan.increments(3)[0]
        else:
            ph = face_hex(name.split("-")[0])
            if name.endswith("tet4"):
                ph = remeshed(ph, "tet4")
            mesh, segments = ph.mesh, ph.segments
            plan = default_plan(ph).increments(3)[0]
        bc = BoundaryConditions.from_mesh(mesh, segments)
        nodes, values = dirichlet(mesh, bc, plan)
        mucosa = bc.nodes(NodeType.MUCOSA_SLIDING)
        normals = np.tile([0.0, 1.0, 0.0], (mucosa.size, 1))  # any valid sliding rows: the solver sees their shape
        c = Constraints(mesh.n_points, nodes, values, mucosa, normals, np.zeros(mucosa.size))
        free = bc.nodes(NodeType.FREE)
    problem = StaticProblem(mesh, material_assignment("linear", mesh), "amg")
    ties = free[:10]
    return problem, c, ties


def _reduced(problem, c):
    from toolkit.static.problem import reduced_matrix

    T, u0 = c.reduction()
    K = problem.stiffness
    A = reduced_matrix(K, T)
    d = A.diagonal()
    A = A + sp.diags(np.where(d == 0, d[d > 0].mean(), 0.0))  # tie slaves' idle columns, as StaticProblem
    return T, A, -(T.T @ (K @ u0))


def run_one(name: str, method: str) -> dict:
    from dataclasses import replace

    from toolkit.common.fem.coarse import reduced_coarse_space
    from toolkit.common.fem.solvers import LinearSolver, SolverError, choose_method, estimate_factor_entries

    t0 = time.perf_counter()
    problem, c, ties = _system(name)
    T, A, b = _reduced(problem, c)
    t_build = time.perf_counter() - t0
    entries = estimate_factor_entries(problem.pattern.node_graph())
    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    row = {"mesh": name, "method": method, "dofs": A.shape[0], "nnz": A.nnz, "build_s": t_build,
           "expected_factor_entries": entries, "auto_choice": choose_method("auto", A.shape[0], entries)}
    corners = problem._corners if method in ("amg", "auto") else None  # a tet10 mesh's corner nodes

    def coarse(T):
        return None if corners is None else reduced_coarse_space(corners, T, problem.mesh.points)

    try:
        solver = LinearSolver(method.removesuffix("-sa"), factor_entries=entries, timed_budget=False)
        modes = T.T @ problem._modes if method in ("amg", "amg-sa", "auto") else None
        x, info = solver.solve(A, b, near_nullspace=modes, coarse_space=partial(coarse, T))
        row.update(status="ok", solve_s=info.seconds, iterations=info.iterations, residual=info.residual,
                   used=info.method)
        # the next lip-contact iteration: 5 more pairs tied (same size: tie slaves keep their columns)
        c2 = replace(c, tie_slaves=ties[:5], tie_masters=ties[5:10], tie_offsets=np.zeros(5))
        T2, A2, b2 = _reduced(problem, c2)
        x2, info2 = solver.solve(A2, b2, near_nullspace=T2.T @ problem._modes if modes is not None else None,
                                 coarse_space=partial(coarse, T2))
        row.update(reuse_s=info2.seconds, reuse_iterations=info2.iterations, reused=info2.reused)
    except SolverError as exc:
        row.update(status=f"unavailable: {str(exc)[:80]}")
    row["peak_rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    row["rss_before_solve_mib"] = rss_before
    return row


def main(argv=None) -> pd.DataFrame:
    parser = argparse.ArgumentParser(description="static linear solver comparison")
    parser.add_argument("--meshes", nargs="+", default=list(MESHES), choices=MESHES)
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    parser.add_argument("--superlu-max-dofs", type=int, default=60_000)
    parser.add_argument("--out", type=Path, default=RESULTS / "static_solvers.csv")
    args = parser.parse_args(argv)
    from toolkit.common.runtime import set_threads

    set_threads(1)  # one thread is fastest on the 2-core AMD EPYC; worker processes inherit it
    from toolkit.common.phantoms.phantom import face_hex

    rows = []
    with ProcessPoolExecutor(max_workers=1, max_tasks_per_child=1) as pool:
        for name in args.meshes:
            n_dofs = (3 * 21 * 21 * 20 if name == "bulk-tet4" else np.inf if name.startswith("meshed-")
                      else 3 * face_hex(name.split("-")[0]).mesh.n_points)
            for method in args.methods:
                if method == "superlu" and n_dofs > args.superlu_max_dofs:
                    rows.append({"mesh": name, "method": method, "dofs": n_dofs,
                                 "status": f"skipped (> {args.superlu_max_dofs} dofs)"})
                    continue
                rows.append(pool.submit(run_one, name, method).result())
                write_result(args.out, pd.DataFrame(rows), sidecar=False)
    df = pd.DataFrame(rows)
    write_result(args.out, df)
    with pd.option_context("display.width", 200, "display.float_format", "{:.3g}".format):
        print(df.to_string(index=False))
    print(f"wrote {args.out}")
    return df


if __name__ == "__main__":
    main()
