"""Convergence of the static FE under mesh refinement, and its time per resolution.

Runs the packaged default plan (3 increments, linear, mucosa + lip sliding) on the coarse,
paper and fine phantoms, interpolates each result's skin displacement at common points
(the skin nodes of the coarsest mesh off the mouth slit, whose two lip copies move apart,
by closest point and barycentric interpolation on each mesh's skin triangles) and reports the
differences between resolutions: mean, 95th percentile and max of |u_a - u_b| (mm). Writes
``benchmarks/results/static_convergence.csv`` (the pairs) and ``static_convergence_runs.csv``
(per resolution: nodes, wall time of the simulation on one thread, mean skin displacement),
each with its provenance sidecar, and prints the tables.

Usage::

    python benchmarks/static_convergence.py [--resolutions coarse paper fine]
"""

from __future__ import annotations

import argparse
import itertools
import json
import time
from pathlib import Path

import numpy as np
import pandas as pd
from _provenance import RESULTS, write_result

#: the code this benchmark measures: a result is stale once any of these changed after its commit
MEASURES = ("toolkit/static/", "toolkit/common/fem/", "toolkit/common/meshes/", "toolkit/common/phantoms/",
            "toolkit/common/analysis/surface_distance.py", "toolkit/common/papers.py", "toolkit/common/defaults.py")


def skin_triangles(mesh):
    """Outward skin triangles ``(t, 3)`` of a phantom (boundary faces whose nodes are all skin)."""
    from toolkit.common.meshes.topology import triangulated_boundary

    tris = triangulated_boundary(mesh.cells)
    skin = np.zeros(mesh.n_points, dtype=bool)
    skin[mesh.node_sets["skin"]] = True
    return tris[skin[tris].all(axis=1)]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--resolutions", nargs="+", default=["coarse", "paper", "fine"])
    ap.add_argument("--out", type=Path, default=RESULTS / "static_convergence.csv")
    args = ap.parse_args(argv)

    from toolkit.common.analysis.surface_distance import interpolate_on_surface
    from toolkit.common.phantoms.phantom import face_hex
    from toolkit.common.runtime import set_threads
    from toolkit.static import default_plan, simulate

    set_threads(1)
    runs, timings = {}, []
    for res in args.resolutions:
        phantom = face_hex(res)
        t0 = time.perf_counter()
        result = simulate(phantom, default_plan(phantom))
        seconds = time.perf_counter() - t0
        s = result.summary()
        runs[res] = (phantom.mesh, result.displacement)
        timings.append({"resolution": res, "nodes": phantom.mesh.n_points, "elements": phantom.mesh.n_cells,
                        "increments": s["increments"], "seconds": seconds,
                        "min_scaled_jacobian": s["min_scaled_jacobian"],
                        "mean_skin_displacement_mm": s["mean_skin_displacement_mm"],
                        "max_displacement_mm": s["max_displacement_mm"], "regulated_nodes": s["regulated_nodes"]})
        print(f"{res}: {phantom.mesh.n_points} nodes, {seconds:.1f} s, min SJ "
              f"{s['min_scaled_jacobian']:.3f}, mean skin |u| {s['mean_skin_displacement_mm']:.3f} mm, "
              f"regulated nodes {s['regulated_nodes']}")
    coarsest = args.resolutions[0]
    mesh0 = runs[coarsest][0]
    # the skin nodes of the coarsest mesh, except those on the mouth slit, where the two lips'
    # copies of a point move apart (the field is double-valued there)
    common = mesh0.points[np.setdiff1d(mesh0.node_sets["skin"], mesh0.node_sets["lip_sliding"])]
    fields = {}
    for res, (mesh, u) in runs.items():
        fields[res] = interpolate_on_surface(common, mesh.points, skin_triangles(mesh), u)
    rows = []
    for a, b in itertools.combinations(args.resolutions, 2):
        d = np.linalg.norm(fields[a] - fields[b], axis=1)
        rows.append({"pair": f"{a}-{b}", "points": d.size, "mean_mm": d.mean(), "p95_mm": np.percentile(d, 95),
                     "max_mm": d.max(), "mean_skin_displacement_mm": np.linalg.norm(fields[b], axis=1).mean()})
    table = pd.DataFrame(rows)
    runs_path = args.out.with_name(f"{args.out.stem}_runs.csv")
    write_result(args.out, table)
    write_result(runs_path, pd.DataFrame(timings))
    print(pd.DataFrame(timings).to_string(index=False, float_format=lambda v: f"{v:.3f}"))
    print(table.to_string(index=False, float_format=lambda v: f"{v:.3f}"))
    print(json.dumps({"wrote": [str(args.out), str(runs_path)]}))
    return table


if __name__ == "__main__":
    main()
