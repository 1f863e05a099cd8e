"""Why a face's static solve needs many CG iterations: the slowest modes of its system.

Takes the first reduced system the static simulation solves (the default plan's first
increment, mucosa sliding and lip contact; on the head CT the 5 mm advance) on a face of
``static_meshed_speed.py`` (meshed once, kept under ``benchmarks/work/``), builds the solver's
AMG hierarchy, counts the CG iterations to a relative residual of 1e-9, and finds the
``--modes`` smallest eigenpairs of the system (LOBPCG preconditioned by the hierarchy). Each mode
is described where it lives: the nodes holding 95 % of its energy (squared nodal displacement),
their centre and extent, how many of them slide on a bone (``mucosa_sliding``) or lie on the skin,
the volume elements wholly among them and the elements joining them to the rest, and the
coherence of their motion (1: a rigid translation). A mode that lives on a few hundred nodes with
an eigenvalue a million times below the diagonal is a near-mechanism: a piece of tissue held by
few elements, which CG must resolve iteration by iteration.

Writes ``benchmarks/results/slow_modes.csv`` with provenance.

Usage::

    python benchmarks/slow_modes.py --faces phantom ct
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import pandas as pd
from _provenance import RESULTS, write_result
from static_meshed_speed import prepare

#: the code this benchmark measures: a result is stale once any of these changed after its commit
MEASURES = ("toolkit/mesh/", "toolkit/static/", "toolkit/common/fem/", "toolkit/common/meshes/",
            "toolkit/common/phantoms/", "toolkit/common/analysis/surface_distance.py", "toolkit/common/papers.py")


class _Captured(Exception):
    pass


def first_system(folder: Path) -> dict:
    """The first reduced system the simulation of ``folder``'s plan solves: ``T`` (3n, m), ``A``
    (m, m), ``b`` (m,), the mesh, the rigid-body modes and the corner-node coarse space."""
    from toolkit.static import load_case
    from toolkit.static.plan import SurgicalPlan
    from toolkit.static.problem import StaticProblem

    captured = {}

    def capture(problem, T, A, b, x0=None):
        captured.update(T=T, A=A, b=b, mesh=problem.mesh, modes=T.T @ problem._modes, corners=problem._corners)
        raise _Captured

    bones = {p.stem: p for p in folder.glob("*.vtu") if p.stem != "face"}
    plan = SurgicalPlan.from_dict(json.loads((folder / "plan.json").read_text()))
    case = load_case(folder / "face.vtu", plan=plan, bones=bones)
    solve = StaticProblem.solve_reduced
    StaticProblem.solve_reduced = capture
    try:
        case.simulate(increments=3, material="linear", sliding="mucosa+lip")
    except _Captured:
        pass
    finally:
        StaticProblem.solve_reduced = solve
    return captured


def describe(face: str, system: dict, count: int) -> list[dict]:
    import scipy.sparse as sp
    from scipy.sparse.linalg import lobpcg

    from toolkit.common.fem.coarse import reduced_coarse_space
    from toolkit.common.fem.factors import amg_hierarchy

    T, A, b, mesh = system["T"], sp.csr_matrix(system["A"]), system["b"], system["mesh"]
    diag = A.diagonal()
    idle = diag == 0
    if idle.any():
        A = A + sp.diags(np.where(idle, diag[~idle].mean(), 0.0))
    t0 = time.perf_counter()
    ml = amg_hierarchy(A, system["modes"], reduced_coarse_space(system["corners"], T, mesh.points))
    setup_s = time.perf_counter() - t0
    residuals = []
    t0 = time.perf_counter()
    ml.solve(b, tol=1e-9, accel="cg", maxiter=2000, residuals=residuals)
    solve_s = time.perf_counter() - t0
    X = np.random.default_rng(0).standard_normal((A.shape[0], count))
    values, vectors = lobpcg(A, X, M=ml.aspreconditioner(), largest=False, tol=1e-6, maxiter=300)
    cells = mesh.volume_cells[:, :4]  # the corners of toolkit mesh's tetrahedra
    sets = mesh.node_sets
    rows = []
    for k in np.argsort(values):
        u = (T @ vectors[:, k]).reshape(-1, 3)
        energy = np.einsum("ij,ij->i", u, u)
        order = np.argsort(energy)[::-1]
        n95 = int(np.searchsorted(np.cumsum(energy[order]) / energy.sum(), 0.95) + 1)
        hot = np.zeros(mesh.n_points, bool)
        hot[order[:n95]] = True
        inside = hot[cells].all(axis=1)
        joining = hot[cells].any(axis=1) & ~inside
        p = mesh.points[hot]
        uu = u[hot]
        rows.append({
            "face": face, "nodes": mesh.n_points, "dofs": A.shape[0], "amg_setup_s": setup_s,
            "cg_iterations": len(residuals) - 1, "cg_s": solve_s, "mode": len(rows),
            "eigenvalue": float(values[k]), "diagonal_mean": float(diag.mean()),
            "relative": float(values[k] / diag.mean()), "nodes_95": n95,
            "centre_mm": np.round(p.mean(axis=0), 1).tolist(), "extent_mm": np.round(np.ptp(p, axis=0), 1).tolist(),
            "sliding_nodes": int(np.isin(np.flatnonzero(hot), sets.get("mucosa_sliding", [])).sum()),
            "skin_nodes": int(np.isin(np.flatnonzero(hot), sets.get("skin", [])).sum()),
            "elements_inside": int(inside.sum()), "elements_joining": int(joining.sum()),
            "coherence": float(np.linalg.norm(uu.mean(axis=0)) / np.linalg.norm(uu, axis=1).mean())})
        print({k: (round(v, 4) if isinstance(v, float) else v) for k, v in rows[-1].items()}, flush=True)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--faces", nargs="+", choices=("phantom", "ct"), default=["phantom", "ct"])
    ap.add_argument("--size", type=float, default=3.0, help="tetrahedron edge length, mm")
    ap.add_argument("--modes", type=int, default=6)
    ap.add_argument("--out", type=Path, default=RESULTS / "slow_modes.csv")
    args = ap.parse_args(argv)

    from toolkit.common.runtime import set_threads

    set_threads(1)
    rows = []
    for face in args.faces:
        rows += describe(face, first_system(prepare(face, args.size, 2)), args.modes)
    table = pd.DataFrame(rows)
    write_result(args.out, table, argv=argv)
    return table


if __name__ == "__main__":
    main()
