"""The static learning database on a meshed face: how many sampled plans complete.

The phantom's surfaces (:func:`toolkit.mesh.phantom.phantom_surfaces`), or with ``--ct`` the
surfaces of the head CT in ``tests/data/headsq`` (:func:`toolkit.mesh.ct.ct_surfaces`, its condyles
as the proximal segments' pivots), are meshed by ``toolkit mesh`` (:func:`toolkit.mesh.mesh_face`)
at ``--size`` and ``--order``, written with their bone surfaces, and
``toolkit static database --mesh`` (:func:`toolkit.static.database.build_database`) runs ``--plans``
sampled plans of each ``--modes`` on it, as a user would. Per simulation: status, reason, time,
the release band it used, the cut nodes and the mucosa nodes it freed (the retries a plan may
need, stored with its own boundary types). Writes ``benchmarks/results/meshed_database.csv``; a
rerun resumes on the mesh and databases in ``benchmarks/work/meshed_database/`` (delete the folder to start afresh).

Usage::

    python benchmarks/meshed_database.py                     # paper phantom, 7 mm, 10 plans per mode
    python benchmarks/meshed_database.py --size 5 --plans 20 --modes sagittal
    python benchmarks/meshed_database.py --ct --size 3 --order 1 --out benchmarks/results/meshed_database_ct.csv
    python benchmarks/meshed_database.py --size 3 --plans 4 --report-only   # what a stopped run finished
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pandas as pd
from _provenance import RESULTS, ROOT, work_folder, write_result

#: the code this benchmark measures: a result is stale once any of these changed after its commit
MEASURES = ("toolkit/mesh/", "toolkit/static/", "toolkit/common/fem/", "toolkit/common/meshes/",
            "toolkit/common/phantoms/", "toolkit/common/training/database.py",
            "toolkit/common/analysis/surface_distance.py", "toolkit/common/papers.py")

HEADSQ = ROOT / "tests" / "data" / "headsq" / "quarter.nhdr"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--resolution", default="paper")
    ap.add_argument("--ct", action="store_true", help="the head CT's surfaces instead of the phantom's")
    ap.add_argument("--size", type=float, default=7.0, help="tetrahedron edge length, mm")
    ap.add_argument("--order", type=int, default=2, choices=[1, 2], help="tet4 (1) or tet10 (2)")
    ap.add_argument("--plans", type=int, default=10, help="plans per mode")
    ap.add_argument("--modes", nargs="+", default=["sagittal", "full"], choices=["sagittal", "full"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--report-only", action="store_true",
                    help="tabulate what the databases in the work folder hold, running nothing (plans not yet run "
                         "are listed as such)")
    ap.add_argument("--out", type=Path, default=RESULTS / "meshed_database.csv")
    args = ap.parse_args(argv)

    import h5py

    from toolkit.common.meshes.io import read, write
    from toolkit.common.phantoms.phantom import face_hex
    from toolkit.common.runtime import set_threads
    from toolkit.common.training.database import read_failures
    from toolkit.mesh import mesh_face
    from toolkit.mesh.phantom import phantom_surfaces, write_surfaces
    from toolkit.static.database import DatabaseConfig, build_database

    set_threads(1)
    face = "ct" if args.ct else args.resolution
    work = work_folder(args.out) / f"{face}_{args.size:g}mm_order{args.order}"
    work.mkdir(parents=True, exist_ok=True)
    condyles = None
    if args.ct:
        from toolkit.mesh.ct import ct_surfaces

        surfaces = ct_surfaces(HEADSQ)
        files = surfaces.write(work / "surfaces")
        marks = surfaces.report["landmarks_mm"]
        condyles = [marks["condyle_left"], marks["condyle_right"]]
    else:
        surfaces = phantom_surfaces(face_hex(args.resolution))
        files = write_surfaces(work / "surfaces", surfaces)
    if (work / "face.vtu").exists():  # a rerun resumes on the same mesh (fTetWild's differs run to run)
        face_mesh = read(work / "face.vtu")
    else:
        face_mesh = mesh_face(surfaces.tissue, surfaces.bones, surfaces.commissures, size_mm=args.size,
                              order=args.order).mesh
        write(work / "face.vtu", face_mesh)
    bones = {k: files[k] for k in surfaces.bones if k != "skull"}
    rows = []
    for mode in args.modes:
        path = work / f"{mode}.h5"
        config = DatabaseConfig.for_mesh(work / "face.vtu", bones, condyles=condyles, plans=args.plans, mode=mode,
                                        seed=args.seed)
        if not args.report_only:
            build_database(path, config, workers=1)
        # every failure the database holds, those of earlier runs (skipped on resume) included
        failed = dict(zip(*read_failures(path)[["key", "reason"]].to_numpy().T)) if path.exists() else {}
        records = {}
        if path.exists():
            with h5py.File(path) as f:
                records = {k: json.loads(g.attrs["attrs"]) for k, g in f["records"].items()} if "records" in f else {}
        # the first --plans plans of the mode (a database may hold more, from a run that asked for more)
        keys = sorted(k for k in set(records) | set(failed) if int(k.rsplit("-p", 1)[1]) < args.plans)
        if args.report_only:  # the plans the command asks for that neither finished nor failed
            keys += [f"not run ({n})" for n in range(args.plans - len(keys))]
        for key in keys:
            a = records.get(key, {})
            status = "ok" if key in records else "failed" if key in failed else "not run"
            rows.append({"face": face, "size_mm": args.size, "order": args.order, "nodes": face_mesh.n_points,
                         "mode": mode, "key": key, "status": status,
                         "reason": str(failed.get(key, ""))[:200], "seconds": a.get("seconds"),
                         "release_width_mm": a.get("release_width_mm"), "freed_cut_nodes": a.get("freed_cut_nodes"),
                         "freed_mucosa_nodes": a.get("freed_mucosa_nodes"),
                         "min_scaled_jacobian": a.get("min_scaled_jacobian")})
    table = pd.DataFrame(rows)
    write_result(args.out, table, argv=argv)
    print(table.groupby("mode").agg(plans=("status", "size"), completed=("status", lambda s: (s == "ok").sum()),
                                    median_s=("seconds", "median"), wider_band=("release_width_mm",
                                                                                lambda s: (s > 10).sum()),
                                    freed=("freed_cut_nodes", lambda s: (s > 0).sum()),
                                    mucosa=("freed_mucosa_nodes", lambda s: (s > 0).sum())).to_string())
    return table


if __name__ == "__main__":
    main()
