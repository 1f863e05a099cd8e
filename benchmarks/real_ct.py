"""A real head CT end to end: CT -> surfaces -> labelled mesh -> two surgical plans.

The VTK sample head CT (``tests/data/headsq``, 64 x 64 x 93 voxels of 3.2 x 3.2 x 1.5 mm) goes
through :func:`toolkit.mesh.ct.ct_surfaces` (``toolkit ct``), :func:`toolkit.mesh.mesh_face`
(``toolkit mesh``) for each ``--meshes SIZE:ORDER``, and :meth:`toolkit.static.StaticCase.simulate`
(linear material, mucosa sliding, 3 increments; a plan that fails is run again with 6) on the
meshes of ``--simulate-orders`` for two plans placed by the face's own landmarks:

- ``advance``: the distal mandible 5 mm anterior (a mandibular advancement), the proximal
  segments rotating about their condyles to follow it;
- ``bimax``: the Le Fort I segment 3 mm anterior, the distal mandible 6 mm anterior and 2 mm up,
  the proximal segments following.

Pivots: the Le Fort I segment's is the centroid of its carried tissue (``maxilla`` nodes, the
rule of :func:`toolkit.static.anatomy.face_anatomy`), the distal segment's the midpoint of the
condyles found in the CT, each proximal segment's its condyle.

Per stage it records the time; per mesh the nodes, elements, quality, node sets and what each
segment carries (``labels.json``); per plan the status, increments, time, the smallest scaled
Jacobian after the motion and the chin's advance: the y displacement of the skin node most
anterior-inferior (largest y - z) within 5 mm of the midline below the incisal point.

fTetWild keeps the input surface's resolution (the toolkit runs it without coarsening), so the
CT's voxel-sized triangles keep the mesh large at coarser sizes too: the tet10 mesh is measured
but, by default, only the tet4 one is simulated (the tet10 face has about seven times its nodes).

Writes ``benchmarks/results/real_ct.csv`` (one row per mesh and plan; a mesh not simulated has one
row without a plan) with its provenance sidecar (``extra``: the CT's landmarks, planes and cuts).

Usage::

    python benchmarks/real_ct.py                                 # 3 mm tet10 and tet4, tet4 simulated
    python benchmarks/real_ct.py --meshes 8:1                    # quicker
    python benchmarks/real_ct.py --meshes 3:2 --simulate-orders 2
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pandas as pd
from _provenance import RESULTS, ROOT, write_result

#: the code this benchmark measures: a result is stale once any of these changed after its commit
MEASURES = ("toolkit/mesh/", "toolkit/static/", "toolkit/common/fem/", "toolkit/common/meshes/",
            "toolkit/common/analysis/surface_distance.py", "toolkit/common/papers.py", "toolkit/common/defaults.py")

HEADSQ = ROOT / "tests" / "data" / "headsq" / "quarter.nhdr"


def plans(face, condyles: np.ndarray) -> dict:
    """The two plans on the meshed face (module docstring)."""
    from toolkit.static.plan import RigidMotion, SurgicalPlan

    maxilla = face.mesh.points[face.mesh.node_sets["maxilla"]].mean(axis=0)
    hinge = condyles.mean(axis=0)
    proximal = (face.bones["proximal_left"].points, face.bones["proximal_right"].points)
    advance = SurgicalPlan({"distal": RigidMotion(translation=(0.0, 5.0, 0.0), pivot=hinge)})
    bimax = SurgicalPlan({"lefort": RigidMotion(translation=(0.0, 3.0, 0.0), pivot=maxilla),
                          "distal": RigidMotion(translation=(0.0, 6.0, 2.0), pivot=hinge)})
    return {name: plan.with_proximal_following(condyles, *proximal) for name, plan in
            (("advance", advance), ("bimax", bimax))}


def chin_node(mesh) -> int:
    """The skin node most anterior-inferior (largest y - z) within 5 mm of the midline, below the
    incisal point (z < 0)."""
    skin = mesh.node_sets["skin"]
    p = mesh.points[skin]
    ok = (np.abs(p[:, 0]) < 5.0) & (p[:, 2] < 0.0)
    return int(skin[ok][np.argmax(p[ok, 1] - p[ok, 2])])


def simulated(case, chin: int, increments: list[int]) -> dict:
    """Simulate ``case`` with each number of ``increments`` in turn until one completes; the
    first failure's reason is kept."""
    failures, t0 = [], time.perf_counter()
    for n in increments:
        try:
            result = case.simulate(increments=n)
        except Exception as exc:  # noqa: BLE001 - recorded
            failures.append(f"{n} increments: {type(exc).__name__}: {str(exc)[:240]}")
            continue
        s = result.summary()
        return {"status": "ok", "increments": n, "simulate_s": round(time.perf_counter() - t0, 1),
                "chin_advance_mm": float(result.displacement[chin, 1]),
                "chin_up_mm": float(result.displacement[chin, 2]),
                "max_displacement_mm": s["max_displacement_mm"],
                "mean_skin_displacement_mm": s["mean_skin_displacement_mm"],
                "min_scaled_jacobian_after": s["min_scaled_jacobian"], "substeps": s["substeps"],
                "release_width_mm": s["release_width_mm"], "failed_first": " | ".join(failures)}
    return {"status": "failed", "simulate_s": round(time.perf_counter() - t0, 1), "failed_first": " | ".join(failures)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--volume", type=Path, default=HEADSQ)
    ap.add_argument("--meshes", nargs="+", default=["3:2", "3:1"], help="SIZE:ORDER of each mesh (mm, 1 or 2)")
    ap.add_argument("--simulate-orders", type=int, nargs="*", default=[1], help="simulate the meshes of these orders")
    ap.add_argument("--plans", nargs="+", default=["advance", "bimax"], choices=["advance", "bimax"])
    ap.add_argument("--increments", type=int, nargs="+", default=[3, 6],
                    help="increments of the first run of a plan, then of each retry after a failure")
    ap.add_argument("--out", type=Path, default=RESULTS / "real_ct.csv")
    args = ap.parse_args(argv)

    from toolkit.common.runtime import set_threads
    from toolkit.mesh import mesh_face
    from toolkit.mesh.ct import ct_surfaces
    from toolkit.static import load_case

    set_threads(1)
    t0 = time.perf_counter()
    surfaces = ct_surfaces(args.volume)
    ct_s = time.perf_counter() - t0
    r = surfaces.report
    print(surfaces.summary(), flush=True)
    condyles = np.array([r["landmarks_mm"]["condyle_left"], r["landmarks_mm"]["condyle_right"]])
    rows = []
    for spec in args.meshes:
        size, order = float(spec.split(":")[0]), int(spec.split(":")[1])
        t0 = time.perf_counter()
        try:
            face = mesh_face(surfaces.tissue, surfaces.bones, surfaces.commissures, size_mm=size, order=order)
        except Exception as exc:  # noqa: BLE001 - recorded
            rows.append({"size_mm": size, "order": order, "ct_s": ct_s, "mesh_face_s": time.perf_counter() - t0,
                         "status": f"mesh: {type(exc).__name__}: {str(exc)[:300]}"})
            continue
        mesh_s = time.perf_counter() - t0
        q, sets, seg = face.report["quality"], face.report["node_sets"], face.report["segments"]
        base = {"size_mm": size, "order": order, "ct_s": round(ct_s, 2), "mesh_face_s": round(mesh_s, 1),
                **{f"{k}_s": v for k, v in face.report["seconds"].items()},
                "tissue_triangles": r["surfaces"]["tissue"]["triangles"], "nodes": face.report["nodes"],
                "elements": face.report["elements"], "element_type": face.report["element_type"],
                "min_scaled_jacobian": q["min_scaled_jacobian"], "p1_scaled_jacobian": q["p1_scaled_jacobian"],
                "min_dihedral_deg": q["min_dihedral_deg"], "max_dihedral_deg": q["max_dihedral_deg"],
                "slivers": q["slivers_below_10deg"],
                **{f"set_{k}": sets.get(k, 0) for k in ("bone", "skin", "fixed", "maxilla", "mandible",
                                                       "mucosa_sliding")},
                **{f"{k}_attached_mm2": seg[k]["attached_area_mm2"] for k in ("lefort", "distal") if k in seg},
                **{f"{k}_facing_mm2": seg[k]["facing_area_mm2"] for k in ("lefort", "distal") if k in seg}}
        print({k: v for k, v in base.items()}, flush=True)
        if order not in args.simulate_orders:
            rows.append({**base, "status": "meshed, not simulated (--simulate-orders)"})
            continue
        chin = chin_node(face.mesh)
        bones = {k: v for k, v in face.bones.items() if k != "skull"}
        for name, plan in plans(face, condyles).items():
            if name not in args.plans:
                continue
            row = {**base, "plan": name, "chin_node_mm": np.round(face.mesh.points[chin], 1).tolist()}
            row.update(simulated(load_case(face.mesh, plan=plan, bones=bones), chin, args.increments))
            rows.append(row)
            print({k: (round(v, 3) if isinstance(v, float) else v) for k, v in row.items()
                   if k not in base}, flush=True)
    table = pd.DataFrame(rows)
    extra = {"ct": {k: r[k] for k in ("volume", "thresholds", "axes", "landmarks_mm", "occlusal_plane",
                                      "osteotomy_mm", "cuts_mm", "mouth", "surfaces", "seconds")}}
    write_result(args.out, table, argv=argv, extra=extra)
    with pd.option_context("display.width", 250, "display.max_columns", 60):
        print(table.to_string(index=False))
    return table


if __name__ == "__main__":
    main()
