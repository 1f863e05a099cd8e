"""Benchmark: accuracy of hex8, wedge6, tet4 and the mixed bar against a closed form, by nu.

Lame's field around a pressurised spherical cavity in an infinite solid, u = B e_r / r^2
(divergence-free, the same for every nu), is prescribed on the whole boundary of a
20 x 10 x 10 mm box (one cell type: hexahedra; each cube cut into 2 wedges; or into 6
Kuhn tetrahedra) and of the L-section ``mixed_bar`` (hex8 + wedge6 + tet4). The table
gives the max nodal error relative to max |u| at cell sizes h = 5, 2.5, 1.25 mm and the
log-log slope: 2 is the O(h^2) of linear elements, ~0 is volumetric locking.

Writes ``benchmarks/results/mixed_elements.csv`` (or ``--out``) with its provenance sidecar.

    python benchmarks/mixed_elements.py [--out benchmarks/results/mixed_elements.csv]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pandas as pd
from _provenance import RESULTS, write_result

from toolkit.common.fem.materials import LinearElastic
from toolkit.common.meshes.mesh import Mesh
from toolkit.common.meshes.topology import triangulated_boundary, wedges_from_hexes
from toolkit.common.phantoms.mixed_bar import mixed_bar
from toolkit.common.phantoms.phantom import block
from toolkit.static.constraints import Constraints
from toolkit.static.problem import StaticProblem
from toolkit.static.stiffness import MaterialAssignment

#: the code this benchmark measures: a result is stale once any of these changed after its commit
MEASURES = ("toolkit/static/problem.py", "toolkit/static/stiffness.py", "toolkit/static/constraints.py",
            "toolkit/common/fem/", "toolkit/common/meshes/", "toolkit/common/phantoms/mixed_bar.py",
            "toolkit/common/phantoms/phantom.py")

CENTRE = np.array([-12.0, 5.0, 5.0])  # cavity centre, mm
B = 20.0  # p a^3 / (4 mu), mm^3
_VTK_BITS = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)]


def cavity(points: np.ndarray) -> np.ndarray:
    d = points - CENTRE
    return (B / np.linalg.norm(d, axis=1) ** 3)[:, None] * d


def box(n: int, kind: str) -> Mesh:
    """20 x 10 x 10 mm box of cubes of side 5 / n mm, as hex8, wedge6 or tet4."""
    axes = [np.linspace(0, 20, 4 * n + 1), np.linspace(0, 10, 2 * n + 1), np.linspace(0, 10, 2 * n + 1)]
    if kind == "mixed":
        return mixed_bar(n, length=20.0)
    if kind != "wedge6":
        return block(axes, kind)
    hexes = block(axes, "hex8")
    H = hexes.cells["hex8"]
    corners = np.empty((H.shape[0], 2, 2, 2), dtype=np.int64)
    for a, (i, j, k) in enumerate(_VTK_BITS):
        corners[:, i, j, k] = H[:, a]
    return Mesh(hexes.points, {"wedge6": wedges_from_hexes(corners, hexes.points)})


def run(kind: str, nu: float, n: int) -> dict:
    mesh = box(n, kind)
    U = cavity(mesh.points)
    bnd = np.unique(triangulated_boundary(mesh.cells))
    t0 = time.perf_counter()
    u = StaticProblem(mesh, MaterialAssignment(LinearElastic(0.003, nu))).solve(
        Constraints(mesh.n_points, bnd, U[bnd])).displacement
    err = np.linalg.norm(u - U, axis=1).max() / np.linalg.norm(U, axis=1).max()
    return {"mesh": kind, "nu": nu, "h_mm": 5.0 / n, "nodes": mesh.n_points, "elements": mesh.n_cells,
            "max_error_rel": err, "seconds": round(time.perf_counter() - t0, 3)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=RESULTS / "mixed_elements.csv")
    args = parser.parse_args()
    from toolkit.common.runtime import set_threads

    set_threads(1)  # one thread is fastest on the 2-core AMD EPYC; worker processes inherit it
    rows = [run(kind, nu, n) for kind in ("hex8", "wedge6", "tet4", "mixed") for nu in (0.3, 0.47, 0.4999)
            for n in (1, 2, 4)]
    df = pd.DataFrame(rows)
    slopes = df.groupby(["mesh", "nu"], sort=False).apply(
        lambda g: np.polyfit(np.log(g.h_mm), np.log(g.max_error_rel), 1)[0], include_groups=False)
    df["slope"] = [slopes[(m, nu)] for m, nu in zip(df["mesh"], df["nu"])]
    write_result(args.out, df)
    table = df.pivot_table(index=["mesh", "nu"], columns="h_mm", values="max_error_rel", sort=False)
    table["slope"] = slopes
    print(table.to_string(float_format=lambda v: f"{v:.2e}" if v < 0.5 else f"{v:.2f}"))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
