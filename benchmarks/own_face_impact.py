"""The impact round trip: the ball impact on the phantom's surfaces meshed by ``toolkit mesh``
against the same impact on the phantom, across the impact paper's velocities.

The paper phantom's closed tissue surface and bone surfaces (:func:`toolkit.mesh.phantom.phantom_surfaces`)
are meshed by :func:`toolkit.mesh.mesh_face` (``--size``, tet10); the meshed face runs
:func:`toolkit.impact.meshed_scene` (held by the tissue on its bones) and the phantom the
skull-held :func:`toolkit.impact.yielding_scene` (its tet10 face), both with the same ball, the
same default aim (30 mm above the most anterior skin point), ``--integrator`` and velocity.
Compared per velocity: the largest skin displacement, the peak contact force, the yielded volume
share at the end, and the skin displacement at the last frame at the phantom's skin nodes (those
within 0.5 mm of the meshed skin; mean, 95th percentile and maximum difference).

Writes ``benchmarks/results/own_face_impact.csv`` with its provenance sidecar.

    python benchmarks/own_face_impact.py                               # paper, 7 mm, 20 30 50 mm/s
    python benchmarks/own_face_impact.py --resolution coarse --size 10 --velocities 30 --ball rigid
"""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
from _provenance import RESULTS, WORK, write_result
from own_face import skin_difference

#: the code this benchmark measures: a result is stale once any of these changed after its commit
MEASURES = ("toolkit/mesh/", "toolkit/impact/", "toolkit/common/fem/", "toolkit/common/meshes/",
            "toolkit/common/phantoms/", "toolkit/common/analysis/surface_distance.py", "toolkit/common/papers.py")


def run(scene) -> tuple[object, float]:
    from toolkit.impact import SceneGeometryWarning, simulate

    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SceneGeometryWarning)
        result = simulate(scene, progress=False)
    return result, time.perf_counter() - t0


def describe(result) -> dict:
    skin = result.face.node_sets["skin"]
    force = np.linalg.norm(result.contact_force, axis=1)
    share = result.plastic_volume_fraction
    return {"max_skin_displacement_mm": float(np.linalg.norm(result.displacement[:, skin], axis=2).max()),
            "peak_force_n": float(force.max()),
            "yielded_share": float(share[-1]) if share is not None else np.nan}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--resolution", default="paper")
    ap.add_argument("--size", type=float, default=7.0, help="element size of the meshed face, mm")
    ap.add_argument("--velocities", type=float, nargs="+", default=[20.0, 30.0, 50.0], help="mm/s")
    ap.add_argument("--ball", default="deformable", choices=["deformable", "rigid"])
    ap.add_argument("--integrator", default="quasi-static", choices=["quasi-static", "explicit"])
    ap.add_argument("--out", type=Path, default=RESULTS / "own_face_impact.csv")
    args = ap.parse_args(argv)

    from toolkit.common import write
    from toolkit.common.phantoms.phantom import face_hex
    from toolkit.common.runtime import set_threads
    from toolkit.impact import meshed_scene, yielding_scene
    from toolkit.mesh import mesh_face
    from toolkit.mesh.phantom import phantom_surfaces

    set_threads(1)
    surfaces = phantom_surfaces(face_hex(args.resolution))
    t0 = time.perf_counter()
    face = mesh_face(surfaces.tissue, surfaces.bones, surfaces.commissures, size_mm=args.size, order=2)
    mesh_s = time.perf_counter() - t0
    folder = WORK / "own_face_impact"
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"face_{args.resolution}_{args.size:g}.vtu"
    write(path, face.mesh)
    rows = []
    for v in args.velocities:
        rigid = args.ball == "rigid"
        phantom = yielding_scene(v).with_face(resolution=args.resolution).with_ball(rigid=rigid) \
            .with_fidelity(order=2, integrator=args.integrator)
        meshed = meshed_scene(path, velocity=v).with_ball(rigid=rigid).with_fidelity(integrator=args.integrator)
        row = {"resolution": args.resolution, "size_mm": args.size, "velocity_mm_s": v, "ball": args.ball,
               "integrator": args.integrator, "mesh_s": mesh_s}
        results = {}
        for name, scene in (("phantom", phantom), ("meshed", meshed)):
            try:
                results[name], seconds = run(scene)
            except Exception as exc:  # noqa: BLE001 - recorded
                row[f"{name}_status"] = f"{type(exc).__name__}: {str(exc)[:160]}"
                continue
            row.update({f"{name}_status": "ok", f"{name}_nodes": results[name].face.n_points,
                        f"{name}_s": seconds, **{f"{name}_{k}": x for k, x in describe(results[name]).items()}})
        if len(results) == 2:
            row.update(skin_difference(results["meshed"].face, results["meshed"].displacement[-1],
                                       results["phantom"].face, results["phantom"].displacement[-1]))
        rows.append(row)
        print({k: (round(x, 3) if isinstance(x, float) else x) for k, x in row.items()}, flush=True)
    table = pd.DataFrame(rows)
    write_result(args.out, table, argv=argv)
    return table


if __name__ == "__main__":
    main()
