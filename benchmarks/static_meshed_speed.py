"""Time per plan of the static simulation on a meshed face, one code beside another.

The default plan (linear, mucosa and lip sliding, 3 increments; on the head CT the 5 mm
mandibular advance of ``real_ct.py``) on a face meshed by ``toolkit mesh`` at ``--size`` mm
(tet10 unless ``--order 1``): the paper phantom's surfaces, or with ``--face ct`` the head CT's
(``tests/data/headsq``). The mesh is made once and kept under ``benchmarks/work/`` so that every
run solves the same one.

``--code DIR ...`` runs checkouts of the toolkit (``git worktree add /tmp/before HEAD~1``) beside
each other: each repeat runs every checkout once, in turn, in a fresh single-threaded process, so
that each pair of runs shares the machine's load of the same minutes. Each row is one run: its
wall time, the linear solves and their CG iterations, the solver's seconds, the peak memory and
the largest nodal difference to the first checkout's answer of the same repeat, over every node
and over the skin (mm).

Writes ``benchmarks/results/static_meshed_speed.csv`` with provenance.

Usage::

    python benchmarks/static_meshed_speed.py                                  # this checkout, 2 runs
    python benchmarks/static_meshed_speed.py --code /tmp/before . --repeats 2 # interleaved, before/after
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
from _provenance import RESULTS, write_result

#: the code this benchmark measures: a result is stale once any of these changed after its commit
MEASURES = ("toolkit/mesh/", "toolkit/static/", "toolkit/common/fem/", "toolkit/common/meshes/",
            "toolkit/common/phantoms/", "toolkit/common/analysis/surface_distance.py", "toolkit/common/papers.py")

WORK = Path(__file__).resolve().parent / "work" / "static_meshed_speed"
HERE = Path(__file__).resolve().parent


def prepare(face: str, size: float, order: int) -> Path:
    """Mesh ``face`` once (kept under ``WORK``); the folder holding ``face.vtu``, the bone
    surfaces and ``plan.json``."""
    from toolkit.common.meshes.io import write
    from toolkit.mesh import mesh_face

    folder = WORK / f"{face}_{size:g}mm_order{order}"
    if (folder / "plan.json").exists():
        return folder
    folder.mkdir(parents=True, exist_ok=True)
    if face == "ct":
        from real_ct import HEADSQ, plans

        from toolkit.mesh.ct import ct_surfaces

        surfaces = ct_surfaces(HEADSQ)
        marks = surfaces.report["landmarks_mm"]
        condyles = np.array([marks["condyle_left"], marks["condyle_right"]])
    else:
        from toolkit.common.phantoms.phantom import face_hex
        from toolkit.mesh.phantom import phantom_surfaces
        from toolkit.static import load_case

        surfaces = phantom_surfaces(face_hex("paper"))
    meshed = mesh_face(surfaces.tissue, surfaces.bones, surfaces.commissures, size_mm=size, order=order)
    write(folder / "face.vtu", meshed.mesh)
    for name, bone in meshed.bones.items():
        if name != "skull":
            write(folder / f"{name}.vtu", bone)
    plan = plans(meshed, condyles)["advance"] if face == "ct" else load_case(resolution="paper").plan
    (folder / "plan.json").write_text(json.dumps(plan.to_dict()))
    return folder


def worker(folder: Path, out: Path) -> None:
    """One run in this process: simulate the folder's plan on its face; write a JSON summary and
    the displacement (``.npy``) beside ``out``."""
    import resource

    from toolkit.common.fem import solvers
    from toolkit.common.runtime import set_threads
    from toolkit.static import load_case
    from toolkit.static.plan import SurgicalPlan

    set_threads(1)
    solves = []
    solve = solvers.LinearSolver.solve

    def counted(self, *args, **kwargs):
        x, info = solve(self, *args, **kwargs)
        solves.append((info.iterations, info.seconds))
        return x, info

    solvers.LinearSolver.solve = counted
    bones = {p.stem: p for p in folder.glob("*.vtu") if p.stem != "face"}
    plan = SurgicalPlan.from_dict(json.loads((folder / "plan.json").read_text()))
    case = load_case(folder / "face.vtu", plan=plan, bones=bones)
    t0 = time.perf_counter()
    result = case.simulate(increments=3, material="linear", sliding="mucosa+lip")
    seconds = time.perf_counter() - t0
    s = result.summary()
    np.save(out.with_suffix(".npy"), result.displacement)
    out.write_text(json.dumps({
        "nodes": s["nodes"], "seconds": seconds, "solves": len(solves),
        "cg_iterations": int(sum(i for i, _ in solves)), "solve_s": float(sum(t for _, t in solves)),
        "peak_memory_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "max_displacement_mm": s["max_displacement_mm"], "min_scaled_jacobian": s["min_scaled_jacobian"],
        "release_width_mm": s["release_width_mm"], "passed": s["checks"]["answer"]["passed"],
        "toolkit": str(Path(solvers.__file__).parents[3])}))


def _commit(code: Path) -> str:
    run = subprocess.run(["git", "-C", str(code), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    dirty = subprocess.run(["git", "-C", str(code), "status", "--porcelain", "--untracked-files=no"],
                           capture_output=True, text=True).stdout.strip()
    return run.stdout.strip() + (" with uncommitted changes" if dirty else "")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--face", choices=("phantom", "ct"), default="phantom")
    ap.add_argument("--size", type=float, default=3.0, help="tetrahedron edge length, mm (toolkit mesh's default)")
    ap.add_argument("--order", type=int, choices=(1, 2), default=2)
    ap.add_argument("--code", type=Path, nargs="+", default=[HERE.parent],
                    help="toolkit checkouts to run in turn (the first is the reference of the differences)")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--out", type=Path, default=RESULTS / "static_meshed_speed.csv")
    ap.add_argument("--worker", nargs=2, type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        return worker(*args.worker)
    folder = prepare(args.face, args.size, args.order)
    from toolkit.common.meshes.io import read

    skin = read(folder / "face.vtu").node_sets["skin"]
    rows = []
    for repeat in range(args.repeats):
        first = None
        for code in args.code:
            code = code.resolve()
            out = WORK / f"run_{args.face}_{code.name}_{repeat}.json"
            env = {**os.environ, "PYTHONPATH": str(code)}
            t0 = time.perf_counter()
            run = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--worker", str(folder), str(out)],
                                 env=env, capture_output=True, text=True)
            row = {"face": args.face, "size_mm": args.size, "order": args.order, "code": _commit(code),
                   "repeat": repeat, "process_s": time.perf_counter() - t0}
            if run.returncode:
                row["status"] = f"failed: {run.stderr.strip().splitlines()[-1][:300]}"
            else:
                row.update(status="ok", **json.loads(out.read_text()))
                u = np.load(out.with_suffix(".npy"))
                first = u if first is None else first
                difference = np.linalg.norm(u - first, axis=1)
                row["max_difference_mm"] = float(difference.max())
                row["max_skin_difference_mm"] = float(difference[skin].max())
            rows.append(row)
            print(row, flush=True)
    table = pd.DataFrame(rows)
    write_result(args.out, table, argv=argv)
    ok = table[table.status == "ok"]
    if len(args.code) > 1 and len(ok):
        means = ok.groupby("code", sort=False)[["seconds", "cg_iterations", "solve_s"]].mean()
        print(means.to_string(float_format=lambda v: f"{v:.1f}"))
    return table


if __name__ == "__main__":
    main()
