"""Mesh-size convergence of ``toolkit mesh`` faces: what each ``--size`` costs and how far its
answer is from the finest one's.

The phantom's closed tissue surface, bone surfaces and commissures
(:func:`toolkit.mesh.phantom.phantom_surfaces`) are meshed at each ``--sizes`` (tet10 by
default) and the default plan runs on each (linear, mucosa and lip sliding, 3 increments; the
toolkit's defaults). Each size runs in its own process, so that its peak memory is its own.
Per size: nodes, meshing and simulation seconds, peak resident memory, and the skin
displacement at the phantom's skin points (those within 0.5 mm of every meshed skin),
compared with the finest size's (mean, 95th percentile, max) and with the phantom's own
hexahedral run.

The default ``--size`` of ``toolkit mesh`` is the coarsest size whose 95th percentile lies
within :data:`TOLERANCE_MM` of the finest's.

Writes ``benchmarks/results/mesh_convergence.csv`` (one row per size) with provenance. Each
size's fields go to ``benchmarks/work/mesh_convergence/`` first: a rerun resumes from the sizes
already there (``--fresh`` to redo them).

Usage::

    python benchmarks/mesh_convergence.py                        # sizes 7 5 4 3 2.5 mm
    python benchmarks/mesh_convergence.py --sizes 7 5 --order 1  # linear tetrahedra
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
from _provenance import RESULTS, WORK, write_result

#: the code this benchmark measures: a result is stale once any of these changed after its commit
MEASURES = ("toolkit/mesh/", "toolkit/static/", "toolkit/common/fem/", "toolkit/common/meshes/",
            "toolkit/common/phantoms/", "toolkit/common/analysis/surface_distance.py", "toolkit/common/papers.py",
            "toolkit/common/defaults.py")

#: mm, the 95th percentile of the skin displacement's difference from the finest size within
#: which a size counts as converged
TOLERANCE_MM = 0.2


def run_one(size: float, order: int, resolution: str, folder: Path) -> None:
    """Mesh and simulate one size; write its fields and figures to ``folder``."""
    from own_face import skin_difference

    from toolkit.common.analysis.surface_distance import closest_points, interpolate_on_surface
    from toolkit.common.meshes.topology import boundary_faces
    from toolkit.common.phantoms.phantom import face_hex
    from toolkit.common.runtime import set_threads
    from toolkit.mesh import mesh_face
    from toolkit.mesh.phantom import phantom_surfaces
    from toolkit.static import load_case

    set_threads(1)
    phantom = face_hex(resolution)
    surfaces = phantom_surfaces(phantom)
    t0 = time.perf_counter()
    face = mesh_face(surfaces.tissue, surfaces.bones, surfaces.commissures, size_mm=size, order=order)
    mesh_s = time.perf_counter() - t0
    reference = load_case(resolution=resolution)
    case = load_case(face.mesh, plan=reference.plan, bones={k: v for k, v in face.bones.items() if k != "skull"})
    t0 = time.perf_counter()
    result = case.simulate()
    simulate_s = time.perf_counter() - t0
    summary = result.summary()
    u = result.displacement  # (n, 3) mm, after the last increment
    # the displacement at the phantom's skin points, NaN where this face's skin is not within 0.5 mm
    faces = boundary_faces("tet4", face.mesh.volume_cells[:, :4])
    skin = np.zeros(face.mesh.n_points, bool)
    skin[face.mesh.node_sets["skin"]] = True
    skin_faces = faces[skin[faces].all(axis=1)]
    X = phantom.mesh.points[phantom.mesh.node_sets["skin"]]
    near = closest_points(X, face.mesh.points, skin_faces).distance < 0.5
    at_skin = np.full(X.shape, np.nan)
    at_skin[near] = interpolate_on_surface(X[near], face.mesh.points, skin_faces, u)
    hexahedral = skin_difference(face.mesh, u, phantom.mesh, reference.simulate().displacement)
    row = {"size_mm": size, "order": order, "nodes": face.report["nodes"], "elements": face.report["elements"],
           "mesh_s": mesh_s, "simulate_s": simulate_s,
           "linear_solves": int(sum(r["linear_solves"] for r in summary["increments_report"])),
           "min_scaled_jacobian": summary["min_scaled_jacobian"],
           "peak_memory_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
           "hex_diff_p95_mm": hexahedral["diff_p95_mm"]}
    np.save(folder / f"skin_{size:g}.npy", at_skin)
    (folder / f"row_{size:g}.json").write_text(json.dumps(row))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=float, nargs="+", default=[7.0, 5.0, 4.0, 3.0, 2.5])
    ap.add_argument("--order", type=int, default=2, choices=(1, 2))
    ap.add_argument("--resolution", default="paper", help="phantom whose surfaces are meshed")
    ap.add_argument("--fresh", action="store_true", help="redo the sizes already in the work folder")
    ap.add_argument("--one", type=float, help=argparse.SUPPRESS)  # one size, in this process
    ap.add_argument("--out", type=Path, default=RESULTS / "mesh_convergence.csv")
    args = ap.parse_args(argv)
    folder = WORK / "mesh_convergence" / f"{args.resolution}_order{args.order}"
    folder.mkdir(parents=True, exist_ok=True)
    if args.one is not None:
        run_one(args.one, args.order, args.resolution, folder)
        return
    sizes = sorted(args.sizes, reverse=True)
    for size in sizes:
        if (folder / f"row_{size:g}.json").exists() and not args.fresh:
            continue
        print(f"size {size:g} mm ...", flush=True)
        done = subprocess.run([sys.executable, __file__, "--one", str(size), "--order", str(args.order),
                               "--resolution", args.resolution], check=False)
        if done.returncode:
            print(f"size {size:g} mm failed (exit {done.returncode}); see above", flush=True)
    rows, skins = [], {}
    for size in sizes:
        path = folder / f"row_{size:g}.json"
        if path.exists():
            rows.append(json.loads(path.read_text()))
            skins[size] = np.load(folder / f"skin_{size:g}.npy")
    if not rows:
        raise SystemExit("no size completed")
    finest = min(skins)
    for row in rows:
        d = np.linalg.norm(skins[row["size_mm"]] - skins[finest], axis=1)
        d = d[np.isfinite(d)]
        row.update(finest_mm=finest, points=int(d.size), diff_mean_mm=float(d.mean()),
                   diff_p95_mm=float(np.percentile(d, 95)), diff_max_mm=float(d.max()))
    table = pd.DataFrame(rows)
    converged = table[(table["diff_p95_mm"] <= TOLERANCE_MM)]
    table["converged"] = table["size_mm"].isin(converged["size_mm"])
    print(table.round(3).to_string(index=False))
    write_result(args.out, table, extra={"tolerance_mm": TOLERANCE_MM, "coarsest_converged_mm":
                                         float(converged["size_mm"].max()) if len(converged) else None})


if __name__ == "__main__":
    main()
