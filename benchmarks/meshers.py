"""Benchmark: the tetrahedral meshers on the phantom's tissue surface and on damaged copies of it.

For every (mesher, repair, input, size) case, in a fresh process (a mesher that crashes or hangs
costs one row), :func:`toolkit.mesh.backends.tetrahedralize` on one thread (``--threads``), and
per case:

- ``status`` (``ok``, or the error's class and message; ``timeout``, ``crash``);
- ``wall_s`` (median of ``--repeat`` runs on the undamaged surfaces, one run on the damaged
  ones) and ``cpu_s`` (process CPU time of that run), and ``repair_s`` of the repair step;
- node and tetrahedron counts, mean edge length; minimum and 1st-percentile scaled Jacobian; minimum and maximum
  dihedral angle; the share of slivers (minimum dihedral under 10 degrees);
- fidelity: the largest and mean distance of the mesh's boundary vertices to the undamaged input
  surface (``out_to_in``), the largest distance of the undamaged surface's vertices to the mesh's
  boundary (``in_to_out``: a part left out), the mesh volume over the surface's enclosed volume;
- whether the mesh's boundary is closed and edge-manifold.

Inputs: the closed tissue surface of the ``paper`` phantom (mouth closed:
:func:`toolkit.mesh.surface.tissue_surface_of`) at 4 and 3 mm, of the ``fine`` phantom at 2 mm
(about 45k nodes), and copies of the paper surface damaged as segmentation exports hold them
(:data:`DAMAGE`), at 3 mm. A run over 60 s is not repeated; a TetGen or Gmsh case over 120 s is
stopped (``timeout``). Repairs before meshing:
``none``, ``toolkit`` (:func:`toolkit.mesh.surface.closed_surface`), ``trimesh`` (merge vertices,
drop duplicate faces, fix winding, fill holes) and ``pymeshfix`` (MeshFix: also removes
self-intersections).

    python benchmarks/meshers.py [--sizes 4 3 2] [--meshers ftetwild tetgen gmsh] [--repeat 3]
    python benchmarks/meshers.py --meshers ftetwild --sizes 2 --damages clean --threads 2 --add
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

#: the code this benchmark measures: a result is stale once any of these changed after its commit
MEASURES = ("toolkit/mesh/", "toolkit/common/phantoms/", "toolkit/common/meshes/", "toolkit/common/fem/reference.py",
            "toolkit/common/analysis/surface_distance.py")

ROOT = Path(__file__).resolve().parent.parent
#: target mean edge (mm) -> phantom whose tissue surface is meshed: about 5k, 13k and 45k nodes
SIZES = {4.0: "paper", 3.0: "paper", 2.0: "fine"}
DAMAGE_SIZE = 3.0  #: the size the damaged surfaces are meshed at
MESHERS = ("ftetwild", "wildmeshing", "tetgen", "gmsh")
REPAIRS = ("none", "toolkit", "trimesh", "pymeshfix")
DAMAGE = ("clean", "duplicate_vertices", "holes", "flipped_faces", "duplicate_faces", "self_intersection")
SLIVER_DEG = 10.0


# ----------------------------------------------------------------------------------------------
# inputs


def clean_surface(phantom: str) -> tuple[np.ndarray, np.ndarray]:
    """The closed tissue surface of a phantom (mouth closed), ``(points (n, 3) mm, triangles (m, 3))``."""
    from toolkit.common import face_hex
    from toolkit.mesh.surface import tissue_surface_of

    surface = tissue_surface_of(face_hex(phantom).mesh)
    return surface.points, surface.cells["tri3"]


def _vertex_normals(p, t):
    n = np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]])
    vn = np.zeros_like(p)
    for k in range(3):
        np.add.at(vn, t[:, k], n)
    return vn / np.linalg.norm(vn, axis=1, keepdims=True)


def damaged(points, triangles, kind: str, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A copy of a closed surface with one defect of a segmentation export.

    ``duplicate_vertices``: every triangle with its own three vertices (an unmerged STL);
    ``holes``: 1, 5 and 20 triangles removed at three places; ``flipped_faces``: 5 % of the
    triangles reversed; ``duplicate_faces``: 5 % of the triangles twice; ``self_intersection``:
    the vertices within 4 mm of the thinnest place pushed through the opposite side (2 mm past
    it); ``metres``: the coordinates / 1000.
    """
    p, t = np.array(points, dtype=float), np.array(triangles, dtype=np.int64)
    rng = np.random.default_rng(seed)
    if kind == "clean":
        return p, t
    if kind == "duplicate_vertices":
        return p[t].reshape(-1, 3), np.arange(t.size).reshape(-1, 3)
    if kind == "holes":
        from scipy.spatial import cKDTree

        centres = p[t].mean(axis=1)
        drop = []
        for count, seed_tri in zip((1, 5, 20), rng.choice(len(t), 3, replace=False), strict=True):
            drop.extend(cKDTree(centres).query(centres[seed_tri], k=count)[1].ravel().tolist() if count > 1
                        else [int(seed_tri)])
        return p, np.delete(t, np.unique(drop), axis=0)
    if kind == "flipped_faces":
        flip = rng.choice(len(t), int(0.05 * len(t)), replace=False)
        t[flip] = t[flip][:, ::-1]
        return p, t
    if kind == "duplicate_faces":
        return p, np.vstack([t, t[rng.choice(len(t), int(0.05 * len(t)), replace=False)]])
    if kind == "self_intersection":
        from scipy.spatial import cKDTree

        normals = _vertex_normals(p, t)
        dist, near = cKDTree(p).query(p, k=min(64, len(p)))
        opposite = np.einsum("ij,ikj->ik", normals, normals[near]) < -0.5
        thick = np.where(opposite, dist, np.inf).min(axis=1)
        v = int(np.argmin(thick))
        patch = np.flatnonzero(np.linalg.norm(p - p[v], axis=1) < 4.0)
        p[patch] -= (thick[v] + 2.0) * normals[v]
        return p, t
    if kind == "metres":
        return p / 1000.0, t
    raise ValueError(f"unknown damage {kind!r}; expected one of {(*DAMAGE, 'metres')}")


def repaired(points, triangles, repair: str) -> tuple[np.ndarray, np.ndarray]:
    """The surface after one of :data:`REPAIRS`."""
    if repair == "none":
        return points, triangles
    if repair == "toolkit":
        from toolkit.mesh.surface import closed_surface

        surface, _ = closed_surface(points, triangles)
        return surface.points, surface.cells["tri3"]
    if repair == "trimesh":
        import trimesh

        m = trimesh.Trimesh(points, triangles, process=True)  # merges vertices
        m.update_faces(m.unique_faces())
        m.update_faces(m.nondegenerate_faces())
        m.remove_unreferenced_vertices()
        trimesh.repair.fix_winding(m)
        trimesh.repair.fix_inversion(m)
        trimesh.repair.fill_holes(m)
        return np.asarray(m.vertices), np.asarray(m.faces)
    if repair == "pymeshfix":
        import pymeshfix

        fix = pymeshfix.MeshFix(np.asarray(points, dtype=float), np.asarray(triangles, dtype=np.int32))
        fix.repair()
        return np.asarray(fix.points), np.asarray(fix.faces)
    raise ValueError(f"unknown repair {repair!r}; expected one of {REPAIRS}")


# ----------------------------------------------------------------------------------------------
# metrics


def boundary_faces(tets: np.ndarray) -> np.ndarray:
    """Faces of a tet mesh that belong to one tetrahedron, ``(f, 3)``."""
    faces = tets[:, [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]]].reshape(-1, 3)
    _, index, counts = np.unique(np.sort(faces, axis=1), axis=0, return_index=True, return_counts=True)
    return faces[index[counts == 1]]


def closed_manifold(faces: np.ndarray) -> bool:
    """Every edge of the triangles in exactly two of them, once in each direction."""
    directed = faces[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2)
    forward = np.unique(directed, axis=0)
    if len(forward) != len(directed):
        return False
    undirected, counts = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
    return bool((counts == 2).all())


def metrics(points, tets, ref_points, ref_triangles) -> dict:
    from toolkit.common.analysis.surface_distance import closest_points
    from toolkit.common.meshes.quality import scaled_jacobian
    from toolkit.mesh.face import dihedral_angles

    sj = scaled_jacobian("tet4", points[tets])
    dihedral = dihedral_angles(points, tets)
    faces = boundary_faces(tets)
    skin = np.unique(faces)
    out_in = closest_points(points[skin], ref_points, ref_triangles).distance
    in_out = closest_points(ref_points, points, faces).distance
    x = points[tets]
    volume = np.einsum("ij,ij->i", np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), x[:, 3] - x[:, 0]).sum() / 6
    r = ref_points[ref_triangles]
    ref_volume = np.einsum("ij,ij->i", r[:, 0], np.cross(r[:, 1], r[:, 2])).sum() / 6
    edges = np.linalg.norm(x[:, [1, 2, 3, 2, 3, 3]] - x[:, [0, 0, 0, 1, 1, 2]], axis=2)
    return {"nodes": len(points), "tets": len(tets), "mean_edge_mm": float(edges.mean()), "min_sj": float(sj.min()),
            "p01_sj": float(np.percentile(sj, 1)), "min_dihedral_deg": float(dihedral.min()),
            "max_dihedral_deg": float(dihedral.max()),
            "sliver_share": float((dihedral.min(axis=1) < SLIVER_DEG).mean()),
            "out_to_in_max_mm": float(out_in.max()), "out_to_in_mean_mm": float(out_in.mean()),
            "in_to_out_max_mm": float(in_out.max()), "volume_ratio": float(volume / ref_volume),
            "boundary_closed_manifold": closed_manifold(faces)}


# ----------------------------------------------------------------------------------------------
# one case, in a child process


def case(mesher: str, repair: str, damage: str, size: float, repeat: int, threads: int = 1) -> dict:
    from toolkit.mesh.backends import tetrahedralize

    ref_p, ref_t = clean_surface(SIZES[size])
    p, t = damaged(ref_p, ref_t, damage)
    row = {}
    t0 = time.perf_counter()
    try:
        p, t = repaired(p, t, repair)
    except Exception as exc:  # a repair that refuses is a result
        return {"status": f"repair: {type(exc).__name__}: {exc}"[:300], "repair_s": time.perf_counter() - t0}
    row["repair_s"] = time.perf_counter() - t0
    walls = []
    for _ in range(repeat):
        c0, w0 = time.process_time(), time.perf_counter()
        try:
            points, tets = tetrahedralize(p, t, size, backend=mesher, threads=threads)
        except Exception as exc:  # a mesher that fails is a result
            row["status"] = f"{type(exc).__name__}: {exc}"[:300]
            row["wall_s"] = time.perf_counter() - w0
            return row
        walls.append(time.perf_counter() - w0)
        row["cpu_s"] = time.process_time() - c0
        if walls[-1] > 60.0:  # one run of a slow case is its measure
            break
    row["runs"] = len(walls)
    row.update(status="ok", wall_s=statistics.median(walls), **metrics(points, tets, ref_p, ref_t))
    return row


def run_case(mesher, repair, damage, size, repeat, timeout, threads=1) -> dict:
    n = str(threads)
    env = dict(os.environ, OMP_NUM_THREADS=n, OPENBLAS_NUM_THREADS=n, MKL_NUM_THREADS=n)
    cmd = [sys.executable, __file__, "--case", mesher, repair, damage, str(size), str(repeat), n]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env, cwd=ROOT)
    except subprocess.TimeoutExpired:
        return {"status": f"timeout after {timeout:g} s"}
    lines = [line for line in proc.stdout.splitlines() if line.startswith("{")]
    if proc.returncode != 0 or not lines:
        tail = (proc.stderr.strip().splitlines() or [""])[-1]
        return {"status": f"crash (exit code {proc.returncode}): {tail}"[:300]}
    return json.loads(lines[-1])


def cases(meshers, sizes, damages) -> list[tuple]:
    out = []
    for size in sizes:
        for damage in damages if size == DAMAGE_SIZE else [d for d in damages if d == "clean"]:
            for mesher in meshers:
                ftetwild = mesher in ("ftetwild", "wildmeshing")
                if mesher == "wildmeshing" and damage != "clean":
                    continue  # the same fTetWild as ftetwild
                repairs = ("none",) if ftetwild or damage == "clean" else REPAIRS
                out += [(mesher, repair, damage, size) for repair in repairs]
    return out


def main(argv=None) -> pd.DataFrame:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=float, nargs="+", default=list(SIZES), choices=list(SIZES))
    parser.add_argument("--meshers", nargs="+", default=list(MESHERS), choices=MESHERS)
    parser.add_argument("--damages", nargs="+", default=list(DAMAGE), choices=DAMAGE)
    parser.add_argument("--repeat", type=int, default=3, help="runs per undamaged case (median wall time)")
    parser.add_argument("--timeout", type=float, default=600.0,
                        help="seconds per fTetWild case; TetGen and Gmsh get at most 120 s")
    parser.add_argument("--threads", type=int, default=1, help="threads the mesher may use")
    parser.add_argument("--add", action="store_true",
                        help="keep the rows of the result that this command does not measure again")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from _provenance import RESULTS, write_result

    rows = []
    for mesher, repair, damage, size in cases(args.meshers, args.sizes, args.damages):
        repeat = args.repeat if damage == "clean" else 1
        row = {"mesher": mesher, "repair": repair, "input": damage, "size_mm": size, "phantom": SIZES[size],
               "threads": args.threads,
               **run_case(mesher, repair, damage, size, repeat,
                          args.timeout if mesher in ("ftetwild", "wildmeshing") else min(args.timeout, 120.0),
                          args.threads)}
        rows.append(row)
        print(f"{mesher:12s} {repair:9s} {damage:19s} {size:4g} mm  {row['status'][:60]:60s} "
              f"{row.get('wall_s', float('nan')):7.2f} s  nodes {row.get('nodes', 0):>7}  "
              f"min SJ {row.get('min_sj', float('nan')):.3f}", flush=True)
    df = pd.DataFrame(rows)
    out = args.out or RESULTS / "meshers.csv"
    if args.add and out.exists():
        old = pd.read_csv(out)
        old["threads"] = old["threads"].fillna(1).astype(int) if "threads" in old else 1
        key = ["mesher", "repair", "input", "size_mm", "threads"]
        old = old[~old.set_index(key).index.isin(df.set_index(key).index)]
        df = pd.concat([old, df], ignore_index=True)
    from toolkit.mesh.backends import BACKENDS

    extra = {"licences": {name: b.licence for name, b in BACKENDS.items()}, "sliver_deg": SLIVER_DEG}
    write_result(out, df, extra=extra, resumed=args.add)
    return df


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--case":
        mesher, repair, damage, size, repeat, *threads = sys.argv[2:9]
        print(json.dumps(case(mesher, repair, damage, float(size), int(repeat), int(threads[0]) if threads else 1)))
    else:
        main()
