"""Round trip of ``toolkit mesh`` on the phantom, and its speed.

The phantom's closed tissue surface, bone surfaces and commissures
(:func:`toolkit.mesh.phantom.phantom_surfaces`) go through :func:`toolkit.mesh.mesh_face`; the
result is compared with the phantom it came from:

- **labels**: per set, the share of the meshed face's nodes whose nearest phantom node carries
  the same set, and the other way round (the phantom's set nodes whose nearest boundary node
  of the meshed face carries it);
- **displacement**: the default plan on both (linear, mucosa+lip sliding, 3 increments), the
  meshed face's displacement interpolated at the phantom's skin nodes (those within 0.5 mm of
  the meshed skin): mean, 95th percentile and maximum difference, beside the phantom's mean
  and maximum skin displacement;
- **speed**: the stage times of ``mesh_face`` at each ``--sizes`` (a ~50k-node mesh among them);
- **robustness** (``--plans N``): N plans of each sampling mode (:func:`toolkit.static.plan.sample_plans`,
  the physiological ranges, the phantom's pivots) on the meshed face of the first size: completion,
  minimum scaled Jacobian, time (``own_face_robustness.csv``).

Writes ``benchmarks/results/own_face.csv`` (stages and the displacement comparison, one row per
size and order) and ``own_face_labels.csv`` (label agreement), with provenance sidecars.

Usage::

    python benchmarks/own_face.py                      # paper phantom, sizes 5 and 3.5 mm, tet10
    python benchmarks/own_face.py --sizes 5 --orders 1 2 --resolution paper
    python benchmarks/own_face.py --sizes 7 5 3.5 --simulate-sizes 7 5
    python benchmarks/own_face.py --sizes 7 --plans 25 --no-simulate    # 50 sampled plans
    python benchmarks/own_face.py --sizes 3.5 --merge  # add a size to the committed tables
    python benchmarks/own_face.py --sizes 7 --lip-muscle none --merge   # the tissue isotropic throughout
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pandas as pd
from _provenance import RESULTS, write_result

#: the code this benchmark measures: a result is stale once any of these changed after its commit
MEASURES = ("toolkit/mesh/", "toolkit/static/", "toolkit/common/fem/", "toolkit/common/meshes/",
            "toolkit/common/phantoms/", "toolkit/common/analysis/surface_distance.py", "toolkit/common/papers.py")

SETS = ("bone", "skin", "fixed", "maxilla", "mandible", "mucosa_sliding", "lip_sliding")


def label_agreement(face_mesh, phantom_mesh) -> list[dict]:
    from scipy.spatial import cKDTree

    from toolkit.common.meshes.topology import boundary_faces

    rows = []
    boundary = np.unique(boundary_faces("tet4", face_mesh.volume_cells[:, :4]))
    tree_ph, tree_face = cKDTree(phantom_mesh.points), cKDTree(face_mesh.points[boundary])
    for name in SETS:
        if name not in face_mesh.node_sets or name not in phantom_mesh.node_sets:
            continue
        ids = face_mesh.node_sets[name]
        ph_mask = np.zeros(phantom_mesh.n_points, bool)
        ph_mask[phantom_mesh.node_sets[name]] = True
        face_mask = np.zeros(face_mesh.n_points, bool)
        face_mask[ids] = True
        near_ph = tree_ph.query(face_mesh.points[ids])[1]
        near_face = boundary[tree_face.query(phantom_mesh.points[phantom_mesh.node_sets[name]])[1]]
        rows.append({"set": name, "nodes": int(ids.size), "phantom_nodes": int(ph_mask.sum()),
                     "agree_meshed_to_phantom": float(ph_mask[near_ph].mean()),
                     "agree_phantom_to_meshed": float(face_mask[near_face].mean())})
    return rows


#: the bone-side sets the static boundary conditions read, carried over by --labels phantom
CARRIED = ("fixed", "maxilla", "mandible", "mucosa_sliding", "mucosa_lefort", "mucosa_distal", "mucosa_proximal_left",
           "mucosa_proximal_right", "mucosa_skull")


def phantom_labels(face_mesh, phantom_mesh):
    """``face_mesh`` whose :data:`CARRIED` sets are the phantom's: each boundary corner node takes
    the membership of the nearest boundary node of the phantom (bone-side sets only on its bone
    nodes), and on a tet10 face each set takes the mid-edge nodes of the boundary edges whose two
    ends it holds, as ``toolkit mesh`` extends its own sets."""
    from scipy.spatial import cKDTree

    from toolkit.common.meshes.topology import boundary_faces

    ours, theirs = (np.unique(boundary_faces(m.volume_type, m.volume_cells)) for m in (face_mesh, phantom_mesh))
    nearest = theirs[cKDTree(phantom_mesh.points[theirs]).query(face_mesh.points[ours])[1]]
    on_bone = np.isin(ours, face_mesh.node_sets["bone"])
    sets = dict(face_mesh.node_sets)
    for name in CARRIED:
        if name not in phantom_mesh.node_sets:
            sets.pop(name, None)
            continue
        member = np.isin(nearest, phantom_mesh.node_sets[name]) & (on_bone | (name == "fixed"))
        sets[name] = _with_mid_edge_nodes(face_mesh, ours[member])
    per_segment = [sets[k] for k in CARRIED if k.startswith("mucosa_") and k != "mucosa_sliding" and k in sets]
    if per_segment:  # a mid-edge node between two segments' mucosa slides on neither, as toolkit mesh has it
        sets["mucosa_sliding"] = np.unique(np.concatenate(per_segment))
    return type(face_mesh)(face_mesh.points, face_mesh.cells, node_sets=sets, element_sets=face_mesh.element_sets,
                           cell_data=face_mesh.cell_data)


def _with_mid_edge_nodes(mesh, ids: np.ndarray) -> np.ndarray:
    """``ids`` (corner nodes) and, on a tet10 mesh, the mid-edge nodes of the boundary edges whose
    two ends are in ``ids``."""
    from toolkit.common.fem.reference import REFERENCE_ELEMENTS
    from toolkit.common.meshes.topology import boundary_faces, unique_edges
    from toolkit.mesh.face import mid_edge_lookup

    if mesh.volume_type != "tet10":
        return ids
    edges = unique_edges(boundary_faces("tet10", mesh.volume_cells), REFERENCE_ELEMENTS["tri3"].edges)[0]
    member = np.zeros(mesh.n_points, dtype=bool)
    member[ids] = True
    both = edges[member[edges[:, 0]] & member[edges[:, 1]]]
    return np.union1d(ids, mid_edge_lookup(mesh.volume_cells)(both))


def skin_difference(face_mesh, u_face, phantom_mesh, u_phantom) -> dict:
    from toolkit.common.analysis.surface_distance import closest_points, interpolate_on_surface
    from toolkit.common.meshes.topology import boundary_faces

    faces = boundary_faces("tet4", face_mesh.volume_cells[:, :4])
    skin = np.zeros(face_mesh.n_points, bool)
    skin[face_mesh.node_sets["skin"]] = True
    skin_faces = faces[skin[faces].all(axis=1)]
    X = phantom_mesh.points[phantom_mesh.node_sets["skin"]]
    near = closest_points(X, face_mesh.points, skin_faces).distance < 0.5
    u_t = interpolate_on_surface(X[near], face_mesh.points, skin_faces, u_face)
    u_h = u_phantom[phantom_mesh.node_sets["skin"]][near]
    d = np.linalg.norm(u_t - u_h, axis=1)
    mag = np.linalg.norm(u_h, axis=1)
    return {"skin_points": int(near.sum()), "phantom_mean_mm": float(mag.mean()), "phantom_max_mm": float(mag.max()),
            "diff_mean_mm": float(d.mean()), "diff_p95_mm": float(np.percentile(d, 95)),
            "diff_max_mm": float(d.max())}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--resolution", default="paper")
    ap.add_argument("--sizes", type=float, nargs="+", default=[5.0, 3.5])
    ap.add_argument("--orders", type=int, nargs="+", default=[2])
    ap.add_argument("--backend", default=None, help="mesher (default: toolkit.mesh.DEFAULT)")
    ap.add_argument("--no-simulate", action="store_true", help="no default-plan comparison")
    ap.add_argument("--simulate-sizes", type=float, nargs="+", default=None,
                    help="compare the default plan at these sizes only (default: every size)")
    ap.add_argument("--plans", type=int, default=0, help="sampled plans per mode on the first size's mesh")
    ap.add_argument("--labels", nargs="+", default=["rules"], choices=["rules", "phantom"],
                    help="simulate the meshed face with its labelling rules' sets, and/or with the phantom's "
                         "bone-side sets carried over (what the labels account for in the difference)")
    ap.add_argument("--lip-muscle", nargs="+", default=["fibres"], choices=["fibres", "none"],
                    help="simulate with the mesher's transversely isotropic lip muscle, and/or with none (the "
                         "tissue isotropic throughout: what the lip muscle accounts for in the difference)")
    ap.add_argument("--out", type=Path, default=RESULTS / "own_face.csv")
    ap.add_argument("--merge", action="store_true",
                    help="keep the rows of --out (and its labels table) for the sizes, orders and labels not run now")
    args = ap.parse_args(argv)

    from toolkit.common.phantoms.phantom import face_hex
    from toolkit.common.runtime import set_threads
    from toolkit.mesh import DEFAULT, mesh_face
    from toolkit.mesh.phantom import phantom_surfaces
    from toolkit.static import load_case

    set_threads(1)
    backend = args.backend or DEFAULT
    phantom = face_hex(args.resolution)
    surfaces = phantom_surfaces(phantom)
    reference = None
    rows, label_rows = [], []
    for size in args.sizes:
        for order in args.orders:
            t0 = time.perf_counter()
            face = mesh_face(surfaces.tissue, surfaces.bones, surfaces.commissures, size_mm=size, order=order,
                             backend=backend)
            row = {"resolution": args.resolution, "backend": backend, "size_mm": size, "order": order,
                   "nodes": face.report["nodes"], "elements": face.report["elements"],
                   "mesh_face_s": time.perf_counter() - t0,
                   **{f"{k}_s": v for k, v in face.report["seconds"].items()},
                   "min_scaled_jacobian": face.report["quality"]["min_scaled_jacobian"],
                   "min_dihedral_deg": face.report["quality"]["min_dihedral_deg"],
                   "max_dihedral_deg": face.report["quality"]["max_dihedral_deg"]}
            for r in label_agreement(face.mesh, phantom.mesh):
                label_rows.append({"size_mm": size, "order": order, **r})
            simulated = not args.no_simulate and (args.simulate_sizes is None or size in args.simulate_sizes)
            base = row
            variants = [(la, li) for la in args.labels for li in args.lip_muscle] if simulated \
                else [("rules", "fibres")]
            for labels, lip in variants:
                row = {**base, "labels": labels, "lip_muscle": lip}
                if simulated:
                    if reference is None:
                        case = load_case(resolution=args.resolution)
                        t1 = time.perf_counter()
                        reference = case.simulate(increments=3, material="linear", sliding="mucosa+lip")
                        ref_s = time.perf_counter() - t1
                    mesh = face.mesh if labels == "rules" else phantom_labels(face.mesh, phantom.mesh)
                    if lip == "none":
                        mesh = type(mesh)(mesh.points, mesh.cells, node_sets=mesh.node_sets)
                    meshed = load_case(mesh, plan=case.plan, bones={k: v for k, v in face.bones.items()
                                                                    if k != "skull"})
                    t1 = time.perf_counter()
                    try:
                        res = meshed.simulate(increments=3, material="linear", sliding="mucosa+lip")
                        row.update(status="ok", simulate_s=time.perf_counter() - t1, phantom_simulate_s=ref_s,
                                   min_sj_after=res.summary()["min_scaled_jacobian"],
                                   **skin_difference(face.mesh, res.displacement, phantom.mesh,
                                                     reference.displacement))
                    except Exception as exc:  # noqa: BLE001 - recorded
                        row.update(status=f"{type(exc).__name__}: {str(exc)[:200]}",
                                   simulate_s=time.perf_counter() - t1)
                rows.append(row)
                print({k: (round(v, 3) if isinstance(v, float) else v) for k, v in row.items()}, flush=True)
    if args.plans:
        robustness(args, phantom, surfaces, backend)
        if args.no_simulate:
            return None
    table = _merged(args.out, pd.DataFrame(rows), ["size_mm", "order", "labels", "lip_muscle"], args.merge)
    write_result(args.out, table, argv=argv, resumed=args.merge)
    labels_out = args.out.with_name(args.out.stem + "_labels.csv")
    labels = _merged(labels_out, pd.DataFrame(label_rows), ["size_mm", "order", "set"], args.merge)
    write_result(labels_out, labels, argv=argv, resumed=args.merge)
    with pd.option_context("display.width", 200):
        print(table.to_string(index=False, float_format=lambda v: f"{v:.3g}"))
        print(labels.to_string(index=False, float_format=lambda v: f"{v:.2f}"))
    return table


def _merged(path: Path, new: pd.DataFrame, key: list[str], merge: bool) -> pd.DataFrame:
    """``new``, with (``merge``) the rows of the table at ``path`` whose ``key`` is not in ``new``:
    sizes from coarse to fine, then element order."""
    if not merge or not path.exists():
        return new
    old = pd.read_csv(path)
    done = set(map(tuple, new[key].astype(str).to_numpy()))
    keep = old[[tuple(r) not in done for r in old[key].astype(str).to_numpy()]]
    out = pd.concat([keep, new], ignore_index=True)
    return out.sort_values(key[:2], ascending=[False, True], kind="stable").reset_index(drop=True)


def robustness(args, phantom, surfaces, backend) -> pd.DataFrame:
    from tqdm import tqdm

    from toolkit.mesh import mesh_face
    from toolkit.static import load_case
    from toolkit.static.plan import sample_plans

    face = mesh_face(surfaces.tissue, surfaces.bones, surfaces.commissures, size_mm=args.sizes[0],
                     order=args.orders[0], backend=backend)
    bones = {k: v for k, v in face.bones.items() if k != "skull"}
    rows = []
    for mode in ("sagittal", "full"):
        for i, plan in enumerate(tqdm(sample_plans(args.plans, 0, mode, phantom=phantom), desc=mode)):
            case = load_case(face.mesh, plan=plan, bones=bones)
            t0 = time.perf_counter()
            try:
                s = case.simulate(increments=3, material="linear", sliding="mucosa+lip").summary()
                row = {"status": "ok", "min_scaled_jacobian": s["min_scaled_jacobian"], "substeps": s["substeps"],
                       "release_width_mm": s["release_width_mm"], "max_displacement_mm": s["max_displacement_mm"]}
            except Exception as exc:  # noqa: BLE001 - recorded
                row = {"status": type(exc).__name__, "message": str(exc)[:200]}
            rows.append({"size_mm": args.sizes[0], "order": args.orders[0], "mode": mode, "plan": i,
                         "seconds": time.perf_counter() - t0, **row})
            if row["status"] != "ok":
                tqdm.write(f"{mode} plan {i}: {row['status']}: {row.get('message', '')[:150]}")
    table = pd.DataFrame(rows)
    write_result(args.out.with_name(args.out.stem + "_robustness.csv"), table)
    summary = table.groupby("mode").agg(plans=("status", "size"), completed=("status", lambda x: (x == "ok").sum()),
                                        min_sj=("min_scaled_jacobian", "min"), median_s=("seconds", "median"))
    print(summary.to_string())
    return table


if __name__ == "__main__":
    main()
